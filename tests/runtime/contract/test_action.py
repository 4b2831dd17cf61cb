"""The action mapping and its MAVSDK form."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from runtime.contract import (
    ActionLimits,
    LimitError,
    action_to_mavsdk,
    action_to_velocity_flu,
    mavsdk_to_velocity_flu,
    velocity_flu_to_mavsdk,
)
from runtime.contract import constants as c

actions = arrays(np.float64, 3, elements=st.floats(-3, 3, allow_nan=False))


def test_paper_ranges():
    np.testing.assert_allclose(action_to_velocity_flu([-1, 0, 0]), [0, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(action_to_velocity_flu([1, 0, 0]), [2, 0, 0, 0], atol=1e-12)
    s = 2 * math.sqrt(0.5)
    np.testing.assert_allclose(action_to_velocity_flu([1, 1, 0]), [s, 0, s, 0], atol=1e-12)
    np.testing.assert_allclose(action_to_velocity_flu([0, 0, 1]), [1, 0, 0, math.pi / 3], atol=1e-12)


@given(actions)
def test_bounds_and_vy_zero(a):
    vx, vy, vz, wz = action_to_velocity_flu(a)
    speed = math.hypot(vx, vz)
    assert 0 <= speed <= c.MAX_SPEED_M_S + 1e-9
    assert vx >= -1e-12 and vy == 0
    assert abs(vz) <= speed * math.sin(c.MAX_INCLINATION_RAD) + 1e-9
    assert abs(wz) <= c.MAX_YAW_RATE_RAD_S + 1e-9


@given(actions, st.floats(0, 2), st.floats(0, math.pi / 4))
def test_tighter_limits_are_respected(a, max_speed, max_incl):
    limits = ActionLimits(max_speed_m_s=max_speed, max_inclination_rad=max_incl)
    vx, _, vz, _ = action_to_velocity_flu(a, limits)
    assert math.hypot(vx, vz) <= max_speed + 1e-9
    assert abs(math.atan2(vz, vx)) <= max_incl + 1e-9 or math.hypot(vx, vz) < 1e-12


def test_looser_limits_are_refused():
    with pytest.raises(LimitError, match="max_speed_m_s"):
        ActionLimits(max_speed_m_s=2.5)
    with pytest.raises(LimitError, match="max_inclination_rad"):
        ActionLimits(max_inclination_rad=1.0)


@given(arrays(np.float64, 4, elements=st.floats(-10, 10, allow_nan=False)))
def test_mavsdk_roundtrip(cmd):
    np.testing.assert_allclose(mavsdk_to_velocity_flu(velocity_flu_to_mavsdk(cmd)), cmd, atol=1e-9)


def test_mavsdk_signs():
    # Positive yaw action = turn left (FLU) = negative yaw speed in MAVSDK (FRD, + = right).
    left = action_to_mavsdk([0, 0, 1])
    assert left.yawspeed_deg_s == pytest.approx(-60.0)
    # Positive inclination = climb = negative down velocity.
    climb = action_to_mavsdk([1, 1, 0])
    assert climb.down_m_s < 0 and climb.forward_m_s > 0 and climb.right_m_s == 0


def test_nan_passes_through_for_the_watchdog():
    assert np.isnan(action_to_velocity_flu([np.nan, 0, 0])).any()
