"""The vehicle as the runtime sees it: pure data types, no MAVSDK, no foxglove, no onnxruntime.

:class:`VehicleState` (a telemetry snapshot on the policy side), its :class:`VehicleHealth`, the
autopilot's STATUSTEXTs, the flight-mode names the runtime acts on, and the errors of the
autopilot link.  ``runtime.vehicle`` (the MAVSDK adapter) fills them; the flight loop, the policy
step, the watchdog, the recorder and the log reader only read them, so none of those needs MAVSDK.

PX4 announces what it detects itself in STATUSTEXT (collision, failure detector, battery, EKF):
severity CRITICAL or worse means the vehicle is no longer fit to fly the policy, and the watchdog
ends the episode on it (``vehicle_fault``).  Severities are MAVLink's MAV_SEVERITY names.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .contract.frames import euler_from_quat, quat_conjugate, quat_rotate

# MAV_SEVERITY, most severe first (the MAVLink values 0..7).
SEVERITIES = ("EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING", "NOTICE", "INFO", "DEBUG")
FAULT_SEVERITIES = frozenset(SEVERITIES[: SEVERITIES.index("CRITICAL") + 1])
# How many of the latest messages a VehicleState snapshot carries.
STATUS_TEXTS_KEPT = 16


@dataclass(frozen=True)
class StatusText:
    """One STATUSTEXT: ``seq`` counts messages from 1 in order of receipt, ``t_ns`` is the
    receive time (CLOCK_MONOTONIC), ``severity`` a MAV_SEVERITY name."""

    seq: int
    t_ns: int
    severity: str
    text: str

    @property
    def is_fault(self) -> bool:
        """Severity CRITICAL or worse: the autopilot says the vehicle is in trouble."""
        return self.severity in FAULT_SEVERITIES


def append_status_text(kept: tuple[StatusText, ...], t_ns: int, severity: str, text: str) -> tuple[StatusText, ...]:
    """``kept`` with a new message at the end, the oldest dropped beyond STATUS_TEXTS_KEPT."""
    seq = kept[-1].seq + 1 if kept else 1
    return (*kept, StatusText(seq, t_ns, severity, text))[-STATUS_TEXTS_KEPT:]


# MAVSDK's FlightMode names (telemetry.FlightMode) the runtime cares about.
MODE_OFFBOARD = "OFFBOARD"
MODE_HOLD = "HOLD"


class VehicleError(RuntimeError):
    """Talking to the autopilot failed; the message names the command, the cause and the fix."""


class VehicleTimeoutError(VehicleError):
    """The autopilot did not answer (or a state was not reached) in time."""


class VehicleCommandError(VehicleError):
    """The autopilot (or MAVSDK) refused a command."""


@dataclass(frozen=True)
class VehicleHealth:
    """The autopilot's pre-flight health flags (MAVSDK ``Telemetry.Health``)."""

    armable: bool = False
    local_position_ok: bool = False
    global_position_ok: bool = False
    home_position_ok: bool = False
    gyro_ok: bool = False
    accel_ok: bool = False
    mag_ok: bool = False


@dataclass(frozen=True)
class VehicleState:
    """Telemetry snapshot on the policy side.

    Positions are in the autopilot's local frame turned ENU (metres; origin = the local NED
    origin, *not* necessarily home — use ``home_enu_m``); velocities world ENU (m/s): ``vel_enu_m_s``
    is the vehicle's (the autopilot's estimate less ``vel_bias_enu_m_s``, the estimate's velocity
    error measured against the rate of its own position: ``runtime.tracking.VelocityBias``); attitude
    ``quat_enu_flu`` (w, x, y, z) rotates body FLU into world ENU; ``angvel_body_flu_rad_s`` body
    FLU.  Every ``t_*_ns`` is the receive time on this host's CLOCK_MONOTONIC, 0 = never received.
    """

    t_estimate_us: int = 0  # the autopilot's time of the estimate below (ODOMETRY time_usec, its boot clock), 0 = none
    pos_enu_m: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    vel_enu_m_s: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    vel_bias_enu_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    t_posvel_ns: int = 0
    quat_enu_flu: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    t_att_ns: int = 0
    angvel_body_flu_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    t_angvel_ns: int = 0
    flight_mode: str = "UNKNOWN"
    t_mode_ns: int = 0
    armed: bool = False
    t_armed_ns: int = 0
    in_air: bool = False
    landed_state: str = "UNKNOWN"
    health: VehicleHealth = field(default_factory=VehicleHealth)
    t_health_ns: int = 0
    home_enu_m: np.ndarray | None = None
    status_texts: tuple[StatusText, ...] = ()  # the latest STATUSTEXTs, oldest first (StatusText above)

    @property
    def t_telemetry_ns(self) -> int:
        """Receive time of the staler of position/velocity and attitude (0 until both arrived)."""
        return min(self.t_posvel_ns, self.t_att_ns)

    @property
    def vel_body_flu_m_s(self) -> np.ndarray:
        """World velocity rotated into body FLU (m/s)."""
        return quat_rotate(quat_conjugate(self.quat_enu_flu), self.vel_enu_m_s)

    @property
    def yaw_enu_rad(self) -> float:
        """Heading, counter-clockwise from east (rad)."""
        return float(euler_from_quat(self.quat_enu_flu)[2])

    @property
    def height_above_home_m(self) -> float:
        """Height above home (m); NaN until home and position are known."""
        if self.home_enu_m is None:
            return float("nan")
        return float(self.pos_enu_m[2] - self.home_enu_m[2])
