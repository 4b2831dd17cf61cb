"""The SITL vehicle's mission protocol, driven as a ground station drives PX4: a 3-waypoint plan
uploaded with pymavlink (MISSION_COUNT / REQUEST_INT / ITEM_INT / ACK), downloaded back, the
current item set, and MISSION_CURRENT broadcast to the ground station."""

import socket
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from sim.sitl_session import free_port
from tests.e2e.fly_helpers import Sitl

pytestmark = pytest.mark.timeout(120)

HOME_LAT_DEG, HOME_LON_DEG = 47.397742, 8.545594  # sim.sitl.geodetic.GeodeticHome (PX4 SITL's)
WAYPOINTS_ENU_M = [(3.0, 0.0, 2.0), (5.0, 1.0, 2.5), (8.0, -0.5, 2.0)]


def waypoint_items(waypoints_enu_m, lat0=HOME_LAT_DEG, lon0=HOME_LON_DEG):
    """MISSION_ITEM_INT fields of NAV_WAYPOINTs (global, altitude relative to home) at ENU offsets."""
    import math

    items = []
    for seq, (east, north, up) in enumerate(waypoints_enu_m):
        lat = lat0 + math.degrees(north / 6_371_000.0)
        lon = lon0 + math.degrees(east / (6_371_000.0 * math.cos(math.radians(lat0))))
        items.append(dict(seq=seq, frame=mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=mavlink.MAV_CMD_NAV_WAYPOINT,
                          current=int(seq == 0), autocontinue=1, param1=0.0, param2=1.0, param3=0.0, param4=float("nan"),
                          x=round(lat * 1e7), y=round(lon * 1e7), z=float(up)))  # fmt: skip
    return items


def _recv(link, kind: str, timeout_s: float, predicate=lambda m: True):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = link.recv_match(type=kind, blocking=True, timeout=0.1)
        if msg is not None and predicate(msg):
            return msg
    raise AssertionError(f"no {kind} within {timeout_s} s")


def upload(link, items) -> int:
    """Upload as QGroundControl does; returns the MISSION_ACK type."""
    link.mav.mission_count_send(1, 1, len(items), mavlink.MAV_MISSION_TYPE_MISSION)
    while True:
        msg = _recv(link, ["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], 5.0)
        if msg.get_type() == "MISSION_ACK":
            return msg.type
        item = items[msg.seq]
        link.mav.mission_item_int_send(1, 1, item["seq"], item["frame"], item["command"], item["current"], item["autocontinue"],
                                       item["param1"], item["param2"], item["param3"], item["param4"], item["x"], item["y"],
                                       item["z"], mavlink.MAV_MISSION_TYPE_MISSION)  # fmt: skip


def download(link) -> list:
    link.mav.mission_request_list_send(1, 1, mavlink.MAV_MISSION_TYPE_MISSION)
    count = _recv(link, "MISSION_COUNT", 5.0).count
    items = []
    for seq in range(count):
        link.mav.mission_request_int_send(1, 1, seq, mavlink.MAV_MISSION_TYPE_MISSION)
        items.append(_recv(link, "MISSION_ITEM_INT", 5.0, lambda m, s=seq: m.seq == s))
    link.mav.mission_ack_send(1, 1, mavlink.MAV_MISSION_ACCEPTED, mavlink.MAV_MISSION_TYPE_MISSION)
    return items


@pytest.fixture
def ground_station(tmp_path):
    port = free_port(socket.SOCK_DGRAM)
    link = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    sitl = Sitl(tmp_path, port)
    try:
        link.wait_heartbeat(timeout=30)
        yield link
    finally:
        sitl.stop()
        link.close()


def test_a_plan_uploads_downloads_and_reports_its_current_item(ground_station):
    link = ground_station
    # MAVSDK's mission_raw refuses a vehicle that does not advertise MISSION_ITEM_INT, as PX4 does.
    link.mav.command_long_send(1, 1, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 0, 1, 0, 0, 0, 0, 0, 0)
    assert _recv(link, "AUTOPILOT_VERSION", 5.0).capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    items = waypoint_items(WAYPOINTS_ENU_M)
    assert upload(link, items) == mavlink.MAV_MISSION_ACCEPTED
    current = _recv(link, "MISSION_CURRENT", 5.0, lambda m: m.total == 3)
    assert current.seq == 0 and current.mission_state == mavlink.MISSION_STATE_ACTIVE

    back = download(link)
    assert [(m.seq, m.frame, m.command, m.x, m.y, m.z) for m in back] == \
        [(i["seq"], i["frame"], i["command"], i["x"], i["y"], i["z"]) for i in items]  # fmt: skip

    link.mav.mission_set_current_send(1, 1, 2)
    assert _recv(link, "MISSION_CURRENT", 5.0, lambda m: m.seq == 2).total == 3
    link.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MISSION_CURRENT, 0, 1, 0, 0, 0, 0, 0, 0)
    ack = _recv(link, "COMMAND_ACK", 5.0, lambda m: m.command == mavlink.MAV_CMD_DO_SET_MISSION_CURRENT)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert _recv(link, "MISSION_CURRENT", 5.0, lambda m: m.seq == 1).total == 3
    link.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MISSION_CURRENT, 0, 7, 0, 0, 0, 0, 0, 0)
    ack = _recv(link, "COMMAND_ACK", 5.0, lambda m: m.command == mavlink.MAV_CMD_DO_SET_MISSION_CURRENT)
    assert ack.result == mavlink.MAV_RESULT_DENIED  # no item 7

    # An empty plan clears the mission; a geofence upload is refused as unsupported.
    assert upload(link, []) == mavlink.MAV_MISSION_ACCEPTED
    assert download(link) == []
    link.mav.mission_count_send(1, 1, 4, mavlink.MAV_MISSION_TYPE_FENCE)
    assert _recv(link, "MISSION_ACK", 5.0).type == mavlink.MAV_MISSION_UNSUPPORTED


def test_mavsdk_mission_raw_downloads_the_plan_and_its_progress_reaches_the_ground_station(tmp_path):
    """What the runtime's goal_source = "mission" stands on: MAVSDK 4's mission_raw (the runtime's
    side, on its own link through a router) downloads the plan the ground station uploaded, the
    waypoints become goals relative to home, and set_current_mission_item shows on the ground
    station's link as MISSION_CURRENT."""
    import asyncio

    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.mission_raw import MissionRawAsync
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

    from runtime.config import WatchdogConfig
    from runtime.programs.mission_goals import MissionError, RawMissionItem, check_geofence, mission_waypoints
    from tests.e2e.fly_helpers import MavlinkRouter

    runtime_port, gcs_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    router = MavlinkRouter(runtime_port, gcs_port)
    link = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gcs_port}", source_system=255, source_component=190)
    sitl = Sitl(tmp_path, router.port)
    try:
        link.wait_heartbeat(timeout=30)
        assert upload(link, waypoint_items(WAYPOINTS_ENU_M)) == mavlink.MAV_MISSION_ACCEPTED

        async def runtime_side():
            async with Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)) as sdk:
                await sdk.add_any_connection(f"udpin://127.0.0.1:{runtime_port}")
                system = await sdk.first_autopilot(timeout_s=20.0)
                mission, telemetry = MissionRawAsync(system), TelemetryAsync(system)
                items = await asyncio.wait_for(mission.download_mission(), 20.0)
                home = await asyncio.wait_for(telemetry.home(), 20.0)
                await asyncio.wait_for(mission.set_current_mission_item(2), 20.0)
                return [RawMissionItem(i.seq, i.frame, i.command, i.x, i.y, i.z) for i in items], home

        items, home = asyncio.run(runtime_side())
        assert _recv(link, "MISSION_CURRENT", 5.0, lambda m: m.seq == 2).total == 3
    finally:
        sitl.stop()
        link.close()
        router.close()
    waypoints = mission_waypoints(items, home.latitude_deg, home.longitude_deg)
    assert [w.seq for w in waypoints] == [0, 1, 2]
    for waypoint, expected in zip(waypoints, WAYPOINTS_ENU_M):
        assert max(abs(a - b) for a, b in zip(waypoint.goal_rel_home_enu_m, expected)) < 0.05
    check_geofence(waypoints, WatchdogConfig())  # inside the default fence: flown
    with pytest.raises(MissionError, match=r"mission item 2 is 8\.0 m from home, outside the geofence"):
        check_geofence(waypoints, WatchdogConfig(geofence_radius_m=6.0))
