"""A scripted ground station / RC pilot over pymavlink, for the programs that fly a SITL vehicle in
pilot mode without a person: the soak (``bench.soak``) and the end-to-end tests.  It arms, takes off
and selects offboard as a pilot does, and keeps the vehicle's latest HEARTBEAT and height.
Loopback only."""

from __future__ import annotations

import time

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from .px4 import HOLD, MainMode

LOOPBACK = "127.0.0.1"
ACK_WAIT_S = 0.5  # for each COMMAND_LONG sent
RESEND_PAUSE_S = 0.2  # after a refusal or no answer


class GroundStationTimeout(RuntimeError):
    """What the ground station waited for did not happen in time (the message names it)."""


class GroundStation:
    """System 255, component 190, listening on 127.0.0.1:``port``; talks to system 1."""

    def __init__(self, port: int) -> None:
        self.link = mavutil.mavlink_connection(f"udpin:{LOOPBACK}:{port}", source_system=255, source_component=190)
        self.heartbeat = None  # the vehicle's latest HEARTBEAT
        self.t_heartbeat_s = 0.0  # when it came (time.monotonic)
        self.height_m = 0.0  # -LOCAL_POSITION_NED.z

    def _recv(self, timeout_s: float):
        msg = self.link.recv_match(blocking=True, timeout=timeout_s)
        if msg is not None and msg.get_srcSystem() == 1:
            if msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == 1:
                self.heartbeat, self.t_heartbeat_s = msg, time.monotonic()
            elif msg.get_type() == "LOCAL_POSITION_NED":
                self.height_m = -msg.z
        return msg

    def main_mode(self) -> int:
        """PX4's main mode in the latest HEARTBEAT (0 before any)."""
        return (self.heartbeat.custom_mode >> 16) & 0xFF if self.heartbeat is not None else 0

    def in_hold(self) -> bool:
        return self.heartbeat is not None and self.heartbeat.custom_mode == HOLD.custom_mode

    def in_offboard(self) -> bool:
        return self.main_mode() == MainMode.OFFBOARD

    def wait(self, predicate, timeout_s: float, what: str) -> None:
        """Handle what arrives until ``predicate()``; :class:`GroundStationTimeout` after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self._recv(0.05)
            if predicate():
                return
        raise GroundStationTimeout(f"{what} not seen within {timeout_s} s")

    def command_until_accepted(self, command: int, params: list[float], timeout_s: float, what: str) -> None:
        """COMMAND_LONG, repeated until the vehicle ACKs it as accepted (e.g. arming waits for health)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.link.mav.command_long_send(1, 1, command, 0, *(params + [0.0] * (7 - len(params))))
            ack_deadline = time.monotonic() + ACK_WAIT_S
            while time.monotonic() < ack_deadline:
                msg = self._recv(0.05)
                if msg is not None and msg.get_type() == "COMMAND_ACK" and msg.command == command:
                    if msg.result == mavlink.MAV_RESULT_ACCEPTED:
                        return
                    break
            time.sleep(RESEND_PAUSE_S)
        raise GroundStationTimeout(f"{what} not accepted within {timeout_s} s")

    def arm_and_take_off(self, takeoff_alt_m: float, arm_timeout_s: float = 20.0) -> None:
        """Arm, take off, and wait for the climb to end in Hold (as a pilot does before offboard)."""
        self.command_until_accepted(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [1.0], arm_timeout_s, "arm")
        self.command_until_accepted(mavlink.MAV_CMD_NAV_TAKEOFF, [float("nan")] * 7, 5.0, "takeoff")
        self.wait(lambda: self.in_hold() and self.height_m > 0.9 * takeoff_alt_m, 30.0, "takeoff done, Hold")

    def switch_to_offboard(self, timeout_s: float = 5.0) -> None:
        """Select offboard; return once the HEARTBEAT reports it (the ACK comes first: a HEARTBEAT
        still saying Hold after it would read as "offboard already left")."""
        self.command_until_accepted(mavlink.MAV_CMD_DO_SET_MODE,
                                    [mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, float(MainMode.OFFBOARD), 0.0],
                                    timeout_s, "switch to offboard")  # fmt: skip
        self.wait(self.in_offboard, timeout_s, "OFFBOARD in the vehicle's HEARTBEAT")

    def close(self) -> None:
        self.link.close()
