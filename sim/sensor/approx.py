"""A parametric stand-in for the simulated D455 (:mod:`sim.sensor.stereo`), cheap enough to train
with: the stereo path costs ~40 ms a frame on one core, this one ~3 ms (`cmnav bench train`, the
field at 16 envs: 72 env-steps/s against 24, the encoder then the largest share).

From the rendered depth and gray image at any camera's resolution:

- the minimum range, the occlusion shadow (a pixel the right imager cannot see: a nearer surface
  to its right shifts over it, ``u - d(u)``, exact from the depth map and the baseline) and the
  threshold filter's maximum range, as geometry;
- the loss of the remaining pixels, a logistic regression per projector state on cues the rendered
  images carry (log range, below the minimum range, occluded, log local gray texture, gray level,
  relative depth jump, grazing angle), fitted to the stereo path's own masks on `cmnav dataset
  --depth stereo` views, and drawn in blobs as matching fails in regions;
- the range error of what is kept: relative, ``noise_rel_per_m x z`` (the z^2 law) plus a floor,
  from a Student-t (heavy tails: the stereo path's 95th percentile is ~3.5 of its robust sigma),
  smooth over the subpixel fit's window.

Its error against the stereo path is measured by ``python -m bench.stereo_approx DATASET`` and
stated in docs/sensor.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from runtime.contract.constants import DEPTH_INVALID_VALUE

from .config import D455_BASELINE_M

# The loss model's cues, in the order of the weights below.
CUES = ("bias", "log_range", "below_min_range", "occluded", "log_texture", "gray_per_100", "depth_jump", "log1p_grazing")


@dataclass(frozen=True)
class StereoApproxConfig:
    """The stand-in's numbers.  ``loss_weights_*``: the logistic weights of ``CUES``, fitted by
    ``python -m bench.stereo_approx runs/data/sim-stereo8k --fit`` (the train split of 600 views,
    2026-12-02); the rest set by the same tool's comparison (docs/sensor.md)."""

    projector_on: bool = True
    baseline_m: float = D455_BASELINE_M
    min_range_m: float = 0.53  # the stereo path's disparity search reaches D455_MIN_RANGE_M at 424 px: 0.53 m
    max_range_m: float = 20.0
    occlusion_tolerance_px: float = 0.5  # at 424 px width; scaled to the camera's
    texture_window_px: int = 7  # at 212 px width
    jump_window_px: int = 5
    loss_weights_projector_on: tuple[float, ...] = (-1.111, 0.064, 2.552, 2.05, -0.273, -0.419, 0.245, -0.123)
    loss_weights_projector_off: tuple[float, ...] = (3.166, -0.354, -0.875, 1.056, -1.436, 0.349, -0.398, -0.011)
    # How far lost regions extend (px at 212 px width): the stereo masks' own reach.
    loss_blob_px_projector_on: float = 24.0
    loss_blob_px_projector_off: float = 10.0
    # The relative range error: scale x a Student-t (heavy tails: wrong matches); the scale is
    # noise_rel_per_m x z (the z^2 law) plus, without the projector, passive matching's floor.
    noise_rel_per_m: float = 0.0026
    noise_rel_floor_projector_off: float = 0.022
    noise_dof_projector_on: int = 2
    noise_dof_projector_off: int = 2
    noise_rel_max: float = 0.5  # a match farther off than this is not a depth any filter would keep
    noise_blob_px: float = 4.0  # at 212 px width: the subpixel fit's window

    def weights(self) -> tuple[float, ...]:
        return self.loss_weights_projector_on if self.projector_on else self.loss_weights_projector_off


def loss_cues(depth_m: Tensor, gray_u8: Tensor, fx_px: float, config: StereoApproxConfig) -> Tensor:
    """[B, len(CUES), H, W] the loss model's cues of rendered depth [B, H, W] (m) and gray [B, H, W]."""
    depth = depth_m.float().clamp_min(1e-3)
    width = depth.shape[-1]
    scale = width / 212.0
    texture_px = max(3, int(config.texture_window_px * scale) | 1)  # odd, as at 212 px
    jump_px = max(3, int(config.jump_window_px * scale) | 1)
    gray = gray_u8.float().unsqueeze(1)
    mean = F.avg_pool2d(gray, texture_px, 1, texture_px // 2, count_include_pad=False)
    mean_sq = F.avg_pool2d(gray * gray, texture_px, 1, texture_px // 2, count_include_pad=False)
    texture = (mean_sq - mean * mean).clamp_min(0.0).sqrt().squeeze(1)
    d4 = depth.unsqueeze(1)
    jump = (F.max_pool2d(d4, jump_px, 1, jump_px // 2) + F.max_pool2d(-d4, jump_px, 1, jump_px // 2)).squeeze(1) / depth
    grad_v, grad_u = torch.gradient(depth, dim=(1, 2))
    grazing = torch.sqrt(grad_u**2 + grad_v**2) * fx_px / depth
    occluded = occlusion_mask(depth, fx_px, config)
    return torch.stack([
        torch.ones_like(depth), depth.clamp(0.1, 30.0).log(), (depth < config.min_range_m).float(), occluded.float(),
        (texture + 0.5).log(), gray.squeeze(1) / 100.0, jump.clamp(0.0, 1.0), grazing.log1p(),
    ], dim=1)  # fmt: skip


def occlusion_mask(depth_m: Tensor, fx_px: float, config: StereoApproxConfig) -> Tensor:
    """[B, H, W] True where the right imager (baseline to the right) cannot see the left imager's
    pixel: a pixel u maps to u - d(u) in the right image (d = fx B / z), and a nearer surface to
    its right lands on or left of that."""
    width = depth_m.shape[-1]
    disparity = fx_px * config.baseline_m / depth_m.clamp_min(1e-3)
    u = torch.arange(width, dtype=disparity.dtype, device=disparity.device)
    right_u = u - disparity
    # The smallest right-image column of any pixel to the right of each one.
    later_min = torch.flip(torch.cummin(torch.flip(right_u, dims=[-1]), dim=-1).values, dims=[-1])
    later_min = torch.cat([later_min[..., 1:], torch.full_like(later_min[..., :1], math.inf)], dim=-1)
    return later_min < right_u - config.occlusion_tolerance_px * width / 424.0


def loss_probability(depth_m: Tensor, gray_u8: Tensor, fx_px: float, config: StereoApproxConfig) -> Tensor:
    """[B, H, W] the probability that the stereo path reports no depth at each pixel."""
    cues = loss_cues(depth_m, gray_u8, fx_px, config)
    weights = torch.tensor(config.weights(), dtype=cues.dtype, device=cues.device).view(1, -1, 1, 1)
    return torch.sigmoid((cues * weights).sum(dim=1))


def _smooth_field(shape: tuple[int, int, int], blob_px: float, generator: torch.Generator, device) -> Tensor:
    """[B, H, W] noise with a standard normal marginal at every pixel, smooth over about
    ``blob_px``: bilinear from a coarse grid of normals, divided by the interpolation's own
    standard deviation there (sqrt of the summed squared weights), so that no pixel is favoured."""
    batch, height, width = shape
    cells_h, cells_w = max(2, math.ceil(height / blob_px) + 1), max(2, math.ceil(width / blob_px) + 1)
    coarse = torch.randn(batch, 1, cells_h, cells_w, generator=generator)
    field = F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False).squeeze(1)

    def weight_norm(size: int, cells: int) -> Tensor:  # sqrt((1 - f)^2 + f^2) along one axis
        x = ((torch.arange(size, dtype=torch.float32) + 0.5) * cells / size - 0.5).clamp(0.0, cells - 1.0)
        f = x - x.floor()
        return ((1.0 - f) ** 2 + f**2).sqrt()

    norm = weight_norm(height, cells_h).view(-1, 1) * weight_norm(width, cells_w).view(1, -1)
    return (field / norm).to(device)


def approx_stereo_depth(depth_m: Tensor, gray_u8: Tensor, fx_px: float, config: StereoApproxConfig,
                        generator: torch.Generator) -> Tensor:  # fmt: skip
    """[B, H, W] depth as the simulated D455 would report it (m, 0 = none), from the rendered depth
    [B, H, W] and gray [B, H, W] of a camera with focal length ``fx_px``."""
    batch, height, width = depth_m.shape
    scale = width / 212.0
    p = loss_probability(depth_m, gray_u8, fx_px, config)
    # A pixel is lost where a smooth uniform field falls below its probability: regions, not speckle.
    blob_px = config.loss_blob_px_projector_on if config.projector_on else config.loss_blob_px_projector_off
    uniform = 0.5 * (1.0 + torch.erf(_smooth_field((batch, height, width), blob_px * scale, generator, p.device) / math.sqrt(2.0)))
    lost = (uniform < p) | (depth_m < config.min_range_m) | (depth_m > config.max_range_m) | ~torch.isfinite(depth_m)
    sigma = config.noise_rel_per_m * depth_m + (0.0 if config.projector_on else config.noise_rel_floor_projector_off)
    dof = config.noise_dof_projector_on if config.projector_on else config.noise_dof_projector_off
    shape = (batch, height, width)
    gauss = _smooth_field(shape, config.noise_blob_px * scale, generator, depth_m.device)
    # Student-t: a normal over sqrt(chi2 / dof), the chi2 drawn in blobs as the normal is.
    chi2 = sum(_smooth_field(shape, config.noise_blob_px * scale, generator, depth_m.device) ** 2 for _ in range(dof))
    t = gauss / (chi2 / dof).clamp_min(1e-4).sqrt()
    measured = depth_m * (1.0 + (sigma * t).clamp(-config.noise_rel_max, config.noise_rel_max))
    return torch.where(lost | (measured <= 0.0), torch.full_like(depth_m, DEPTH_INVALID_VALUE), measured)
