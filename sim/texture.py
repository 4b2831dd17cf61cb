"""Procedural surface textures: an albedo in (0, 1] at a point of a surface, deterministic from
the world's texture seed and the surface id.

Each surface gets its own pattern: a base albedo, a coarse and a fine sinusoidal grating (random
orientation, wavelength and phase) and a checker of random tile size, evaluated at the point's
2D coordinates (metres) in the surface's own plane.  Parameters come from an integer hash of
(texture seed, surface id) computed in int64 without overflow, so CPU and CUDA agree bit for bit.

Surface ids: the room's faces are 0..5 (x = 0, x = L, y = 0, y = W, floor z = 0, ceiling z = H);
face f of box slot k (f = 2 * local axis + (1 if on the + side)) is ``6 + 6 * k + f``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

ROOM_SURFACE_COUNT = 6
FACES_PER_BOX = 6

_U32 = 0xFFFFFFFF
# (low, high) ranges of the per-surface parameters.
_BASE_ALBEDO = (0.35, 0.75)
_COARSE_WAVELENGTH_M = (0.8, 3.0)
_COARSE_AMPLITUDE = (0.06, 0.18)
# Wavelengths stay above ~5 px at 5 m (212 px over 87 deg) so gratings do not alias into moire.
_FINE_WAVELENGTH_M = (0.25, 0.6)
_FINE_AMPLITUDE = (0.03, 0.10)
_TILE_SIZE_M = (0.25, 1.0)
_TILE_AMPLITUDE = (0.0, 0.15)
_MIN_ALBEDO = 0.02


def box_surface_id(slot: Tensor, face: Tensor) -> Tensor:
    """Surface id of face(s) 0..5 (2 * local axis + (1 if on the + side)) of box slot(s)."""
    return ROOM_SURFACE_COUNT + FACES_PER_BOX * slot + face


def _hash_u32(x: Tensor) -> Tensor:
    """32-bit integer hash of int64 values in [0, 2^32); every product stays below 2^63."""
    x = (((x >> 16) ^ x) * 0x45D9F3B) & _U32
    x = (((x >> 16) ^ x) * 0x45D9F3B) & _U32
    return (x >> 16) ^ x


def _uniform(key: Tensor, index: int, low: float, high: float) -> Tensor:
    """Parameter ``index`` of the surfaces with hash ``key``, uniform in [low, high), float32."""
    bits = _hash_u32(key ^ ((index + 1) * 0x27D4EB2D & _U32))
    return low + (high - low) * (bits.to(torch.float32) * (1.0 / 2**32))


def surface_albedo(texture_seed: Tensor, surface_id: Tensor, s_m: Tensor, t_m: Tensor) -> Tensor:
    """Albedo in [0.02, 1] (float32) of the given surfaces at in-plane coordinates (s_m, t_m).

    texture_seed and surface_id are int64, s_m and t_m float (metres); all broadcast together.
    """
    key = _hash_u32((texture_seed & _U32) ^ _hash_u32(surface_id & _U32))
    s = s_m.to(torch.float32)
    t = t_m.to(torch.float32)
    albedo = _uniform(key, 0, *_BASE_ALBEDO)
    for octave, (wavelength, amplitude) in enumerate(
        [(_COARSE_WAVELENGTH_M, _COARSE_AMPLITUDE), (_FINE_WAVELENGTH_M, _FINE_AMPLITUDE)]
    ):
        first = 1 + 4 * octave
        theta = _uniform(key, first, 0.0, math.pi)
        phase_arg = (s * torch.cos(theta) + t * torch.sin(theta)) / _uniform(key, first + 1, *wavelength)
        grating = torch.sin(2.0 * math.pi * phase_arg + _uniform(key, first + 2, 0.0, 2.0 * math.pi))
        albedo = albedo + _uniform(key, first + 3, *amplitude) * grating
    tile = _uniform(key, 9, *_TILE_SIZE_M)
    parity = (torch.floor(s / tile) + torch.floor(t / tile)).remainder(2.0)
    albedo = albedo + _uniform(key, 10, *_TILE_AMPLITUDE) * (2.0 * parity - 1.0)
    return albedo.clamp(_MIN_ALBEDO, 1.0)
