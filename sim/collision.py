"""Sphere-vs-world collision: the vehicle is a sphere; the world is the room's six faces plus
yawed boxes.  Positions in world ENU metres."""

from __future__ import annotations

import torch
from torch import Tensor

from .rotations import rotate_about_z
from .world import WorldBatch

DEFAULT_VEHICLE_RADIUS_M = 0.2


def box_signed_distance_m(world: WorldBatch, pos_enu_m: Tensor) -> Tensor:
    """[B, K] signed distance (m) from pos_enu_m [B, 3] to each box slot's surface.

    Positive outside (Euclidean distance to the nearest surface point), negative inside (minus the
    depth below the nearest face); padding slots give +inf.
    """
    local = rotate_about_z(pos_enu_m.unsqueeze(1) - world.box_center_m, -world.box_yaw_rad)
    excess = local.abs() - world.box_half_extent_m  # > 0 along axes where the point is outside
    outside_m = torch.linalg.vector_norm(excess.clamp_min(0.0), dim=-1)
    inside_m = excess.amax(dim=-1).clamp_max(0.0)
    distance = outside_m + inside_m
    return torch.where(world.box_valid, distance, torch.full_like(distance, torch.inf))


def room_signed_distance_m(world: WorldBatch, pos_enu_m: Tensor) -> Tensor:
    """[B] signed distance (m) from pos_enu_m [B, 3] to the nearest room face (negative outside)."""
    return torch.minimum(pos_enu_m, world.room_size_m - pos_enu_m).amin(dim=-1)


def min_clearance_m(world: WorldBatch, pos_enu_m: Tensor) -> Tensor:
    """[B] distance (m) from pos_enu_m [B, 3] to the nearest surface: box, wall, floor or ceiling.

    Negative when the point is inside a box or outside the room.
    """
    room = room_signed_distance_m(world, pos_enu_m)
    if world.num_slots == 0:
        return room
    return torch.minimum(room, box_signed_distance_m(world, pos_enu_m).amin(dim=-1))


def collides(world: WorldBatch, pos_enu_m: Tensor, radius_m: float = DEFAULT_VEHICLE_RADIUS_M) -> Tensor:
    """[B] bool: a sphere of radius_m at pos_enu_m [B, 3] touches or penetrates any surface."""
    return min_clearance_m(world, pos_enu_m) < radius_m
