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
many threads as torch uses), each thread with its own matcher: a StereoSGBM object keeps its
working buffer between calls, and two threads computing on one wrote into each other's (a
segfault in cv2 an evaluation of the ``field`` condition met 15 s in).  The pool lives as long
as the process, so its threads and their matchers (and buffers) carry over from batch to batch.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from numba import njit
from torch import Tensor

from runtime.contract.constants import DEPTH_INVALID_VALUE

from .config import StereoConfig


_THREAD = threading.local()  # per thread: {config: its StereoSGBM}, the oldest dropped past the bound
_MATCHERS_PER_THREAD = 8
_POOLS: dict[tuple[int, int], ThreadPoolExecutor] = {}  # (process id, threads): a forked child makes its own
_POOLS_LOCK = threading.Lock()


def _matcher(config: StereoConfig):
    """The calling thread's StereoSGBM for ``config`` (made on its first call there)."""
    matchers = _THREAD.__dict__.setdefault("matchers", {})
    if config not in matchers:
        if len(matchers) >= _MATCHERS_PER_THREAD:
            del matchers[next(iter(matchers))]
        matchers[config] = _new_matcher(config)
    return matchers[config]


def _pool(threads: int) -> ThreadPoolExecutor:
    """The process's matching pool of ``threads`` threads (made on first use, kept)."""
    with _POOLS_LOCK:
        key = (os.getpid(), threads)
        if key not in _POOLS:
            _POOLS[key] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="stereo-match")
        return _POOLS[key]


def _new_matcher(config: StereoConfig):
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
    # The parabola's curvature is twice the window's squared intensity gradient along the
    # baseline: too little, and the match is the noise's, not the surface's.
    min_curvature = 2.0 * config.subpixel_window_px**2 * config.min_texture_levels_px**2
    return _refine_kernel(np.ascontiguousarray(left_u8, dtype=np.uint8), np.ascontiguousarray(right_u8, dtype=np.uint8),
                          np.ascontiguousarray(disparity, dtype=np.float32), config.subpixel_window_px, np.float32(min_curvature))  # fmt: skip


@njit(cache=True, nogil=True)
def _refine_kernel(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, window: int, min_curvature: np.float32) -> np.ndarray:
    """Per valid pixel, the window's sums of squared differences at the whole disparity d - 1, d,
    d + 1 (rows and columns beyond the image repeat its edge; a window reaching past the right
    image's edge has no cost), in exact integers, then the parabola's vertex.  Cost independent
    of the disparity range: a near obstacle (wide range) costs what a far wall does."""
    height, width = left.shape
    refined = np.full((height, width), np.nan, dtype=np.float32)
    before = window // 2
    low, high = np.inf, -np.inf
    for d in disparity.ravel():
        if np.isfinite(d):
            low, high = min(low, d), max(high, d)
    if low > high:
        return refined
    lowest = int(np.rint(low)) - 1
    shifts = int(np.rint(high)) + 1 - lowest + 1
    # The window's column sums of squared differences at (shift, column), for the current row:
    # neighbours at the same disparity share them.  ``row_of`` says which row a sum is for.
    column_sum = np.zeros((shifts, width), dtype=np.int64)
    row_of = np.full((shifts, width), -1, dtype=np.int64)
    costs = np.zeros(3, dtype=np.int64)  # at whole - 1, whole, whole + 1: exact integers
    for y in range(height):
        for x in range(width):
            d = disparity[y, x]
            if not np.isfinite(d):
                continue
            whole = int(np.rint(d))
            # The window's columns (the image's edge repeated) and the right image's columns they
            # meet at the largest and smallest of the three disparities: all inside, or no cost.
            first, last = max(x - before, 0), min(x - before + window - 1, width - 1)
            if first - (whole + 1) < 0 or last - (whole - 1) >= width:
                continue
            costs[:] = 0
            for dx in range(-before, window - before):
                xx = min(max(x + dx, 0), width - 1)
                for k in range(3):
                    shift = whole + k - 1
                    at = shift - lowest
                    if row_of[at, xx] != y:
                        total = 0
                        for dy in range(-before, window - before):
                            yy = min(max(y + dy, 0), height - 1)
                            diff = np.int64(left[yy, xx]) - np.int64(right[yy, xx - shift])
                            total += diff * diff
                        column_sum[at, xx] = total
                        row_of[at, xx] = y
                    costs[k] += column_sum[at, xx]
            below32, centre32, above32 = np.float32(costs[0]), np.float32(costs[1]), np.float32(costs[2])
            curvature = below32 + above32 - np.float32(2.0) * centre32
            if curvature <= np.float32(0.0) or curvature < min_curvature:
                continue
            offset = (below32 - above32) / (np.float32(2.0) * curvature)
            offset = min(max(offset, np.float32(-0.5)), np.float32(0.5))
            refined[y, x] = np.float32(np.float64(whole) + np.float64(offset))
    return refined


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
    threads = max(1, threads or torch.get_num_threads())

    def one(i: int) -> np.ndarray:
        disparity = refine_subpixel(left[i], right[i], disparity_px(left[i], right[i], config), config)
        return depth_from_disparity(disparity, config)

    if min(threads, left.shape[0]) == 1:
        depths = [one(i) for i in range(left.shape[0])]
    else:
        depths = list(_pool(threads).map(one, range(left.shape[0])))  # one pool per thread count, whatever the batch
    return torch.from_numpy(np.stack(depths))
