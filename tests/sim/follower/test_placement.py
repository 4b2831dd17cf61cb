"""The followed pose: an autopilot's NED/FRD pose, converted by the contract's functions and
placed in the room, is the room's ENU/FLU pose it came from (property tests, both ways)."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.contract.frames import (
    enu_to_ned,
    euler_from_quat,
    flu_to_frd,
    ned_to_enu,
    quat_enu_flu_to_ned_frd,
    quat_from_euler,
    quat_multiply,
    quat_rotate,
)
from sim.follower.placement import AutopilotPose, place_room

finite = st.floats(-20.0, 20.0, allow_nan=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False)
tilt = st.floats(-1.2, 1.2, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)


def _same_rotation(q1, q2, tol=1e-9):
    return abs(abs(float(np.dot(q1, q2))) - 1.0) < tol


@settings(max_examples=200, deadline=None)
@given(home=vec3, heading=angle, start=vec3, pos_world=vec3, vel_world=vec3, rates=vec3, roll=tilt, pitch=tilt, yaw=angle)
def test_autopilot_pose_maps_to_the_room_pose_it_came_from(home, heading, start, pos_world, vel_world, rates, roll, pitch, yaw):
    placement = place_room(home, heading, start, 0.15)
    q_world = quat_from_euler(roll, pitch, yaw)
    # What the autopilot would report for that room pose: local ENU, then NED / FRD.
    pos_local = placement.local_position(pos_world)
    q_local = quat_multiply(quat_from_euler(0.0, 0.0, heading), q_world)
    pose = AutopilotPose(
        7, enu_to_ned(pos_local), enu_to_ned(placement.local_from_world(vel_world)), quat_enu_flu_to_ned_frd(q_local),
        flu_to_frd(rates),
    )  # fmt: skip
    kin = placement.kinematics(pose, on_ground=False)
    np.testing.assert_allclose(kin.pos_enu_m, pos_world, atol=1e-9)
    np.testing.assert_allclose(kin.vel_enu_m_s, vel_world, atol=1e-9)
    np.testing.assert_allclose(kin.angvel_body_flu_rad_s, rates, atol=1e-12)
    assert _same_rotation(kin.quat_enu_flu, q_world)
    # Body axes agree: the room's forward/left/up of the body are the autopilot's forward/right/down.
    for axis_flu in np.eye(3):
        world_axis = quat_rotate(kin.quat_enu_flu, axis_flu)
        local_axis = quat_rotate(quat_enu_flu_to_ned_frd(q_local), flu_to_frd(axis_flu))
        np.testing.assert_allclose(world_axis, placement.world_from_local(ned_to_enu(local_axis)), atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(home=vec3, heading=angle, start=vec3, v=vec3)
def test_world_and_local_are_inverse(home, heading, start, v):
    placement = place_room(home, heading, start, 0.15)
    np.testing.assert_allclose(placement.local_position(placement.world_position(v)), v, atol=1e-9)
    np.testing.assert_allclose(placement.world_from_local(placement.local_from_world(v)), v, atol=1e-9)
    assert math.isclose(np.linalg.norm(placement.world_from_local(v)), np.linalg.norm(v), rel_tol=1e-12, abs_tol=1e-12)


@given(heading=angle)
def test_home_is_the_start_on_the_floor_facing_the_room_x_axis(heading):
    home = np.array([3.0, -2.0, 0.4])
    placement = place_room(home, heading, np.array([1.5, 4.0, 1.8]), 0.15)
    np.testing.assert_allclose(placement.world_position(home), [1.5, 4.0, 0.15], atol=1e-12)
    ahead_local = np.array([math.cos(heading), math.sin(heading), 0.0])  # the autopilot's nose, local ENU
    np.testing.assert_allclose(placement.world_from_local(ahead_local), [1.0, 0.0, 0.0], atol=1e-12)
    q_local = quat_from_euler(0.0, 0.0, heading)
    assert abs(float(euler_from_quat(placement.world_quat(q_local))[2])) < 1e-9


def test_px4_north_heading_example():
    # PX4 SIH starts facing north: local ENU heading +90 deg.  A step north (NED x) is the room's +x.
    placement = place_room(np.zeros(3), math.pi / 2, np.array([1.0, 3.0, 1.5]), 0.15)
    north_ned = np.array([1.0, 0.0, 0.0])
    pose = AutopilotPose(0, north_ned, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3))
    kin = placement.kinematics(pose, on_ground=False)
    np.testing.assert_allclose(kin.pos_enu_m, [2.0, 3.0, 0.15], atol=1e-12)
    assert abs(kin.yaw_enu_rad) < 1e-12  # facing the room's +x
