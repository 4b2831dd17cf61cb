"""Procedural rooms with floating box obstacles, sampled in batches from one seed.

World frame ENU; each room spans x in [0, L] (length: start side at small x, goal side at large
x), y in [0, W], z in [0, H] (floor at z = 0).  Obstacles are boxes yawed about the world z axis;
a box's half extents are along its own axes (x = thickness).  Curriculum level k puts k
obstacles in the room: panels only up to level 5, the whole library above.

Obstacles fill the middle of the room only (their footprint lies in x in
[0.20 L, 0.85 L] by default), so the start region (x < 0.2 L), the column above and below the
start (straight take-off from the floor) and the goal region (x > 0.9 L) are always clear.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import torch
from torch import Tensor

# Obstacle library: full sizes (m) along the box's own x (thickness), y, z axes.
OBSTACLE_LIBRARY_M: dict[str, tuple[float, float, float]] = {
    "panel": (0.1, 1.2, 3.0),
    "rod": (0.1, 0.1, 2.0),
    "plate_small": (0.1, 0.5, 0.5),
    "plate_large": (0.1, 1.0, 1.0),
}
_LIBRARY_SIZES_M = torch.tensor(list(OBSTACLE_LIBRARY_M.values()), dtype=torch.float64)
_PANEL_INDEX = list(OBSTACLE_LIBRARY_M).index("panel")

_SEED_MASK = (1 << 64) - 1


@dataclass(frozen=True)
class WorldConfig:
    """How rooms, obstacles, start and goal are sampled (all distances in metres)."""

    room_length_range_m: tuple[float, float] = (10.0, 12.0)
    room_width_range_m: tuple[float, float] = (5.0, 8.0)
    room_height_range_m: tuple[float, float] = (4.0, 6.0)
    # Obstacle footprints (their axis-aligned extent in x) lie in this fraction range of L.
    obstacle_x_fraction: tuple[float, float] = (0.20, 0.85)
    # Start x lies in [wall_margin_m, start_x_fraction * L - start_gap_m].
    start_x_fraction: float = 0.20
    start_gap_m: float = 0.5
    # Goal x lies in [goal_x_fraction * L, L - goal_wall_gap_m].
    goal_x_fraction: float = 0.90
    goal_wall_gap_m: float = 0.5
    # Start and goal keep at least this from the side walls, floor and ceiling (and the start
    # from the wall behind it).
    wall_margin_m: float = 1.0
    panels_only_max_level: int = 5

    def validate(self) -> None:
        """Raise ValueError naming the key whose value makes a room impossible to sample."""
        for key in ("room_length_range_m", "room_width_range_m", "room_height_range_m"):
            lo, hi = getattr(self, key)
            if not 0.0 < lo <= hi:
                raise ValueError(f"WorldConfig.{key}={(lo, hi)} must satisfy 0 < low <= high")
        lo, hi = self.obstacle_x_fraction
        if not self.start_x_fraction <= lo < hi <= self.goal_x_fraction:
            raise ValueError(
                f"WorldConfig.obstacle_x_fraction={(lo, hi)} must lie within "
                f"[start_x_fraction={self.start_x_fraction}, goal_x_fraction={self.goal_x_fraction}]"
            )
        length_m = self.room_length_range_m[0]
        if self.wall_margin_m > self.start_x_fraction * length_m - self.start_gap_m:
            raise ValueError(
                f"WorldConfig.start_gap_m={self.start_gap_m} / wall_margin_m={self.wall_margin_m} leave no "
                f"room for the start in the first {self.start_x_fraction:.0%} of a {length_m} m room"
            )
        if self.goal_x_fraction * length_m > length_m - self.goal_wall_gap_m:
            raise ValueError(f"WorldConfig.goal_wall_gap_m={self.goal_wall_gap_m} leaves no room for the goal")
        if 2.0 * self.wall_margin_m >= min(self.room_width_range_m[0], self.room_height_range_m[0]):
            raise ValueError(f"WorldConfig.wall_margin_m={self.wall_margin_m} is too large for the smallest room")
        tallest_m = max(size[2] for size in OBSTACLE_LIBRARY_M.values())
        if tallest_m > self.room_height_range_m[0]:
            raise ValueError(f"WorldConfig.room_height_range_m must exceed the tallest obstacle ({tallest_m} m)")


@dataclass
class WorldBatch:
    """B rooms with up to K obstacle slots each; every tensor on one device.

    room_size_m [B, 3] (L, W, H); box_center_m [B, K, 3] world ENU; box_half_extent_m [B, K, 3]
    along the box's own axes; box_yaw_rad [B, K] about world z (counter-clockwise from above);
    box_valid [B, K] bool (padding slots are False, with zero size, and are never hit);
    start_m, goal_m [B, 3] world ENU; texture_seed [B] int64.
    """

    room_size_m: Tensor
    box_center_m: Tensor
    box_half_extent_m: Tensor
    box_yaw_rad: Tensor
    box_valid: Tensor
    start_m: Tensor
    goal_m: Tensor
    texture_seed: Tensor

    @property
    def batch_size(self) -> int:
        return int(self.room_size_m.shape[0])

    @property
    def num_slots(self) -> int:
        """K, the number of obstacle slots per env (valid or padding)."""
        return int(self.box_valid.shape[1])

    @property
    def device(self) -> torch.device:
        return self.room_size_m.device

    def obstacle_count(self) -> Tensor:
        """[B] int64: number of valid obstacles per env (= its curriculum level)."""
        return self.box_valid.sum(dim=1)

    def to(self, device: torch.device | str) -> WorldBatch:
        return WorldBatch(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})

    def select(self, idx: int | slice | Sequence[int] | Tensor) -> WorldBatch:
        """The envs at idx, as a batch (an int index keeps the batch axis: B = 1)."""
        if isinstance(idx, int):
            idx = [idx]
        if not isinstance(idx, (slice, Tensor)):
            idx = torch.as_tensor(idx, dtype=torch.long, device=self.device)
        return WorldBatch(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})

    @classmethod
    def from_descriptions(cls, descriptions: Sequence[dict], device: torch.device | str = "cpu") -> WorldBatch:
        """The batch of the rooms ``describe`` gave (the inverse of it), boxes padded to the most any has."""
        slots = max(1, max(len(d["boxes"]) for d in descriptions))

        def boxes(key: str, empty: object) -> list:
            return [[b[key] for b in d["boxes"]] + [empty] * (slots - len(d["boxes"])) for d in descriptions]

        def tensor(values: object, dtype: torch.dtype = torch.float32) -> Tensor:
            return torch.tensor(values, dtype=dtype, device=device)

        return cls(
            room_size_m=tensor([d["room_size_m"] for d in descriptions]),
            box_center_m=tensor(boxes("center_m", [0.0, 0.0, 0.0])),
            box_half_extent_m=tensor(boxes("half_extent_m", [0.0, 0.0, 0.0])),
            box_yaw_rad=tensor(boxes("yaw_rad", 0.0)),
            box_valid=tensor([[True] * len(d["boxes"]) + [False] * (slots - len(d["boxes"])) for d in descriptions], torch.bool),
            start_m=tensor([d["start_m"] for d in descriptions]),
            goal_m=tensor([d["goal_m"] for d in descriptions]),
            texture_seed=tensor([d["texture_seed"] for d in descriptions], torch.int64),
        )

    def describe(self, i: int) -> dict[str, object]:
        """Env i as a JSON-able dict: room, valid boxes (center, half extents, yaw), start, goal."""
        valid = self.box_valid[i].cpu()
        centers = self.box_center_m[i].cpu()[valid]
        halves = self.box_half_extent_m[i].cpu()[valid]
        yaws = self.box_yaw_rad[i].cpu()[valid]
        return {
            "room_size_m": self.room_size_m[i].cpu().tolist(),
            "boxes": [
                {"center_m": c.tolist(), "half_extent_m": h.tolist(), "yaw_rad": float(y)}
                for c, h, y in zip(centers, halves, yaws)
            ],
            "start_m": self.start_m[i].cpu().tolist(),
            "goal_m": self.goal_m[i].cpu().tolist(),
            "texture_seed": int(self.texture_seed[i]),
        }


def env_seed(seed: int, env_index: int) -> int:
    """The generator seed of env ``env_index`` (SplitMix64 of the pair), so env i of a batch is
    the same world whatever the batch size."""
    z = (seed * 0x9E3779B97F4A7C15 + (env_index + 1) * 0xBF58476D1CE4E5B9) & _SEED_MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _SEED_MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _SEED_MASK
    return z ^ (z >> 31)


def make_worlds(
    levels: Sequence[int] | int,
    seed: int,
    batch_size: int | None = None,
    device: torch.device | str = "cpu",
    config: WorldConfig = WorldConfig(),
) -> WorldBatch:
    """Sample ``batch_size`` rooms; env i has ``levels[i]`` obstacles (or ``levels`` if an int).

    Deterministic: sampled on the CPU from one torch.Generator per env seeded by
    :func:`env_seed` (seed, i), then moved to ``device``, so the same seed gives the same worlds
    on every device and env i does not depend on the batch size.  ``batch_size`` defaults to
    ``len(levels)`` (or 1 for an int level).
    """
    config.validate()
    if isinstance(levels, int):
        level_list = [levels] * (1 if batch_size is None else batch_size)
    else:
        level_list = [int(k) for k in levels]
        if batch_size is not None and batch_size != len(level_list):
            raise ValueError(f"batch_size={batch_size} but {len(level_list)} levels were given; pass one per env")
    if not level_list:
        raise ValueError("make_worlds needs batch_size >= 1")
    if min(level_list) < 0:
        raise ValueError(f"curriculum levels must be >= 0, got {min(level_list)}")
    num_slots = max(level_list)
    envs = [_sample_env(level, env_seed(seed, i), num_slots, config) for i, level in enumerate(level_list)]
    batch = {name: torch.stack([env[name] for env in envs]) for name in envs[0]}
    world = WorldBatch(
        room_size_m=batch["room_size_m"].float(),
        box_center_m=batch["box_center_m"].float(),
        box_half_extent_m=batch["box_half_extent_m"].float(),
        box_yaw_rad=batch["box_yaw_rad"].float(),
        box_valid=batch["box_valid"],
        start_m=batch["start_m"].float(),
        goal_m=batch["goal_m"].float(),
        texture_seed=batch["texture_seed"],
    )
    return world.to(device)


def _uniform(gen: torch.Generator, low: Tensor | float, high: Tensor | float, n: int | None = None) -> Tensor:
    shape = () if n is None else (n,)
    return low + (high - low) * torch.rand(shape, generator=gen, dtype=torch.float64)


def _sample_env(level: int, seed: int, num_slots: int, config: WorldConfig) -> dict[str, Tensor]:
    gen = torch.Generator(device="cpu").manual_seed(seed)
    length_m = _uniform(gen, *config.room_length_range_m)
    width_m = _uniform(gen, *config.room_width_range_m)
    height_m = _uniform(gen, *config.room_height_range_m)

    if level <= config.panels_only_max_level:
        kinds = torch.full((level,), _PANEL_INDEX, dtype=torch.long)
    else:
        kinds = torch.randint(len(OBSTACLE_LIBRARY_M), (level,), generator=gen)
    half_m = _LIBRARY_SIZES_M[kinds] / 2.0
    yaw_rad = _uniform(gen, -math.pi, math.pi, level)
    # Half extents of each yawed box's axis-aligned footprint.
    cos_abs, sin_abs = yaw_rad.cos().abs(), yaw_rad.sin().abs()
    reach_x_m = cos_abs * half_m[:, 0] + sin_abs * half_m[:, 1]
    reach_y_m = sin_abs * half_m[:, 0] + cos_abs * half_m[:, 1]
    x_lo_m = config.obstacle_x_fraction[0] * length_m
    x_hi_m = config.obstacle_x_fraction[1] * length_m
    center_m = torch.stack(
        [
            _uniform(gen, x_lo_m + reach_x_m, x_hi_m - reach_x_m, level),
            _uniform(gen, reach_y_m, width_m - reach_y_m, level),
            _uniform(gen, half_m[:, 2], height_m - half_m[:, 2], level),
        ],
        dim=-1,
    )

    margin_m = config.wall_margin_m
    start_m = torch.stack(
        [
            _uniform(gen, margin_m, config.start_x_fraction * length_m - config.start_gap_m),
            _uniform(gen, margin_m, width_m - margin_m),
            _uniform(gen, margin_m, height_m - margin_m),
        ]
    )
    goal_m = torch.stack(
        [
            _uniform(gen, config.goal_x_fraction * length_m, length_m - config.goal_wall_gap_m),
            _uniform(gen, margin_m, width_m - margin_m),
            _uniform(gen, margin_m, height_m - margin_m),
        ]
    )
    texture_seed = torch.randint(2**31 - 1, (), generator=gen, dtype=torch.int64)

    pad = num_slots - level
    return {
        "room_size_m": torch.stack([length_m, width_m, height_m]),
        "box_center_m": torch.cat([center_m, torch.zeros(pad, 3, dtype=torch.float64)]),
        "box_half_extent_m": torch.cat([half_m, torch.zeros(pad, 3, dtype=torch.float64)]),
        "box_yaw_rad": torch.cat([yaw_rad, torch.zeros(pad, dtype=torch.float64)]),
        "box_valid": torch.arange(num_slots) < level,
        "start_m": start_m,
        "goal_m": goal_m,
        "texture_seed": texture_seed,
    }
