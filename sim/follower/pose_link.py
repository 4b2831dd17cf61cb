"""The follower's MAVLink link to an external autopilot: listens on one UDP address (by default
127.0.0.1, as PX4 SITL's GCS link sends to 127.0.0.1:14550), learns the autopilot's address
from its first HEARTBEAT, asks it for the pose at POSE_RATE_HZ (SET_MESSAGE_INTERVAL) and
home (REQUEST_MESSAGE), and keeps the latest of what it reports.

Loopback only unless told otherwise: :func:`sim.follower.url.parse_autopilot_url` refuses a host other than
127.0.0.1 without ``allow_remote``.
"""

from __future__ import annotations

import logging
import math
import socket
import time
from dataclasses import dataclass, field

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from runtime.contract.frames import enu_to_ned
from sim.sitl.geodetic import GeodeticHome
from sim.sitl.mavlink_endpoint import MAX_DATAGRAM_BYTES, MAX_DATAGRAMS_PER_POLL, RECEIVE_BUFFER_BYTES, parse_datagram
from sim.sitl.px4 import Px4Mode, UnknownModeError

from .placement import AutopilotPose

log = logging.getLogger(__name__)

POSE_RATE_HZ = 50.0
# PX4 SIH's ground truth (HIL_STATE_QUATERNION, requested like the pose) is followed while it is at
# most this old; otherwise the estimate (LOCAL_POSITION_NED + ATTITUDE_QUATERNION) is.
GROUND_TRUTH_FRESH_S = 0.2
# Our identity on the link: the companion's system id, a component of its own.
SYSTEM_ID = 1
COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER2
AUTOPILOT_COMPONENT_ID = mavlink.MAV_COMP_ID_AUTOPILOT1
REQUEST_RETRY_S = 1.0
HEARTBEAT_PERIOD_S = 1.0


def prearm_passed(sensors_health: int) -> bool:
    """PX4's pre-arm checks pass, as SYS_STATUS tells: the MAV_SYS_STATUS_PREARM_CHECK bit of
    ``onboard_control_sensors_health``.  PX4 v1.16 never sets that bit in ``..._present`` nor
    ``..._enabled`` (recorded: tests/sim/follower/fixtures/px4_v1_16_startup.json), so a check that
    needs it there waits for ever."""
    return bool(sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK)


# HEARTBEAT.system_status of an autopilot past its boot (PX4: UNINIT for ~4 s, then STANDBY).
READY_SYSTEM_STATES = (mavlink.MAV_STATE_STANDBY, mavlink.MAV_STATE_ACTIVE)


class AutopilotLinkError(OSError):
    """The pose link could not be opened."""


@dataclass
class AutopilotView:
    """What the autopilot reported last (None/False until it has).  Times: time.monotonic_ns."""

    system_id: int | None = None
    armed: bool = False
    mode: str = "UNKNOWN"
    system_status: int = mavlink.MAV_STATE_UNINIT  # HEARTBEAT.system_status (MAV_STATE)
    prearm_ok: bool = False  # SYS_STATUS: prearm_passed
    landed_state: int = mavlink.MAV_LANDED_STATE_UNDEFINED
    home_local_ned_m: np.ndarray | None = None
    home_geodetic: GeodeticHome | None = None  # HOME_POSITION's latitude, longitude, altitude
    # The simulator's ground truth (HIL_STATE_QUATERNION), in the local NED frame through home.
    truth_pos_ned_m: np.ndarray | None = None
    truth_vel_ned_m_s: np.ndarray | None = None
    truth_quat_ned_frd: np.ndarray | None = None
    truth_rates_frd_rad_s: np.ndarray | None = None
    t_truth_ns: int = 0
    truth_messages: int = 0
    pos_ned_m: np.ndarray | None = None
    vel_ned_m_s: np.ndarray | None = None
    t_position_ns: int = 0
    quat_ned_frd: np.ndarray | None = None
    rates_frd_rad_s: np.ndarray | None = None
    t_attitude_ns: int = 0
    position_messages: int = 0
    attitude_messages: int = 0
    t_first_position_ns: int = 0
    events: list[tuple[float, str]] = field(default_factory=list)

    def pose(self) -> AutopilotPose | None:
        """Where the vehicle is: the simulator's ground truth while it is fresh (what the camera
        really sees and what really touches a wall), else the autopilot's estimate; None before
        either.  PX4 SIH's EKF estimate wanders from the truth by up to ~1 m near the ground
        (docs/px4-sitl.md), with a velocity of the opposite sign."""
        if self.truth_pos_ned_m is not None and time.monotonic_ns() - self.t_truth_ns <= GROUND_TRUTH_FRESH_S * 1e9:
            return AutopilotPose(self.t_truth_ns, self.truth_pos_ned_m, self.truth_vel_ned_m_s,
                                 self.truth_quat_ned_frd, self.truth_rates_frd_rad_s)  # fmt: skip
        return self.estimate()

    def estimate(self) -> AutopilotPose | None:
        """The autopilot's estimate: the latest position and attitude combined (stamped with the newer)."""
        if self.pos_ned_m is None or self.quat_ned_frd is None:
            return None
        return AutopilotPose(max(self.t_position_ns, self.t_attitude_ns), self.pos_ned_m, self.vel_ned_m_s,
                             self.quat_ned_frd, self.rates_frd_rad_s)  # fmt: skip

    @property
    def following_truth(self) -> bool:
        return self.truth_pos_ned_m is not None and time.monotonic_ns() - self.t_truth_ns <= GROUND_TRUTH_FRESH_S * 1e9

    def position_rate_hz(self) -> float | None:
        """LOCAL_POSITION_NED messages per second received so far (None: fewer than two)."""
        if self.position_messages < 2 or self.t_position_ns <= self.t_first_position_ns:
            return None
        return (self.position_messages - 1) / ((self.t_position_ns - self.t_first_position_ns) * 1e-9)

    @property
    def armable(self) -> bool:
        """Ready to arm as PX4 v1.16 reports it: booted (STANDBY) and its pre-arm checks passed."""
        return self.system_status in READY_SYSTEM_STATES and self.prearm_ok

    @property
    def on_ground(self) -> bool:
        if self.landed_state == mavlink.MAV_LANDED_STATE_UNDEFINED:
            return not self.armed
        return self.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND


class PoseLink:
    """UDP MAVLink 2 link to one autopilot; :meth:`poll` handles what arrived and keeps the
    requests going.  One thread uses it."""

    def __init__(self, host: str, port: int) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
        try:
            self._sock.bind((host, port))
        except OSError as err:
            self._sock.close()
            raise AutopilotLinkError(
                f"cannot listen for the autopilot on udp {host}:{port} ({err}): is another program (a ground "
                f"station) using that port? Close it or give --autopilot another port the autopilot sends to"
            ) from err
        self._sock.setblocking(False)
        self._mav = mavlink.MAVLink(None, srcSystem=SYSTEM_ID, srcComponent=COMPONENT_ID)
        self._peer: tuple[str, int] | None = None
        self.view = AutopilotView()
        # command id, message id -> time of the last request (0 = not yet); removed once accepted.
        self._requests: dict[tuple[int, int], float] = {
            (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED): 0.0,
            (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION): 0.0,
            (mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION): 0.0,
            (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION): 0.0,
        }
        self._refused: set[tuple[int, int]] = set()
        self._t_heartbeat_s = 0.0
        self.bad_datagrams = 0
        log.info("pose link listening on udp %s:%d", host, self.local_port)

    @property
    def local_port(self) -> int:
        return int(self._sock.getsockname()[1])

    @property
    def peer(self) -> tuple[str, int] | None:
        """The autopilot's address, once it sent a HEARTBEAT."""
        return self._peer

    @property
    def requests_pending(self) -> list[str]:
        return [f"{mavlink.enums['MAV_CMD'][c].name}({m})" for c, m in self._requests]

    def fileno(self) -> int:
        return self._sock.fileno()

    def close(self) -> None:
        self._sock.close()

    def poll(self, t_s: float) -> list[str]:
        """Handle every datagram waiting (never blocks) and send what is due; returns the
        message types that changed the view (``"pose"`` for a position or attitude)."""
        changed: list[str] = []
        for _ in range(MAX_DATAGRAMS_PER_POLL):
            try:
                data, addr = self._sock.recvfrom(MAX_DATAGRAM_BYTES)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:
                continue  # ICMP from an earlier send: the autopilot restarted
            good, problems = parse_datagram(data)
            self.bad_datagrams += len(problems)
            for problem in problems[:1]:
                log.warning("pose link: %s (ignored; %d bad so far)", problem, self.bad_datagrams)
            for msg in good:
                changed.extend(self._handle(msg, addr))
        self._send_due(t_s)
        return changed

    # ---- incoming -------------------------------------------------------------------------

    def _from_autopilot(self, msg: mavlink.MAVLink_message) -> bool:
        return msg.get_srcSystem() == self.view.system_id and msg.get_srcComponent() == AUTOPILOT_COMPONENT_ID

    def _handle(self, msg: mavlink.MAVLink_message, addr: tuple[str, int]) -> list[str]:
        kind = msg.get_type()
        v = self.view
        if kind == "HEARTBEAT" and v.system_id is None and msg.get_srcComponent() == AUTOPILOT_COMPONENT_ID \
                and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID:  # fmt: skip
            v.system_id = msg.get_srcSystem()
            self._peer = addr
            log.info("autopilot system %d at udp %s:%d", v.system_id, *addr)
        if not self._from_autopilot(msg):
            return []
        now_ns = time.monotonic_ns()
        if kind == "HEARTBEAT":
            self._peer = addr
            v.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            v.mode = _mode_name(msg.custom_mode)
            v.system_status = msg.system_status
        elif kind == "SYS_STATUS":
            v.prearm_ok = prearm_passed(msg.onboard_control_sensors_health)
        elif kind == "EXTENDED_SYS_STATE":
            v.landed_state = msg.landed_state
        elif kind == "HOME_POSITION":
            v.home_local_ned_m = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
            v.home_geodetic = GeodeticHome(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        elif kind == "HIL_STATE_QUATERNION":
            if v.home_geodetic is None or v.home_local_ned_m is None:
                return []
            q = np.array(msg.attitude_quaternion, dtype=np.float64)
            norm = float(np.linalg.norm(q))
            if not math.isfinite(norm) or norm < 0.5:
                return []
            offset_enu = v.home_geodetic.to_enu(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
            v.truth_pos_ned_m = v.home_local_ned_m + enu_to_ned(offset_enu)
            v.truth_vel_ned_m_s = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64) * 0.01  # cm/s
            v.truth_quat_ned_frd = q / norm
            v.truth_rates_frd_rad_s = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=np.float64)
            v.t_truth_ns = now_ns
            v.truth_messages += 1
            kind = "pose"
        elif kind == "LOCAL_POSITION_NED":
            v.pos_ned_m = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
            v.vel_ned_m_s = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
            v.t_position_ns = now_ns
            v.t_first_position_ns = v.t_first_position_ns or now_ns
            v.position_messages += 1
            kind = "pose"
        elif kind == "ATTITUDE_QUATERNION":
            q = np.array([msg.q1, msg.q2, msg.q3, msg.q4], dtype=np.float64)
            norm = float(np.linalg.norm(q))
            if not math.isfinite(norm) or norm < 0.5:
                log.warning("ignoring ATTITUDE_QUATERNION with quaternion %s", q.tolist())
                return []
            v.quat_ned_frd = q / norm
            v.rates_frd_rad_s = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=np.float64)
            v.t_attitude_ns = now_ns
            v.attitude_messages += 1
            kind = "pose"
        elif kind == "STATUSTEXT":
            text = msg.text.rstrip("\x00") if isinstance(msg.text, str) else bytes(msg.text).decode(errors="replace")
            v.events.append((now_ns * 1e-9, text))
            log.info("autopilot: %s", text)
        elif kind == "COMMAND_ACK":
            self._on_ack(msg)
        return [kind]

    def _on_ack(self, msg: mavlink.MAVLink_message) -> None:
        pending = [key for key in self._requests if key[0] == msg.command]
        if not pending:
            return
        # ACKs carry the command, not its parameter: the oldest request of that command is answered.
        key = min(pending, key=lambda k: self._requests[k])
        if msg.result == mavlink.MAV_RESULT_ACCEPTED:
            del self._requests[key]
            log.info("autopilot accepted %s for message %d", mavlink.enums["MAV_CMD"][key[0]].name, key[1])
        elif msg.result != mavlink.MAV_RESULT_IN_PROGRESS and key[1] == mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION:
            del self._requests[key]  # no simulator ground truth here (a real vehicle): follow the estimate
            log.info("autopilot has no ground truth (HIL_STATE_QUATERNION %s): following its estimate",
                     mavlink.enums["MAV_RESULT"][msg.result].name)  # fmt: skip
        elif msg.result != mavlink.MAV_RESULT_IN_PROGRESS and key not in self._refused:
            self._refused.add(key)
            log.error("autopilot answered %s for message %d with %s; retrying every %.0f s",
                      mavlink.enums["MAV_CMD"][key[0]].name, key[1], mavlink.enums["MAV_RESULT"][msg.result].name,
                      REQUEST_RETRY_S)  # fmt: skip

    # ---- outgoing -------------------------------------------------------------------------

    def _send(self, msg: mavlink.MAVLink_message) -> None:
        if self._peer is None:
            return
        try:
            self._sock.sendto(msg.pack(self._mav), self._peer)
        except OSError as err:
            log.warning("pose link: send to %s:%d failed (%s)", *self._peer, err)

    def _send_due(self, t_s: float) -> None:
        if self._peer is None:
            return
        if t_s - self._t_heartbeat_s >= HEARTBEAT_PERIOD_S:
            self._t_heartbeat_s = t_s
            self._send(mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3))  # fmt: skip
        target = self.view.system_id or 0
        for (command, msg_id), t_sent in list(self._requests.items()):
            if t_s - t_sent < REQUEST_RETRY_S:
                continue
            self._requests[(command, msg_id)] = t_s
            param2 = 1e6 / POSE_RATE_HZ if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL else 0.0
            self._send(mavlink.MAVLink_command_long_message(
                target, AUTOPILOT_COMPONENT_ID, command, 0, float(msg_id), param2, 0, 0, 0, 0, 0))  # fmt: skip


def _mode_name(custom_mode: int) -> str:
    """PX4 custom mode -> MAVSDK's name (HOLD, OFFBOARD, ...)."""
    try:
        return Px4Mode.from_custom_mode(custom_mode).name
    except UnknownModeError:
        return f"UNKNOWN({custom_mode})"
