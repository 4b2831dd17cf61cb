"""The follower's MAVLink pose link against a scripted autopilot on loopback, and the
loopback-only rule for --autopilot URLs."""

import socket
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from sim.sitl.geodetic import GeodeticHome
from sim.follower.pose_link import GROUND_TRUTH_FRESH_S, POSE_RATE_HZ, PoseLink
from sim.follower.url import AutopilotUrlError, parse_autopilot_url
from sim.sitl.px4 import HOLD, OFFBOARD

LOOPBACK = "127.0.0.1"


@pytest.mark.parametrize("url, expected", [("udp://127.0.0.1:14550", ("127.0.0.1", 14550)),
                                           ("udpin://127.0.0.1:14551", ("127.0.0.1", 14551))])  # fmt: skip
def test_loopback_urls(url, expected):
    assert parse_autopilot_url(url) == expected


@pytest.mark.parametrize("url", ["udp://0.0.0.0:14550", "udp://192.168.1.20:14550", "udp://localhost:14550"])
def test_another_host_is_refused_unless_allowed(url):
    with pytest.raises(AutopilotUrlError, match="--allow-remote"):
        parse_autopilot_url(url)
    assert parse_autopilot_url(url, allow_remote=True)[1] == 14550


@pytest.mark.parametrize("url", ["tcp://127.0.0.1:5760", "udp://127.0.0.1", "udp://127.0.0.1:0", "127.0.0.1:14550",
                                 "udp://127.0.0.1:99999", "serial:///dev/ttyACM0"])  # fmt: skip
def test_malformed_urls_say_what_is_expected(url):
    with pytest.raises(AutopilotUrlError, match="udp://"):
        parse_autopilot_url(url)


class FakeAutopilot:
    """System 1, component 1, sending to the link from its own loopback port."""

    def __init__(self, link_port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOPBACK, 0))
        self.sock.settimeout(2.0)
        self.dest = (LOOPBACK, link_port)
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)

    def send(self, *msgs) -> None:
        for msg in msgs:
            self.sock.sendto(msg.pack(self.mav), self.dest)

    def receive(self, count: int) -> list:
        parser = mavlink.MAVLink(None)
        got = []
        while len(got) < count:
            data, _ = self.sock.recvfrom(65535)
            got.extend(parser.parse_buffer(data) or [])
        return got

    def close(self) -> None:
        self.sock.close()


def _poll_until(link: PoseLink, t_s: float, done) -> None:
    deadline = time.monotonic() + 5.0
    while not done() and time.monotonic() < deadline:
        link.poll(t_s)
        time.sleep(0.005)
    assert done()


@pytest.fixture
def link_and_autopilot():
    link = PoseLink(LOOPBACK, 0)
    autopilot = FakeAutopilot(link.local_port)
    yield link, autopilot
    autopilot.close()
    link.close()


def test_requests_the_pose_at_50_hz_and_follows_what_arrives(link_and_autopilot):
    link, ap = link_and_autopilot
    ap.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                              mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, HOLD.custom_mode, 3, 3))  # fmt: skip
    _poll_until(link, 10.0, lambda: link.peer is not None)
    assert link.view.system_id == 1 and link.view.mode == "HOLD" and not link.view.armed
    commands = [m for m in ap.receive(5) if m.get_type() == "COMMAND_LONG"]
    asked = {(c.command, int(c.param1)): c.param2 for c in commands}
    assert asked[(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED)] == 1e6 / POSE_RATE_HZ
    assert asked[(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION)] <= 20_000.0
    assert (mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION) in asked
    assert asked[(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION)] == 1e6 / POSE_RATE_HZ
    assert len(link.requests_pending) == 4
    ap.send(*(mavlink.MAVLink_command_ack_message(cmd, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 1, 194) for cmd, _ in asked))
    corrupt = bytearray(mavlink.MAVLink_local_position_ned_message(1, 9.0, 9.0, 9.0, 0, 0, 0).pack(ap.mav))
    corrupt[12] ^= 0xFF  # a payload byte: the CRC no longer matches
    ap.sock.sendto(bytes(corrupt), ap.dest)
    prearm = mavlink.MAV_SYS_STATUS_PREARM_CHECK
    ap.send(
        mavlink.MAVLink_sys_status_message(prearm, prearm, prearm, 0, 0, -1, 100, 0, 0, 0, 0, 0, 0, 0, 0, 0),
        mavlink.MAVLink_home_position_message(0, 0, 0, 0.5, -0.25, 0.0, [1, 0, 0, 0], 0, 0, 0, 0),
        mavlink.MAVLink_local_position_ned_message(100, 1.0, 2.0, -3.0, 0.1, 0.2, -0.3),
        mavlink.MAVLink_attitude_quaternion_message(100, 0.0, 0.0, 0.0, 2.0, 0.01, 0.02, 0.03, [0, 0, 0, 0]),
        mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                          mavlink.MAV_MODE_FLAG_SAFETY_ARMED, OFFBOARD.custom_mode, 4, 3),
    )  # fmt: skip
    _poll_until(link, 10.1, lambda: link.view.pose() is not None and link.view.armed)
    v = link.view
    assert link.requests_pending == [] and v.armable and v.mode == "OFFBOARD"
    np.testing.assert_allclose(v.home_local_ned_m, [0.5, -0.25, 0.0])
    pose = v.pose()
    np.testing.assert_allclose(pose.pos_ned_m, [1.0, 2.0, -3.0], atol=1e-6)
    np.testing.assert_allclose(pose.vel_ned_m_s, [0.1, 0.2, -0.3], atol=1e-6)
    np.testing.assert_allclose(pose.quat_ned_frd, [0.0, 0.0, 0.0, 1.0])  # normalised
    np.testing.assert_allclose(pose.rates_frd_rad_s, [0.01, 0.02, 0.03], atol=1e-6)
    assert link.bad_datagrams >= 1


def test_unanswered_requests_are_repeated_and_others_ignored(link_and_autopilot):
    link, ap = link_and_autopilot
    stranger = mavlink.MAVLink(None, srcSystem=42, srcComponent=1)
    ap.sock.sendto(mavlink.MAVLink_local_position_ned_message(1, 9.0, 9.0, 9.0, 0, 0, 0).pack(stranger), ap.dest)
    ap.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 3, 3))
    _poll_until(link, 20.0, lambda: link.peer is not None)
    ap.receive(4)  # heartbeat + three requests
    link.poll(20.5)  # within the retry period: nothing new
    link.poll(21.1)  # past it: the three requests again (and no heartbeat yet: 1 s after the last)
    again = [m for m in ap.receive(4) if m.get_type() == "COMMAND_LONG"]
    assert len(again) >= 3
    assert link.view.pos_ned_m is None  # system 42 is not the autopilot we follow


def test_the_simulators_ground_truth_is_followed_while_it_is_fresh(link_and_autopilot):
    """PX4 SIH streams its ground truth (HIL_STATE_QUATERNION) on request: the follower renders
    and judges at it, in the local frame through home, not at the EKF's estimate, which wanders
    from it near the ground; when the truth stops, the estimate is followed again."""
    link, ap = link_and_autopilot
    geo = GeodeticHome(47.397742, 8.545594, 488.0)
    ap.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                              mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, HOLD.custom_mode, 3, 3))  # fmt: skip
    _poll_until(link, 10.0, lambda: link.peer is not None)
    lat, lon, alt = geo.to_geodetic(np.array([2.0, 1.0, 0.5]))  # 2 m east, 1 m north, 0.5 m up of home
    ap.send(
        mavlink.MAVLink_home_position_message(round(geo.lat_deg * 1e7), round(geo.lon_deg * 1e7), round(geo.alt_amsl_m * 1e3),
                                              0.5, -0.25, 0.0, [1, 0, 0, 0], 0, 0, 0, 0),
        mavlink.MAVLink_local_position_ned_message(100, 9.0, 9.0, -1.0, 0.3, 0.0, 0.0),  # the estimate, elsewhere
        mavlink.MAVLink_attitude_quaternion_message(100, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [0, 0, 0, 0]),
        mavlink.MAVLink_hil_state_quaternion_message(100, [0.0, 0.0, 0.0, 1.0], 0.0, 0.0, 0.1, round(lat * 1e7),
                                                     round(lon * 1e7), round(alt * 1e3), -20, 40, 0, 0, 0, 0, 0, 0),
    )  # fmt: skip
    _poll_until(link, 10.1, lambda: link.view.truth_messages > 0 and link.view.estimate() is not None)
    truth = link.view.pose()
    # Home's local NED plus the truth's offset from home (north 1, east 2, down -0.5).
    np.testing.assert_allclose(truth.pos_ned_m, [0.5 + 1.0, -0.25 + 2.0, -0.5], atol=0.02)
    np.testing.assert_allclose(truth.vel_ned_m_s, [-0.2, 0.4, 0.0], atol=1e-6)
    np.testing.assert_allclose(truth.quat_ned_frd, [0.0, 0.0, 0.0, 1.0])
    assert link.view.following_truth
    time.sleep(GROUND_TRUTH_FRESH_S + 0.05)
    np.testing.assert_allclose(link.view.pose().pos_ned_m, [9.0, 9.0, -1.0])  # the truth is stale: the estimate
