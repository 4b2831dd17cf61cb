"""Depth degradation models shared by datasets, RL and SITL (PAPER.md §CMWAE, §Policy).

Square-patch corruption works in the preprocessed 224x224 space: square patches of random side
are set to the invalid value (0.0, as the sensor reports) until the masked fraction of the image
reaches a target coverage.  The paper's schemes are presets of it:

- ``S1``: sides U{50..100} px; coverage per image drawn from {25: 5%, 30: 10%, 35: 15%,
  40: 20%, 45: 20%, 50: 30%} (coverage %: share of images);
- ``S2``: sides 100 px; coverage U(20%, 50%); half the images corrupted, half pristine;
- evaluation (Table I): sides U{1..50} px to a fixed coverage in {0, 20, 30, 40, 50}%;
- RL training: sides U{1..30} px to 50%.

:class:`ProjectorOffModel` is the physically motivated one: it works on the raw depth and gray
images and loses depth where a D455 without its IR projector would.

Everything is drawn from a ``torch.Generator`` so a seed reproduces the masks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from runtime.contract.constants import DEPTH_INVALID_VALUE, IMAGE_SIZE_PX

# S1's coverage levels and the share of images at each (PAPER.md §CMWAE).
S1_COVERAGE_LEVELS = (0.25, 0.30, 0.35, 0.40, 0.45, 0.50)
S1_COVERAGE_SHARES = (0.05, 0.10, 0.15, 0.20, 0.20, 0.30)


@dataclass(frozen=True)
class PatchScheme:
    """Square patches of side U{min_side_px..max_side_px} until a coverage in [min, max]
    (uniform) or drawn from ``coverage_levels`` with ``coverage_shares``; a fraction
    ``pristine_fraction`` of images is left untouched."""

    min_side_px: int
    max_side_px: int
    min_coverage: float = 0.0
    max_coverage: float = 0.0
    coverage_levels: tuple[float, ...] = ()
    coverage_shares: tuple[float, ...] = ()
    pristine_fraction: float = 0.0

    def validate(self) -> None:
        if not 1 <= self.min_side_px <= self.max_side_px <= IMAGE_SIZE_PX:
            raise ValueError(f"patch sides {self.min_side_px}..{self.max_side_px} px must lie in 1..{IMAGE_SIZE_PX}")
        if not 0.0 <= self.min_coverage <= self.max_coverage <= 1.0:
            raise ValueError(f"coverage range ({self.min_coverage}, {self.max_coverage}) must lie in [0, 1]")
        if len(self.coverage_levels) != len(self.coverage_shares):
            raise ValueError("coverage_levels and coverage_shares must have the same length")
        if self.coverage_shares and abs(sum(self.coverage_shares) - 1.0) > 1e-6:
            raise ValueError(f"coverage_shares must sum to 1, got {sum(self.coverage_shares)}")
        if not 0.0 <= self.pristine_fraction <= 1.0:
            raise ValueError(f"pristine_fraction={self.pristine_fraction} must lie in [0, 1]")

    def sample_coverage(self, batch: int, generator: torch.Generator) -> Tensor:
        """[B] target coverage per image (0 for pristine images), on the CPU."""
        if self.coverage_levels:
            idx = torch.multinomial(torch.tensor(self.coverage_shares), batch, replacement=True, generator=generator)
            coverage = torch.tensor(self.coverage_levels)[idx]
        else:
            u = torch.rand(batch, generator=generator)
            coverage = self.min_coverage + (self.max_coverage - self.min_coverage) * u
        pristine = torch.rand(batch, generator=generator) < self.pristine_fraction
        return torch.where(pristine, torch.zeros_like(coverage), coverage)


S1 = PatchScheme(50, 100, coverage_levels=S1_COVERAGE_LEVELS, coverage_shares=S1_COVERAGE_SHARES)
S2 = PatchScheme(100, 100, min_coverage=0.20, max_coverage=0.50, pristine_fraction=0.5)
RL_TRAINING = PatchScheme(1, 30, min_coverage=0.50, max_coverage=0.50)
# Not the paper's: the policy's patches (1-30 px) at S2's coverages on S2's half of the images, to
# fine-tune an encoder (latent anchoring) for the corruption the policy flies with, not S2's squares.
POLICY_PATCHES = PatchScheme(1, 30, min_coverage=0.20, max_coverage=0.50, pristine_fraction=0.5)
# Not the paper's: large squares held for a whole training episode (NavEnvConfig.squares_episode_fraction),
# the kind of loss S2 and Table II's ``patches-100px`` are (100 px to 50 %), which the per-step 1-30 px
# patches do not teach: a blind region that stays where it is.
EPISODE_SQUARES = PatchScheme(50, 100, min_coverage=0.20, max_coverage=0.50)
EVALUATION_COVERAGES = (0.0, 0.2, 0.3, 0.4, 0.5)
SCHEMES = {"s1": S1, "s2": S2, "rl": RL_TRAINING, "policy": POLICY_PATCHES}


EVALUATION_PATCH_SIDES_PX = (1, 50)


def evaluation_scheme(coverage: float, sides_px: tuple[int, int] = EVALUATION_PATCH_SIDES_PX) -> PatchScheme:
    """Table I's evaluation corruption: sides U{1..50} px (or ``sides_px``) to exactly this coverage."""
    scheme = PatchScheme(sides_px[0], sides_px[1], min_coverage=coverage, max_coverage=coverage)
    scheme.validate()
    return scheme


def _paint_squares(size_px: int, top: Tensor, left: Tensor, side: Tensor, use: Tensor) -> Tensor:
    """[B, size, size] bool union of squares (top, left, side) [B, P] where ``use`` [B, P]:
    pixel (i, j) is covered iff sum_p row_p(i) * col_p(j) > 0, one batched matrix product."""
    pixels = torch.arange(size_px).view(1, 1, size_px)
    rows = ((pixels >= top.unsqueeze(-1)) & (pixels < (top + side).unsqueeze(-1)) & use.unsqueeze(-1)).float()
    cols = ((pixels >= left.unsqueeze(-1)) & (pixels < (left + side).unsqueeze(-1))).float()
    return torch.bmm(rows.transpose(1, 2), cols) > 0.5


def patch_masks(
    coverage: Tensor,
    scheme: PatchScheme,
    generator: torch.Generator,
    size_px: int = IMAGE_SIZE_PX,
) -> Tensor:
    """[B, size, size] bool masks: square patches added until each image's masked fraction
    reaches ``coverage`` [B] (the last patch may overshoot by at most its own area).  Drawn on
    the CPU.  Each round adds to every unfinished image 80% of the patches that would reach its
    target on average, counting overlaps as for randomly placed patches
    (1 - c' = (1 - c)(1 - a/A)^k), down to one patch at a time near the end."""
    scheme.validate()
    batch = coverage.shape[0]
    masks = torch.zeros(batch, size_px, size_px, dtype=torch.bool)
    sides = torch.arange(scheme.min_side_px, scheme.max_side_px + 1, dtype=torch.float64)
    mean_area_px = float((sides**2).mean())
    total_px = size_px * size_px
    covered = torch.zeros(batch)
    while True:
        need = covered < coverage
        if not bool(need.any()):
            return masks
        idx = need.nonzero().squeeze(1)
        keep = (1.0 - coverage[idx]).clamp_min(1e-6) / (1.0 - covered[idx]).clamp_min(1e-6)
        expected = torch.log(keep) / math.log(1.0 - mean_area_px / total_px)
        count = (0.8 * expected).floor().clamp(min=1).long()
        n, most = idx.shape[0], int(count.max())
        side = torch.randint(scheme.min_side_px, scheme.max_side_px + 1, (n, most), generator=generator)
        top = (torch.rand(n, most, generator=generator) * (size_px - side + 1)).long()
        left = (torch.rand(n, most, generator=generator) * (size_px - side + 1)).long()
        use = torch.arange(most).unsqueeze(0) < count.unsqueeze(1)
        masks[idx] |= _paint_squares(size_px, top, left, side, use)
        covered[idx] = masks[idx].float().mean(dim=(1, 2))


def corrupt_depth(depth_norm: Tensor, masks: Tensor) -> Tensor:
    """Preprocessed depth [B, (1,) H, W] with masked pixels set to the invalid value."""
    masks = masks.to(depth_norm.device)
    if depth_norm.dim() == masks.dim() + 1:
        masks = masks.unsqueeze(1)
    return depth_norm.masked_fill(masks, DEPTH_INVALID_VALUE)


def corrupt_with_scheme(depth_norm: Tensor, scheme: PatchScheme, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Corrupt a batch by ``scheme``; returns (corrupted depth, masks)."""
    coverage = scheme.sample_coverage(depth_norm.shape[0], generator)
    masks = patch_masks(coverage, scheme, generator, size_px=depth_norm.shape[-1])
    return corrupt_depth(depth_norm, masks), masks


@dataclass(frozen=True)
class ProjectorOffModel:
    """A D455 with its IR projector off: passive stereo fails where the surface has little texture,
    is dark, is seen at a grazing angle or is far.  Each cue gives a loss probability (a logistic
    ramp around its threshold); they combine as independent causes, p = 1 - prod(1 - p_i), scaled
    by ``severity``; a pixel is lost where a spatially smooth uniform noise field (blobs about
    ``blob_px`` wide, as stereo matching fails in regions, not single pixels) falls below p.
    With the defaults, views from `cmnav dataset` lose 26 % of their pixels on average (2-68 %),
    like the paper's D455 with the projector off (25-30 % on average, up to 61 %)."""

    texture_std_threshold: float = 1.5  # local gray std (levels) below which matching fails
    dark_threshold: float = 25.0  # gray level below which the image is too dark
    grazing_tan_threshold: float = 3.5  # tan(incidence angle) above which the surface is too oblique
    far_threshold_m: float = 7.0  # beyond this passive stereo is unreliable
    ramp_width: float = 0.15  # logistic width, as a fraction of each threshold
    window_px: int = 7  # local texture window (odd)
    blob_px: int = 8
    severity: float = 1.0

    def loss_probability(self, depth_m: Tensor, gray_u8: Tensor, fx_px: float) -> Tensor:
        """[B, H, W] probability that each pixel's depth is lost."""
        gray = gray_u8.float().unsqueeze(1)
        pad = self.window_px // 2
        mean = torch.nn.functional.avg_pool2d(gray, self.window_px, 1, pad, count_include_pad=False)
        mean_sq = torch.nn.functional.avg_pool2d(gray * gray, self.window_px, 1, pad, count_include_pad=False)
        texture_std = (mean_sq - mean * mean).clamp_min(0.0).sqrt().squeeze(1)
        depth = depth_m.float()
        grad_v, grad_u = torch.gradient(depth, dim=(1, 2))
        # tan(incidence) of a z-depth surface: metres of depth change per metre across the view.
        grazing_tan = torch.sqrt(grad_u**2 + grad_v**2) * fx_px / depth.clamp_min(1e-3)

        def ramp(value: Tensor, threshold: float, above: bool) -> Tensor:
            x = (value - threshold) / (self.ramp_width * threshold)
            return torch.sigmoid(x if above else -x)

        survive = (
            (1 - ramp(texture_std, self.texture_std_threshold, above=False))
            * (1 - ramp(gray.squeeze(1), self.dark_threshold, above=False))
            * (1 - ramp(grazing_tan, self.grazing_tan_threshold, above=True))
            * (1 - ramp(depth, self.far_threshold_m, above=True))
        )
        return ((1 - survive) * self.severity).clamp(0.0, 1.0)

    def apply(self, depth_m: Tensor, gray_u8: Tensor, fx_px: float, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """Raw depth [B, H, W] (m) with lost pixels set to 0 (invalid), and the [B] lost fraction."""
        batch, height, width = depth_m.shape
        p = self.loss_probability(depth_m, gray_u8, fx_px)
        coarse = torch.rand(batch, 1, -(-height // self.blob_px) + 1, -(-width // self.blob_px) + 1, generator=generator)
        noise = torch.nn.functional.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
        # Bilinear blending pulls uniform noise toward 0.5: restore a uniform marginal (rank by
        # the normal CDF of the standardised field) so p keeps its meaning as a probability.
        noise = noise.squeeze(1).to(p.device)
        z = (noise - 0.5) / noise.flatten(1).std(dim=1).clamp_min(1e-6).view(-1, 1, 1)
        uniform = 0.5 * (1 + torch.erf(z / math.sqrt(2.0)))
        lost = uniform < p
        return depth_m.masked_fill(lost, 0.0), lost.float().mean(dim=(1, 2))
