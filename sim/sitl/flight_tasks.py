"""What each PX4 mode asks of the velocity controller: position hold (braking to a stop first
when engaged in flight), take-off climb, landing descent, offboard velocity, position-mode
sticks.  Each returns a world-ENU velocity and a yaw rate for ``sim.dynamics.QuadrotorDynamics``
(which plays PX4's velocity/attitude loops).

Gains and limits follow PX4's multicopter position controller defaults where they matter
(MPC_XY_P 0.95, MPC_Z_P 1, MC_YAW_P 2.8), rounded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.contract.frames import vehicle_to_world_enu, wrap_angle

from .kinematics import Kinematics
from .setpoints import OffboardSetpoint, Sticks

POSITION_GAIN_XY_1_S = 1.0
POSITION_GAIN_Z_1_S = 1.0
YAW_GAIN_1_S = 2.8
HOLD_MAX_SPEED_XY_M_S = 2.0
HOLD_MAX_SPEED_UP_M_S = 1.0
HOLD_MAX_SPEED_DOWN_M_S = 0.7
MAX_YAW_RATE_RAD_S = math.radians(60.0)
# Hold and Position mode lock the position once braking brought the speed below this (m/s).
LOCK_SPEED_M_S = 0.1
# Position mode: full stick deflection (PX4's MPC_VEL_MANUAL is faster; indoors we keep it slow).
STICK_MAX_SPEED_XY_M_S = 2.0
STICK_MAX_SPEED_Z_M_S = 1.0


@dataclass(frozen=True)
class VelocityCommand:
    """Input of the velocity controller: world ENU velocity (m/s) and yaw rate (rad/s, + = left)."""

    vel_enu_m_s: np.ndarray
    yaw_rate_enu_rad_s: float



def stopping_point(kin: Kinematics) -> np.ndarray:
    """Where a P-controlled position hold engaged now settles: pos + vel / gain (world ENU, m).

    Take-off and landing hold x, y here: their first command equals the current velocity, so
    they never jump back to where the switch happened.
    """
    gains = np.array([POSITION_GAIN_XY_1_S, POSITION_GAIN_XY_1_S, POSITION_GAIN_Z_1_S])
    target = kin.pos_enu_m + kin.vel_enu_m_s / gains
    if kin.on_ground:
        target[2] = kin.pos_enu_m[2]
    return target


class Brake:
    """Hold engaged in flight, as PX4's position lock does it: brake to a stop first (a zero
    velocity setpoint, as hard as the velocity loop and the tilt limit allow), then lock the
    position where the speed fell below LOCK_SPEED_M_S and hold that.

    A hold that aimed at a point computed at the switch would either crawl to it (P-control
    from far away) or overshoot and fly back; braking first and locking where the vehicle
    stopped does neither.  Mutable: the lock is taken by :meth:`command`.
    """

    def __init__(self, lock_enu_m: np.ndarray | None = None) -> None:
        self.lock_enu_m = None if lock_enu_m is None else np.asarray(lock_enu_m, dtype=np.float64).copy()

    @classmethod
    def engage(cls, kin: Kinematics) -> "Brake":
        """Brake from the vehicle's state now (a landed vehicle holds where it is)."""
        return cls(kin.pos_enu_m if kin.on_ground else None)

    def command(self, kin: Kinematics, target_yaw_enu_rad: float) -> VelocityCommand:
        """Zero velocity until the vehicle is slower than LOCK_SPEED_M_S, then hold that position."""
        if self.lock_enu_m is None and float(np.linalg.norm(kin.vel_enu_m_s)) < LOCK_SPEED_M_S:
            self.lock_enu_m = np.asarray(kin.pos_enu_m, dtype=np.float64).copy()
        if self.lock_enu_m is None:
            return VelocityCommand(np.zeros(3), yaw_rate_towards(kin.yaw_enu_rad, target_yaw_enu_rad))
        return hold_position(kin, self.lock_enu_m, target_yaw_enu_rad)


def yaw_rate_towards(yaw_enu_rad: float, target_yaw_enu_rad: float) -> float:
    """P-control of the heading (rad/s, + = left), limited to MAX_YAW_RATE_RAD_S."""
    error = float(wrap_angle(target_yaw_enu_rad - yaw_enu_rad))
    return float(np.clip(YAW_GAIN_1_S * error, -MAX_YAW_RATE_RAD_S, MAX_YAW_RATE_RAD_S))


def hold_position(kin: Kinematics, target_enu_m: np.ndarray, target_yaw_enu_rad: float) -> VelocityCommand:
    """P-control towards target_enu_m with PX4-like speed limits, holding the heading."""
    error = np.asarray(target_enu_m, dtype=np.float64) - kin.pos_enu_m
    vel_xy = POSITION_GAIN_XY_1_S * error[:2]
    speed_xy = float(np.linalg.norm(vel_xy))
    if speed_xy > HOLD_MAX_SPEED_XY_M_S:
        vel_xy *= HOLD_MAX_SPEED_XY_M_S / speed_xy
    vel_z = float(np.clip(POSITION_GAIN_Z_1_S * error[2], -HOLD_MAX_SPEED_DOWN_M_S, HOLD_MAX_SPEED_UP_M_S))
    return VelocityCommand(np.array([vel_xy[0], vel_xy[1], vel_z]), yaw_rate_towards(kin.yaw_enu_rad, target_yaw_enu_rad))


def climb_to(
    kin: Kinematics, target_enu_m: np.ndarray, target_yaw_enu_rad: float, climb_speed_m_s: float
) -> VelocityCommand:
    """Take-off: hold x, y and heading, climb to target z at up to climb_speed_m_s."""
    hold = hold_position(kin, target_enu_m, target_yaw_enu_rad)
    error_z = float(target_enu_m[2] - kin.pos_enu_m[2])
    vel_z = float(np.clip(POSITION_GAIN_Z_1_S * error_z, -HOLD_MAX_SPEED_DOWN_M_S, climb_speed_m_s))
    return VelocityCommand(np.array([hold.vel_enu_m_s[0], hold.vel_enu_m_s[1], vel_z]), hold.yaw_rate_enu_rad_s)


def descend(
    kin: Kinematics, target_enu_m: np.ndarray, target_yaw_enu_rad: float, land_speed_m_s: float
) -> VelocityCommand:
    """Landing: hold x, y and heading, descend at land_speed_m_s until the ground stops us."""
    hold = hold_position(kin, target_enu_m, target_yaw_enu_rad)
    return VelocityCommand(np.array([hold.vel_enu_m_s[0], hold.vel_enu_m_s[1], -land_speed_m_s]), hold.yaw_rate_enu_rad_s)


def follow_setpoint(kin: Kinematics, setpoint: OffboardSetpoint, hold_yaw_enu_rad: float) -> VelocityCommand:
    """Offboard: the setpoint's velocity; its yaw rate, or P-control to its heading, or keep
    ``hold_yaw_enu_rad`` when it carries neither."""
    if setpoint.yaw_rate_enu_rad_s is not None:
        yaw_rate = setpoint.yaw_rate_enu_rad_s
    else:
        target = setpoint.yaw_enu_rad if setpoint.yaw_enu_rad is not None else hold_yaw_enu_rad
        yaw_rate = yaw_rate_towards(kin.yaw_enu_rad, target)
    return VelocityCommand(setpoint.vel_enu_m_s.copy(), yaw_rate)


def fly_sticks(kin: Kinematics, sticks: Sticks) -> VelocityCommand:
    """Position mode with deflected sticks: velocity in the yaw-rotated body frame."""
    vel_v = np.array(
        [sticks.forward * STICK_MAX_SPEED_XY_M_S, -sticks.right * STICK_MAX_SPEED_XY_M_S, sticks.up * STICK_MAX_SPEED_Z_M_S]
    )
    return VelocityCommand(vehicle_to_world_enu(vel_v, kin.yaw_enu_rad), -sticks.yaw_right * MAX_YAW_RATE_RAD_S)
