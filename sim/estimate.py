"""The autopilot's state estimate as the policy receives it: PX4 EKF2's output is late, noisy and
biased, and its error wanders; the runtime's observation is built from it, not from the true state.

Model (per env; the truth is recorded at the physics rate in a :class:`sim.delay.DelayLine`):

    estimate(t) = truth(t - delay) + bias (per episode) + drift(t) + white noise (per observation)

on position and velocity (world ENU; horizontal axes and the vertical one each with their own
sizes), attitude (a small rotation about the body axes, applied on the right: roll/pitch/yaw
errors in body FLU: bias + noise) and body rates (noise).  The delay is drawn per episode in
``delay_range_s``; the drift is an Ornstein-Uhlenbeck process per axis (stationary standard
deviation ``*_drift_*``, correlation times ``drift_correlation_s`` for position and
``velocity_drift_correlation_s`` for velocity), advanced every physics step and drawn from its
stationary law when an episode starts.

Measured (position and velocity): PX4 v1.16 SIH, the 58 offboard flights of the PX4 campaign
runs/px4-campaign/student-px4t (levels 0/3/6, 20 seeds each; two never reached offboard), the
runtime's logged estimate (MCAP ``/vehicle/state``, ~10 Hz of new estimates, in the air, in
offboard) against the follower's ground truth (SIH's), in the room's axes x, y, z:
``python -m sim.response replay runs/px4-campaign/student-px4t`` (:mod:`sim.response.replay`):

- each flight's mean error, its spread over flights (sd): position 0.05 / 0.09 / 0.24 m,
  velocity 0.07 / 0.15 / 0.15 m/s -> the per-episode biases (horizontal: RMS of x and y);
- the error about that mean within a flight (sd): position 0.10 / 0.15 / 0.18 m, velocity
  0.17 / 0.24 / 0.15 m/s, autocorrelated 0.83-0.90 at 0.5 s, 0.60-0.76 at 1 s, 0.15-0.48 at
  2 s -> an Ornstein-Uhlenbeck drift with a 2.5 s correlation time; white noise small against
  it;
- delay: the truth shifted by -0.1 ... +0.3 s fits the estimate best at 0 ... +0.04 s (a lag
  scan of the same data; the assumed 20-40 ms stands).

The autopilot flies its estimate: PX4 holds its *estimated* velocity at the setpoint, so the true
velocity misses the setpoint by the estimate's error.  Measured on the same flights (the logged
commands replayed through ``sim.dynamics.PX4_SIH_V1_16`` in windows every 0.25 s, each started
from the recorded state of a flight the model has flown held to that record since offboard began;
2,732 windows, same command as above): 1 s ahead, the velocity error against PX4's estimate is
0.11 / 0.09 / 0.06 m/s RMS (forward / left / up), against the truth 0.25 / 0.41 / 0.16.  The
batched env therefore commands the dynamics (which track the truth) with the setpoint less the
estimate's bias and drift (:meth:`StateEstimator.velocity_error_m_s`).

**What the runtime flies** (:data:`PX4_EKF2_CORRECTED`): the runtime measures the velocity
estimate's disagreement with the rate of the position estimate and removes it
(``runtime.tracking.VelocityBias``, ``vehicle.velocity_bias_correction``, on by default): it
reasons with the estimate less that bias and sends each setpoint plus it, so the vehicle flies the
setpoint less what is left.  Measured on 106 PX4 SIH flights flown so (the campaigns
runs/px4-campaign/px4t-bias, px4t-bias-fresh, default-bias-fresh; ``python -m sim.response
replay``, its "corrected estimate" lines): the velocity's per-flight mean spread 0.02 / 0.05 /
0.04 m/s, within a flight 0.08 / 0.13 / 0.11 m/s, autocorrelated 0.42-0.60 at 0.5 s, 0.10-0.27 at
1 s, none at 2 s -> a 0.7 s velocity drift (the position's error is the autopilot's, unchanged).

Assumed (not measured here: the follower's trace keeps no attitude estimate): the attitude
noise and bias (0.5 deg, typical of EKF2 flight logs) and the rate noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .delay import DelayLine, delay_steps
from .dynamics import QuadState
from .rotations import quat_from_euler, quat_multiply


@dataclass(frozen=True)
class StateEstimateConfig:
    """1-sigma values (Gaussian), delays and times in seconds; pairs are (each horizontal axis,
    vertical).  Defaults: PX4 v1.16 SIH's EKF2 as measured (see the module doc)."""

    delay_range_s: tuple[float, float] = (0.020, 0.040)  # per episode, uniform
    position_noise_m: float = 0.02  # white, per observation, each axis
    position_bias_m: tuple[float, float] = (0.09, 0.24)  # per episode
    position_drift_m: tuple[float, float] = (0.13, 0.18)  # stationary sd of the wandering error
    velocity_noise_m_s: float = 0.03
    velocity_bias_m_s: tuple[float, float] = (0.12, 0.15)
    velocity_drift_m_s: tuple[float, float] = (0.21, 0.15)
    drift_correlation_s: float = 2.5  # position's drift
    velocity_drift_correlation_s: float = 2.5
    attitude_noise_rad: float = math.radians(0.5)
    attitude_bias_rad: float = math.radians(0.5)  # per episode, roll, pitch and yaw
    rate_noise_rad_s: float = 0.01  # body rates (PX4's filtered gyro)

    def validate(self) -> None:
        low, high = self.delay_range_s
        if not 0.0 <= low <= high <= 1.0:
            raise ValueError(f"StateEstimateConfig.delay_range_s={self.delay_range_s} must satisfy 0 <= low <= high <= 1 s")
        for key in ("position_noise_m", "velocity_noise_m_s", "attitude_noise_rad", "attitude_bias_rad", "rate_noise_rad_s"):
            if not getattr(self, key) >= 0.0:
                raise ValueError(f"StateEstimateConfig.{key}={getattr(self, key)} must be >= 0")
        for key in _PAIRS:
            pair = getattr(self, key)
            if len(pair) != 2 or not all(v >= 0.0 for v in pair):
                raise ValueError(f"StateEstimateConfig.{key}={pair} must be (horizontal, vertical), both >= 0")
        for key in ("drift_correlation_s", "velocity_drift_correlation_s"):
            if not getattr(self, key) > 0.0:
                raise ValueError(f"StateEstimateConfig.{key}={getattr(self, key)} must be > 0 s")

    @property
    def drifts(self) -> bool:
        return any(v > 0.0 for v in self.position_drift_m + self.velocity_drift_m_s)


# The estimate as the runtime uses and flies it, with its velocity correction on (module doc):
# horizontal values the RMS of the room's x and y.
PX4_EKF2_CORRECTED = StateEstimateConfig(velocity_bias_m_s=(0.04, 0.04), velocity_drift_m_s=(0.11, 0.11),
                                         velocity_drift_correlation_s=0.7)  # fmt: skip

_PAIRS = ("position_bias_m", "position_drift_m", "velocity_bias_m_s", "velocity_drift_m_s")


def _per_axis(pair: tuple[float, float]) -> Tensor:
    """(horizontal, vertical) -> [3] per ENU axis."""
    return torch.tensor([pair[0], pair[0], pair[1]], dtype=torch.float32)


# Channels of the recorded truth: position 3, velocity 3, attitude quaternion 4, body rates 3.
_CHANNELS = 13


class StateEstimator:
    """Batched estimate of B vehicles' states (see the module doc).  :meth:`reset` starts an
    episode (draws its delay and biases), :meth:`record` takes the truth after every physics
    step, :meth:`estimate` gives what the policy sees now.  Random draws come from the generator
    passed in (CPU), so a seed replays the same estimates."""

    def __init__(self, config: StateEstimateConfig, batch_size: int, physics_dt_s: float,
                 device: torch.device | str = "cpu") -> None:  # fmt: skip
        config.validate()
        self.config = config
        self.physics_dt_s = physics_dt_s
        self.device = torch.device(device)
        self._line = DelayLine(DelayLine.capacity_for(config.delay_range_s[1], physics_dt_s), batch_size, _CHANNELS, self.device)
        self.delay_s = torch.zeros(batch_size)
        self.delay_steps = torch.zeros(batch_size, dtype=torch.long)
        self.position_bias_m = torch.zeros(batch_size, 3)
        self.velocity_bias_m_s = torch.zeros(batch_size, 3)
        self.attitude_bias_rad = torch.zeros(batch_size, 3)
        # Position and velocity drift [B, 6] (an Ornstein-Uhlenbeck process per axis).
        self.drift = torch.zeros(batch_size, 6)
        self._drift_sd = torch.cat([_per_axis(config.position_drift_m), _per_axis(config.velocity_drift_m_s)])
        # Per-step decay of the drift [6]: position's, then velocity's correlation time.
        self._drift_decay = torch.tensor([math.exp(-physics_dt_s / config.drift_correlation_s)] * 3
                                         + [math.exp(-physics_dt_s / config.velocity_drift_correlation_s)] * 3)  # fmt: skip

    def reset(self, envs: Tensor, state: QuadState, generator: torch.Generator) -> None:
        """New episodes in ``envs`` [K] (CPU indices) whose first true state is ``state`` (batch K)."""
        c = self.config
        k = len(envs)
        low, high = c.delay_range_s
        self.delay_s[envs] = low + (high - low) * torch.rand(k, generator=generator)
        self.delay_steps[envs] = delay_steps(self.delay_s[envs], self.physics_dt_s)
        self.position_bias_m[envs] = _per_axis(c.position_bias_m) * torch.randn(k, 3, generator=generator)
        self.velocity_bias_m_s[envs] = _per_axis(c.velocity_bias_m_s) * torch.randn(k, 3, generator=generator)
        self.attitude_bias_rad[envs] = c.attitude_bias_rad * torch.randn(k, 3, generator=generator)
        if c.drifts:
            self.drift[envs] = self._drift_sd * torch.randn(k, 6, generator=generator)
        self._line.fill(envs.to(self.device), _pack(state))

    def record(self, state: QuadState, generator: torch.Generator) -> None:
        """The true states [B] after a physics step; the drift advances one physics step."""
        self._line.push(_pack(state))
        if self.config.drifts:
            a = self._drift_decay
            shock = torch.randn(self.drift.shape, generator=generator)
            self.drift = a * self.drift + torch.sqrt(1.0 - a * a) * self._drift_sd * shock

    def velocity_error_m_s(self) -> Tensor:
        """[B, 3] the estimate's velocity error now, bias + drift (world ENU, m/s; the white noise
        left out): what the autopilot's velocity controller acts on besides the truth, so that
        the truth follows a setpoint off by it (see the module doc)."""
        return (self.velocity_bias_m_s + self.drift[:, 3:6]).to(self.device)

    def estimate(self, generator: torch.Generator) -> QuadState:
        """What the autopilot reports now: the truth ``delay`` ago, plus bias, drift and noise."""
        c = self.config
        truth = self._line.read(self.delay_steps)
        n = truth.shape[0]
        noise = torch.randn(n, 12, generator=generator).to(self.device)
        dev = self.device
        drift = self.drift.to(dev)
        pos = truth[:, 0:3] + self.position_bias_m.to(dev) + drift[:, 0:3] + c.position_noise_m * noise[:, 0:3]
        vel = truth[:, 3:6] + self.velocity_bias_m_s.to(dev) + drift[:, 3:6] + c.velocity_noise_m_s * noise[:, 3:6]
        error = self.attitude_bias_rad.to(dev) + c.attitude_noise_rad * noise[:, 6:9]
        quat = quat_multiply(truth[:, 6:10], quat_from_euler(error[:, 0], error[:, 1], error[:, 2]))
        rates = truth[:, 10:13] + c.rate_noise_rad_s * noise[:, 9:12]
        return QuadState(pos, vel, quat / torch.linalg.vector_norm(quat, dim=-1, keepdim=True), rates)


def _pack(state: QuadState) -> Tensor:
    return torch.cat([state.pos_enu_m, state.vel_enu_m_s, state.quat_enu_flu, state.angvel_body_flu_rad_s], dim=-1)
