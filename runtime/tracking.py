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

Velocity bias (:class:`VelocityBias`): PX4's velocity controller holds its *estimated* velocity
at the setpoint, so the vehicle really flies the setpoint less the estimate's velocity error.  On
PX4 v1.16 SIH that error is large and slow (EKF2 follows the simulated GPS velocity; 0.17 / 0.32 /
0.19 m/s RMS in room x / y / z over 8 offboard flights, correlated over ~1-2 s: docs/px4-sitl.md
§5), while EKF2's *position* estimate moves with the truth: its rate over 0.3 s misses the true
velocity by ~0.08-0.13 m/s.  An EKF's
velocity and the rate of its position disagree only by what the position fusion keeps pulling
back, so their difference over a short window is the velocity error the vehicle flies on top of
the setpoint.

:class:`VelocityBias` measures it from the stream of estimates: over the last ``window_s``, the
mean of the reported velocity less the displacement / time (the two averaged over the same
window, so acceleration does not show as bias), bounded to ``max_m_s``.  The runtime then treats
``reported - bias`` as the vehicle's velocity (the policy's observation, the watchdog, the brake)
and adds ``bias`` to every velocity setpoint it sends (``runtime.vehicle.Vehicle``), so the
vehicle's true velocity follows the command instead of the estimate.  A gap in the estimates or
a position jump (an EKF reset) starts the window afresh with no bias.

Pure numpy on numbers passed in (times in ``time.monotonic_ns``; the velocity bias's in the
autopilot's clock, s), so tests drive it directly.
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


# `cmnav sitl --velocity-bias`: the runtime corrects the autopilot's velocity error, or flies it as reported.
VELOCITY_BIAS_MODES = ("correct", "off")

# The window VelocityBias averages over (s): a few estimates (PX4 sends ODOMETRY at ~10 Hz or faster)
# and short beside the error's ~1-2 s correlation; vehicle.velocity_bias_window_s is held to it.
VELOCITY_BIAS_WINDOW_RANGE_S = (0.05, 2.0)

# A position step this much faster than the reported velocity explains is an estimator reset.
RESET_SPEED_MARGIN_M_S = 3.0


class VelocityBias:
    """World-ENU velocity bias (m/s) of an autopilot's estimate; :meth:`update` on each new one."""

    def __init__(self, window_s: float = 0.3, max_m_s: float = 0.5, max_gap_s: float = 0.5) -> None:
        low_s, high_s = VELOCITY_BIAS_WINDOW_RANGE_S
        if not low_s <= window_s <= high_s:
            raise ValueError(f"window_s={window_s} must be {low_s}-{high_s} s")
        if not 0.0 <= max_m_s <= 2.0:
            raise ValueError(f"max_m_s={max_m_s} must be 0-2 m/s")
        self.window_s = window_s
        self.max_m_s = max_m_s
        self.max_gap_s = max_gap_s
        self._samples: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        self.bias_enu_m_s = np.zeros(3)
        self.resets = 0  # windows restarted on a gap or a position jump

    def update(self, t_s: float, pos_enu_m: np.ndarray, vel_enu_m_s: np.ndarray) -> np.ndarray:
        """Take the estimate of time ``t_s`` (the autopilot's clock, s; increasing) and return the
        bias now ([3], m/s; zero until the window is full)."""
        pos = np.asarray(pos_enu_m, dtype=np.float64)
        vel = np.asarray(vel_enu_m_s, dtype=np.float64)
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(vel)) and math.isfinite(t_s)):
            return self._restart()
        if self._samples:
            t_last, pos_last, vel_last = self._samples[-1]
            dt = t_s - t_last
            if dt <= 0.0:
                # Not newer: nothing learnt, unless the clock went far back (a rebooted autopilot).
                return self._restart() if dt < -self.max_gap_s else self.bias_enu_m_s
            jump_m_s = float(np.linalg.norm(pos - pos_last)) / dt
            if dt > self.max_gap_s or jump_m_s > max(np.linalg.norm(vel), np.linalg.norm(vel_last)) + RESET_SPEED_MARGIN_M_S:
                self._restart()
        self._samples.append((t_s, pos, vel))
        while len(self._samples) > 2 and t_s - self._samples[1][0] >= self.window_s:
            self._samples.popleft()
        t0 = self._samples[0][0]
        if t_s - t0 < self.window_s:
            self.bias_enu_m_s = np.zeros(3)
            return self.bias_enu_m_s
        ts = np.array([s[0] for s in self._samples])
        vels = np.stack([s[2] for s in self._samples])
        mean_vel = np.sum(0.5 * (vels[1:] + vels[:-1]) * np.diff(ts)[:, None], axis=0) / (ts[-1] - t0)
        rate = (pos - self._samples[0][1]) / (ts[-1] - t0)
        bias = mean_vel - rate
        norm = float(np.linalg.norm(bias))
        if norm > self.max_m_s:
            bias *= self.max_m_s / norm
        self.bias_enu_m_s = bias
        return bias

    def _restart(self) -> np.ndarray:
        if self._samples:
            self.resets += 1
        self._samples.clear()
        self.bias_enu_m_s = np.zeros(3)
        return self.bias_enu_m_s


def setpoint_with_bias(forward_m_s: float, right_m_s: float, down_m_s: float, bias_enu_m_s: np.ndarray,
                       yaw_enu_rad: float) -> tuple[float, float, float]:  # fmt: skip
    """A body setpoint (PX4's yaw-only frame, FRD: forward, right, down, m/s) with the world-ENU
    ``bias`` added: what the autopilot must hold on its estimate for the vehicle to fly the
    setpoint."""
    bias_x, bias_y, bias_z = (float(v) for v in world_enu_to_vehicle(bias_enu_m_s, yaw_enu_rad))  # V: x fwd, y left, z up
    return forward_m_s + bias_x, right_m_s - bias_y, down_m_s - bias_z
