"""The torch quaternion helpers agree with the contract's numpy frames module."""

from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.contract import frames
from sim import rotations

finite = st.floats(-10.0, 10.0, allow_nan=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False)
quat_parts = st.tuples(finite, finite, finite, finite).filter(lambda q: sum(c * c for c in q) > 1e-3)


def unit(q: tuple[float, ...]) -> np.ndarray:
    a = np.asarray(q, dtype=np.float64)
    return a / np.linalg.norm(a)


@settings(max_examples=50, deadline=None)
@given(q=quat_parts, r=quat_parts, v=st.tuples(finite, finite, finite))
def test_multiply_rotate_match_contract(q: tuple, r: tuple, v: tuple) -> None:
    qa, ra, va = unit(q), unit(r), np.asarray(v)
    qt, rt, vt = (torch.from_numpy(x) for x in (qa, ra, va))
    np.testing.assert_allclose(rotations.quat_multiply(qt, rt).numpy(), frames.quat_multiply(qa, ra), atol=1e-12)
    np.testing.assert_allclose(rotations.quat_rotate(qt, vt).numpy(), frames.quat_rotate(qa, va), atol=1e-9)
    np.testing.assert_allclose(rotations.quat_rotate_inverse(qt, rotations.quat_rotate(qt, vt)).numpy(), va, atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(roll=angle, pitch=st.floats(-1.5, 1.5), yaw=angle)
def test_euler_round_trip_matches_contract(roll: float, pitch: float, yaw: float) -> None:
    r, p, y = (torch.tensor(x, dtype=torch.float64) for x in (roll, pitch, yaw))
    q = rotations.quat_from_euler(r, p, y)
    np.testing.assert_allclose(q.numpy(), frames.quat_from_euler(roll, pitch, yaw), atol=1e-12)
    np.testing.assert_allclose(rotations.euler_from_quat(q).numpy(), [roll, pitch, yaw], atol=1e-7)
    np.testing.assert_allclose(rotations.quat_from_yaw(y).numpy(), frames.quat_from_euler(0.0, 0.0, yaw), atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(axis=st.tuples(finite, finite, finite).filter(lambda a: sum(c * c for c in a) > 1e-3), turn=st.floats(0.0, 3.1))
def test_quat_log_is_axis_times_angle(axis: tuple, turn: float) -> None:
    a = torch.from_numpy(unit(axis))
    q = torch.cat([torch.tensor([math.cos(turn / 2)], dtype=torch.float64), math.sin(turn / 2) * a])
    np.testing.assert_allclose(rotations.quat_log(q).numpy(), (turn * a).numpy(), atol=1e-9)
    np.testing.assert_allclose(rotations.quat_log(-q).numpy(), (turn * a).numpy(), atol=1e-9)


def test_rotate_about_z_is_counter_clockwise() -> None:
    out = rotations.rotate_about_z(torch.tensor([1.0, 0.0, 2.0]), torch.tensor(math.pi / 2))
    np.testing.assert_allclose(out.numpy(), [0.0, 1.0, 2.0], atol=1e-7)
