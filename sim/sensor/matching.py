"""Depth from the IR pair by semi-global matching (OpenCV StereoSGBM), as the D455's ASIC does.

SGBM searches disparities ``min_disparity_px`` .. ``max_disparity_px`` (see
:mod:`sim.sensor.config`: the top of the search is the minimum range), with subpixel refinement
(1/16 px), the uniqueness test (a pixel whose best match is not clearly better than the second
is left invalid: repeated or missing texture), the left-right consistency check (a pixel the
right image cannot see, the occlusion shadow beside a near object, fails it) and speckle
removal (small islands of disparity, such as a thin rod far away, are dropped).  Then a subpixel
fit on the IR images (:func:`refine_subpixel`) with its texture check (a window whose intensity
barely changes along the baseline has no reliable match: holes on smooth surfaces without the
projector).  Every invalid pixel comes out of those tests on the images; nothing else is masked
except depth beyond ``max_range_m``.

OpenCV releases the GIL while it matches, so a batch is matched by a small thread pool (as
many threads as torch uses).
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from torch import Tensor

from runtime.contract.constants import DEPTH_INVALID_VALUE

from .config import StereoConfig


@functools.lru_cache(maxsize=8)
def _matcher(config: StereoConfig):
    import cv2  # here: importing sim.sensor does not need OpenCV (the offline GPU machine has none)

    block = config.block_size_px
    return cv2.StereoSGBM_create(
        minDisparity=config.min_disparity_px,
        numDisparities=config.num_disparities,
        blockSize=block,
        P1=config.p1_per_pixel * block * block,
        P2=config.p2_per_pixel * block * block,
        disp12MaxDiff=config.left_right_max_diff_px,
        preFilterCap=config.pre_filter_cap,
        uniquenessRatio=config.uniqueness_ratio_pct,
        speckleWindowSize=config.speckle_window_px,
        speckleRange=config.speckle_range_px,
        mode=cv2.STEREO_SGBM_MODE_SGBM,
    )


def disparity_px(left_u8: np.ndarray, right_u8: np.ndarray, config: StereoConfig) -> np.ndarray:
    """float32 [H, W] disparity (px) of one rectified pair; NaN where SGBM found no match."""
    raw = _matcher(config).compute(np.ascontiguousarray(left_u8), np.ascontiguousarray(right_u8))
    disparity = raw.astype(np.float32) * np.float32(1.0 / 16.0)
    disparity[raw < config.min_disparity_px * 16] = np.nan  # SGBM's "no match" is (minDisparity - 1) x 16
    return disparity


def refine_subpixel(left_u8: np.ndarray, right_u8: np.ndarray, disparity: np.ndarray, config: StereoConfig) -> np.ndarray:
    """Disparity (px) re-estimated to a fraction of a pixel around SGBM's: the sum of squared
    differences over a ``subpixel_window_px`` square at the nearest whole disparity and its two
    neighbours, and the vertex of the parabola through them (kept within half a pixel).

    SGBM's own subpixel step reads its path-aggregated costs, and on a smooth surface the
    smoothness penalty P1 makes them symmetric about the whole disparity: its output locks to
    whole pixels (0.2-0.4 px RMS on a flat wall).  The D455's ASIC, too, refines the disparity
    after its semi-global pass."""
    left = left_u8.astype(np.float32)
    right = right_u8.astype(np.float32)
    height, width = left.shape
    valid = np.isfinite(disparity)
    if not valid.any():
        return disparity
    import cv2  # here: importing sim.sensor does not need OpenCV

    whole = np.where(valid, np.rint(disparity), 0).astype(np.int64)
    costs = np.full((3, height, width), np.inf, dtype=np.float32)
    window = (config.subpixel_window_px, config.subpixel_window_px)
    low, high = int(whole[valid].min()) - 1, int(whole[valid].max()) + 1
    for shift in range(low, high + 1):
        near = valid & (np.abs(whole - shift) <= 1)
        if not near.any():
            continue
        shifted = np.full_like(right, np.nan)  # right image moved by `shift` px: column x holds right[x - shift]
        if shift >= 0:
            shifted[:, shift:] = right[:, : width - shift]
        else:
            shifted[:, : width + shift] = right[:, -shift:]
        squared = (left - shifted) ** 2
        outside = ~np.isfinite(squared)
        squared[outside] = 0.0
        cost = cv2.boxFilter(squared, -1, window, normalize=False, borderType=cv2.BORDER_REPLICATE)
        touches = cv2.boxFilter(outside.astype(np.float32), -1, window, normalize=False, borderType=cv2.BORDER_REPLICATE)
        cost[touches > 0.0] = np.inf
        for k in (-1, 0, 1):
            at = near & (whole + k == shift)
            costs[k + 1][at] = cost[at]
    below, centre, above = costs
    with np.errstate(invalid="ignore"):
        curvature = below + above - 2.0 * centre
        fit = valid & np.isfinite(below) & np.isfinite(above) & (curvature > 0.0)
        offset = np.where(fit, (below - above) / np.where(fit, 2.0 * curvature, 1.0), 0.0)
    refined = np.where(fit, whole + np.clip(offset, -0.5, 0.5), np.nan).astype(np.float32)
    # The parabola's curvature is twice the window's squared intensity gradient along the
    # baseline: too little, and the match is the noise's, not the surface's.
    pixels = config.subpixel_window_px**2
    with np.errstate(invalid="ignore"):
        textured = curvature >= 2.0 * pixels * config.min_texture_levels_px**2
    return np.where(textured, refined, np.nan).astype(np.float32)


def depth_from_disparity(disparity: np.ndarray, config: StereoConfig) -> np.ndarray:
    """float32 z-depth (m) from disparity (px); invalid (0) where there is none, it is not
    positive, or the depth lies beyond max_range_m."""
    min_disparity = config.focal_baseline_px_m / config.max_range_m
    valid = np.isfinite(disparity) & (disparity >= min_disparity)
    depth = np.full(disparity.shape, DEPTH_INVALID_VALUE, dtype=np.float32)
    depth[valid] = np.float32(config.focal_baseline_px_m) / disparity[valid]
    return depth


def match_depth(left_u8: Tensor, right_u8: Tensor, config: StereoConfig, threads: int | None = None) -> Tensor:
    """[B, H, W] float32 depth (m, left imager's frame, invalid = 0) from IR pairs [B, H, W] uint8."""
    left = left_u8.cpu().numpy()
    right = right_u8.cpu().numpy()
    workers = max(1, min(threads or torch.get_num_threads(), left.shape[0]))

    def one(i: int) -> np.ndarray:
        disparity = refine_subpixel(left[i], right[i], disparity_px(left[i], right[i], config), config)
        return depth_from_disparity(disparity, config)

    if workers == 1:
        depths = [one(i) for i in range(left.shape[0])]
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            depths = list(pool.map(one, range(left.shape[0])))
    return torch.from_numpy(np.stack(depths))
