"""Image preprocessing: the one function runtime, dataset generation and the RL env share.

gray: uint8 (H, W) or BGR uint8 (H, W, 3) -> (224, 224) float32 in [0, 1] (bilinear resize).
depth: metres float32 (H, W), 0 / NaN / inf / negative = invalid -> (224, 224) float32,
``d / DEPTH_MAX_M`` clipped to [0, 1], invalid = 0.0, beyond range = 1.0.  Depth is resized with
centre-aligned nearest neighbour so invalid pixels are never blended into valid ones.

The torch twin for batched training lives in ``sim`` and is tested against these functions.

OpenCV is a base dependency of the runtime, but it is imported inside the functions: everything
imports this package for its constants, including training on the offline GPU machine, which has
no OpenCV (it uses the torch twin there).
"""

from __future__ import annotations

import numpy as np

from .constants import DEPTH_INVALID_VALUE, DEPTH_MAX_M, IMAGE_SIZE_PX


class ImageContractError(ValueError):
    """An image does not have the shape or dtype the contract expects."""


def gray_from_bgr(bgr_u8: np.ndarray) -> np.ndarray:
    """BGR uint8 (H, W, 3) -> gray uint8 (H, W) by the ITU-R BT.601 luma weights."""
    if bgr_u8.ndim != 3 or bgr_u8.shape[2] != 3 or bgr_u8.dtype != np.uint8:
        raise ImageContractError(
            f"expected a BGR uint8 image of shape (H, W, 3), got {bgr_u8.dtype} {bgr_u8.shape}"
        )
    import cv2  # here, not at the top: the offline GPU machine has no OpenCV

    return cv2.cvtColor(bgr_u8, cv2.COLOR_BGR2GRAY)


def preprocess_gray(image_u8: np.ndarray) -> np.ndarray:
    """Gray (H, W) or BGR (H, W, 3) uint8 -> (224, 224) float32 in [0, 1]."""
    image_u8 = np.asarray(image_u8)
    if image_u8.ndim == 3:
        image_u8 = gray_from_bgr(image_u8)
    if image_u8.ndim != 2 or image_u8.dtype != np.uint8 or min(image_u8.shape) < 2:
        raise ImageContractError(
            f"expected a gray uint8 image of shape (H, W), got {image_u8.dtype} {image_u8.shape}"
        )
    import cv2  # here, not at the top: the offline GPU machine has no OpenCV

    resized = cv2.resize(image_u8, (IMAGE_SIZE_PX, IMAGE_SIZE_PX), interpolation=cv2.INTER_LINEAR)
    return resized.astype(np.float32) * np.float32(1.0 / 255.0)


def depth_invalid_mask(depth_m: np.ndarray) -> np.ndarray:
    """True where a raw depth pixel is invalid (0, negative, NaN or inf)."""
    depth_m = np.asarray(depth_m)
    return ~np.isfinite(depth_m) | (depth_m <= 0.0)


def preprocess_depth(depth_m: np.ndarray) -> np.ndarray:
    """Depth in metres (H, W) -> (224, 224) float32 normalised by DEPTH_MAX_M, invalid = 0."""
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2 or not np.issubdtype(depth_m.dtype, np.floating) or min(depth_m.shape) < 2:
        raise ImageContractError(
            f"expected a float depth image in metres of shape (H, W), got {depth_m.dtype} {depth_m.shape}"
        )
    import cv2  # here, not at the top: the offline GPU machine has no OpenCV

    depth = depth_m.astype(np.float32, copy=True)
    invalid = depth_invalid_mask(depth)
    depth[invalid] = 0.0
    resized = cv2.resize(depth, (IMAGE_SIZE_PX, IMAGE_SIZE_PX), interpolation=cv2.INTER_NEAREST_EXACT)
    normalised = np.clip(resized * np.float32(1.0 / DEPTH_MAX_M), 0.0, 1.0)
    normalised[resized <= 0.0] = DEPTH_INVALID_VALUE
    return normalised


def invalid_depth_fraction(depth_m: np.ndarray) -> float:
    """Fraction of invalid pixels in a raw depth image (the figure SITL and flights report)."""
    return float(np.mean(depth_invalid_mask(depth_m)))
