"""CPU path of :func:`sim.render.render`: a numba kernel that slab-tests each box only against
the pixels inside its projected screen rectangle (rasterise, then ray-test).

Once per env and frame: the camera rotation; each valid box's camera-to-box rotation, the
camera's position in the box frame and the box's screen rectangle (the bounding rectangle of its
projection, clipped at a plane just in front of the camera, widened by one pixel); each
surface's Lambert shade and texture parameters.  Then, in parallel over env x image row: the
room's six faces for every pixel of the row, the slab test of each box whose rectangle covers
the row over the rectangle's columns only, and the texture and shade of the nearest hit.

Same geometry as :func:`sim.render.reference.render_reference` (float64, slab test in the box's frame,
same tie-breaks) and the same texture arithmetic (float32, :mod:`sim.texture`).  Rays keep a
unit forward component (camera frame C, x forward), so a hit's ray parameter is its z-depth.
Threads: as many as torch is set to use (``torch.set_num_threads``), through numba's OpenMP
layer; like torch's own OpenMP, it does not survive a fork (use the "spawn" start method).
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from ..camera import CameraModel
from ..texture import (
    FACES_PER_BOX,
    GRATING_FIRST_PARAMETER,
    MIN_ALBEDO,
    ROOM_SURFACE_COUNT,
    TILE_AMPLITUDE_PARAMETER,
    TILE_SIZE_PARAMETER,
    surface_parameters,
)
from ..world import WorldBatch
from .reference import AMBIENT_FRACTION, LIGHT_DIR_ENU, RenderOutput

# A box's projection is taken of its part at least this far in front of the camera plane (m):
# only a ray whose whole path through the box is nearer than this is culled wrongly.
_CLIP_FORWARD_M = 1e-6
_ROOM = -1  # best-hit "box slot" of a room face

# Per-surface shading table: base albedo, then per grating cos and sin of its orientation,
# 1 / wavelength (1/m), phase (rad), amplitude; 1 / tile size (1/m), tile amplitude; Lambert
# shade factor.
_GRATING_COLUMNS = 5
_TILE_COLUMN = 1 + 2 * _GRATING_COLUMNS
_SHADE_COLUMN = _TILE_COLUMN + 2
_SURFACE_COLUMNS = _SHADE_COLUMN + 1

_F32 = np.float32
_TWO_PI_F32 = _F32(2.0 * math.pi)
_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi
# Taylor coefficients of sin up to x^13: error below 1e-9 on [-pi/2, pi/2].
_SIN_COEFFICIENTS = tuple((-1.0) ** n / math.factorial(2 * n + 1) for n in range(7))
_S1, _S3, _S5, _S7, _S9, _S11, _S13 = _SIN_COEFFICIENTS
_ZERO_F32, _ONE_F32, _TWO_F32, _HALF_F32, _255_F32 = _F32(0.0), _F32(1.0), _F32(2.0), _F32(0.5), _F32(255.0)
_MIN_ALBEDO_F32 = _F32(MIN_ALBEDO)
_AMBIENT_F32 = _F32(AMBIENT_FRACTION)
_DIFFUSE_F32 = _F32(1.0 - AMBIENT_FRACTION)
_LIGHT_X, _LIGHT_Y, _LIGHT_Z = LIGHT_DIR_ENU
_COARSE, _FINE = GRATING_FIRST_PARAMETER


def render_cpu(
    world: WorldBatch, cam_pos_enu_m: Tensor, cam_quat_enu_flu: Tensor, camera: CameraModel
) -> RenderOutput:
    """Render depth and gray for camera poses cam_pos_enu_m [B, 3] (m, world ENU) and unit
    quaternions cam_quat_enu_flu [B, 4] (camera frame C -> world ENU); all tensors on the CPU."""
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
    batch = world.batch_size
    texture = _texture_table(tuple(world.texture_seed.tolist()), world.num_slots)
    depth_m = torch.empty((batch, camera.height_px, camera.width_px), dtype=torch.float32)
    gray_u8 = torch.empty((batch, camera.height_px, camera.width_px), dtype=torch.uint8)
    _render_kernel(
        _f64(world.room_size_m),
        _f64(world.box_center_m),
        _f64(world.box_half_extent_m),
        _f64(world.box_yaw_rad),
        world.box_valid.contiguous().numpy(),
        _f64(cam_pos_enu_m),
        _f64(cam_quat_enu_flu),
        texture,
        camera.fx_px,
        camera.fy_px,
        camera.cx_px,
        camera.cy_px,
        depth_m.numpy(),
        gray_u8.numpy(),
    )
    return RenderOutput(depth_m=depth_m, gray_u8=gray_u8)


@functools.lru_cache(maxsize=16)
def _texture_table(texture_seeds: tuple[int, ...], slots: int) -> np.ndarray:
    """[B, 6 + 6 * slots, TEXTURE_PARAMETER_COUNT] float32 texture parameters of every surface of
    B worlds (read-only).  Cached: computing them costs more than rendering one frame, and a
    world keeps its textures from frame to frame."""
    surface_ids = torch.arange(ROOM_SURFACE_COUNT + FACES_PER_BOX * slots)
    table = surface_parameters(torch.tensor(texture_seeds).unsqueeze(1), surface_ids).numpy()
    table.flags.writeable = False
    return table


def _f64(t: Tensor) -> np.ndarray:
    return t.detach().to(torch.float64).contiguous().numpy()


@njit(cache=True, error_model="numpy")
def _quat_rotate(q: np.ndarray, v0: float, v1: float, v2: float) -> tuple[float, float, float]:
    """sim.rotations.quat_rotate for one quaternion (w, x, y, z) and one vector (linear in v)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    t0 = 2.0 * (y * v2 - z * v1)
    t1 = 2.0 * (z * v0 - x * v2)
    t2 = 2.0 * (x * v1 - y * v0)
    return (
        v0 + w * t0 + (y * t2 - z * t1),
        v1 + w * t1 + (z * t0 - x * t2),
        v2 + w * t2 + (x * t1 - y * t0),
    )


@njit(cache=True, error_model="numpy")
def _lambert_shade(n0: float, n1: float, n2: float) -> np.float32:
    """Ambient + diffuse factor of a surface with world normal n (float64 dot, float32 result)."""
    lambert = max(0.0, n0 * _LIGHT_X + n1 * _LIGHT_Y + n2 * _LIGHT_Z)
    return _AMBIENT_F32 + _DIFFUSE_F32 * _F32(lambert)


@njit(cache=True, error_model="numpy")
def _setup_env(
    b, box_center_m, box_half_m, box_yaw_rad, box_valid, cam_pos_m, cam_quat, texture,
    fx, fy, cx, cy, width, height, rot, box_rot, box_origin, box_rect, surfaces,
):  # fmt: skip
    """Fill env b's camera rotation, box transforms and rectangles, and surface table."""
    q = cam_quat[b]
    rot[b, 0, 0], rot[b, 1, 0], rot[b, 2, 0] = _quat_rotate(q, 1.0, 0.0, 0.0)
    rot[b, 0, 1], rot[b, 1, 1], rot[b, 2, 1] = _quat_rotate(q, 0.0, 1.0, 0.0)
    rot[b, 0, 2], rot[b, 1, 2], rot[b, 2, 2] = _quat_rotate(q, 0.0, 0.0, 1.0)

    for surface in range(surfaces.shape[1]):
        p = texture[b, surface]
        row = surfaces[b, surface]
        row[0] = p[0]
        for g in range(2):
            first = _COARSE if g == 0 else _FINE
            col = 1 + g * _GRATING_COLUMNS
            row[col] = math.cos(p[first])
            row[col + 1] = math.sin(p[first])
            row[col + 2] = _ONE_F32 / p[first + 1]
            row[col + 3] = p[first + 2]
            row[col + 4] = p[first + 3]
        row[_TILE_COLUMN] = _ONE_F32 / p[TILE_SIZE_PARAMETER]
        row[_TILE_COLUMN + 1] = p[TILE_AMPLITUDE_PARAMETER]
    # Room face 2a + side has normal +e_a on the near side (0), -e_a on the far side (1).
    for face in range(ROOM_SURFACE_COUNT):
        sign = -1.0 if face % 2 else 1.0
        axis = face // 2
        surfaces[b, face, _SHADE_COLUMN] = _lambert_shade(
            sign if axis == 0 else 0.0, sign if axis == 1 else 0.0, sign if axis == 2 else 0.0
        )

    corners = np.empty((8, 3))
    points = np.empty((4, 3))
    rel = np.empty(3)
    for k in range(box_valid.shape[1]):
        box_rect[b, k, 0], box_rect[b, k, 1] = 1, 0  # empty unless visible
        if not box_valid[b, k]:
            continue
        c, s = math.cos(box_yaw_rad[b, k]), math.sin(box_yaw_rad[b, k])
        # World -> box frame is a rotation by -yaw about z.
        for j in range(3):
            box_rot[b, k, 0, j] = c * rot[b, 0, j] + s * rot[b, 1, j]
            box_rot[b, k, 1, j] = -s * rot[b, 0, j] + c * rot[b, 1, j]
            box_rot[b, k, 2, j] = rot[b, 2, j]
        rel0 = cam_pos_m[b, 0] - box_center_m[b, k, 0]
        rel1 = cam_pos_m[b, 1] - box_center_m[b, k, 1]
        box_origin[b, k, 0] = c * rel0 + s * rel1
        box_origin[b, k, 1] = -s * rel0 + c * rel1
        box_origin[b, k, 2] = cam_pos_m[b, 2] - box_center_m[b, k, 2]
        for face in range(FACES_PER_BOX):
            sign = 1.0 if face % 2 else -1.0
            axis = face // 2
            n0 = sign * c if axis == 0 else (-sign * s if axis == 1 else 0.0)
            n1 = sign * s if axis == 0 else (sign * c if axis == 1 else 0.0)
            n2 = sign if axis == 2 else 0.0
            surfaces[b, ROOM_SURFACE_COUNT + FACES_PER_BOX * k + face, _SHADE_COLUMN] = _lambert_shade(n0, n1, n2)

        # Corners in frame C (box frame -> C is the transpose of box_rot), clipped at x = _CLIP_FORWARD_M.
        to_box = box_rot[b, k]
        for i in range(8):
            for a in range(3):
                half = box_half_m[b, k, a]
                rel[a] = (half if (i >> a) & 1 else -half) - box_origin[b, k, a]
            for a in range(3):
                corners[i, a] = to_box[0, a] * rel[0] + to_box[1, a] * rel[1] + to_box[2, a] * rel[2]
        lo_a, hi_a, lo_b, hi_b = np.inf, -np.inf, np.inf, -np.inf
        for i in range(8):
            count = 0
            if corners[i, 0] >= _CLIP_FORWARD_M:
                points[0] = corners[i]
                count = 1
            for a in range(3):  # the edges from corner i to its neighbour along a
                j = i | (1 << a)
                if j == i:
                    continue
                x_i, x_j = corners[i, 0] - _CLIP_FORWARD_M, corners[j, 0] - _CLIP_FORWARD_M
                if (x_i < 0.0) != (x_j < 0.0):
                    f = x_i / (x_i - x_j)
                    points[count] = corners[i] + f * (corners[j] - corners[i])
                    points[count, 0] = _CLIP_FORWARD_M
                    count += 1
            for m in range(count):
                img_a = -points[m, 1] / points[m, 0]  # (u + 0.5 - cx) / fx of the pixel it lies in
                img_b = -points[m, 2] / points[m, 0]
                lo_a, hi_a = min(lo_a, img_a), max(hi_a, img_a)
                lo_b, hi_b = min(lo_b, img_b), max(hi_b, img_b)
        if lo_a > hi_a:
            continue  # wholly behind the camera
        box_rect[b, k, 0] = int(max(math.floor(max(lo_a * fx + cx - 0.5, -2.0)) - 1.0, 0.0))
        box_rect[b, k, 1] = int(min(math.ceil(min(hi_a * fx + cx - 0.5, width + 1.0)) + 1.0, width - 1.0))
        box_rect[b, k, 2] = int(max(math.floor(max(lo_b * fy + cy - 0.5, -2.0)) - 1.0, 0.0))
        box_rect[b, k, 3] = int(min(math.ceil(min(hi_b * fy + cy - 0.5, height + 1.0)) + 1.0, height - 1.0))
        if box_rect[b, k, 2] > box_rect[b, k, 3]:
            box_rect[b, k, 0], box_rect[b, k, 1] = 1, 0


@njit(cache=True, error_model="numpy")
def _sin(x: float) -> float:
    """sin(x) to 1e-9 (float64): whole turns removed, folded into [-pi/2, pi/2], Taylor series.
    Unlike libm's sinf (which would dominate the kernel's time) it vectorises."""
    r = x - np.rint(x * (1.0 / _TWO_PI)) * _TWO_PI
    r = math.copysign(math.pi, r) - r if abs(r) > _HALF_PI else r
    r2 = r * r
    return r * (_S1 + r2 * (_S3 + r2 * (_S5 + r2 * (_S7 + r2 * (_S9 + r2 * (_S11 + r2 * _S13))))))


@njit(cache=True, error_model="numpy")
def _shade_run(surface: np.ndarray, s_m: np.ndarray, t_m: np.ndarray, gray_u8: np.ndarray) -> None:
    """Gray of the pixels of one surface (its row of the shading table) at in-plane coordinates
    s_m, t_m (float32, m): sim.texture.albedo_from_parameters times the shade, in the same float32
    arithmetic except for multiplications by reciprocals and the polynomial sine (phases within
    about 1e-5 rad, far below a gray level).  A straight loop over uniform parameters, so it
    compiles to SIMD."""
    base = surface[0]
    cos1, sin1, inv_wavelength1, phase1, amplitude1 = surface[1], surface[2], surface[3], surface[4], surface[5]
    cos2, sin2, inv_wavelength2, phase2, amplitude2 = surface[6], surface[7], surface[8], surface[9], surface[10]
    inv_tile, tile_amplitude, shade = surface[_TILE_COLUMN], surface[_TILE_COLUMN + 1], surface[_SHADE_COLUMN]
    for i in range(s_m.shape[0]):
        s = s_m[i]
        t = t_m[i]
        albedo = base + amplitude1 * _F32(_sin(_TWO_PI_F32 * ((s * cos1 + t * sin1) * inv_wavelength1) + phase1))
        albedo = albedo + amplitude2 * _F32(_sin(_TWO_PI_F32 * ((s * cos2 + t * sin2) * inv_wavelength2) + phase2))
        parity = np.floor(s * inv_tile) + np.floor(t * inv_tile)
        parity = parity - _TWO_F32 * np.floor(parity * _HALF_F32)
        albedo = albedo + tile_amplitude * (_TWO_F32 * parity - _ONE_F32)
        albedo = min(max(albedo, _MIN_ALBEDO_F32), _ONE_F32)
        gray = np.floor(albedo * shade * _255_F32 + _HALF_F32)
        gray_u8[i] = np.uint8(min(max(gray, _ZERO_F32), _255_F32))


@njit(cache=True, error_model="numpy")
def _slab_run(slot, box_rot, box_origin, half, img_b, img_a, best_t, best_slot, best_face):  # fmt: skip
    """Slab-test box ``slot`` (rotation frame C -> box frame, camera position in the box frame,
    half extents) against the rays (1, -img_a, -img_b) of a run of pixels of one row; where it is
    hit nearer than best_t, make it the best hit (slot, face 2 * axis + (1 if on the + side)).

    Branch-free, so it compiles to SIMD: a ray parallel to a slab gets an infinite reciprocal,
    whose products with the slab's offsets (nonzero unless the camera lies exactly on a face
    plane) put the slab everywhere or nowhere, as the reference's explicit test does.  The first
    axis of the largest entry distance wins ties, as in the reference."""
    r0 = box_rot[0, 0] - img_b * box_rot[0, 2]
    r1 = box_rot[1, 0] - img_b * box_rot[1, 2]
    r2 = box_rot[2, 0] - img_b * box_rot[2, 2]
    c0, c1, c2 = box_rot[0, 1], box_rot[1, 1], box_rot[2, 1]
    lo0, hi0 = -half[0] - box_origin[0], half[0] - box_origin[0]
    lo1, hi1 = -half[1] - box_origin[1], half[1] - box_origin[1]
    lo2, hi2 = -half[2] - box_origin[2], half[2] - box_origin[2]
    for i in range(img_a.shape[0]):
        d0 = r0 - img_a[i] * c0
        d1 = r1 - img_a[i] * c1
        d2 = r2 - img_a[i] * c2
        inv0, inv1, inv2 = 1.0 / d0, 1.0 / d1, 1.0 / d2
        near0, far0 = min(lo0 * inv0, hi0 * inv0), max(lo0 * inv0, hi0 * inv0)
        near1, far1 = min(lo1 * inv1, hi1 * inv1), max(lo1 * inv1, hi1 * inv1)
        near2, far2 = min(lo2 * inv2, hi2 * inv2), max(lo2 * inv2, hi2 * inv2)
        t_near, axis, d_near = near0, 0, d0
        if near1 > t_near:
            t_near, axis, d_near = near1, 1, d1
        if near2 > t_near:
            t_near, axis, d_near = near2, 2, d2
        t_far = min(far0, min(far1, far2))
        hit = (t_near <= t_far) & (t_near > 0.0) & (t_near < best_t[i])
        best_t[i] = t_near if hit else best_t[i]
        best_slot[i] = slot if hit else best_slot[i]
        # Heading + along the axis, the ray enters through the face on the - side.
        best_face[i] = (2 * axis + (0 if d_near > 0.0 else 1)) if hit else best_face[i]


@njit(cache=True, error_model="numpy")
def _setup_frame(
    box_center_m, box_half_m, box_yaw_rad, box_valid, cam_pos_m, cam_quat, texture, fx, fy, cx, cy, width, height
):  # fmt: skip
    """Per-env tables of one frame: camera rotation, box rotations, origins and rectangles, and
    the surface table (see :func:`_setup_env`)."""
    batch, slots = box_valid.shape
    rot = np.empty((batch, 3, 3))  # frame C -> world ENU
    box_rot = np.empty((batch, slots, 3, 3))  # frame C -> box frame
    box_origin = np.empty((batch, slots, 3))  # camera position in the box frame (m)
    box_rect = np.empty((batch, slots, 4), dtype=np.int64)  # u0, u1, v0, v1 inclusive; u0 > u1: none
    surfaces = np.empty((batch, texture.shape[1], _SURFACE_COLUMNS), dtype=np.float32)
    for b in range(batch):
        _setup_env(
            b, box_center_m, box_half_m, box_yaw_rad, box_valid, cam_pos_m, cam_quat, texture,
            fx, fy, cx, cy, width, height, rot, box_rot, box_origin, box_rect, surfaces,
        )  # fmt: skip
    return rot, box_rot, box_origin, box_rect, surfaces


@njit(cache=True, error_model="numpy")
def _render_line(
    line, room_m, box_half_m, cam_pos_m, fy, cy, img_a, rot, box_rot, box_origin, box_rect, surfaces,
    depth_out, gray_out,
):  # fmt: skip
    """Render image row ``line`` of the flattened (env, row) index into depth_out and gray_out."""
    _, height, width = depth_out.shape
    slots = box_rect.shape[1]
    b = line // height
    v = line - b * height
    img_b = (v + 0.5 - cy) / fy
    o0, o1, o2 = cam_pos_m[b, 0], cam_pos_m[b, 1], cam_pos_m[b, 2]
    r = rot[b]
    # World ray of column u: row_d - img_a[u] * r[:, 1] (r times the ray in C).
    row_d0, row_d1, row_d2 = r[0, 0] - img_b * r[0, 2], r[1, 0] - img_b * r[1, 2], r[2, 0] - img_b * r[2, 2]
    best_t = np.empty(width)
    best_slot = np.empty(width, dtype=np.int64)
    best_face = np.empty(width, dtype=np.int64)
    surface_id = np.empty(width, dtype=np.int64)
    s_m = np.empty(width, dtype=np.float32)
    t_m = np.empty(width, dtype=np.float32)

    # Room from inside: along each axis the ray heads towards one face; the nearest wins.
    for u in range(width):
        a_u = img_a[u]
        d = (row_d0 - a_u * r[0, 1], row_d1 - a_u * r[1, 1], row_d2 - a_u * r[2, 1])
        o = (o0, o1, o2)
        t_best = np.inf
        face_best = 0
        for a in range(3):
            if d[a] > 0.0:
                t = (room_m[b, a] - o[a]) / d[a]
                face = 2 * a + 1
            elif d[a] < 0.0:
                t = (0.0 - o[a]) / d[a]
                face = 2 * a
            else:
                continue
            if t < t_best:
                t_best, face_best = t, face
        best_t[u], best_slot[u], best_face[u] = t_best, _ROOM, face_best

    # Boxes, in slot order (ties keep the earlier hit, as in the reference).
    for k in range(slots):
        u0, u1, v0, v1 = box_rect[b, k, 0], box_rect[b, k, 1], box_rect[b, k, 2], box_rect[b, k, 3]
        if u0 > u1 or v < v0 or v > v1:
            continue
        _slab_run(
            k, box_rot[b, k], box_origin[b, k], box_half_m[b, k], img_b, img_a[u0 : u1 + 1],
            best_t[u0 : u1 + 1], best_slot[u0 : u1 + 1], best_face[u0 : u1 + 1],
        )  # fmt: skip

    # In-plane coordinates and surface of each pixel's nearest hit, then texture and shade
    # over each run of pixels on one surface.
    for u in range(width):
        a_u = img_a[u]
        t = best_t[u]
        k = best_slot[u]
        face = best_face[u]
        if k == _ROOM:
            point = (
                o0 + t * (row_d0 - a_u * r[0, 1]),
                o1 + t * (row_d1 - a_u * r[1, 1]),
                o2 + t * (row_d2 - a_u * r[2, 1]),
            )
            surface_id[u] = face
        else:
            m = box_rot[b, k]
            bo = box_origin[b, k]
            point = (
                bo[0] + t * (m[0, 0] - img_b * m[0, 2] - a_u * m[0, 1]),
                bo[1] + t * (m[1, 0] - img_b * m[1, 2] - a_u * m[1, 1]),
                bo[2] + t * (m[2, 0] - img_b * m[2, 2] - a_u * m[2, 1]),
            )
            surface_id[u] = ROOM_SURFACE_COUNT + FACES_PER_BOX * k + face
        axis = face // 2
        if axis == 0:
            s_m[u], t_m[u] = point[1], point[2]
        elif axis == 1:
            s_m[u], t_m[u] = point[2], point[0]
        else:
            s_m[u], t_m[u] = point[0], point[1]
        depth_out[b, v, u] = t
    first = 0
    while first < width:
        end = first + 1
        while end < width and surface_id[end] == surface_id[first]:
            end += 1
        _shade_run(surfaces[b, surface_id[first]], s_m[first:end], t_m[first:end], gray_out[b, v, first:end])
        first = end


@njit(parallel=True, cache=True, error_model="numpy")
def _render_kernel(
    room_m, box_center_m, box_half_m, box_yaw_rad, box_valid, cam_pos_m, cam_quat, texture,
    fx, fy, cx, cy, depth_out, gray_out,
):  # fmt: skip
    """Render every env into depth_out [B, H, W] (m) and gray_out [B, H, W], rows in parallel."""
    batch, height, width = depth_out.shape
    rot, box_rot, box_origin, box_rect, surfaces = _setup_frame(
        box_center_m, box_half_m, box_yaw_rad, box_valid, cam_pos_m, cam_quat, texture,
        fx, fy, cx, cy, width, height,
    )  # fmt: skip
    img_a = (np.arange(width) + 0.5 - cx) / fx  # ray of column u: (1, -img_a[u], -img_b) in C
    for line in prange(batch * height):
        _render_line(
            line, room_m, box_half_m, cam_pos_m, fy, cy, img_a, rot, box_rot, box_origin, box_rect, surfaces,
            depth_out, gray_out,
        )  # fmt: skip

