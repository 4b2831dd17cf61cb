"""The batched torch preprocessing matches the contract's numpy/cv2 functions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.contract.images import ImageContractError, preprocess_depth, preprocess_gray
from sim.camera import CameraModel
from sim.preprocess_torch import depth_invalid_mask_batch, preprocess_depth_batch, preprocess_gray_batch
from sim.render import render
from sim.world import make_worlds

# cv2 INTER_LINEAR on uint8 uses 11-bit fixed-point weights; the twin interpolates in float and
# rounds, so a pixel may be one gray level off (about 12% of them are on random images).
GRAY_TOL = 1.0 / 255.0 + 1e-6
SIZES = [(120, 212), (240, 424), (480, 848), (224, 224), (2, 2), (7, 5), (300, 100)]


def random_depth(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Depth with every kind of pixel: valid, beyond range, 0, negative, NaN, +-inf."""
    depth = rng.uniform(0.05, 14.0, shape).astype(np.float32)
    kind = rng.integers(0, 10, shape)
    depth[kind == 0] = np.nan
    depth[kind == 1] = np.inf
    depth[kind == 2] = -np.inf
    depth[kind == 3] = 0.0
    depth[kind == 4] = -rng.uniform(0.0, 3.0, int((kind == 4).sum()))
    depth[kind == 5] = 10.0  # exactly the range limit
    return depth


@pytest.mark.parametrize("height, width", SIZES)
def test_gray_matches_within_one_level(height: int, width: int) -> None:
    rng = np.random.default_rng(height * 1000 + width)
    gray = rng.integers(0, 256, (3, height, width), dtype=np.uint8)
    ours = preprocess_gray_batch(torch.from_numpy(gray)).numpy()
    theirs = np.stack([preprocess_gray(g) for g in gray])
    assert ours.shape == theirs.shape == (3, 224, 224) and ours.dtype == np.float32
    diff = np.abs(ours - theirs)
    assert diff.max() <= GRAY_TOL
    assert (diff > 1e-6).mean() < 0.2
    assert ours.min() >= 0.0 and ours.max() <= 1.0


@pytest.mark.parametrize("height, width", SIZES)
def test_depth_matches_exactly(height: int, width: int) -> None:
    rng = np.random.default_rng(height * 1000 + width + 1)
    depth = random_depth(rng, (3, height, width))
    ours = preprocess_depth_batch(torch.from_numpy(depth)).numpy()
    theirs = np.stack([preprocess_depth(d) for d in depth])
    np.testing.assert_array_equal(ours, theirs)
    assert ours.dtype == np.float32


not_multiple_of_64 = st.integers(2, 1000).filter(lambda n: n % 64 != 0)


@settings(max_examples=25, deadline=None)
@given(height=not_multiple_of_64, width=not_multiple_of_64, seed=st.integers(0, 2**32 - 1))
def test_any_size_matches(height: int, width: int, seed: int) -> None:
    """Depth is equal for every size whose nearest-neighbour sampling has no ties (see below)."""
    rng = np.random.default_rng(seed)
    depth = random_depth(rng, (1, height, width)).astype(np.float64)
    ours = preprocess_depth_batch(torch.from_numpy(depth)).numpy()[0]
    np.testing.assert_array_equal(ours, preprocess_depth(depth[0]))
    gray = rng.integers(0, 256, (1, height, width), dtype=np.uint8)
    diff = np.abs(preprocess_gray_batch(torch.from_numpy(gray)).numpy()[0] - preprocess_gray(gray[0]))
    assert diff.max() <= GRAY_TOL


@pytest.mark.parametrize("width", [64, 128, 640])
def test_depth_ties_at_multiples_of_64_pick_a_neighbour(width: int) -> None:
    """Output pixel x samples source position (x + 0.5) * width / 224, which lands exactly on a
    boundary between two source pixels only when width is a multiple of 64.  There cv2 (IPP
    fixed point) and torch may take different neighbours; both are a nearest pixel."""
    columns = np.tile(np.arange(1, width + 1, dtype=np.float32), (4, 1))  # value = index + 1, all valid
    scaled = columns * (10.0 / width)  # depth in (0, 10] m: normalised value = index / width
    torch_idx = np.rint(preprocess_depth_batch(torch.from_numpy(scaled[None])).numpy()[0, 0] * width).astype(int)
    cv_idx = np.rint(preprocess_depth(scaled)[0] * width).astype(int)
    position = (2 * np.arange(224) + 1) * width / 448  # continuous source x of each output pixel centre
    tie = position == np.floor(position)
    assert tie.any() and np.array_equal(torch_idx[~tie], cv_idx[~tie])
    # Value v (1-based) is a nearest pixel when pixel v - 1 = [v - 1, v) touches the position.
    for idx in (torch_idx, cv_idx):
        assert np.all(np.abs(idx - 0.5 - position) <= 0.5)


def test_rendered_frames_match() -> None:
    world = make_worlds([0, 10], seed=8)
    quat = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(2, 1)
    out = render(world, world.start_m, quat, CameraModel())
    depth = out.depth_m.clone()
    depth[:, :10] = float("nan")  # a band of lost depth
    ours_d = preprocess_depth_batch(depth).numpy()
    ours_g = preprocess_gray_batch(out.gray_u8).numpy()
    for i in range(2):
        np.testing.assert_array_equal(ours_d[i], preprocess_depth(depth[i].numpy()))
        assert np.abs(ours_g[i] - preprocess_gray(out.gray_u8[i].numpy())).max() <= GRAY_TOL


def test_invalid_mask() -> None:
    depth = torch.tensor([[[1.0, 0.0, -1.0, float("nan"), float("inf"), 20.0]]])
    assert depth_invalid_mask_batch(depth).tolist() == [[[False, True, True, True, True, False]]]


def test_wrong_inputs_raise_contract_errors() -> None:
    with pytest.raises(ImageContractError, match="gray uint8"):
        preprocess_gray_batch(torch.zeros(2, 10, 10))
    with pytest.raises(ImageContractError, match="gray uint8"):
        preprocess_gray_batch(torch.zeros(10, 10, dtype=torch.uint8))
    with pytest.raises(ImageContractError, match="float depth"):
        preprocess_depth_batch(torch.zeros(2, 10, 10, dtype=torch.int32))
    with pytest.raises(ImageContractError, match="float depth"):
        preprocess_depth_batch(torch.zeros(2, 1, 10))
