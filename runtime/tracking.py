"""Is the vehicle doing what it is told?  The outcome checks of the watchdog (DESIGN §3).

Velocity tracking: the commanded velocity (the contract's action mapping, a body command that
PX4 applies in the vehicle frame V: ENU turned by the current yaw only, MAV_FRAME_BODY_NED)
is turned into world ENU with the measured yaw and passed through a first-order lag of time
constant ``lag_s``: the *reference*, where a vehicle that follows its setpoints would be by now.
The tracking error is reference minus measured velocity; a vehicle that does not follow (hit
something, motor failure, snagged) shows an error as large as the commanded speed for as long as
it is commanded, while a healthy one shows only its controller's lag and gain deficit (a real
PX4 levels at ~1.6 m/s when 2.0 m/s is commanded) and its height drift.  The error is compared
with a bound; it must stay above it for longer than a window before it counts.

Tilt: the angle between the body's up axis and the world's; above the bound for longer than a
window means flipped or tumbling (no velocity command of the contract needs it).

Pure numpy on numbers passed in (times in ``time.monotonic_ns``), so tests drive it directly.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from .contract.frames import vehicle_to_world_enu, world_enu_to_vehicle

_NS_PER_S = 1_000_000_000


class OverBound:
    """Since when a quantity has stayed over its bound without a break: the watchdog's checks that
    trip on "over the bound for longer than a window" (tracking error, tilt, invalid depth) share it."""

    def __init__(self) -> None:
        self.since_ns: int | None = None  # None: not over the bound now

    def update(self, t_ns: int, over: bool) -> None:
        """The quantity measured at ``t_ns`` is (``over``) or is not over its bound."""
        if not over:
            self.since_ns = None
        elif self.since_ns is None:
            self.since_ns = t_ns

    def reset(self) -> None:
        self.since_ns = None

    def held_past(self, window_ns: int, now_ns: int) -> bool:
        """Over the bound, without a break, for longer than ``window_ns`` at ``now_ns``."""
        return self.since_ns is not None and now_ns - self.since_ns > window_ns


@dataclass(frozen=True)
class TrackingStatus:
    """The latest comparison: error in the vehicle frame V (m/s) and since when it has been above
    the bound (ns, None = it is not)."""

    t_ns: int
    error_vehicle_m_s: np.ndarray
    over_since_ns: int | None

    @property
    def error_m_s(self) -> float:
        return float(np.linalg.norm(self.error_vehicle_m_s))


class TrackingMonitor:
    """Reference velocity (lagged command, world ENU) against measured velocity.

    Call :meth:`start` when supervision starts, :meth:`command` for every velocity command sent
    (vehicle frame V, m/s) and :meth:`update` for every new velocity measurement (world ENU, m/s,
    with the yaw at that time); :meth:`update` returns the status the watchdog checks.
    """

    def __init__(self, error_max_m_s: float, lag_s: float, window_s: float) -> None:
        self.error_max_m_s = error_max_m_s
        self.lag_s = lag_s
        self.window_s = window_s
        self._recent: deque[tuple[int, float]] = deque()  # (t_ns, error) over the last window
        self.sustained_peak_m_s = 0.0
        self._t_ns = 0
        self._ref_enu_m_s = np.zeros(3)
        self._cmd_vehicle_m_s = np.zeros(3)
        self._yaw_enu_rad = 0.0
        self.over = OverBound()  # since when the error has been over the bound

    def start(self, t_ns: int, vel_enu_m_s: np.ndarray, yaw_enu_rad: float) -> None:
        """Supervision starts at ``t_ns``: the reference is the measured velocity, the command zero
        (offboard starts on a hover setpoint)."""
        vel = np.asarray(vel_enu_m_s, dtype=np.float64)
        self._t_ns = t_ns
        self._ref_enu_m_s = vel.copy() if np.all(np.isfinite(vel)) else np.zeros(3)
        self._cmd_vehicle_m_s = np.zeros(3)
        self._yaw_enu_rad = float(yaw_enu_rad)
        self.over.reset()
        self._recent.clear()
        self.sustained_peak_m_s = 0.0

    def command(self, t_ns: int, vel_cmd_vehicle_m_s: np.ndarray) -> None:
        """A new velocity setpoint (vehicle frame V: forward, left, up; m/s) in force from ``t_ns``."""
        self._advance(t_ns)
        self._cmd_vehicle_m_s = np.asarray(vel_cmd_vehicle_m_s, dtype=np.float64)[:3].copy()

    def update(self, t_ns: int, vel_enu_m_s: np.ndarray, yaw_enu_rad: float) -> TrackingStatus:
        """Compare the velocity measured at ``t_ns`` (world ENU, m/s) with the reference."""
        self._advance(t_ns)
        self._yaw_enu_rad = float(yaw_enu_rad)
        error_enu = self._ref_enu_m_s - np.asarray(vel_enu_m_s, dtype=np.float64)
        error_v = world_enu_to_vehicle(error_enu, self._yaw_enu_rad)
        norm = float(np.linalg.norm(error_v))
        self.over.update(t_ns, math.isfinite(norm) and norm > self.error_max_m_s)
        self._note_sustained(t_ns, norm if math.isfinite(norm) else 0.0)
        return TrackingStatus(t_ns, error_v, self.over.since_ns)

    def _note_sustained(self, t_ns: int, error_m_s: float) -> None:
        """Track ``sustained_peak_m_s``: the largest error that held for a whole window (the
        smallest error of a window, at its largest).  A trip needs it above the bound; how far
        below it stays in normal flight is the margin the defaults were tuned with."""
        self._recent.append((t_ns, error_m_s))
        window_ns = int(self.window_s * _NS_PER_S)
        while len(self._recent) > 1 and self._recent[1][0] <= t_ns - window_ns:
            self._recent.popleft()
        if self._recent[0][0] <= t_ns - window_ns:
            self.sustained_peak_m_s = max(self.sustained_peak_m_s, min(e for _, e in self._recent))

    @property
    def reference_enu_m_s(self) -> np.ndarray:
        return self._ref_enu_m_s.copy()

    def _advance(self, t_ns: int) -> None:
        dt_s = (t_ns - self._t_ns) / _NS_PER_S
        if dt_s <= 0.0:
            return
        target = vehicle_to_world_enu(self._cmd_vehicle_m_s, self._yaw_enu_rad)
        self._ref_enu_m_s = target + (self._ref_enu_m_s - target) * math.exp(-dt_s / self.lag_s)
        self._t_ns = t_ns


def tilt_rad(quat_enu_flu: np.ndarray) -> float:
    """Angle between the body up axis and world up (rad, 0 = level, pi = upside down) for the
    attitude ``quat_enu_flu`` (w, x, y, z)."""
    w, x, y, z = (float(v) for v in np.asarray(quat_enu_flu, dtype=np.float64))
    norm_sq = w * w + x * x + y * y + z * z
    if not norm_sq > 0.0:
        return math.nan
    cos_tilt = 1.0 - 2.0 * (x * x + y * y) / norm_sq
    return math.acos(min(1.0, max(-1.0, cos_tilt)))
