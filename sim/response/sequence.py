"""The identification command sequence: velocity steps per axis at 1 and 2 m/s, yaw-rate steps,
then a seeded stretch of piecewise-constant commands like the policy's, all in the yaw-only vehicle
frame V (forward, left, up in m/s; yaw rate in rad/s, + = counter-clockwise), sent at the control
rate.  The same sequence flies PX4 and our SITL vehicle, so their responses compare one to one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.contract import CONTROL_PERIOD_S
from runtime.contract.constants import MAX_SPEED_M_S

AXES = ("forward", "left", "up", "yaw_rate")
POLICY_LIKE_SEED = 7
POLICY_LIKE_S = 20.0
# Inclination of the policy-like commands, rad: well inside the contract's pi/4, so the height
# stays within a room-sized band over the stretch.
POLICY_LIKE_MAX_INCLINATION_RAD = 0.35


@dataclass(frozen=True)
class Segment:
    """Hold ``command_v`` (forward, left, up m/s; yaw rate rad/s) for ``duration_s``; ``step_axis``
    names the axis a step identification reads (None: not a step)."""

    duration_s: float
    command_v: tuple[float, float, float, float]
    step_axis: str | None = None


def _step(axis: str, value: float, on_s: float, off_s: float) -> list[Segment]:
    command = [0.0, 0.0, 0.0, 0.0]
    command[AXES.index(axis)] = value
    return [Segment(on_s, tuple(command), axis), Segment(off_s, (0.0, 0.0, 0.0, 0.0), axis)]


def identification_sequence() -> list[Segment]:
    """Steps on and off (each a rising and a falling step), then the policy-like stretch."""
    segments = [Segment(2.0, (0.0, 0.0, 0.0, 0.0))]
    for value in (1.0, 2.0):
        segments += _step("forward", value, 3.5, 3.0)
    for value in (1.0, 2.0):
        segments += _step("left", value, 3.5, 3.0)
    for value in (1.0, -1.0):
        segments += _step("up", value, 2.5, 2.5)
    for value in (0.5, 1.0):
        segments += _step("yaw_rate", value, 3.0, 2.5)
    return segments + policy_like_segments()


def policy_like_segments(seed: int = POLICY_LIKE_SEED, duration_s: float = POLICY_LIKE_S) -> list[Segment]:
    """Commands the policy could send (speed in [0, MAX_SPEED_M_S] along an inclination, no
    lateral part, yaw rate within +-1 rad/s), each held 0.3-1.0 s; the inclination alternates
    sign so the height stays within a band."""
    rng = np.random.default_rng(seed)
    segments, t_s, sign = [], 0.0, 1.0
    while t_s < duration_s:
        hold_s = float(rng.uniform(0.3, 1.0))
        speed = float(rng.uniform(0.0, MAX_SPEED_M_S))
        incl = sign * float(rng.uniform(0.0, POLICY_LIKE_MAX_INCLINATION_RAD))
        sign = -sign
        yaw_rate = float(rng.uniform(-1.0, 1.0))
        segments.append(Segment(hold_s, (speed * math.cos(incl), 0.0, speed * math.sin(incl), yaw_rate)))
        t_s += hold_s
    return segments


def command_schedule(segments: list[Segment]) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """The sequence at the control rate: (t_s [N] from its start, command_v [N, 4]) and the steps
    to identify, ``{t_s, t_end_s, axis, before, after}`` (commanded values on that axis)."""
    times, commands, steps = [], [], []
    t_s = 0.0
    previous = np.zeros(4)
    for segment in segments:
        command = np.asarray(segment.command_v, dtype=np.float64)
        if segment.step_axis is not None:
            axis = AXES.index(segment.step_axis)
            steps.append({"t_s": t_s, "t_end_s": t_s + segment.duration_s, "axis": segment.step_axis,
                          "before": float(previous[axis]), "after": float(command[axis])})  # fmt: skip
        n = int(round(segment.duration_s / CONTROL_PERIOD_S))
        times.extend(t_s + CONTROL_PERIOD_S * np.arange(n))
        commands.extend([command] * n)
        t_s += n * CONTROL_PERIOD_S
        previous = command
    return np.asarray(times), np.asarray(commands).reshape(-1, 4), steps
