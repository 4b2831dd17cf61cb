"""The D455's IR dot projector: its pattern, and the light it throws on what each imager sees.

The pattern is fixed in the projector's image plane: a square grid of ``dot_pitch_px`` (in
imager pixels: the projector is modelled with the imager's focal length), each cell holding, with
probability ``dot_fill``, one Gaussian dot of radius ``dot_sigma_px`` at a hashed position with a
hashed brightness in [0.5, 1].  A surface point is lit when the projector sees it (no nearer
surface in the projector's own depth render, the shadow map) and inside its field of view; its
irradiance is ``projector_electrons_at_1m x pattern / range^2`` with range the point's distance
(m) from the projector.  Each imager sees the dots painted on the surfaces from its own viewpoint,
so matching them gives depth where the scene has no texture.

The pattern is tabulated once (numba) and read bilinearly by a numba kernel parallel over
image rows: evaluating it per sample costs more than rendering the images.
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
from .config import StereoConfig

PATTERN_SEED = 455  # the projector's own pattern (every unit has one, fixed)
# A point is lit when it is no farther from the projector than the shadow map's surface plus
# this slack (relative, and absolute in metres): the two renders sample a surface at different points.
_SHADOW_SLACK_REL = 2e-3
_SHADOW_SLACK_M = 5e-3
_U32 = np.uint64(0xFFFFFFFF)


@njit(cache=True, inline="always")
def _hash_u32(x: np.uint64) -> np.uint64:
    x = (((x >> np.uint64(16)) ^ x) * np.uint64(0x45D9F3B)) & _U32
    x = (((x >> np.uint64(16)) ^ x) * np.uint64(0x45D9F3B)) & _U32
    return (x >> np.uint64(16)) ^ x


@njit(cache=True, inline="always")
def _unit(key: np.uint64, salt: int) -> float:
    """Uniform [0, 1) from a key and a salt."""
    return float(_hash_u32(key ^ ((np.uint64(salt) * np.uint64(0x27D4EB2D)) & _U32))) * (1.0 / 4294967296.0)


@njit(cache=True)
def _pattern(u_px: float, v_px: float, pitch: float, inv_two_var: float, fill: float, seed: int) -> float:
    """The pattern (peak about 1) at projector image coordinates (pixel edges at integers)."""
    gu, gv = u_px / pitch, v_px / pitch
    cu0, cv0 = int(math.floor(gu)), int(math.floor(gv))
    total = 0.0
    for du in range(-1, 2):
        for dv in range(-1, 2):
            cu, cv = cu0 + du, cv0 + dv
            key = _hash_u32(np.uint64(((cu & 0xFFFF) << 16) | (cv & 0xFFFF)) ^ np.uint64(seed))
            if _unit(key, 1) >= fill:
                continue
            centre_u = cu + 0.15 + 0.7 * _unit(key, 2)
            centre_v = cv + 0.15 + 0.7 * _unit(key, 3)
            dist2 = ((gu - centre_u) ** 2 + (gv - centre_v) ** 2) * (pitch * pitch)
            total += (0.5 + 0.5 * _unit(key, 4)) * math.exp(-dist2 * inv_two_var)
    return total


# The pattern is tabulated once per config at this many texels per projector pixel and read
# bilinearly (a dot of radius 0.45 px spans about 4 texels: interpolation error below 1 % of a dot's peak).
TEXELS_PER_PX = 4


@njit(parallel=True, cache=True)
def _tabulate(height, width, texels, pitch, inv_two_var, fill, seed, out):
    for i in prange(height):
        for j in range(width):
            out[i, j] = _pattern(j / texels, i / texels, pitch, inv_two_var, fill, seed)


@functools.lru_cache(maxsize=4)
def pattern_table(config: StereoConfig) -> np.ndarray:
    """[Hp x TEXELS_PER_PX + 1, Wp x TEXELS_PER_PX + 1] float32 pattern at texel corners j / TEXELS_PER_PX
    (projector pixels) over the projector's image (read-only)."""
    projector = config.projector_camera
    table = np.empty((projector.height_px * TEXELS_PER_PX + 1, projector.width_px * TEXELS_PER_PX + 1), dtype=np.float32)
    _tabulate(table.shape[0], table.shape[1], TEXELS_PER_PX, config.dot_pitch_px, 1.0 / (2.0 * config.dot_sigma_px**2),
              config.dot_fill, PATTERN_SEED, table)  # fmt: skip
    table.flags.writeable = False
    return table


@njit(parallel=True, cache=True)
def _irradiance_kernel(depth, fx, cx, cy, imager_y_m, shadow, pfx, pcx, pcy, table, peak_e, out):  # fmt: skip
    batch, height, width = depth.shape
    p_height, p_width = shadow.shape[1], shadow.shape[2]
    texels = (table.shape[1] - 1) // p_width
    for line in prange(batch * height):
        b = line // height
        v = line - b * height
        down = (v + 0.5 - cy) / fx
        for u in range(width):
            z = max(depth[b, v, u], 1e-3)
            right_m = (u + 0.5 - cx) / fx * z - imager_y_m
            down_m = down * z
            u_p = right_m / z * pfx + pcx
            v_p = down_m / z * pfx + pcy
            value = 0.0
            if 0.0 <= u_p < p_width and 0.0 <= v_p < p_height:
                if z <= shadow[b, int(v_p), int(u_p)] * (1.0 + _SHADOW_SLACK_REL) + _SHADOW_SLACK_M:
                    tu, tv = u_p * texels, v_p * texels
                    i, j = int(tv), int(tu)
                    fu, fv = tu - j, tv - i
                    pattern = ((1.0 - fv) * ((1.0 - fu) * table[i, j] + fu * table[i, j + 1])
                               + fv * ((1.0 - fu) * table[i + 1, j] + fu * table[i + 1, j + 1]))  # fmt: skip
                    range2 = z * z + right_m * right_m + down_m * down_m
                    value = peak_e * pattern / range2
            out[b, v, u] = value


def projector_irradiance(depth_m: Tensor, camera: CameraModel, imager_y_from_projector_m: float,
                         shadow_depth_m: Tensor, projector: CameraModel, config: StereoConfig) -> Tensor:  # fmt: skip
    """[B, H, W] float32 projector light (photo-electrons on a reflectance-1 surface) at each pixel's
    surface.  depth_m [B, H, W]: the imager's z-depth (m) through ``camera``; the imager sits
    ``imager_y_from_projector_m`` along +y_C from the projector, axes parallel; shadow_depth_m
    [B, Hp, Wp]: z-depth rendered from the projector through ``projector`` (same focal length)."""
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
    depth = depth_m.detach().cpu().to(torch.float32).contiguous().numpy()
    shadow = shadow_depth_m.detach().cpu().to(torch.float32).contiguous().numpy()
    out = np.empty(depth.shape, dtype=np.float32)
    _irradiance_kernel(depth, camera.fx_px, camera.cx_px, camera.cy_px, imager_y_from_projector_m, shadow,
                       projector.fx_px, projector.cx_px, projector.cy_px, pattern_table(config),
                       config.projector_electrons_at_1m, out)  # fmt: skip
    return torch.from_numpy(out)
