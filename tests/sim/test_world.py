"""World sampling: determinism, curriculum, placement rules."""

from __future__ import annotations

import json
from dataclasses import fields

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.collision import box_signed_distance_m, min_clearance_m
from sim.world import OBSTACLE_LIBRARY_M, WorldBatch, WorldConfig, make_worlds

CONFIG = WorldConfig()
TOL_M = 1e-5  # float32 storage of positions sampled in float64


def assert_worlds_equal(a: WorldBatch, b: WorldBatch) -> None:
    for f in fields(WorldBatch):
        assert torch.equal(getattr(a, f.name).cpu(), getattr(b, f.name).cpu()), f.name


def box_corners_m(world: WorldBatch) -> torch.Tensor:
    """[B, K, 8, 3] world corners of every slot."""
    signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float32)
    local = signs * world.box_half_extent_m.unsqueeze(2)
    c = torch.cos(world.box_yaw_rad).unsqueeze(-1)
    s = torch.sin(world.box_yaw_rad).unsqueeze(-1)
    x, y, z = local.unbind(-1)
    return torch.stack([c * x - s * y, s * x + c * y, z], dim=-1) + world.box_center_m.unsqueeze(2)


def test_same_seed_same_world_and_different_seed_differs() -> None:
    assert_worlds_equal(make_worlds([3, 8, 12], seed=7), make_worlds([3, 8, 12], seed=7))
    a, b = make_worlds(8, seed=7), make_worlds(8, seed=8)
    assert not torch.equal(a.box_center_m, b.box_center_m)
    assert not torch.equal(a.room_size_m, b.room_size_m)


def test_env_does_not_depend_on_batch_size_or_other_levels() -> None:
    big = make_worlds([2, 9, 4, 0], seed=3)
    small = make_worlds([0, 9], seed=3)
    assert big.describe(1) == small.describe(1)
    assert make_worlds(5, seed=3, batch_size=3).describe(2) == make_worlds([1, 1, 5], seed=3).describe(2)


def test_level_k_gives_k_valid_obstacles_and_zero_padding() -> None:
    levels = [0, 1, 5, 6, 13, 26]
    world = make_worlds(levels, seed=11)
    assert world.batch_size == len(levels)
    assert world.num_slots == max(levels)
    assert world.obstacle_count().tolist() == levels
    pad = ~world.box_valid
    assert torch.all(world.box_half_extent_m[pad] == 0) and torch.all(world.box_center_m[pad] == 0)
    # Valid slots come first.
    assert torch.equal(world.box_valid, torch.arange(world.num_slots) < torch.tensor(levels).unsqueeze(1))


def test_panels_only_up_to_level_5_then_whole_library() -> None:
    panel = torch.tensor(OBSTACLE_LIBRARY_M["panel"]) / 2
    library = torch.tensor(list(OBSTACLE_LIBRARY_M.values())) / 2
    low = make_worlds(list(range(6)) * 20, seed=1)
    assert torch.allclose(low.box_half_extent_m[low.box_valid], panel.expand(int(low.box_valid.sum()), 3))
    high = make_worlds([30] * 20, seed=1)
    halves = high.box_half_extent_m[high.box_valid]
    matches = torch.isclose(halves.unsqueeze(1), library.unsqueeze(0)).all(dim=-1)  # [n, library]
    assert torch.all(matches.any(dim=1))
    assert torch.all(matches.any(dim=0)), "every obstacle kind appears over 600 draws"


def check_placement(world: WorldBatch, config: WorldConfig = CONFIG) -> None:
    length, width, height = world.room_size_m.unbind(-1)
    for key, size in (("room_length_range_m", length), ("room_width_range_m", width), ("room_height_range_m", height)):
        lo, hi = getattr(config, key)
        assert torch.all((size >= lo - TOL_M) & (size <= hi + TOL_M)), key

    corners = box_corners_m(world)  # [B, K, 8, 3]
    valid = world.box_valid.unsqueeze(-1)
    room = world.room_size_m.view(-1, 1, 1, 3)
    inside = (corners >= -TOL_M) & (corners <= room + TOL_M)
    assert torch.all(inside.all(dim=(-1, -2)) | ~world.box_valid), "obstacles fully inside the room"
    x = corners[..., 0]
    in_zone = (x >= config.obstacle_x_fraction[0] * length.view(-1, 1, 1) - TOL_M) & (
        x <= config.obstacle_x_fraction[1] * length.view(-1, 1, 1) + TOL_M
    )
    assert torch.all(in_zone | ~valid), "obstacles in the middle of the room"

    margin = config.wall_margin_m
    start, goal = world.start_m, world.goal_m
    assert torch.all(start[:, 0] >= margin - TOL_M)
    assert torch.all(start[:, 0] <= config.start_x_fraction * length - config.start_gap_m + TOL_M)
    assert torch.all(goal[:, 0] >= config.goal_x_fraction * length - TOL_M)
    assert torch.all(goal[:, 0] <= length - config.goal_wall_gap_m + TOL_M)
    for point in (start, goal):
        assert torch.all((point[:, 1] >= margin - TOL_M) & (point[:, 1] <= width - margin + TOL_M))
        assert torch.all((point[:, 2] >= margin - TOL_M) & (point[:, 2] <= height - margin + TOL_M))
        assert torch.all(min_clearance_m(world, point) >= config.start_gap_m - TOL_M)

    if world.num_slots:
        # The column above and below the start (straight take-off from the floor) is clear.
        for fraction in torch.linspace(0.0, 1.0, 11):
            column = start.clone()
            column[:, 2] = fraction * height
            clearance = box_signed_distance_m(world, column).amin(dim=-1)
            assert torch.all(clearance >= config.start_gap_m - TOL_M)


def test_placement_rules_hold_over_many_envs() -> None:
    check_placement(make_worlds([k % 31 for k in range(400)], seed=2024))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**63 - 1), level=st.integers(0, 40))
def test_placement_rules_hold_for_any_seed(seed: int, level: int) -> None:
    check_placement(make_worlds([level, 0, 5], seed=seed))


def test_describe_is_json_and_lists_only_valid_boxes() -> None:
    world = make_worlds([2, 7], seed=5)
    text = json.dumps(world.describe(0))
    desc = json.loads(text)
    assert set(desc) == {"room_size_m", "boxes", "start_m", "goal_m", "texture_seed"}
    assert len(desc["boxes"]) == 2
    assert set(desc["boxes"][0]) == {"center_m", "half_extent_m", "yaw_rad"}
    assert desc["start_m"] == world.start_m[0].tolist()
    assert desc["boxes"][1]["yaw_rad"] == pytest.approx(float(world.box_yaw_rad[0, 1]))


def test_from_descriptions_rebuilds_the_rooms_described() -> None:
    world = make_worlds([0, 2, 7], seed=5)
    rebuilt = WorldBatch.from_descriptions([json.loads(json.dumps(world.describe(i))) for i in range(3)])
    assert rebuilt.num_slots == 7 and rebuilt.obstacle_count().tolist() == [0, 2, 7]
    assert [rebuilt.describe(i) for i in range(3)] == [world.describe(i) for i in range(3)]
    points = torch.rand(3, 3) * world.room_size_m  # the same surfaces, wherever one looks
    torch.testing.assert_close(min_clearance_m(rebuilt, points), min_clearance_m(world, points))
    assert WorldBatch.from_descriptions([world.describe(0)]).num_slots == 1  # an empty room keeps one padding slot


def test_select_and_to() -> None:
    world = make_worlds([1, 2, 3, 4], seed=9)
    one = world.select(2)
    assert one.batch_size == 1 and one.describe(0) == world.describe(2)
    picked = world.select(torch.tensor([3, 0]))
    assert picked.describe(0) == world.describe(3) and picked.describe(1) == world.describe(0)
    assert world.select(slice(1, 3)).batch_size == 2
    assert_worlds_equal(world.to("cpu"), world)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_same_world_on_cuda() -> None:
    on_gpu = make_worlds([0, 6, 20], seed=4, device="cuda")
    assert on_gpu.device.type == "cuda"
    assert_worlds_equal(on_gpu, make_worlds([0, 6, 20], seed=4))


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ValueError, match="levels must be >= 0"):
        make_worlds(-1, seed=0)
    with pytest.raises(ValueError, match="batch_size=3 but 2 levels"):
        make_worlds([1, 2], seed=0, batch_size=3)
    with pytest.raises(ValueError, match="wall_margin_m"):
        make_worlds(1, seed=0, config=WorldConfig(wall_margin_m=3.0))
    with pytest.raises(ValueError, match="obstacle_x_fraction"):
        make_worlds(1, seed=0, config=WorldConfig(obstacle_x_fraction=(0.1, 0.8)))
