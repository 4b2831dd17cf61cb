"""The autopilot's velocity estimate against the rate of its own position estimate.

PX4's velocity controller holds its *estimated* velocity at the setpoint, so the vehicle really
flies the setpoint less the estimate's velocity error.  On PX4 v1.16 SIH that error is large and
slow (EKF2 follows the simulated GPS velocity; 0.17 / 0.32 / 0.19 m/s RMS in room x / y / z over 8
offboard flights, correlated over ~1-2 s: docs/px4-sitl.md §5), while EKF2's *position* estimate
moves with the truth: its rate over 0.3 s misses the true velocity by ~0.08-0.13 m/s.  An EKF's
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
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

# `cmnav sitl --velocity-bias`: the runtime corrects the autopilot's velocity error, or flies it as reported.
VELOCITY_BIAS_MODES = ("correct", "off")

# A position step this much faster than the reported velocity explains is an estimator reset.
RESET_SPEED_MARGIN_M_S = 3.0


class VelocityBias:
    """World-ENU velocity bias (m/s) of an autopilot's estimate; :meth:`update` on each new one."""

    def __init__(self, window_s: float = 0.3, max_m_s: float = 0.5, max_gap_s: float = 0.5) -> None:
        if not 0.05 <= window_s <= 2.0:
            raise ValueError(f"window_s={window_s} must be 0.05-2 s")
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
    bx, by, bz = (float(v) for v in bias_enu_m_s)
    c, s = math.cos(yaw_enu_rad), math.sin(yaw_enu_rad)
    return forward_m_s + c * bx + s * by, right_m_s - (-s * bx + c * by), down_m_s - bz
