"""The MAVLink side in one process: a real UDP endpoint and a fake ground station socket, the
autopilot's dispatch driven by hand (no physics, no threads)."""

import math
import socket
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from runtime.contract.frames import quat_from_euler
from sim.sitl.autopilot import Autopilot
from sim.sitl.commander import Commander
from sim.sitl.geodetic import GeodeticHome
from sim.sitl.kinematics import Kinematics
from sim.sitl.mavlink_endpoint import MavlinkEndpoint
from sim.sitl.params import ParamTable
from sim.sitl.px4 import OFFBOARD
from sim.sitl.streams import StreamScheduler
from sim.sitl.telemetry import Telemetry

HOME = np.array([1.0, 2.0, 0.15])
GCS_SYSTEM, GCS_COMPONENT = 1, 195


def _landed() -> Kinematics:
    return Kinematics(0, HOME.copy(), np.zeros(3), quat_from_euler(0.0, 0.0, 0.0), np.zeros(3), True)


class Link:
    """Vehicle endpoint + autopilot, and a ground-station socket talking to it."""

    def __init__(self) -> None:
        self.gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.gcs.bind(("127.0.0.1", 0))
        self.gcs.settimeout(1.0)
        self.endpoint = MavlinkEndpoint(self.gcs.getsockname()[1])
        self.kin = _landed()
        self.params = ParamTable(takeoff_alt_m=1.5)
        self.commander = Commander(self.params, HOME, self.kin, 0.0)
        self.autopilot = Autopilot(
            self.endpoint, self.commander, self.params, Telemetry(HOME, GeodeticHome(), 0),
            StreamScheduler(0.0, max_rate_hz=100.0), GeodeticHome(), 0,
        )  # fmt: skip
        self.packer = mavlink.MAVLink(None, srcSystem=GCS_SYSTEM, srcComponent=GCS_COMPONENT)
        self.parser = mavlink.MAVLink(None)

    def close(self) -> None:
        self.endpoint.close()
        self.gcs.close()

    def send_raw(self, data: bytes) -> None:
        self.gcs.sendto(data, ("127.0.0.1", self.endpoint.local_port))

    def send(self, msg: mavlink.MAVLink_message) -> None:
        self.send_raw(msg.pack(self.packer))

    def process(self, t_s: float = 1.0) -> None:
        """Let the vehicle handle everything sent so far."""
        deadline = time.monotonic() + 1.0
        handled = 0
        while time.monotonic() < deadline:
            messages = self.endpoint.receive()
            for msg in messages:
                self.autopilot.handle(msg, self.kin, t_s)
            handled += len(messages)
            if not messages and handled:
                return
            time.sleep(0.005)

    def replies(self) -> list[mavlink.MAVLink_message]:
        out = []
        self.gcs.settimeout(0.05)
        try:
            while True:
                out.extend(self.parser.parse_buffer(self.gcs.recv(65535)) or [])
        except TimeoutError:
            return out

    def command(self, command: int, *params: float, t_s: float = 1.0) -> tuple[int, list]:
        p = list(params) + [0.0] * (7 - len(params))
        self.send(mavlink.MAVLink_command_long_message(1, 1, command, 0, *p))
        self.process(t_s)
        replies = self.replies()
        (ack,) = [m for m in replies if m.get_type() == "COMMAND_ACK"]
        assert (ack.command, ack.target_system, ack.target_component) == (command, GCS_SYSTEM, GCS_COMPONENT)
        return ack.result, [m for m in replies if m.get_type() != "COMMAND_ACK"]


@pytest.fixture
def link():
    lk = Link()
    try:
        yield lk
    finally:
        lk.close()


def test_telemetry_streams_from_system_1_component_1(link):
    link.autopilot.publish(link.kin, 0.0)
    replies = link.replies()
    assert {m.get_type() for m in replies} >= {"HEARTBEAT", "SYS_STATUS", "EXTENDED_SYS_STATE", "HOME_POSITION",
                                               "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"}  # fmt: skip
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in replies} == {(1, 1)}
    assert all(m.get_msgbuf()[0] == mavlink.PROTOCOL_MARKER_V2 for m in replies)  # MAVLink 2 framing


def test_request_message_acks_then_sends(link):
    result, extra = link.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert result == mavlink.MAV_RESULT_ACCEPTED and [m.get_type() for m in extra] == ["AUTOPILOT_VERSION"]
    result, extra = link.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION)
    assert result == mavlink.MAV_RESULT_ACCEPTED and [m.get_type() for m in extra] == ["HOME_POSITION"]
    result, _ = link.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_BATTERY_STATUS)
    assert result == mavlink.MAV_RESULT_UNSUPPORTED


def test_set_message_interval(link):
    msg_id = mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE
    assert link.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6)[0] == mavlink.MAV_RESULT_ACCEPTED
    assert link.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 1e6)[0] == mavlink.MAV_RESULT_DENIED


def test_commands_reach_the_commander(link):
    assert link.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == mavlink.MAV_RESULT_ACCEPTED
    assert link.commander.armed
    mode = (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6, 0)
    assert link.command(mavlink.MAV_CMD_DO_SET_MODE, *mode)[0] == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    link.send(mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, mavlink.MAV_FRAME_BODY_NED, 0x5C7, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0.2))  # fmt: skip
    link.process(t_s=1.0)
    assert link.command(mavlink.MAV_CMD_DO_SET_MODE, *mode, t_s=1.1)[0] == mavlink.MAV_RESULT_ACCEPTED
    assert link.commander.mode == OFFBOARD
    cmd = link.commander.velocity_command(1.1, link.kin)
    np.testing.assert_allclose(cmd.vel_enu_m_s, [1.0, 0.0, 0.0], atol=1e-9)
    assert cmd.yaw_rate_enu_rad_s == pytest.approx(-0.2)
    assert link.command(mavlink.MAV_CMD_DO_SET_MODE, 0, 6, 0)[0] == mavlink.MAV_RESULT_DENIED  # no custom flag
    assert link.command(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH)[0] == mavlink.MAV_RESULT_UNSUPPORTED


def test_command_int_takeoff_with_an_amsl_altitude(link):
    link.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    link.send(mavlink.MAVLink_command_int_message(
        1, 1, mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, math.nan, 0, 0,
        GeodeticHome().alt_amsl_m + 2.0))  # fmt: skip
    link.process()
    (ack,) = [m for m in link.replies() if m.get_type() == "COMMAND_ACK"]
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert link.commander.velocity_command(1.0, link.kin).vel_enu_m_s[2] > 1.0  # climbing to 2 m


def test_parameter_protocol(link):
    link.send(mavlink.MAVLink_param_request_read_message(1, 1, b"MIS_TAKEOFF_ALT", -1))
    link.process()
    (value,) = link.replies()
    assert (value.param_id, value.param_value, value.param_count) == ("MIS_TAKEOFF_ALT", 1.5, len(link.params))
    link.send(mavlink.MAVLink_param_set_message(1, 1, b"MIS_TAKEOFF_ALT", 3.0, mavlink.MAV_PARAM_TYPE_REAL32))
    link.process()
    (echo,) = link.replies()
    assert echo.param_value == 3.0 and link.params["MIS_TAKEOFF_ALT"] == 3.0
    link.send(mavlink.MAVLink_param_request_list_message(1, 1))
    link.process()
    assert sorted(m.param_index for m in link.replies()) == list(range(len(link.params)))


def test_garbage_is_counted_and_does_not_desynchronise(link):
    link.send_raw(b"\xfd\x10\x00\x00")  # a truncated MAVLink 2 header
    link.send_raw(bytes(range(256)))
    link.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, math.nan, 0, 0, 0, 0, 0, 0))
    link.send(mavlink.MAVLink_ping_message(123, 7, 0, 0))
    link.process()
    assert link.endpoint.bad_datagrams >= 1
    replies = {m.get_type(): m for m in link.replies()}
    assert replies["COMMAND_ACK"].result == mavlink.MAV_RESULT_DENIED  # NaN arm parameter
    assert (replies["PING"].seq, replies["PING"].target_system) == (7, GCS_SYSTEM)


def test_commands_for_another_system_are_ignored(link):
    link.send(mavlink.MAVLink_command_long_message(2, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    link.process()
    assert link.replies() == [] and not link.commander.armed
