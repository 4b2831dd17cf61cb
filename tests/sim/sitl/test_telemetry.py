"""Telemetry built from ground truth: NED/FRD conversions, home-relative positions, geodesy,
status bits."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from runtime.contract.frames import quat_from_euler
from sim.sitl.geodetic import GeodeticHome
from sim.sitl.kinematics import Kinematics
from sim.sitl.px4 import HOLD, OFFBOARD

PX4_ODOMETRY = Path(__file__).parents[2] / "runtime" / "fixtures" / "px4_v1_16_odometry.json"
from sim.sitl.telemetry import AutopilotStatus, Telemetry

HOME = np.array([2.0, 3.0, 0.15])
T_BOOT_NS = 1_000_000_000


def _kin(pos=(2.0, 3.0, 0.15), vel=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0), angvel=(0.0, 0.0, 0.0)) -> Kinematics:
    return Kinematics(
        t_ns=T_BOOT_NS + 2_500_000_000,
        pos_enu_m=np.array(pos, dtype=float),
        vel_enu_m_s=np.array(vel, dtype=float),
        quat_enu_flu=quat_from_euler(*rpy),
        angvel_body_flu_rad_s=np.array(angvel, dtype=float),
        on_ground=False,
    )


@pytest.fixture
def telemetry() -> Telemetry:
    return Telemetry(HOME, GeodeticHome(), T_BOOT_NS)


def _status(armed=False, mode=HOLD, armable=True, crashed=False) -> AutopilotStatus:
    return AutopilotStatus(armed, mode, mavlink.MAV_LANDED_STATE_IN_AIR, armable, crashed)


def test_heartbeat(telemetry):
    hb = telemetry.heartbeat(_status(armed=True, mode=OFFBOARD))
    assert (hb.type, hb.autopilot) == (mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4)
    assert hb.base_mode == mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.custom_mode == 6 << 16 and hb.system_status == mavlink.MAV_STATE_ACTIVE
    hb = telemetry.heartbeat(_status(crashed=True))
    assert hb.base_mode == mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and hb.system_status == mavlink.MAV_STATE_EMERGENCY


def test_sys_status_prearm_bit(telemetry):
    ok = telemetry.sys_status(_status())
    prearm = mavlink.MAV_SYS_STATUS_PREARM_CHECK
    # As PX4 v1.16: healthy, but never present nor enabled (the recorded start-up fixture).
    assert ok.onboard_control_sensors_health & prearm
    assert not ok.onboard_control_sensors_present & prearm and not ok.onboard_control_sensors_enabled & prearm
    for bit in (mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO, mavlink.MAV_SYS_STATUS_SENSOR_GPS):
        assert ok.onboard_control_sensors_present & ok.onboard_control_sensors_enabled & ok.onboard_control_sensors_health & bit
    assert not telemetry.sys_status(_status(armable=False)).onboard_control_sensors_health & prearm


def test_local_position_is_ned_relative_to_home(telemetry):
    msg = telemetry.local_position_ned(_kin(pos=(3.0, 5.0, 1.15), vel=(0.5, -1.0, 0.25)))
    assert (msg.x, msg.y, msg.z) == pytest.approx((2.0, 1.0, -1.0))
    assert (msg.vx, msg.vy, msg.vz) == pytest.approx((-1.0, 0.5, -0.25))
    assert msg.time_boot_ms == 2500


def test_heading_and_attitude_in_ned_frd(telemetry):
    # ENU yaw 0 (facing east) is NED yaw +90 deg; a left turn (FLU +z rate) is an FRD -z rate.
    kin = _kin(rpy=(0.1, -0.2, 0.0), angvel=(0.01, 0.02, 0.3))
    att = telemetry.attitude(kin)
    assert (att.roll, att.pitch, att.yaw) == pytest.approx((0.1, 0.2, math.pi / 2))
    assert (att.rollspeed, att.pitchspeed, att.yawspeed) == pytest.approx((0.01, -0.02, -0.3))
    q = telemetry.attitude_quaternion(kin)
    assert (q.rollspeed, q.pitchspeed, q.yawspeed) == pytest.approx((0.01, -0.02, -0.3))
    assert telemetry.global_position_int(kin).hdg == 9000


def test_odometry_velocity_is_local_ned_as_px4_sends_it(telemetry):
    odom = telemetry.odometry(_kin(vel=(0.0, 1.0, 0.0), rpy=(0.0, 0.0, 0.0)))  # facing east, moving north
    assert (odom.vx, odom.vy, odom.vz) == pytest.approx((1.0, 0.0, 0.0), abs=1e-9)
    recorded = json.loads(PX4_ODOMETRY.read_text())["pairs"][0]["odometry"]
    assert (odom.frame_id, odom.child_frame_id) == (recorded["frame_id"], recorded["child_frame_id"])
    assert odom.child_frame_id == mavlink.MAV_FRAME_LOCAL_NED


def test_global_position_and_home(telemetry):
    geo = GeodeticHome()
    home = telemetry.home_position(_kin())
    assert (home.latitude, home.longitude) == (round(geo.lat_deg * 1e7), round(geo.lon_deg * 1e7))
    assert home.altitude == round(geo.alt_amsl_m * 1000)
    gpi = telemetry.global_position_int(_kin(pos=(12.0, 3.0, 2.15)))  # 10 m east, 2 m up
    east, north, up = geo.to_enu(gpi.lat * 1e-7, gpi.lon * 1e-7, gpi.alt * 1e-3)
    assert (east, north, up) == pytest.approx((10.0, 0.0, 2.0), abs=0.02)
    assert gpi.relative_alt == 2000


@given(offset=st.lists(st.floats(-500.0, 500.0), min_size=3, max_size=3))
def test_geodetic_round_trip(offset):
    geo = GeodeticHome()
    np.testing.assert_allclose(geo.to_enu(*geo.to_geodetic(np.array(offset))), offset, atol=1e-6)


def test_build_serves_request_message(telemetry):
    assert telemetry.can_build(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert not telemetry.can_build(mavlink.MAVLINK_MSG_ID_BATTERY_STATUS)
    version = telemetry.build(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, _kin(), _status())
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
