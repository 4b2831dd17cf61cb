"""MAVSDK telemetry (NED/FRD) -> VehicleState (ENU/FLU), without a vehicle."""

import math

import numpy as np
import pytest
from mavsdk.asyncio.plugins.telemetry import (
    AngularVelocityBody, HomePosition, PositionNed, PositionVelocityNed, Quaternion, VelocityNed,
)  # fmt: skip

from runtime.contract.frames import quat_enu_flu_to_ned_frd, quat_from_euler
from runtime.state import VehicleState
from runtime.vehicle import _angvel_fields, _attitude_fields, _home_fields, _posvel_fields


def _px4_quaternion(roll_rad: float, pitch_rad: float, yaw_enu_rad: float) -> Quaternion:
    w, x, y, z = quat_enu_flu_to_ned_frd(quat_from_euler(roll_rad, pitch_rad, yaw_enu_rad))
    return Quaternion(w=w, x=x, y=y, z=z)


def test_heading_north_in_px4_is_yaw_plus_90_deg_in_enu():
    # PX4 yaw 0 = facing north; in ENU north is +y, i.e. yaw +pi/2.
    q_north = Quaternion(w=1.0, x=0.0, y=0.0, z=0.0)
    state = VehicleState(**_attitude_fields(q_north))
    assert state.yaw_enu_rad == pytest.approx(math.pi / 2)


def test_position_velocity_ned_to_enu_and_body_velocity():
    pv = PositionVelocityNed(PositionNed(north_m=2.0, east_m=1.0, down_m=-3.0), VelocityNed(1.0, 0.0, -0.5))
    fields = {**_posvel_fields(pv), **_attitude_fields(_px4_quaternion(0.0, 0.0, math.pi / 2))}
    state = VehicleState(**fields, home_enu_m=np.zeros(3))
    np.testing.assert_allclose(state.pos_enu_m, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(state.vel_enu_m_s, [0.0, 1.0, 0.5])
    # Facing north (ENU yaw +90 deg), flying north and climbing: body forward and up.
    np.testing.assert_allclose(state.vel_body_flu_m_s, [1.0, 0.0, 0.5], atol=1e-9)
    assert state.height_above_home_m == pytest.approx(3.0)


def test_body_rates_frd_to_flu():
    # FRD yaw rate +0.3 (turning right, clockwise from above) = FLU -0.3.
    fields = _angvel_fields(AngularVelocityBody(roll_rad_s=0.1, pitch_rad_s=0.2, yaw_rad_s=0.3))
    np.testing.assert_allclose(fields["angvel_body_flu_rad_s"], [0.1, -0.2, -0.3])


def test_home_local_position_and_missing_home():
    home = HomePosition(local_north_m=4.0, local_east_m=-1.0, local_down_m=0.5)
    np.testing.assert_allclose(_home_fields(home)["home_enu_m"], [-1.0, 4.0, -0.5])
    assert _home_fields(HomePosition()) == {}  # NaN local position: no home yet


def test_fresh_state_is_never_received():
    state = VehicleState()
    assert state.t_telemetry_ns == 0 and state.home_enu_m is None and math.isnan(state.height_above_home_m)
