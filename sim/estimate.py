"""The autopilot's state estimate as the policy receives it: PX4 EKF2's output is late, noisy and
a little biased, and the runtime's observation is built from it, not from the true state.

Model (per env; the truth is recorded at the physics rate in a :class:`sim.delay.DelayLine`):

    estimate(t) = truth(t - delay) + bias (per episode) + white noise (per observation)

on position (world ENU), velocity (world ENU), attitude (a small rotation about the body axes,
applied on the right: roll/pitch/yaw errors in body FLU) and body rates.  The delay is drawn per
episode in ``delay_range_s``.

Which numbers are measured and which assumed: none were measured on our vehicle.  PX4's EKF2
runs its filter on a delayed time horizon (EKF2_*_DELAY, ~10-200 ms by sensor) and predicts the
output forward with the IMU (the output predictor), so what the offboard API reports lags the
truth by the predictor's tracking error and the MAVLink stream's period (50 Hz = 20 ms): 20-40 ms
is our assumption.  Velocity noise 0.05 m/s and attitude noise 0.5 deg (1 sigma) are the
magnitudes typical of EKF2 flight logs with GPS/flow; the per-episode biases, the position
noise and bias, and the rate noise are assumptions of the same order (stated in
:class:`StateEstimateConfig`).
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
    """1-sigma values per axis (Gaussian), delays in seconds; all assumptions (see the module doc)."""

    delay_range_s: tuple[float, float] = (0.020, 0.040)  # per episode, uniform
    position_noise_m: float = 0.02
    position_bias_m: float = 0.05  # per episode, each axis (a local-position offset at start)
    velocity_noise_m_s: float = 0.05
    velocity_bias_m_s: float = 0.02  # per episode, each axis
    attitude_noise_rad: float = math.radians(0.5)
    attitude_bias_rad: float = math.radians(0.5)  # per episode, roll, pitch and yaw
    rate_noise_rad_s: float = 0.01  # body rates (PX4's filtered gyro)

    def validate(self) -> None:
        low, high = self.delay_range_s
        if not 0.0 <= low <= high <= 1.0:
            raise ValueError(f"StateEstimateConfig.delay_range_s={self.delay_range_s} must satisfy 0 <= low <= high <= 1 s")
        for key in ("position_noise_m", "position_bias_m", "velocity_noise_m_s", "velocity_bias_m_s",
                    "attitude_noise_rad", "attitude_bias_rad", "rate_noise_rad_s"):  # fmt: skip
            if not getattr(self, key) >= 0.0:
                raise ValueError(f"StateEstimateConfig.{key}={getattr(self, key)} must be >= 0")


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

    def reset(self, envs: Tensor, state: QuadState, generator: torch.Generator) -> None:
        """New episodes in ``envs`` [K] (CPU indices) whose first true state is ``state`` (batch K)."""
        c = self.config
        k = len(envs)
        low, high = c.delay_range_s
        self.delay_s[envs] = low + (high - low) * torch.rand(k, generator=generator)
        self.delay_steps[envs] = delay_steps(self.delay_s[envs], self.physics_dt_s)
        self.position_bias_m[envs] = c.position_bias_m * torch.randn(k, 3, generator=generator)
        self.velocity_bias_m_s[envs] = c.velocity_bias_m_s * torch.randn(k, 3, generator=generator)
        self.attitude_bias_rad[envs] = c.attitude_bias_rad * torch.randn(k, 3, generator=generator)
        self._line.fill(envs.to(self.device), _pack(state))

    def record(self, state: QuadState) -> None:
        """The true states [B] after a physics step."""
        self._line.push(_pack(state))

    def estimate(self, generator: torch.Generator) -> QuadState:
        """What the autopilot reports now: the truth ``delay`` ago, plus bias and noise."""
        c = self.config
        truth = self._line.read(self.delay_steps)
        n = truth.shape[0]
        noise = torch.randn(n, 12, generator=generator).to(self.device)
        dev = self.device
        pos = truth[:, 0:3] + self.position_bias_m.to(dev) + c.position_noise_m * noise[:, 0:3]
        vel = truth[:, 3:6] + self.velocity_bias_m_s.to(dev) + c.velocity_noise_m_s * noise[:, 3:6]
        error = self.attitude_bias_rad.to(dev) + c.attitude_noise_rad * noise[:, 6:9]
        quat = quat_multiply(truth[:, 6:10], quat_from_euler(error[:, 0], error[:, 1], error[:, 2]))
        rates = truth[:, 10:13] + c.rate_noise_rad_s * noise[:, 9:12]
        return QuadState(pos, vel, quat / torch.linalg.vector_norm(quat, dim=-1, keepdim=True), rates)


def _pack(state: QuadState) -> Tensor:
    return torch.cat([state.pos_enu_m, state.vel_enu_m_s, state.quat_enu_flu, state.angvel_body_flu_rad_s], dim=-1)
