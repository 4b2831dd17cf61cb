"""Preprocessing, observation and contract metadata."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.contract import (
    ContractMismatchError,
    ImageContractError,
    check_contract_metadata,
    contract_metadata,
    observation_state,
    preprocess_depth,
    preprocess_gray,
)
from runtime.contract import constants as c
from runtime.contract import frames as f
from runtime.contract.metadata import METADATA_KEY_VALUES, METADATA_KEY_VERSION


def test_gray_range_and_shape():
    img = np.random.default_rng(0).integers(0, 256, size=(120, 212), dtype=np.uint8)
    out = preprocess_gray(img)
    assert out.shape == (224, 224) and out.dtype == np.float32
    assert 0.0 <= out.min() and out.max() <= 1.0


def test_gray_from_bgr_uses_luma_weights():
    bgr = np.zeros((4, 4, 3), np.uint8)
    bgr[..., 2] = 255  # pure red
    assert preprocess_gray(bgr)[0, 0] == pytest.approx(round(0.299 * 255) / 255, abs=1 / 255)


def test_depth_normalisation_invalid_and_range():
    depth = np.full((120, 212), 5.0, np.float32)
    depth[:, :50] = 0.0
    depth[:10, 100:] = np.nan
    depth[50:, 200:] = 25.0
    depth[0, 60] = -1.0
    out = preprocess_depth(depth)
    assert out.shape == (224, 224) and out.dtype == np.float32
    assert set(np.unique(out).tolist()) <= {0.0, 0.5, 1.0}
    assert np.all(out[:, :40] == c.DEPTH_INVALID_VALUE)
    assert np.all(out[-20:, -5:] == 1.0)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_depth_resize_never_blends_invalid(seed):
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.3, 9.0, size=(120, 212)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.3] = 0.0
    out = preprocess_depth(depth)
    valid_values = set((depth[depth > 0] * np.float32(1.0 / c.DEPTH_MAX_M)).tolist())
    for v in np.unique(out):
        assert v == 0.0 or float(v) in valid_values


def test_bad_images_are_named():
    with pytest.raises(ImageContractError, match="uint8"):
        preprocess_gray(np.zeros((10, 10), np.float32))
    with pytest.raises(ImageContractError, match="depth"):
        preprocess_depth(np.zeros((10, 10, 3), np.float32))


def test_observation_layout():
    pos = np.array([1.0, 2.0, 1.5])
    goal = np.array([1.0, 32.0, 1.5])  # 30 m north
    q = f.quat_from_euler(0.1, -0.2, np.pi / 2)  # facing north
    vel = np.array([0.5, 0.0, 0.1])
    angvel = np.array([0.0, 0.0, 0.3])
    prev = np.array([0.2, -0.1, 0.4])
    s = observation_state(pos, goal, q, vel, angvel, prev)
    assert s.shape == (c.STATE_DIM,) and s.dtype == np.float32
    np.testing.assert_allclose(s[c.OBS_GOAL_DIR_V], [1, 0, 0], atol=1e-6)
    assert s[c.OBS_GOAL_DIST][0] == 1.0  # clipped at 12 m
    np.testing.assert_allclose(s[c.OBS_ROLL_PITCH], [0.1, -0.2], atol=1e-6)
    np.testing.assert_allclose(s[c.OBS_VEL_BODY_FLU], vel, atol=1e-6)
    np.testing.assert_allclose(s[c.OBS_ANGVEL_BODY_FLU], angvel, atol=1e-6)
    np.testing.assert_allclose(s[c.OBS_PREV_ACTION], prev, atol=1e-6)


def test_observation_goal_reached_has_zero_direction():
    s = observation_state(np.zeros(3), np.zeros(3), f.quat_from_euler(0, 0, 0), np.zeros(3), np.zeros(3), np.zeros(3))
    assert np.all(s[:4] == 0.0)


def test_contract_metadata_roundtrip_and_mismatch():
    meta = contract_metadata()
    check_contract_metadata(meta)
    values = json.loads(meta[METADATA_KEY_VALUES])
    values["max_speed_m_s"] = 1.5
    bad = dict(meta, **{METADATA_KEY_VALUES: json.dumps(values)})
    with pytest.raises(ContractMismatchError, match=r"max_speed_m_s: model has 1.5, runtime has 2.0"):
        check_contract_metadata(bad)
    with pytest.raises(ContractMismatchError, match="contract version"):
        check_contract_metadata(dict(meta, **{METADATA_KEY_VERSION: "0"}))
    with pytest.raises(ContractMismatchError, match="no cmnav contract metadata"):
        check_contract_metadata({})
