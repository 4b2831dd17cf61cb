"""Sphere-vs-world collision against analytic cases."""

from __future__ import annotations

import math

import pytest
import torch

from sim.collision import DEFAULT_VEHICLE_RADIUS_M, collides, min_clearance_m
from sim.world import WorldBatch, make_worlds

R = DEFAULT_VEHICLE_RADIUS_M
EPS = 0.01


def one_box_world(yaw_rad: float = 0.0, valid: bool = True) -> WorldBatch:
    """Room 10 x 6 x 4 m with a panel (half 0.05 x 0.6 x 1.5 m) at (5, 3, 2)."""
    return WorldBatch(
        room_size_m=torch.tensor([[10.0, 6.0, 4.0]]),
        box_center_m=torch.tensor([[[5.0, 3.0, 2.0]]]),
        box_half_extent_m=torch.tensor([[[0.05, 0.6, 1.5]]]),
        box_yaw_rad=torch.tensor([[yaw_rad]]),
        box_valid=torch.tensor([[valid]]),
        start_m=torch.tensor([[1.0, 3.0, 2.0]]),
        goal_m=torch.tensor([[9.5, 3.0, 2.0]]),
        texture_seed=torch.tensor([0]),
    )


def hit(world: WorldBatch, *xyz: float) -> bool:
    return bool(collides(world, torch.tensor([xyz]), R)[0])


def clearance(world: WorldBatch, *xyz: float) -> float:
    return float(min_clearance_m(world, torch.tensor([xyz]))[0])


@pytest.mark.parametrize("yaw_rad", [0.0, math.pi, -math.pi])  # a half turn maps the box onto itself
def test_box_faces(yaw_rad: float) -> None:
    world = one_box_world(yaw_rad)
    front_x = 5.0 - 0.05
    assert hit(world, front_x - R + EPS, 3.0, 2.0) and not hit(world, front_x - R - EPS, 3.0, 2.0)
    assert clearance(world, front_x - 0.5, 3.0, 2.0) == pytest.approx(0.5, abs=1e-5)
    side_y = 3.0 + 0.6
    assert hit(world, 5.0, side_y + R - EPS, 2.0) and not hit(world, 5.0, side_y + R + EPS, 2.0)
    top_z = 2.0 + 1.5
    assert clearance(world, 5.0, 3.0, top_z + 0.15) == pytest.approx(0.15, abs=1e-5)  # ceiling 0.35 m away


def test_box_edges_and_corners_use_euclidean_distance() -> None:
    world = one_box_world()
    # Diagonally off the vertical edge at (4.95, 3.6): distance a * sqrt(2).
    for a, expected in ((0.13, True), (0.15, False)):
        assert hit(world, 4.95 - a, 3.6 + a, 2.0) is expected
    # Off the corner (4.95, 3.6, 3.5) along the diagonal: a * sqrt(3).
    assert clearance(world, 4.95 - 0.1, 3.6 + 0.1, 3.5 + 0.1) == pytest.approx(0.1 * math.sqrt(3), abs=1e-5)


def test_yawed_box() -> None:
    world = one_box_world(math.pi / 2)  # now 1.2 m deep along x, 0.1 m wide along y
    assert clearance(world, 5.0 - 0.6 - 0.3, 3.0, 2.0) == pytest.approx(0.3, abs=1e-5)
    assert clearance(world, 5.0, 3.0 + 0.05 + 0.4, 2.0) == pytest.approx(0.4, abs=1e-5)
    quarter = one_box_world(math.pi / 4)
    # The front face's normal is (cos 45, sin 45); step 0.3 m along the reversed normal from its centre.
    n = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0])
    p = torch.tensor([5.0, 3.0, 2.0]) - (0.05 + 0.3) * n
    assert float(min_clearance_m(quarter, p[None])[0]) == pytest.approx(0.3, abs=1e-5)


def test_inside_a_box_is_negative_clearance_and_a_collision() -> None:
    world = one_box_world()
    assert clearance(world, 5.0, 3.0, 2.0) == pytest.approx(-0.05, abs=1e-6)
    assert hit(world, 5.0, 3.0, 2.0)


def test_walls_floor_ceiling() -> None:
    world = one_box_world(valid=False)
    for point in ((R - EPS, 3.0, 2.0), (10.0 - R + EPS, 3.0, 2.0), (2.0, R - EPS, 2.0), (2.0, 6.0 - R + EPS, 2.0),
                  (2.0, 3.0, R - EPS), (2.0, 3.0, 4.0 - R + EPS), (-1.0, 3.0, 2.0), (2.0, 3.0, 0.0)):
        assert hit(world, *point), point
    for point in ((R + EPS, 3.0, 2.0), (2.0, 6.0 - R - EPS, 2.0), (2.0, 3.0, R + EPS), (2.0, 3.0, 4.0 - R - EPS)):
        assert not hit(world, *point), point
    assert clearance(world, 2.0, 2.5, 0.7) == pytest.approx(0.7, abs=1e-6)


def test_padding_slots_never_collide() -> None:
    world = one_box_world(valid=False)
    assert clearance(world, 5.0, 3.0, 2.0) == pytest.approx(2.0)
    assert not hit(world, 5.0, 3.0, 2.0)
    padded = make_worlds([0, 3], seed=1).select(0)  # K = 3 padding slots, all at the origin with zero size
    assert clearance(padded, 0.5, 0.5, 0.5) == pytest.approx(0.5, abs=1e-6)


def test_batched_equals_per_env() -> None:
    world = make_worlds([0, 4, 9, 17, 25, 6], seed=3)
    gen = torch.Generator().manual_seed(0)
    points = torch.rand(world.batch_size, 3, generator=gen) * world.room_size_m
    batched_clear = min_clearance_m(world, points)
    batched_hit = collides(world, points, 0.5)
    for i in range(world.batch_size):
        single = world.select(i)
        assert float(min_clearance_m(single, points[i : i + 1])[0]) == pytest.approx(float(batched_clear[i]), abs=1e-6)
        assert bool(collides(single, points[i : i + 1], 0.5)[0]) == bool(batched_hit[i])
