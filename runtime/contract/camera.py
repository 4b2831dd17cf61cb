"""The camera as the contract has it: a pinhole with square pixels, the principal point at the
image centre and the contract's horizontal field of view (``CAMERA_HFOV_RAD``), looking along body
+x; depth is z-depth (along the optical axis).  Camera frame FLU like the body: x forward, y left,
z up; image column u grows to the right (-y), row v downward (-z); pixel (u, v)'s centre is
(u + 0.5, v + 0.5).  ``sim.camera.CameraModel`` renders this model."""

from __future__ import annotations

import math

import numpy as np

from .constants import CAMERA_HFOV_RAD


def focal_length_px(width_px: int, hfov_rad: float = CAMERA_HFOV_RAD) -> float:
    """Focal length in pixels (horizontal and vertical) of an image ``width_px`` wide."""
    return (width_px / 2.0) / math.tan(hfov_rad / 2.0)


def depth_points_flu(depth_m: np.ndarray, cols: int, rows: int, max_depth_m: float) -> np.ndarray:
    """Points (camera FLU, m; shape (N, 3)) of a ``cols`` x ``rows`` grid of pixels spread evenly
    over the depth image ``depth_m`` (H, W), those with valid depth (finite, > 0, <= ``max_depth_m``)."""
    height, width = depth_m.shape
    u = ((np.arange(cols) + 0.5) * width / cols).astype(np.int64)
    v = ((np.arange(rows) + 0.5) * height / rows).astype(np.int64)
    z = depth_m[np.ix_(v, u)].astype(np.float64)
    f = focal_length_px(width)
    left = np.broadcast_to(-(u + 0.5 - width / 2.0) / f, z.shape)
    up = np.broadcast_to((-(v + 0.5 - height / 2.0) / f)[:, None], z.shape)
    valid = np.isfinite(z) & (z > 0.0) & (z <= max_depth_m)
    return np.stack([z[valid], left[valid] * z[valid], up[valid] * z[valid]], axis=1)
