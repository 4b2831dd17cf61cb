"""The reference ray caster and the batched torch one (the CUDA path of :func:`sim.render.render`).

The camera must be inside the room (every ray then hits a face, so every depth is valid);
from inside a box, that box is invisible (only faces the ray enters from outside count).

``render_reference`` is the plain ray caster: loops over envs, room faces and boxes, float64
geometry, and slab-tests a box only against the rays through its bounding sphere.
``sim.render.render`` is the fast path, tested equal to it: on the CPU a numba kernel that
slab-tests each box only inside its projected screen rectangle (:mod:`sim.render.cpu`); on other
devices ``render_torch``, batched over envs x rays x boxes at once in float32 torch ops.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor
from torch.nn.functional import one_hot

from ..camera import CameraModel
from ..rotations import quat_rotate, rotate_about_z
from ..texture import box_surface_id, surface_albedo
from ..world import WorldBatch

# Unit vector towards a sun-like light, high and behind the start (x small): faces turned towards
# the start (the far wall, box fronts), the floor and the wall at y = 0 are lit; the others
# get ambient light only.
LIGHT_DIR_ENU = tuple(c / math.sqrt(0.5**2 + 0.3**2 + 0.8**2) for c in (-0.5, 0.3, 0.8))
AMBIENT_FRACTION = 0.4
# Slack on the bounding-sphere test that picks the rays the reference slab-tests against a box.
_CULL_SLACK_M = 1e-6
# Bound on 1 / (ray direction component) in the batched slab test.
_MAX_INVERSE_DIRECTION = 1e12

# How closely the fast paths match render_reference: relative depth error and gray difference
# (levels) allowed on all but MAX_MISMATCH_FRACTION of the pixels (a ray grazing a box edge may hit
# in one and miss in the other).
DEPTH_REL_TOLERANCE = 1e-4
GRAY_TOLERANCE_LEVELS = 1
MAX_MISMATCH_FRACTION = 1e-3


@dataclass
class RenderOutput:
    """depth_m [B, H, W] float32 z-depth (m); gray_u8 [B, H, W] uint8."""

    depth_m: Tensor
    gray_u8: Tensor


@dataclass
class _Hits:
    """Nearest hit per ray, [B, N] (normal [B, N, 3])."""

    distance_m: Tensor
    surface_id: Tensor
    s_m: Tensor
    t_m: Tensor
    normal_enu: Tensor


_HIT_FIELDS = [f.name for f in fields(_Hits)]


def _world_rays(cam_quat_enu_cam: Tensor, camera: CameraModel, dtype: torch.dtype) -> Tensor:
    """[B, N, 3] unit ray directions in world ENU, N = H * W in row-major pixel order."""
    rays_c = camera.ray_directions(cam_quat_enu_cam.device, dtype).reshape(1, -1, 3)
    quat = cam_quat_enu_cam.to(dtype).unsqueeze(1).expand(-1, rays_c.shape[1], -1)
    return quat_rotate(quat, rays_c.expand(quat.shape[0], -1, -1))


def _in_plane_coords(point: Tensor, axis: Tensor) -> tuple[Tensor, Tensor]:
    """The two coordinates of point(s) [..., 3] other than ``axis`` [...], in cyclic order."""
    s = torch.gather(point, -1, ((axis + 1) % 3).unsqueeze(-1)).squeeze(-1)
    t = torch.gather(point, -1, ((axis + 2) % 3).unsqueeze(-1)).squeeze(-1)
    return s, t


def _shade(world: WorldBatch, hits: _Hits) -> Tensor:
    """[B, N] uint8 gray: albedo x (ambient + diffuse x max(0, normal . light))."""
    light = torch.tensor(LIGHT_DIR_ENU, dtype=hits.normal_enu.dtype, device=hits.normal_enu.device)
    lambert = (hits.normal_enu * light).sum(dim=-1).clamp_min(0.0).to(torch.float32)
    albedo = surface_albedo(world.texture_seed.unsqueeze(1), hits.surface_id, hits.s_m, hits.t_m)
    intensity = albedo * (AMBIENT_FRACTION + (1.0 - AMBIENT_FRACTION) * lambert)
    return torch.floor(intensity * 255.0 + 0.5).clamp(0.0, 255.0).to(torch.uint8)


def _output(world: WorldBatch, hits: _Hits, camera: CameraModel) -> RenderOutput:
    batch = hits.distance_m.shape[0]
    z_factor = camera.z_factor(hits.distance_m.device, hits.distance_m.dtype).reshape(1, -1)
    depth = (hits.distance_m * z_factor).to(torch.float32)
    shape = (batch, camera.height_px, camera.width_px)
    return RenderOutput(depth_m=depth.reshape(shape), gray_u8=_shade(world, hits).reshape(shape))


def render_reference(
    world: WorldBatch, cam_pos_enu_m: Tensor, cam_quat_enu_flu: Tensor, camera: CameraModel
) -> RenderOutput:
    """Render depth and gray for camera poses cam_pos_enu_m [B, 3], cam_quat_enu_flu [B, 4]
    (camera frame C -> world ENU).  Plain and obviously correct: per env, per surface, in float64."""
    dtype = torch.float64
    rays = _world_rays(cam_quat_enu_flu, camera, dtype)
    num_rays = rays.shape[1]
    per_env: list[_Hits] = []
    for b in range(world.batch_size):
        origin = cam_pos_enu_m[b].to(dtype)
        d = rays[b]
        best_t = torch.full((num_rays,), torch.inf, dtype=dtype, device=d.device)
        best_id = torch.zeros(num_rays, dtype=torch.long, device=d.device)
        best_s = torch.zeros_like(best_t)
        best_tc = torch.zeros_like(best_t)
        best_normal = torch.zeros_like(d)

        def take(rows: Tensor, t: Tensor, surface_id: Tensor, point: Tensor, axis: Tensor, normal: Tensor) -> None:
            """Make the hits of rays ``rows`` (distance t, surface, point on it, its axis, normal) the best."""
            s_m, t_m = _in_plane_coords(point, axis)
            best_t[rows] = t
            best_id[rows] = surface_id
            best_s[rows] = s_m
            best_tc[rows] = t_m
            best_normal[rows] = normal

        # Room: six planes seen from inside; a ray hits the plane it heads towards.
        room = world.room_size_m[b].to(dtype)
        for axis in range(3):
            for far_side in (0, 1):
                plane = room[axis] if far_side else 0.0
                heading = d[:, axis] > 0 if far_side else d[:, axis] < 0
                t = torch.where(heading, (plane - origin[axis]) / d[:, axis], torch.inf)
                rows = (t < best_t).nonzero().squeeze(-1)
                normal = torch.zeros(rows.shape[0], 3, dtype=dtype, device=d.device)
                normal[:, axis] = -1.0 if far_side else 1.0
                point = origin + t[rows].unsqueeze(-1) * d[rows]
                axis_id = torch.full_like(rows, axis)
                take(rows, t[rows], torch.full_like(rows, 2 * axis + far_side), point, axis_id, normal)

        # Boxes: slab test in each box's frame, for the rays that pass through its bounding sphere.
        for k in range(world.num_slots):
            if not bool(world.box_valid[b, k]):
                continue
            center = world.box_center_m[b, k].to(dtype)
            half = world.box_half_extent_m[b, k].to(dtype)
            yaw = world.box_yaw_rad[b, k].to(dtype)
            to_center = center - origin
            along = d @ to_center
            radius = torch.linalg.vector_norm(half) + _CULL_SLACK_M
            near_sphere = (to_center @ to_center - along * along <= radius * radius) & (along + radius > 0)
            rows = near_sphere.nonzero().squeeze(-1)
            if rows.numel() == 0:
                continue
            origin_l = rotate_about_z(-to_center, -yaw)
            d_l = rotate_about_z(d[rows], -yaw)
            t_near = torch.full((rows.shape[0],), -torch.inf, dtype=dtype, device=d.device)
            t_far = torch.full_like(t_near, torch.inf)
            near_axis = torch.zeros_like(rows)
            for axis in range(3):
                inside_slab = bool(origin_l[axis].abs() <= half[axis])
                parallel = d_l[:, axis] == 0
                t1 = (-half[axis] - origin_l[axis]) / d_l[:, axis]
                t2 = (half[axis] - origin_l[axis]) / d_l[:, axis]
                # A ray parallel to the slab is inside it everywhere or nowhere.
                lo = torch.where(parallel, -torch.inf if inside_slab else torch.inf, torch.minimum(t1, t2))
                hi = torch.where(parallel, torch.inf if inside_slab else -torch.inf, torch.maximum(t1, t2))
                near_axis = torch.where(lo > t_near, axis, near_axis)
                t_near = torch.maximum(t_near, lo)
                t_far = torch.minimum(t_far, hi)
            better = (t_near <= t_far) & (t_near > 0) & (t_near < best_t[rows])
            rows, t_near, near_axis, d_l = rows[better], t_near[better], near_axis[better], d_l[better]
            toward_plus = torch.gather(d_l, 1, near_axis.unsqueeze(-1)).squeeze(-1) > 0
            # Heading + along the axis, the ray enters through the face on the - side, and vice versa.
            normal_l = one_hot(near_axis, 3).to(dtype) * torch.where(toward_plus, -1.0, 1.0).unsqueeze(-1)
            surface_id = box_surface_id(torch.full_like(rows, k), 2 * near_axis + (~toward_plus).long())
            point_l = origin_l + t_near.unsqueeze(-1) * d_l
            take(rows, t_near, surface_id, point_l, near_axis, rotate_about_z(normal_l, yaw))
        per_env.append(_Hits(best_t, best_id, best_s, best_tc, best_normal))

    hits = _Hits(*(torch.stack([getattr(h, name) for h in per_env]) for name in _HIT_FIELDS))
    return _output(world, hits, camera)


def render_torch(
    world: WorldBatch,
    cam_pos_enu_m: Tensor,
    cam_quat_enu_flu: Tensor,
    camera: CameraModel,
    max_chunk_elements: int = 1 << 24,
) -> RenderOutput:
    """Same as :func:`render_reference`, batched over envs x rays x boxes in float32 torch ops on
    the world's device (the CUDA path of :func:`sim.render.render`).  Envs are processed in chunks of at most
    ``max_chunk_elements`` ray-box pairs to bound memory."""
    rays = _world_rays(cam_quat_enu_flu, camera, torch.float32)
    pairs_per_env = rays.shape[1] * max(world.num_slots, 1)
    chunk = max(1, max_chunk_elements // pairs_per_env)
    parts = [
        _cast_batched(world.select(slice(i, i + chunk)), cam_pos_enu_m[i : i + chunk].float(), rays[i : i + chunk])
        for i in range(0, world.batch_size, chunk)
    ]
    hits = _Hits(*(torch.cat([getattr(h, name) for h in parts]) for name in _HIT_FIELDS))
    return _output(world, hits, camera)


def _safe_reciprocal(d: Tensor) -> Tensor:
    """1 / d with +-inf (d = +-0) clamped to +-1e12: as if d were nudged off zero, never 0 * inf."""
    return torch.reciprocal(d).clamp(-_MAX_INVERSE_DIRECTION, _MAX_INVERSE_DIRECTION)


def _cast_batched(world: WorldBatch, origin: Tensor, d: Tensor) -> _Hits:
    """Nearest hits of rays d [B, N, 3] (world ENU, unit) from origin [B, 3]."""
    # Room from inside: along each axis the ray exits through the face it heads towards.
    o = origin.unsqueeze(1)
    far_side = d > 0
    gap_m = torch.where(far_side, world.room_size_m.unsqueeze(1) - o, o).clamp_min(0.0)
    t_axes = gap_m / d.abs().clamp_min(1.0 / _MAX_INVERSE_DIRECTION)  # ~inf along axes the ray is parallel to
    t_room, axis_room = t_axes.min(dim=-1)
    far = torch.gather(far_side, -1, axis_room.unsqueeze(-1)).squeeze(-1)
    normal_room = -one_hot(axis_room, 3).to(d.dtype) * torch.where(far, 1.0, -1.0).unsqueeze(-1)
    s_room, t_coord_room = _in_plane_coords(o + t_room.unsqueeze(-1) * d, axis_room)
    hits = _Hits(t_room, 2 * axis_room + far.long(), s_room, t_coord_room, normal_room)
    if world.num_slots == 0:
        return hits

    # Boxes: slab test in every box frame, [B, N, K] per quantity.  The world z axis is every
    # box's z axis, so z needs no rotation.
    cos_yaw = torch.cos(world.box_yaw_rad).unsqueeze(1)
    sin_yaw = torch.sin(world.box_yaw_rad).unsqueeze(1)
    origin_l = rotate_about_z(o - world.box_center_m, -world.box_yaw_rad).unsqueeze(1)  # [B, 1, K, 3]
    dx, dy, dz = (d[..., i].unsqueeze(-1) for i in range(3))
    d_l = (cos_yaw * dx + sin_yaw * dy, cos_yaw * dy - sin_yaw * dx, dz)
    half = world.box_half_extent_m.unsqueeze(1)

    def slab(axis: int) -> tuple[Tensor, Tensor]:
        """Entry and exit distances of every ray through every box's slab along ``axis``."""
        inv = _safe_reciprocal(d_l[axis])
        mid = -origin_l[..., axis] * inv  # where the ray crosses the slab's mid-plane
        spread = half[..., axis] * inv.abs()
        return mid - spread, mid + spread

    t_near, t_far = slab(0)
    near_axis = torch.zeros(t_near.shape, dtype=torch.long, device=t_near.device)
    for axis in (1, 2):
        lo, hi = slab(axis)
        near_axis = torch.where(lo > t_near, axis, near_axis)  # ties go to the first axis
        t_near, t_far = torch.maximum(t_near, lo), torch.minimum(t_far, hi)
    hit = world.box_valid.unsqueeze(1) & (t_near <= t_far) & (t_near > 0)
    t_box, slot = torch.where(hit, t_near, torch.inf).min(dim=-1)  # [B, N]
    box_wins = t_box < t_room

    pick = slot.unsqueeze(-1)
    axis_box = torch.gather(near_axis, -1, pick).squeeze(-1)
    d_box = torch.stack([torch.gather(d_l[0], -1, pick), torch.gather(d_l[1], -1, pick), dz], dim=-1).squeeze(-2)
    o_box = torch.gather(origin_l.squeeze(1), 1, slot.unsqueeze(-1).expand(-1, -1, 3))
    yaw_box = torch.gather(world.box_yaw_rad, 1, slot)
    d_on_axis = torch.gather(d_box, -1, axis_box.unsqueeze(-1)).squeeze(-1)
    toward_plus = d_on_axis > 0
    normal_l = one_hot(axis_box, 3).to(d.dtype) * torch.where(toward_plus, -1.0, 1.0).unsqueeze(-1)
    surface_box = box_surface_id(slot, 2 * axis_box + (~toward_plus).long())
    s_box, t_coord_box = _in_plane_coords(o_box + t_box.unsqueeze(-1) * d_box, axis_box)

    wins3 = box_wins.unsqueeze(-1)
    return _Hits(
        distance_m=torch.where(box_wins, t_box, t_room),
        surface_id=torch.where(box_wins, surface_box, hits.surface_id),
        s_m=torch.where(box_wins, s_box, s_room),
        t_m=torch.where(box_wins, t_coord_box, t_coord_room),
        normal_enu=torch.where(wins3, rotate_about_z(normal_l, yaw_box), normal_room),
    )
