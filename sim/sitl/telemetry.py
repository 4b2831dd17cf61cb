"""The MAVLink telemetry a PX4 autopilot sends, built from ground truth.

World ENU / body FLU in, NED / FRD out (``runtime.contract.frames``).  Local NED positions are
relative to home (PX4's local origin is where its estimator started: the take-off point).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from runtime.contract.frames import (
    enu_to_ned,
    euler_from_quat,
    flu_to_frd,
    quat_enu_flu_to_ned_frd,
)

from .geodetic import GeodeticHome
from .kinematics import Kinematics
from .px4 import Px4Mode

# PX4 v1.16.0 release: major << 24 | minor << 16 | patch << 8 | FIRMWARE_VERSION_TYPE_OFFICIAL.
FLIGHT_SW_VERSION = (1 << 24) | (16 << 16) | (0 << 8) | mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL
VEHICLE_UID = 0x434D4E4156534954  # "CMNAVSIT"
CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT  # PX4 serves missions as MISSION_ITEM_INT (sim.sitl.mission)
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
)
# Sensors and controllers a healthy PX4 multicopter reports present, enabled and healthy.  The
# pre-arm check is reported only in the health bits, as PX4 v1.16 does.
SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_AHRS
)
BATTERY_VOLTAGE_MV = 16_200
_NAN_COVARIANCE = [math.nan] + [0.0] * 20


@dataclass(frozen=True)
class AutopilotStatus:
    """The commander's side of the telemetry: armed, mode, MAV_LANDED_STATE, pre-arm ok, crashed."""

    armed: bool
    mode: Px4Mode
    landed_state: int
    armable: bool
    crashed: bool
    booted: bool = True  # past PX4's start-up: HEARTBEAT STANDBY, not UNINIT


class Telemetry:
    """Builds each telemetry message; ``build(msg_id, ...)`` serves both the periodic streams and
    REQUEST_MESSAGE."""

    def __init__(self, home_enu_m: np.ndarray, geodetic_home: GeodeticHome, t_boot_ns: int) -> None:
        self._home_enu_m = np.asarray(home_enu_m, dtype=np.float64)
        self._geo = geodetic_home
        self._t_boot_ns = t_boot_ns
        # Several messages per tick need the NED/FRD attitude of the same state: compute it once.
        self._attitude_of: tuple[Kinematics, np.ndarray, np.ndarray] | None = None
        self._builders = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: lambda kin, st: self.heartbeat(st),
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: lambda kin, st: self.sys_status(st),
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: lambda kin, st: self.extended_sys_state(st),
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: lambda kin, st: self.home_position(kin),
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: lambda kin, st: self.autopilot_version(),
            mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: lambda kin, st: self.attitude_quaternion(kin),
            mavlink.MAVLINK_MSG_ID_ATTITUDE: lambda kin, st: self.attitude(kin),
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: lambda kin, st: self.local_position_ned(kin),
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: lambda kin, st: self.global_position_int(kin),
            mavlink.MAVLINK_MSG_ID_ODOMETRY: lambda kin, st: self.odometry(kin),
            mavlink.MAVLINK_MSG_ID_ALTITUDE: lambda kin, st: self.altitude(kin),
            mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION: lambda kin, st: self.hil_state_quaternion(kin),
        }

    def can_build(self, msg_id: int) -> bool:
        return msg_id in self._builders

    def build(self, msg_id: int, kin: Kinematics, status: AutopilotStatus) -> mavlink.MAVLink_message:
        """Message ``msg_id`` for this state; KeyError if it is not one this vehicle sends."""
        return self._builders[msg_id](kin, status)

    # ---- time -----------------------------------------------------------------------------

    def _time_boot_ms(self, t_ns: int) -> int:
        return ((t_ns - self._t_boot_ns) // 1_000_000) & 0xFFFFFFFF

    def _time_usec(self, t_ns: int) -> int:
        return max(0, (t_ns - self._t_boot_ns) // 1_000)

    # ---- status ---------------------------------------------------------------------------

    def heartbeat(self, status: AutopilotStatus) -> mavlink.MAVLink_message:
        base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if status.armed:
            base_mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if status.crashed:
            system_status = mavlink.MAV_STATE_EMERGENCY
        elif not status.booted:
            system_status = mavlink.MAV_STATE_UNINIT
        elif status.armed:
            system_status = mavlink.MAV_STATE_ACTIVE
        else:
            system_status = mavlink.MAV_STATE_STANDBY
        return mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base_mode, status.mode.custom_mode, system_status, 3
        )

    def sys_status(self, status: AutopilotStatus) -> mavlink.MAVLink_message:
        health = SENSORS
        if status.armable:
            health |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
        if status.crashed:
            health &= ~mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
        return mavlink.MAVLink_sys_status_message(
            SENSORS, SENSORS, health, 100, BATTERY_VOLTAGE_MV, -1, 100, 0, 0, 0, 0, 0, 0, 0, 0, 0
        )

    def extended_sys_state(self, status: AutopilotStatus) -> mavlink.MAVLink_message:
        return mavlink.MAVLink_extended_sys_state_message(mavlink.MAV_VTOL_STATE_UNDEFINED, status.landed_state)

    def home_position(self, kin: Kinematics) -> mavlink.MAVLink_message:
        lat, lon, alt = self._geo.to_geodetic(np.zeros(3))
        return mavlink.MAVLink_home_position_message(
            int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, self._time_usec(kin.t_ns),
        )  # fmt: skip

    def autopilot_version(self) -> mavlink.MAVLink_message:
        return mavlink.MAVLink_autopilot_version_message(
            CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, VEHICLE_UID, [0] * 18
        )

    # ---- state estimate (here: ground truth) ----------------------------------------------

    def _attitude_ned_frd(self, kin: Kinematics) -> tuple[np.ndarray, np.ndarray]:
        """(quat FRD -> NED (w, x, y, z), body rates FRD rad/s)."""
        if self._attitude_of is None or self._attitude_of[0] is not kin:
            self._attitude_of = (kin, quat_enu_flu_to_ned_frd(kin.quat_enu_flu), flu_to_frd(kin.angvel_body_flu_rad_s))
        return self._attitude_of[1], self._attitude_of[2]

    def attitude_quaternion(self, kin: Kinematics) -> mavlink.MAVLink_message:
        q, rates = self._attitude_ned_frd(kin)
        return mavlink.MAVLink_attitude_quaternion_message(
            self._time_boot_ms(kin.t_ns), *(float(v) for v in q), *(float(v) for v in rates), [0.0, 0.0, 0.0, 0.0]
        )

    def attitude(self, kin: Kinematics) -> mavlink.MAVLink_message:
        q, rates = self._attitude_ned_frd(kin)
        roll, pitch, yaw = (float(v) for v in euler_from_quat(q))
        return mavlink.MAVLink_attitude_message(self._time_boot_ms(kin.t_ns), roll, pitch, yaw, *(float(v) for v in rates))

    def local_position_ned(self, kin: Kinematics) -> mavlink.MAVLink_message:
        pos = enu_to_ned(kin.pos_enu_m - self._home_enu_m)
        vel = enu_to_ned(kin.vel_enu_m_s)
        return mavlink.MAVLink_local_position_ned_message(
            self._time_boot_ms(kin.t_ns), *(float(v) for v in pos), *(float(v) for v in vel)
        )

    def global_position_int(self, kin: Kinematics) -> mavlink.MAVLink_message:
        offset = kin.pos_enu_m - self._home_enu_m
        lat, lon, alt = self._geo.to_geodetic(offset)
        vel_cm_s = np.round(enu_to_ned(kin.vel_enu_m_s) * 100.0).astype(int)
        yaw_ned = float(euler_from_quat(self._attitude_ned_frd(kin)[0])[2])
        heading_cdeg = int(round(math.degrees(yaw_ned) * 100.0)) % 36000
        return mavlink.MAVLink_global_position_int_message(
            self._time_boot_ms(kin.t_ns), int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            int(round(offset[2] * 1000)), *(int(v) for v in vel_cm_s), heading_cdeg,
        )  # fmt: skip

    def odometry(self, kin: Kinematics) -> mavlink.MAVLink_message:
        """Pose and velocity in local NED (``child_frame_id`` MAV_FRAME_LOCAL_NED), as PX4 v1.16
        sends it (recorded: tests/runtime/fixtures/px4_v1_16_odometry.json)."""
        q, rates = self._attitude_ned_frd(kin)
        pos = enu_to_ned(kin.pos_enu_m - self._home_enu_m)
        vel_ned = enu_to_ned(kin.vel_enu_m_s)
        return mavlink.MAVLink_odometry_message(
            self._time_usec(kin.t_ns), mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_NED,
            *(float(v) for v in pos), [float(v) for v in q], *(float(v) for v in vel_ned),
            *(float(v) for v in rates), _NAN_COVARIANCE, _NAN_COVARIANCE, 0, mavlink.MAV_ESTIMATOR_TYPE_NAIVE, 100,
        )  # fmt: skip

    def hil_state_quaternion(self, kin: Kinematics) -> mavlink.MAVLink_message:
        """The simulator's ground truth, as PX4 SIH streams it on request: geodetic position,
        velocity NED (cm/s), attitude FRD -> NED, body rates (our state is exact: the same as the
        estimate)."""
        q, rates = self._attitude_ned_frd(kin)
        lat, lon, alt = self._geo.to_geodetic(kin.pos_enu_m - self._home_enu_m)
        vel_ned = enu_to_ned(kin.vel_enu_m_s)
        return mavlink.MAVLink_hil_state_quaternion_message(
            self._time_usec(kin.t_ns), [float(v) for v in q], *(float(v) for v in rates),
            int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            *(int(round(v * 100)) for v in vel_ned), 0, 0, 0, 0, 0,
        )  # fmt: skip

    def altitude(self, kin: Kinematics) -> mavlink.MAVLink_message:
        """Altitudes above home and AMSL; bottom clearance = height above the floor (z = 0)."""
        rel_m = float(kin.pos_enu_m[2] - self._home_enu_m[2])
        amsl_m = self._geo.alt_amsl_m + rel_m
        return mavlink.MAVLink_altitude_message(
            self._time_usec(kin.t_ns), amsl_m, amsl_m, rel_m, rel_m, math.nan, float(kin.pos_enu_m[2]),
        )  # fmt: skip
