"""What the runtime (or a pilot) asks for: offboard velocity setpoints from
SET_POSITION_TARGET_LOCAL_NED and stick inputs from MANUAL_CONTROL, resolved into world ENU.

PX4 resolves a MAV_FRAME_BODY_NED velocity on receipt: it rotates (forward, right, down) by the
vehicle's *current heading* (yaw only, no tilt) into local NED.  MAVSDK re-sends the setpoint at
20 Hz, so the world direction follows the heading as it turns.  We do the same.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from runtime.contract.frames import ned_to_enu, vehicle_to_world_enu

# type_mask bits (POSITION_TARGET_TYPEMASK): set = "ignore this field".
_IGNORE_POSITION = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
)
_IGNORE_VELOCITY = (
    mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
)
_IGNORE_YAW = mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
_IGNORE_YAW_RATE = mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE

_WORLD_FRAMES = (mavlink.MAV_FRAME_LOCAL_NED,)
# PX4 treats BODY_OFFSET_NED like BODY_NED for velocities (yaw-rotated body axes).
_BODY_FRAMES = (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED)

STICK_TIMEOUT_S = 0.5
STICK_DEADBAND = 0.05


class UnsupportedSetpointError(ValueError):
    """A position target this SITL vehicle cannot follow (it flies velocity setpoints only)."""


@dataclass(frozen=True)
class OffboardSetpoint:
    """A velocity setpoint resolved at receipt.

    vel_enu_m_s (3,): world ENU (m/s).  Exactly one of yaw_rate_enu_rad_s (rad/s, + = turn
    left) and yaw_enu_rad (absolute heading, counter-clockwise from east) is set; both None
    means "keep the heading".  t_rx_s: receipt time (time.monotonic, s).
    """

    t_rx_s: float
    vel_enu_m_s: np.ndarray
    yaw_rate_enu_rad_s: float | None
    yaw_enu_rad: float | None


def setpoint_from_position_target(
    frame: int,
    type_mask: int,
    vel_ned_or_body_m_s: tuple[float, float, float],
    yaw_ned_rad: float,
    yaw_rate_frd_rad_s: float,
    yaw_enu_now_rad: float,
    t_rx_s: float,
) -> OffboardSetpoint:
    """SET_POSITION_TARGET_LOCAL_NED fields -> :class:`OffboardSetpoint`.

    ``vel_ned_or_body_m_s`` is (vx, vy, vz) as sent: local NED for MAV_FRAME_LOCAL_NED,
    (forward, right, down) of the yaw-rotated body for MAV_FRAME_BODY_NED.  ``yaw_rate_frd_rad_s``
    is + = clockwise from above (turn right), ``yaw_ned_rad`` clockwise from north.
    Raises :class:`UnsupportedSetpointError` for position targets, unknown frames or NaN.
    """
    if type_mask & _IGNORE_POSITION != _IGNORE_POSITION:
        raise UnsupportedSetpointError(
            f"type_mask 0x{type_mask:X} asks for position control; this SITL vehicle follows velocity "
            "setpoints only (set the position-ignore bits, e.g. MAVSDK set_velocity_body sends 0x5C7)"
        )
    if type_mask & _IGNORE_VELOCITY:
        raise UnsupportedSetpointError(f"type_mask 0x{type_mask:X} ignores velocity: nothing to follow")
    vel = np.asarray(vel_ned_or_body_m_s, dtype=np.float64)
    if not np.all(np.isfinite(vel)):
        raise UnsupportedSetpointError(f"velocity {vel.tolist()} is not finite")
    if frame in _WORLD_FRAMES:
        vel_enu = ned_to_enu(vel)
    elif frame in _BODY_FRAMES:
        forward, right, down = vel
        vel_enu = vehicle_to_world_enu(np.array([forward, -right, -down]), yaw_enu_now_rad)
    else:
        raise UnsupportedSetpointError(
            f"coordinate frame {frame} is not supported; use MAV_FRAME_LOCAL_NED (1) or MAV_FRAME_BODY_NED (8)"
        )
    yaw_rate = None
    yaw = None
    if not type_mask & _IGNORE_YAW_RATE and math.isfinite(yaw_rate_frd_rad_s):
        yaw_rate = -float(yaw_rate_frd_rad_s)
    elif not type_mask & _IGNORE_YAW and math.isfinite(yaw_ned_rad):
        yaw = math.pi / 2.0 - float(yaw_ned_rad)
    return OffboardSetpoint(t_rx_s, vel_enu, yaw_rate, yaw)


@dataclass(frozen=True)
class Sticks:
    """A pilot's sticks, each in [-1, 1]: forward (pitch), right (roll), up (throttle about its
    centre), yaw_right (+ = turn right).  t_rx_s: receipt time (time.monotonic, s)."""

    t_rx_s: float
    forward: float
    right: float
    up: float
    yaw_right: float

    def is_centred(self) -> bool:
        return max(abs(self.forward), abs(self.right), abs(self.up), abs(self.yaw_right)) <= STICK_DEADBAND


def sticks_from_manual_control(x: int, y: int, z: int, r: int, t_rx_s: float) -> Sticks:
    """MANUAL_CONTROL axes (x, y, r in [-1000, 1000]; z throttle in [0, 1000], 500 = centre as in
    PX4's position mode) -> :class:`Sticks`."""

    def unit(value: float) -> float:
        return float(np.clip(value, -1.0, 1.0))

    return Sticks(t_rx_s, unit(x / 1000.0), unit(y / 1000.0), unit((z - 500) / 500.0), unit(r / 1000.0))
