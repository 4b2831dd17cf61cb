"""Per-env delay lines at the physics rate: what a batched sim needs to hold commands and state
estimates back by a delay that differs from env to env (and per axis).

A :class:`DelayLine` keeps the last ``capacity`` samples of a [B, C] signal, one per physics
step.  ``read(delay_steps)`` gives, per env and channel, the sample pushed ``delay_steps`` steps
before the newest (0: the newest).  :func:`delay_steps` turns a delay in seconds into steps with
the rule of :class:`sim.dynamics.CommandDelay`: the newest sample given at or before ``t - delay``,
so a delay line and a CommandDelay stepped at the same dt give the same commands.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

# Slack of the seconds -> steps rule (CommandDelay compares times with 1e-9 s of slack).
_STEP_SLACK = 1e-6


def delay_steps(delay_s: Tensor | float, dt_s: float) -> Tensor:
    """Delay (s, >= 0) -> whole physics steps: ceil(delay / dt), the newest sample at or before
    ``t - delay`` (CommandDelay's rule).  Returns a long tensor of delay_s's shape."""
    delay = torch.as_tensor(delay_s, dtype=torch.float64)
    if bool((delay < 0).any()):
        raise ValueError(f"delays must be >= 0 s, got {delay.min().item()} s")
    return torch.ceil(delay / dt_s - _STEP_SLACK).clamp_min(0).long()


class DelayLine:
    """The last ``capacity`` samples of a [batch, channels] signal (see the module doc).  After
    :meth:`fill` (or a reset of some envs), every past sample of those envs is the fill value:
    before anything was pushed, what the sim started with holds (as CommandDelay holds its first
    command)."""

    def __init__(self, capacity: int, batch_size: int, channels: int, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32) -> None:  # fmt: skip
        if capacity < 1:
            raise ValueError(f"DelayLine capacity={capacity} must be >= 1 (the longest delay in steps + 1)")
        self.capacity = capacity
        self._buffer = torch.zeros(capacity, batch_size, channels, device=device, dtype=dtype)
        self._head = 0  # index of the newest sample

    @staticmethod
    def capacity_for(max_delay_s: float, dt_s: float) -> int:
        """The capacity that holds a delay of up to ``max_delay_s``."""
        return int(delay_steps(max_delay_s, dt_s)) + 1 if math.isfinite(max_delay_s) else 1

    def fill(self, envs: Tensor, value: Tensor) -> None:
        """Every kept sample of ``envs`` [K] (indices) becomes ``value`` [K, C]."""
        self._buffer[:, envs] = value.to(self._buffer.dtype).unsqueeze(0)

    def push(self, value: Tensor) -> None:
        """Append the newest sample [B, C] (the oldest kept one is dropped)."""
        self._head = (self._head + 1) % self.capacity
        self._buffer[self._head] = value.to(self._buffer.dtype)

    def read(self, delay_steps_: Tensor) -> Tensor:
        """[B, C] the sample ``delay_steps_`` steps before the newest, per env ([B] long) or per env
        and channel ([B, C] long); each delay must be < capacity."""
        batch, channels = self._buffer.shape[1:]
        steps = delay_steps_.to(self._buffer.device).long()
        if steps.dim() == 1:
            steps = steps.unsqueeze(-1).expand(batch, channels)
        if bool((steps >= self.capacity).any()) or bool((steps < 0).any()):
            raise ValueError(f"a delay of {int(steps.max())} steps does not fit a DelayLine of capacity {self.capacity}: "
                             f"build it with DelayLine.capacity_for(the longest delay)")  # fmt: skip
        index = (self._head - steps) % self.capacity  # [B, C]
        env = torch.arange(batch, device=steps.device).unsqueeze(-1).expand(batch, channels)
        channel = torch.arange(channels, device=steps.device).unsqueeze(0).expand(batch, channels)
        return self._buffer[index, env, channel]
