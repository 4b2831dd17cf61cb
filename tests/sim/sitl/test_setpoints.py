"""SET_POSITION_TARGET_LOCAL_NED and MANUAL_CONTROL resolved into world ENU, as PX4 does."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from runtime.contract.action import velocity_flu_to_mavsdk
from sim.sitl.setpoints import UnsupportedSetpointError, setpoint_from_position_target, sticks_from_manual_control

BODY = mavlink.MAV_FRAME_BODY_NED
MASK = 0x5C7  # velocity + yaw rate, as MAVSDK set_velocity_body sends
angles = st.floats(-math.pi, math.pi)
speeds = st.floats(-3.0, 3.0)


@given(yaw=angles, forward=speeds, right=speeds, down=speeds)
def test_body_ned_velocity_is_rotated_by_the_current_heading(yaw, forward, right, down):
    sp = setpoint_from_position_target(BODY, MASK, (forward, right, down), 0.0, 0.0, yaw, 1.0)
    c, s = math.cos(yaw), math.sin(yaw)
    # forward along the heading, right = heading rotated clockwise, down = -up
    expected = forward * np.array([c, s, 0.0]) + right * np.array([s, -c, 0.0]) + np.array([0.0, 0.0, -down])
    np.testing.assert_allclose(sp.vel_enu_m_s, expected, atol=1e-9)


@given(vx=speeds, vz=speeds, wz=st.floats(-1.0, 1.0), yaw=angles)
def test_the_runtime_mapping_round_trips(vx, vz, wz, yaw):
    """A body FLU command sent the runtime's way (contract mapping, deg/s -> rad/s on the wire as
    MAVSDK does) comes out as the same body command in the world."""
    cmd = velocity_flu_to_mavsdk(np.array([vx, 0.0, vz, wz]))
    sp = setpoint_from_position_target(
        BODY, MASK, (cmd.forward_m_s, cmd.right_m_s, cmd.down_m_s), 0.0, math.radians(cmd.yawspeed_deg_s), yaw, 0.0
    )
    np.testing.assert_allclose(sp.vel_enu_m_s, [vx * math.cos(yaw), vx * math.sin(yaw), vz], atol=1e-9)
    assert sp.yaw_rate_enu_rad_s == pytest.approx(wz, abs=1e-9)
    assert sp.yaw_enu_rad is None


def test_positive_frd_yaw_rate_turns_right():
    sp = setpoint_from_position_target(BODY, MASK, (0.0, 0.0, 0.0), 0.0, 0.5, 0.0, 0.0)
    assert sp.yaw_rate_enu_rad_s == -0.5  # ENU: counter-clockwise positive, so right is negative


def test_local_ned_velocity_and_heading_target():
    mask = 0x9C7  # velocity + yaw angle
    sp = setpoint_from_position_target(mavlink.MAV_FRAME_LOCAL_NED, mask, (1.0, 2.0, 3.0), 0.0, 0.0, 1.0, 0.0)
    np.testing.assert_allclose(sp.vel_enu_m_s, [2.0, 1.0, -3.0])
    assert sp.yaw_rate_enu_rad_s is None and sp.yaw_enu_rad == pytest.approx(math.pi / 2)  # north


def test_both_yaw_fields_ignored_keeps_heading():
    sp = setpoint_from_position_target(BODY, 0xDC7, (0.0, 0.0, 0.0), 1.0, 1.0, 0.0, 0.0)
    assert sp.yaw_rate_enu_rad_s is None and sp.yaw_enu_rad is None


@pytest.mark.parametrize(
    "frame, mask, vel, match",
    [
        (BODY, 0x5C0, (0.0, 0.0, 0.0), "position control"),
        (BODY, 0x5FF, (0.0, 0.0, 0.0), "ignores velocity"),
        (mavlink.MAV_FRAME_GLOBAL_INT, MASK, (0.0, 0.0, 0.0), "coordinate frame"),
        (BODY, MASK, (math.nan, 0.0, 0.0), "not finite"),
    ],
)
def test_unsupported_setpoints_name_the_problem(frame, mask, vel, match):
    with pytest.raises(UnsupportedSetpointError, match=match):
        setpoint_from_position_target(frame, mask, vel, 0.0, 0.0, 0.0, 0.0)


def test_sticks_scale_and_centre():
    sticks = sticks_from_manual_control(1000, -500, 500, 2000, 3.0)
    assert (sticks.forward, sticks.right, sticks.up, sticks.yaw_right) == (1.0, -0.5, 0.0, 1.0)
    assert sticks_from_manual_control(10, -10, 510, 0, 0.0).is_centred()
    assert not sticks_from_manual_control(0, 0, 1000, 0, 0.0).is_centred()
