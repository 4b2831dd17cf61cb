"""Property tests: every frame conversion and its inverse (DESIGN §2)."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from runtime.contract import frames as f

finite = st.floats(-1e3, 1e3, allow_nan=False)
vec3 = arrays(np.float64, 3, elements=finite)
angle = st.floats(-np.pi, np.pi, allow_nan=False)
# Pitch away from +-90 deg, where Z-Y-X Euler angles are singular.
pitch = st.floats(-1.5, 1.5, allow_nan=False)


@given(vec3)
def test_enu_ned_roundtrip(v):
    np.testing.assert_allclose(f.ned_to_enu(f.enu_to_ned(v)), v)


@given(vec3)
def test_flu_frd_roundtrip(v):
    np.testing.assert_allclose(f.frd_to_flu(f.flu_to_frd(v)), v)


def test_named_axes():
    east, north, up = np.eye(3)
    np.testing.assert_allclose(f.enu_to_ned(east), [0, 1, 0])
    np.testing.assert_allclose(f.enu_to_ned(north), [1, 0, 0])
    np.testing.assert_allclose(f.enu_to_ned(up), [0, 0, -1])
    left = np.array([0.0, 1.0, 0.0])
    np.testing.assert_allclose(f.flu_to_frd(left), [0, -1, 0])


@given(angle, pitch, angle)
def test_euler_quat_roundtrip(roll, pitch_rad, yaw):
    q = f.quat_from_euler(roll, pitch_rad, yaw)
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-12)
    # Compared on the circle: -pi and pi are one roll (euler_from_quat may return either).
    difference = np.asarray(f.euler_from_quat(q)) - np.array([roll, pitch_rad, yaw])
    np.testing.assert_allclose(np.angle(np.exp(1j * difference)), 0.0, atol=1e-7)


@given(angle, pitch, angle)
def test_attitude_roundtrip(roll, pitch_rad, yaw):
    q = f.quat_from_euler(roll, pitch_rad, yaw)
    back = f.quat_ned_frd_to_enu_flu(f.quat_enu_flu_to_ned_frd(q))
    # q and -q are one rotation: compare the rotations.
    np.testing.assert_allclose(abs(np.dot(back, q)), 1.0, atol=1e-9)


@given(angle, pitch, angle, vec3)
def test_attitude_conversion_is_consistent_with_vector_conversions(roll, pitch_rad, yaw, v_flu):
    """Rotating a body vector must commute with the frame conversions on both sides."""
    q_enu_flu = f.quat_from_euler(roll, pitch_rad, yaw)
    q_ned_frd = f.quat_enu_flu_to_ned_frd(q_enu_flu)
    via_policy = f.enu_to_ned(f.quat_rotate(q_enu_flu, v_flu))
    via_px4 = f.quat_rotate(q_ned_frd, f.flu_to_frd(v_flu))
    np.testing.assert_allclose(via_policy, via_px4, atol=1e-6 * (1 + np.abs(v_flu).max()))


@given(angle, pitch, angle)
def test_euler_conventions_between_sides(roll, pitch_rad, yaw):
    """Roll agrees, pitch flips sign (nose-down positive in FLU), yaw_ned = pi/2 - yaw_enu."""
    q_ned_frd = f.quat_enu_flu_to_ned_frd(f.quat_from_euler(roll, pitch_rad, yaw))
    r_ned, p_ned, y_ned = f.euler_from_quat(q_ned_frd)
    np.testing.assert_allclose(f.wrap_angle(r_ned - roll), 0.0, atol=1e-7)
    np.testing.assert_allclose(p_ned, -pitch_rad, atol=1e-7)
    np.testing.assert_allclose(f.wrap_angle(y_ned - f.yaw_enu_to_ned(yaw)), 0.0, atol=1e-7)


@given(angle)
def test_yaw_roundtrip(yaw):
    np.testing.assert_allclose(f.wrap_angle(f.yaw_ned_to_enu(f.yaw_enu_to_ned(yaw)) - yaw), 0.0, atol=1e-9)


def test_heading_examples():
    assert np.isclose(f.yaw_ned_to_enu(0.0), np.pi / 2)  # facing north
    assert np.isclose(f.yaw_ned_to_enu(np.pi / 2), 0.0)  # facing east


@given(vec3, angle)
def test_vehicle_frame_roundtrip(v, yaw):
    np.testing.assert_allclose(f.vehicle_to_world_enu(f.world_enu_to_vehicle(v, yaw), yaw), v, atol=1e-9)


def test_vehicle_frame_yaw_only():
    # Facing north (ENU yaw = +90 deg): a goal to the north is straight ahead, east is to the right.
    yaw = np.pi / 2
    np.testing.assert_allclose(f.world_enu_to_vehicle([0.0, 3.0, 1.0], yaw), [3.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(f.world_enu_to_vehicle([2.0, 0.0, 0.0], yaw), [0.0, -2.0, 0.0], atol=1e-12)


@given(angle)
def test_wrap_angle_range(a):
    w = f.wrap_angle(a + 6 * np.pi)
    assert -np.pi < w <= np.pi + 1e-12
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-9)


def test_batched_shapes():
    v = np.random.default_rng(0).normal(size=(5, 7, 3))
    assert f.enu_to_ned(v).shape == (5, 7, 3)
    q = f.quat_from_euler(np.zeros(4), np.zeros(4), np.linspace(0, 1, 4))
    assert f.quat_ned_frd_to_enu_flu(q).shape == (4, 4)
