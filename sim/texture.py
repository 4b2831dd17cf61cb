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
MIN_ALBEDO = 0.02


def box_surface_id(slot: Tensor, face: Tensor) -> Tensor:
    """Surface id of face(s) 0..5 (2 * local axis + (1 if on the + side)) of box slot(s)."""
    return ROOM_SURFACE_COUNT + FACES_PER_BOX * slot + face


# Per-surface texture parameters, in the order of TEXTURE_PARAMETER_RANGES (low, high):
# base albedo; coarse grating orientation (rad), wavelength (m), phase (rad), amplitude; the
# same four for the fine grating; checker tile size (m) and amplitude.
TEXTURE_PARAMETER_RANGES: tuple[tuple[float, float], ...] = (
    _BASE_ALBEDO,
    (0.0, math.pi),
    _COARSE_WAVELENGTH_M,
    (0.0, 2.0 * math.pi),
    _COARSE_AMPLITUDE,
    (0.0, math.pi),
    _FINE_WAVELENGTH_M,
    (0.0, 2.0 * math.pi),
    _FINE_AMPLITUDE,
    _TILE_SIZE_M,
    _TILE_AMPLITUDE,
)
TEXTURE_PARAMETER_COUNT = len(TEXTURE_PARAMETER_RANGES)
# Index of the first of a grating's four parameters (orientation, wavelength, phase, amplitude).
GRATING_FIRST_PARAMETER = (1, 5)
TILE_SIZE_PARAMETER = 9
TILE_AMPLITUDE_PARAMETER = 10


def _hash_u32(x: Tensor) -> Tensor:
    """32-bit integer hash of int64 values in [0, 2^32); every product stays below 2^63."""
    x = (((x >> 16) ^ x) * 0x45D9F3B) & _U32
    x = (((x >> 16) ^ x) * 0x45D9F3B) & _U32
    return (x >> 16) ^ x


def surface_parameters(texture_seed: Tensor, surface_id: Tensor) -> Tensor:
    """[..., TEXTURE_PARAMETER_COUNT] float32 texture parameters of the given surfaces.

    texture_seed and surface_id are int64 and broadcast together; parameter i is uniform in
    TEXTURE_PARAMETER_RANGES[i] (float32 arithmetic, identical on every device).
    """
    key = _hash_u32((texture_seed & _U32) ^ _hash_u32(surface_id & _U32)).unsqueeze(-1)
    index = torch.arange(TEXTURE_PARAMETER_COUNT, dtype=torch.int64, device=key.device)
    bits = _hash_u32(key ^ ((index + 1) * 0x27D4EB2D & _U32))
    low = torch.tensor([r[0] for r in TEXTURE_PARAMETER_RANGES], dtype=torch.float32, device=key.device)
    span = torch.tensor([r[1] - r[0] for r in TEXTURE_PARAMETER_RANGES], dtype=torch.float32, device=key.device)
    return low + span * (bits.to(torch.float32) * (1.0 / 2**32))


def albedo_from_parameters(parameters: Tensor, s_m: Tensor, t_m: Tensor) -> Tensor:
    """Albedo in [MIN_ALBEDO, 1] (float32) at in-plane coordinates (s_m, t_m) (metres) of the
    surfaces with ``parameters`` [..., TEXTURE_PARAMETER_COUNT] (from :func:`surface_parameters`)."""
    s = s_m.to(torch.float32)
    t = t_m.to(torch.float32)
    p = parameters.unbind(-1)
    albedo = p[0]
    for first in GRATING_FIRST_PARAMETER:
        theta, wavelength, phase, amplitude = p[first : first + 4]
        phase_arg = (s * torch.cos(theta) + t * torch.sin(theta)) / wavelength
        albedo = albedo + amplitude * torch.sin(2.0 * math.pi * phase_arg + phase)
    tile = p[TILE_SIZE_PARAMETER]
    parity = (torch.floor(s / tile) + torch.floor(t / tile)).remainder(2.0)
    albedo = albedo + p[TILE_AMPLITUDE_PARAMETER] * (2.0 * parity - 1.0)
    return albedo.clamp(MIN_ALBEDO, 1.0)


def surface_albedo(texture_seed: Tensor, surface_id: Tensor, s_m: Tensor, t_m: Tensor) -> Tensor:
    """Albedo in [MIN_ALBEDO, 1] (float32) of the given surfaces at in-plane coordinates (s_m, t_m).

    texture_seed and surface_id are int64, s_m and t_m float (metres); all broadcast together.
    """
    return albedo_from_parameters(surface_parameters(texture_seed, surface_id), s_m, t_m)
