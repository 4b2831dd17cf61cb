"""Small statistics shared by the evaluations and the SITL campaign script (no torch)."""

from __future__ import annotations

import math


def wilson_interval(successes: int, trials: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval (95 % at z = 1.96) of a success rate ``successes / trials``, as
    fractions in [0, 1]; (nan, nan) for no trials."""
    if trials == 0:
        return float("nan"), float("nan")
    if not 0 <= successes <= trials:
        raise ValueError(f"successes={successes} must lie in [0, trials={trials}]")
    p, d = successes / trials, 1 + z * z / trials
    centre = (p + z * z / (2 * trials)) / d
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / d
    return max(centre - half, 0.0), min(centre + half, 1.0)
