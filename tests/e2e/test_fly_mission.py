"""`cmnav fly` with ``mission.goal_source = "mission"`` against the SITL vehicle, real processes
over loopback: a ground station (pymavlink, behind a MAVLink router as on a real vehicle) uploads
a plan as QGroundControl does; the runtime downloads it, refuses a plan with a waypoint outside
the geofence before arming (exit 2, one line), and flies a good one in a dry run, one episode and
one log (with its report) per waypoint, in order, the ground station seeing the current item
advance (MISSION_CURRENT)."""

from __future__ import annotations

import re
import socket
import threading
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from export.goal_seeker import export_goal_seeker
from runtime.report import report_paths
from sim.sitl_session import free_port
from tests.e2e.fly_helpers import MavlinkRouter, NotifyListener, Sitl, finish_fly, fly_config, start_fly
from tests.sim.sitl.test_mission import upload, waypoint_items

pytestmark = pytest.mark.timeout(240)


@dataclass
class GroundStation:
    """What the ground station's link showed while `cmnav fly` ran: MISSION_CURRENT's items in
    the order they were reported (repeats dropped) and whether any HEARTBEAT said armed."""

    link: object
    current_items: list[int] = field(default_factory=list)
    armed_seen: bool = False
    heartbeats: int = 0
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def watch(self) -> None:
        self._stop.clear()
        self.current_items, self.armed_seen, self.heartbeats = [], False, 0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.link.recv_match(type=["MISSION_CURRENT", "HEARTBEAT"], blocking=True, timeout=0.1)
            if msg is None or msg.get_srcSystem() != 1:
                continue
            if msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == 1:
                self.heartbeats += 1
                self.armed_seen |= bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif msg.get_type() == "MISSION_CURRENT" and (not self.current_items or self.current_items[-1] != msg.seq):
                self.current_items.append(msg.seq)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


@dataclass
class Rig:
    runtime_port: int
    sitl: Sitl
    station: GroundStation
    model: Path


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """One SITL vehicle for the module (the refused plan never arms it), its MAVLink shared by
    the runtime and a ground station through a router."""
    tmp = tmp_path_factory.mktemp("mission")
    model = tmp / "goal-seeker.onnx"
    export_goal_seeker(str(model))
    runtime_port, gcs_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    router = MavlinkRouter(runtime_port, gcs_port)
    link = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gcs_port}", source_system=255, source_component=190)
    sitl = None
    try:
        sitl = Sitl(tmp, router.port, level=0)
        link.wait_heartbeat(timeout=30)
        yield Rig(runtime_port, sitl, GroundStation(link), model)
    finally:
        if sitl is not None:
            sitl.stop()
        link.close()
        router.close()


def _fly_mission(rig: Rig, tmp_path: Path, waypoints_enu_m: list[tuple[float, float, float]]) -> tuple[int, dict, str]:
    """Upload ``waypoints_enu_m`` (relative to home) from the ground station, then one `cmnav fly`
    dry run with goal_source = "mission", the ground station watching."""
    assert upload(rig.station.link, waypoint_items(waypoints_enu_m)) == mavlink.MAV_MISSION_ACCEPTED
    mission = (f'goal_source = "mission"\nallow_arm_takeoff = true\n'
               f"takeoff_alt_m = {rig.sitl.episode['takeoff_alt_m']:.3f}")  # fmt: skip
    config = fly_config(rig.model, rig.runtime_port, rig.sitl.camera_port, [0.0, 0.0, 0.0], tmp_path / "logs", mission)
    config = re.sub(r"^goal_rel_home_enu_m = .*\n", "", config, flags=re.M)  # the goals come from the mission
    notify = NotifyListener(tmp_path / "notify")
    rig.station.watch()
    try:
        code, summary = finish_fly(start_fly(tmp_path, config, notify), tmp_path)
    finally:
        rig.station.stop()
        notify.close()
    return code, summary, (tmp_path / "fly.log").read_text()


def test_a_waypoint_outside_the_geofence_is_refused_before_arming(rig, tmp_path):
    gx, gy, gz = rig.sitl.episode["goal_rel_home_enu_m"]
    code, summary, log_text = _fly_mission(rig, tmp_path, [(gx / 2.0, gy / 2.0, gz), (25.0, 0.0, gz)])
    assert code == 2, f"exit {code}: {summary}\n{log_text[-3000:]}"
    assert summary["error"] == ("mission refused, nothing armed: mission item 1 is 25.0 m from home, outside the geofence "
                                "(watchdog.geofence_radius_m = 20 m): move the waypoint in or widen the fence")  # fmt: skip
    assert summary["episodes"] == [] and summary["logs"] == []
    assert rig.station.heartbeats > 0 and not rig.station.armed_seen  # the vehicle was watched and never armed


def test_a_three_waypoint_plan_is_flown_in_order_with_progress_on_the_ground_station(rig, tmp_path):
    gx, gy, gz = rig.sitl.episode["goal_rel_home_enu_m"]
    waypoints = [(gx * f, gy * f, gz) for f in (0.25, 0.5, 0.8)]  # along the room, toward the world's goal
    code, summary, log_text = _fly_mission(rig, tmp_path, waypoints)
    assert code == 0, f"exit {code}: {summary}\n{log_text[-4000:]}"
    assert [w["seq"] for w in summary["mission"]] == [0, 1, 2]
    episodes = summary["episodes"]
    assert [e["mission_item"] for e in episodes] == [0, 1, 2]
    for episode, expected in zip(episodes, waypoints):
        assert episode["outcome"] == "success" and episode["watchdog_trips"] == [], episode
        assert episode["goal_rel_home_enu_m"] == pytest.approx(expected, abs=0.05)
        log = Path(episode["log"])
        assert log.exists() and all(path.exists() for path in report_paths(log)), episode
    assert len({e["log"] for e in episodes}) == 3  # one log per waypoint
    assert rig.station.current_items == [0, 1, 2], rig.station.current_items
    assert rig.station.armed_seen and "landed and disarmed" in log_text
    # Each waypoint re-entered offboard from Hold: three offboard entries in one flight.
    modes = rig.sitl.modes()
    assert sum(1 for a, b in zip(modes, modes[1:]) if b == "OFFBOARD" and a != "OFFBOARD") == 3, modes
    # After the last waypoint the dry run landed in offboard (mission.land_in_offboard): no Land mode.
    assert modes[-1] == "OFFBOARD" and episodes[-1]["brake"]["descent"]["ended"] == "disarmed", (modes, episodes[-1]["brake"])
    assert all("descent" not in (e["brake"] or {}) for e in episodes[:-1])  # the others went on from Hold
