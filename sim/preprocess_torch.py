"""Batched torch twin of ``runtime.contract.images.preprocess_gray`` / ``preprocess_depth``.

gray: uint8 [B, H, W] -> float32 [B, 224, 224] in [0, 1]: bilinear (half-pixel centres, no
antialias, like cv2 INTER_LINEAR), rounded to whole gray levels as cv2 does for uint8 images.
cv2 computes with 11-bit fixed-point weights, so a pixel may differ by one gray level (1/255).

depth: metres float [B, H, W] (0 / NaN / inf / negative = invalid) -> float32 [B, 224, 224]:
invalid set to 0, resized with centre-aligned nearest neighbour ('nearest-exact'), then
d / DEPTH_MAX_M clipped to [0, 1] and invalid = DEPTH_INVALID_VALUE.  Equal to the numpy
function whenever no output pixel centre falls exactly on a boundary between two source pixels,
which for a 224 px output happens only when the input side is a multiple of 64 px (not the sim's
212 x 120 nor the D455's 848 x 480); on such ties cv2 and torch may take different neighbours.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from runtime.contract.constants import DEPTH_INVALID_VALUE, DEPTH_MAX_M, IMAGE_SIZE_PX
from runtime.contract.images import ImageContractError


def preprocess_gray_batch(gray_u8: Tensor) -> Tensor:
    """uint8 [B, H, W] -> float32 [B, 224, 224] in [0, 1] (on the input's device)."""
    if gray_u8.ndim != 3 or gray_u8.dtype != torch.uint8 or min(gray_u8.shape[1:]) < 2:
        raise ImageContractError(
            f"expected gray uint8 images of shape [B, H, W], got {gray_u8.dtype} {tuple(gray_u8.shape)}"
        )
    resized = F.interpolate(
        gray_u8.unsqueeze(1).to(torch.float32),
        size=(IMAGE_SIZE_PX, IMAGE_SIZE_PX),
        mode="bilinear",
        align_corners=False,
        antialias=False,
    ).squeeze(1)
    return torch.round(resized).clamp(0.0, 255.0) * (1.0 / 255.0)


def depth_invalid_mask_batch(depth_m: Tensor) -> Tensor:
    """True where a raw depth pixel is invalid (0, negative, NaN or inf)."""
    return ~torch.isfinite(depth_m) | (depth_m <= 0.0)


def preprocess_depth_batch(depth_m: Tensor) -> Tensor:
    """Depth (m) float [B, H, W] -> float32 [B, 224, 224] normalised by DEPTH_MAX_M, invalid = 0."""
    if depth_m.ndim != 3 or not torch.is_floating_point(depth_m) or min(depth_m.shape[1:]) < 2:
        raise ImageContractError(
            f"expected float depth images in metres of shape [B, H, W], got {depth_m.dtype} {tuple(depth_m.shape)}"
        )
    depth = depth_m.to(torch.float32)
    depth = torch.where(depth_invalid_mask_batch(depth), torch.zeros_like(depth), depth)
    resized = F.interpolate(depth.unsqueeze(1), size=(IMAGE_SIZE_PX, IMAGE_SIZE_PX), mode="nearest-exact").squeeze(1)
    normalised = torch.clamp(resized * (1.0 / DEPTH_MAX_M), 0.0, 1.0)
    return torch.where(resized <= 0.0, torch.full_like(normalised, DEPTH_INVALID_VALUE), normalised)
