"""WAE-MMD loss (Tolstikhin et al. 2018) with the reference's multi-scale inverse multiquadratic
kernel, and the CMWAE objective L = E||D(z) - depth||^2 + lambda * MMD(q(z), N(0, I))."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from runtime.contract.constants import DEPTH_INVALID_VALUE, DEPTH_MAX_M

IMQ_SCALES = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)


def mmd_imq(z: Tensor, prior_z: Tensor, sigma2: float = 1.0, scales: tuple[float, ...] = IMQ_SCALES) -> Tensor:
    """Unbiased MMD^2 estimate between samples z [n, d] and prior samples [n, d].

    k(x, y) = C / (C + ||x - y||^2), C = 2 d sigma2 s, summed over scales s; within-sample terms
    exclude the diagonal and divide by n(n-1), the cross term is 2 sum / n^2 (as the reference).
    """
    n, d = z.shape
    if n < 2 or prior_z.shape != z.shape:
        raise ValueError(f"mmd_imq needs two batches of the same shape with n >= 2, got {tuple(z.shape)} and {tuple(prior_z.shape)}")
    d_zz = torch.cdist(z, z).pow(2)
    d_pp = torch.cdist(prior_z, prior_z).pow(2)
    d_zp = torch.cdist(z, prior_z).pow(2)
    off_diagonal = 1.0 - torch.eye(n, device=z.device, dtype=z.dtype)
    stat = z.new_zeros(())
    for s in scales:
        c = 2.0 * d * sigma2 * s
        within = ((c / (c + d_zz) + c / (c + d_pp)) * off_diagonal).sum() / (n * n - n)
        cross = (c / (c + d_zp)).sum() * 2.0 / (n * n)
        stat = stat + within - cross
    return stat


# The distance (m) under which a surface counts as near: what a crash is made of within a second
# at the policy's speeds.  The encoder's near-weighted loss and eval column, and the student's
# near-obstacle label weight use it.
NEAR_SURFACE_M = 1.5


def check_near_weighting(near_weight: float, near_m: float) -> None:
    """The configured near weighting (the encoder's loss, DAgger's labels) is usable: ValueError if not."""
    if not 0.0 <= near_weight <= 1000.0:
        raise ValueError(f"near_weight={near_weight} must lie in [0, 1000]")
    if not 0.0 < near_m <= DEPTH_MAX_M:
        raise ValueError(f"near_m={near_m} must lie in (0, {DEPTH_MAX_M:g}] m, the depth range")


def near_surface_mask(depth: Tensor, near_m: float) -> Tensor:
    """The valid pixels of normalised depth whose surface is nearer than ``near_m`` metres."""
    return (depth > DEPTH_INVALID_VALUE) & (depth < near_m / DEPTH_MAX_M)


# The teacher's view of the depth image (training.policy.env, NavEnvConfig's privileged depth): the
# nearest surface in each cell of an 18 x 32 (rows x columns) grid over the camera's field of view.
# The pooled reconstruction loss holds the latent to what the teacher flies on; a test keeps the
# two grids equal.
TEACHER_GRID = (18, 32)


def nearest_per_cell(depth: Tensor, grid: tuple[int, int] = TEACHER_GRID) -> Tensor:
    """[B, 1, H, W] normalised depth -> [B, 1, rows, cols]: the nearest valid surface in each cell of
    ``grid`` (adaptive cells, so any H, W); an invalid pixel counts as far (1), a cell with no valid
    pixel reads 1, as the teacher's closed-room depth reads past DEPTH_MAX_M."""
    far = torch.where(depth > DEPTH_INVALID_VALUE, depth, torch.ones_like(depth))
    return -F.adaptive_max_pool2d(-far, grid)


def hidden_pixels(corrupted: Tensor, target: Tensor) -> Tensor:
    """The pixels the encoder's input lost: invalid in the degraded input, valid in the target."""
    return (corrupted <= DEPTH_INVALID_VALUE) & (target > DEPTH_INVALID_VALUE)


def hidden_too_far(recon: Tensor, target: Tensor, hidden: Tensor) -> Tensor:
    """The hidden elements (pixels or cells) whose reconstruction reads farther than the truth: a
    surface the input lost and the encoder placed beyond where it is, so a policy flies into it."""
    return hidden & (recon.detach() > target)


def pooled_nearest_error(recon: Tensor, target: Tensor, near_weight: float = 0.0, near_m: float = NEAR_SURFACE_M,
                         grid: tuple[int, int] = TEACHER_GRID, hidden: Tensor | None = None,
                         hidden_far_weight: float = 0.0) -> Tensor:  # fmt: skip
    """[B] the reconstruction error as the teacher would see it: squared error of the nearest
    surface per grid cell, the reconstruction read only where the target is valid, cells whose true
    nearest surface is nearer than ``near_m`` weighing 1 + ``near_weight``, and, given the input's
    ``hidden`` pixels, cells holding one whose nearest surface reads too far weighing
    ``hidden_far_weight`` more; a weighted mean per image."""
    valid = target > DEPTH_INVALID_VALUE
    cells_true = nearest_per_cell(target, grid)
    cells_recon = nearest_per_cell(torch.where(valid, recon, torch.ones_like(recon)), grid)
    weights = 1.0 + near_weight * near_surface_mask(cells_true, near_m)
    if hidden is not None and hidden_far_weight > 0.0:
        cells_hidden = F.adaptive_max_pool2d(hidden.float(), grid) > 0.0
        weights = weights + hidden_far_weight * hidden_too_far(cells_recon, cells_true, cells_hidden)
    squared = (cells_recon - cells_true) ** 2
    return (squared * weights).flatten(1).sum(dim=1) / weights.flatten(1).sum(dim=1)


def cmwae_loss(recon: Tensor, target: Tensor, z: Tensor, mmd_weight: float, generator: torch.Generator | None = None,
               image_weights: Tensor | None = None, pixel_weights: Tensor | None = None) -> dict[str, Tensor]:  # fmt: skip
    """-> {"loss", "recon_mse", "mmd"}; the prior sample is drawn from N(0, I).  ``pixel_weights``
    (the target's shape) make each image's error a weighted mean over its pixels; ``image_weights``
    [B] weigh each image's error in the batch mean.  ``recon_mse`` stays the plain mean."""
    squared = (recon - target) ** 2
    per_image_mse = squared.flatten(1).mean(dim=1)
    recon_mse = per_image_mse.mean()
    per_image = per_image_mse if pixel_weights is None else \
        (squared * pixel_weights).flatten(1).sum(dim=1) / pixel_weights.flatten(1).sum(dim=1)
    weighted = per_image.mean() if image_weights is None else (per_image * image_weights).sum() / image_weights.sum()
    prior = torch.randn(z.shape, generator=generator, device=z.device, dtype=z.dtype)
    mmd = mmd_imq(z, prior)
    return {"loss": weighted + mmd_weight * mmd, "recon_mse": recon_mse, "mmd": mmd}
