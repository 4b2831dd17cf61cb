"""The ranges of a SITL episode's world arguments, checked in one place: by ``cmnav sitl`` before
it starts any process, and by the SITL vehicle itself (``python -m sim.sitl``).  No torch here."""

from __future__ import annotations

SEED_MAX = 2**64 - 1  # world seeds are 64-bit (sim.world.env_seed); numpy's generators refuse negative ones


def check_level_seed(level: int, seed: int) -> None:
    """Raise ValueError naming the option (``--level``, ``--seed``) that is out of range."""
    if isinstance(level, bool) or not isinstance(level, int) or level < 0:
        raise ValueError(f"--level {level} must be an integer >= 0 (the number of obstacles)")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= SEED_MAX:
        raise ValueError(f"--seed {seed} must be an integer in [0, 2**64 - 1]")
