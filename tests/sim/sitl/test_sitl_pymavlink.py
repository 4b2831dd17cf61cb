"""The SITL vehicle driven with raw pymavlink, for what MAVSDK would hide: the vehicle's own
OFFBOARD refusal, garbage on its UDP port, the offboard-loss failsafe (MAVSDK re-sends setpoints
at 20 Hz, so only a raw client can stop them), a collision, and the episode / trace files."""

from __future__ import annotations

import math
import random
import socket
import statistics
import struct
import time

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from runtime.camera.sim_wire import HEADER, decode_header, decode_payload, payload_size
from sim.sitl.airframe import LANDING_GEAR_HEIGHT_M

pytestmark = pytest.mark.timeout(60)

VELOCITY_YAW_RATE_MASK = 0x5C7  # what MAVSDK's set_velocity_body sends
OFFBOARD = (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6, 0)
FORCE_MAGIC = 21196


class Pilot:
    """A raw MAVLink client on udpin:127.0.0.1:P that can stream a body-velocity setpoint at
    20 Hz while it waits for things (single-threaded: each wait pumps the stream)."""

    def __init__(self, port: int) -> None:
        self.link = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=195)
        self.setpoint: tuple[float, float, float, float] | None = None
        self.t_last_setpoint_s = 0.0
        self.statustexts: list[tuple[float, str]] = []
        self.heartbeat = None

    def close(self) -> None:
        self.link.close()

    def _pump_once(self, timeout_s: float):
        now = time.monotonic()
        if self.setpoint is not None and now - self.t_last_setpoint_s >= 0.05:
            forward, right, down, yaw_rate = self.setpoint
            self.link.mav.set_position_target_local_ned_send(
                0, 1, 1, mavlink.MAV_FRAME_BODY_NED, VELOCITY_YAW_RATE_MASK,
                0, 0, 0, forward, right, down, 0, 0, 0, 0, yaw_rate,
            )  # fmt: skip
            self.t_last_setpoint_s = now
        msg = self.link.recv_match(blocking=True, timeout=min(timeout_s, 0.02))
        if msg is not None:
            if msg.get_type() == "STATUSTEXT":
                self.statustexts.append((time.monotonic(), msg.text))
            elif msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == 1:
                self.heartbeat = msg
        return msg

    def wait(self, predicate, timeout_s: float, what: str):
        """Pump until predicate(msg) is true for a received message; return that message."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            msg = self._pump_once(deadline - time.monotonic())
            if msg is not None and predicate(msg):
                return msg
        raise AssertionError(f"{what} not seen within {timeout_s} s; status texts {self.statustexts}")

    def pump(self, duration_s: float) -> None:
        """Keep streaming (if a setpoint is set) and receiving for duration_s."""
        deadline = time.monotonic() + duration_s
        while time.monotonic() < deadline:
            self._pump_once(deadline - time.monotonic())

    def command(self, command: int, *params: float) -> int:
        """COMMAND_LONG to the autopilot; returns the COMMAND_ACK result."""
        p = list(params) + [0.0] * (7 - len(params))
        self.link.mav.command_long_send(1, 1, command, 0, *p)
        ack = self.wait(lambda m: m.get_type() == "COMMAND_ACK" and m.command == command, 3.0, f"ACK of {command}")
        return ack.result

    def wait_mode(self, main: int, sub: int, timeout_s: float = 3.0) -> None:
        custom = (main << 16) | (sub << 24)
        self.wait(lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1 and m.custom_mode == custom,
                  timeout_s, f"mode {main}/{sub} in HEARTBEAT")  # fmt: skip

    def arm_and_take_off(self) -> None:
        self.wait(lambda m: m.get_type() == "SYS_STATUS" and m.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK,
                  10.0, "pre-arm checks passing")  # fmt: skip
        assert self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        assert self.command(mavlink.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7) == mavlink.MAV_RESULT_ACCEPTED
        self.wait(lambda m: m.get_type() == "STATUSTEXT" and "Takeoff complete" in m.text, 15.0, "take-off complete")


@pytest.fixture
def pilot_and_sitl(launch_sitl):
    sitl = launch_sitl(level=0, seed=3)
    pilot = Pilot(sitl.mavlink_port)
    try:
        yield pilot, sitl
    finally:
        pilot.close()


def _garbage_datagrams(rng: random.Random) -> list[bytes]:
    """Random bytes, MAVLink-looking junk, a truncated and a corrupted valid packet, well-formed
    messages with nonsense content, and an id the common dialect does not know."""
    packer = mavlink.MAVLink(None, srcSystem=1, srcComponent=195)
    valid = mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(packer)
    corrupted = bytearray(valid)
    corrupted[-1] ^= 0xFF
    junk = [bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 400))) for _ in range(150)]
    junk += [bytes([0xFD]) + bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 60))) for _ in range(50)]
    junk += [bytes([0xFE]) + bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 60))) for _ in range(50)]
    junk += [valid[: len(valid) // 2], bytes(corrupted), valid[:10] + valid]
    junk.append(mavlink.MAVLink_command_long_message(1, 1, 176, 0, math.nan, math.nan, math.inf, 0, 0, 0, 0).pack(packer))
    junk.append(mavlink.MAVLink_command_long_message(1, 1, 400, 0, 7, 0, 0, 0, 0, 0, 0).pack(packer))
    junk.append(mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, 99, 0, 1, 2, 3, math.nan, 0, 0, 0, 0, 0, 0, 0).pack(packer))  # fmt: skip
    junk.append(mavlink.MAVLink_param_set_message(1, 1, b"NO_SUCH_PARAM", 1.0, 9).pack(packer))
    unknown = bytearray(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(packer))
    unknown[7:10] = (60000).to_bytes(3, "little")  # a message id outside the dialect
    junk.append(bytes(unknown))
    return junk


def test_refusals_garbage_and_offboard_loss_failsafe(pilot_and_sitl):
    pilot, sitl = pilot_and_sitl
    pilot.wait(lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1, 10.0, "first heartbeat")
    hb = pilot.heartbeat
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4 and hb.type == mavlink.MAV_TYPE_QUADROTOR
    assert hb.custom_mode == (4 << 16) | (3 << 24) and not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED

    # Garbage on the vehicle's own port: it keeps running, and well-formed nonsense is refused.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as attacker:
        for datagram in _garbage_datagrams(random.Random(7)):
            attacker.sendto(datagram, ("127.0.0.1", sitl.episode["vehicle_mavlink_port"]))
            time.sleep(0.001)  # a stream, not a burst that overflows the socket buffer
    for command in (mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_COMPONENT_ARM_DISARM):  # NaN mode, arm = 7
        ack = pilot.wait(lambda m: m.get_type() == "COMMAND_ACK" and m.command == command, 3.0, f"ACK of junk {command}")
        assert ack.result == mavlink.MAV_RESULT_DENIED
    assert sitl.proc.poll() is None
    assert pilot.command(mavlink.MAV_CMD_DO_SET_MODE, *OFFBOARD) == mavlink.MAV_RESULT_DENIED  # disarmed
    assert pilot.command(31999) == mavlink.MAV_RESULT_UNSUPPORTED

    pilot.arm_and_take_off()
    # No setpoints yet: the vehicle itself refuses OFFBOARD; disarming in the air is refused too.
    assert pilot.command(mavlink.MAV_CMD_DO_SET_MODE, *OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    assert pilot.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mavlink.MAV_RESULT_DENIED

    pilot.setpoint = (0.0, 0.0, 0.0, 0.0)
    pilot.pump(0.3)
    assert pilot.command(mavlink.MAV_CMD_DO_SET_MODE, *OFFBOARD) == mavlink.MAV_RESULT_ACCEPTED
    pilot.wait_mode(6, 0)

    # The failsafe action is PX4's parameter, set as a ground station would: Hold (5) instead of
    # the default Position mode (which lands a vehicle without RC: tests/sim/sitl/test_commander.py).
    hold_action = struct.unpack("<f", struct.pack("<i", 5))[0]  # PX4 sends integers bytewise
    pilot.link.mav.param_set_send(1, 1, b"COM_OBL_RC_ACT", hold_action, mavlink.MAV_PARAM_TYPE_INT32)
    value = pilot.wait(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "COM_OBL_RC_ACT", 3.0, "PARAM_VALUE")
    assert value.param_value == hold_action

    # Stop the stream: COM_OF_LOSS_T = 1 s later the vehicle's failsafe switches to Hold.
    pilot.setpoint = None
    t_stop = pilot.t_last_setpoint_s
    text = pilot.wait(lambda m: m.get_type() == "STATUSTEXT" and "offboard lost" in m.text, 5.0, "offboard-loss failsafe")
    t_failsafe = pilot.statustexts[-1][0]
    assert text.severity == mavlink.MAV_SEVERITY_WARNING
    # Never before the 1 s timeout; the generous upper bound only guards against "never".
    assert 1.0 <= t_failsafe - t_stop < 3.0, t_failsafe - t_stop
    pilot.wait_mode(4, 3)
    assert sitl.proc.poll() is None

    # A forced disarm (MAVSDK's kill) is obeyed in the air: the motors stop and it falls.
    assert pilot.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, FORCE_MAGIC) == mavlink.MAV_RESULT_ACCEPTED
    text = pilot.wait(lambda m: m.get_type() == "STATUSTEXT" and m.text.startswith("collision"), 5.0, "the fall")
    assert "floor" in text.text

    assert sitl.stop() == 0, sitl.log_tail()
    trace = sitl.trace()
    assert [mode for _, mode in trace["mode_log"]] == ["HOLD", "TAKEOFF", "HOLD", "OFFBOARD", "HOLD"]
    assert any("offboard lost" in text for _, text in trace["events"])
    assert trace["collision"]["what"].startswith("floor")


def test_collision_with_a_wall_is_recorded(pilot_and_sitl):
    pilot, sitl = pilot_and_sitl
    episode = sitl.episode
    home, start = np.array(episode["home_enu_m"]), np.array(episode["start_enu_m"])
    assert home[2] == pytest.approx(LANDING_GEAR_HEIGHT_M) and home[:2] == pytest.approx(start[:2])
    assert episode["takeoff_alt_m"] == pytest.approx(start[2] - home[2])
    assert episode["goal_rel_home_enu_m"] == pytest.approx((np.array(episode["goal_enu_m"]) - home).tolist())
    assert episode["boxes"] == [] and episode["level"] == 0 and episode["seed"] == 3
    assert (episode["mavlink_port"], episode["camera_port"]) == (sitl.mavlink_port, sitl.camera_port)

    frames = _read_frames(sitl.camera_port, 5)
    pilot.arm_and_take_off()
    # Spawned facing +x: body right is world -y.  Fly sideways into the nearer side wall.
    width_m = episode["room_size_m"][1]
    right_m_s = 2.0 if start[1] < width_m / 2 else -2.0
    pilot.setpoint = (0.0, right_m_s, 0.0, 0.0)
    pilot.pump(0.3)
    assert pilot.command(mavlink.MAV_CMD_DO_SET_MODE, *OFFBOARD) == mavlink.MAV_RESULT_ACCEPTED
    text = pilot.wait(lambda m: m.get_type() == "STATUSTEXT" and m.text.startswith("collision"), 10.0, "collision")
    assert text.severity == mavlink.MAV_SEVERITY_CRITICAL and "wall y=" in text.text
    pilot.setpoint = None
    hb = pilot.wait(lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1, 2.0, "heartbeat")
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED and hb.system_status == mavlink.MAV_STATE_EMERGENCY
    assert pilot.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_DENIED

    assert sitl.stop() == 0, sitl.log_tail()
    trace = sitl.trace()
    collision = trace["collision"]
    wall_y = 0.0 if right_m_s > 0 else width_m
    assert collision is not None and abs(collision["pos_enu_m"][1] - wall_y) < 0.25
    assert trace["collision"]["t_s"] >= trace["mode_log"][-1][0]
    assert trace["mode_log"][-1][1] == "OFFBOARD"
    assert len(trace["pos_enu_m"]) == len(trace["t_s"]) > 20
    assert statistics.median(np.diff(trace["t_s"])) <= 0.1  # >= 10 Hz
    assert trace["frames_served"] >= len(frames) == 5
    assert len(trace["invalid_depth_frac"]) == len(trace["frame_t_s"]) == trace["frames_served"]


def _read_frames(port: int, count: int) -> list:
    frames = []
    with socket.create_connection(("127.0.0.1", port), timeout=5.0) as sock:
        reader = sock.makefile("rb")
        for _ in range(count):
            seq, t_ns, width, height, meta_len = decode_header(reader.read(HEADER.size))
            frames.append(decode_payload(seq, t_ns, width, height, reader.read(payload_size(width, height, meta_len))))
    return frames
