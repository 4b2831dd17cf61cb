"""Policy action -> velocity command, and its MAVSDK ``VelocityBodyYawspeed`` form.

a in [-1, 1]^3 (clipped): speed = (a1 + 1) * 1 m/s in [0, 2]; inclination = a2 * pi/4;
yaw rate = a3 * pi/3 rad/s.  Body FLU command: vx = speed cos(incl), vy = 0,
vz = speed sin(incl), wz = yaw rate (positive = turn left).  A deployment may clamp speed and
inclination tighter than the contract, never looser.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .constants import ACTION_DIM, MAX_INCLINATION_RAD, MAX_SPEED_M_S, MAX_YAW_RATE_RAD_S


class LimitError(ValueError):
    """A configured limit is looser than the contract allows."""


@dataclass(frozen=True)
class ActionLimits:
    """Deployment limits; each must be within the contract's (never looser)."""

    max_speed_m_s: float = MAX_SPEED_M_S
    max_inclination_rad: float = MAX_INCLINATION_RAD

    def __post_init__(self) -> None:
        if not 0.0 <= self.max_speed_m_s <= MAX_SPEED_M_S:
            raise LimitError(f"max_speed_m_s={self.max_speed_m_s} must be in [0, {MAX_SPEED_M_S}]")
        if not 0.0 <= self.max_inclination_rad <= MAX_INCLINATION_RAD:
            raise LimitError(
                f"max_inclination_rad={self.max_inclination_rad} must be in [0, {MAX_INCLINATION_RAD:.6f}]"
            )


@dataclass(frozen=True)
class VelocityBodyYawspeed:
    """The command as MAVSDK takes it: body FRD velocity (m/s) and yaw speed (deg/s, + = right)."""

    forward_m_s: float
    right_m_s: float
    down_m_s: float
    yawspeed_deg_s: float


HOVER = VelocityBodyYawspeed(0.0, 0.0, 0.0, 0.0)


def clip_action(action: np.ndarray) -> np.ndarray:
    """Clip a raw action to [-1, 1]; NaN stays NaN so the watchdog can see it."""
    return np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)


def action_to_velocity_flu(action: np.ndarray, limits: ActionLimits = ActionLimits()) -> np.ndarray:
    """Action(s) (..., 3) -> body FLU command (..., 4): vx, vy, vz (m/s), yaw rate (rad/s)."""
    a = clip_action(action)
    if a.shape[-1] != ACTION_DIM:
        raise ValueError(f"action must have {ACTION_DIM} values on its last axis, got shape {a.shape}")
    speed = np.minimum((a[..., 0] + 1.0) * (MAX_SPEED_M_S / 2.0), limits.max_speed_m_s)
    incl = np.clip(a[..., 1] * MAX_INCLINATION_RAD, -limits.max_inclination_rad, limits.max_inclination_rad)
    yaw_rate = a[..., 2] * MAX_YAW_RATE_RAD_S
    return np.stack([speed * np.cos(incl), np.zeros_like(speed), speed * np.sin(incl), yaw_rate], axis=-1)


def velocity_flu_to_mavsdk(cmd_flu: np.ndarray) -> VelocityBodyYawspeed:
    """Body FLU command (vx, vy, vz, wz) -> MAVSDK's FRD form (yaw speed in deg/s, + = right)."""
    vx, vy, vz, wz = (float(x) for x in np.asarray(cmd_flu, dtype=np.float64))
    return VelocityBodyYawspeed(
        forward_m_s=vx, right_m_s=-vy, down_m_s=-vz, yawspeed_deg_s=-float(np.degrees(wz))
    )


def mavsdk_to_velocity_flu(cmd: VelocityBodyYawspeed) -> np.ndarray:
    """Inverse of :func:`velocity_flu_to_mavsdk`."""
    return np.array(
        [cmd.forward_m_s, -cmd.right_m_s, -cmd.down_m_s, -np.radians(cmd.yawspeed_deg_s)], dtype=np.float64
    )


def action_to_mavsdk(action: np.ndarray, limits: ActionLimits = ActionLimits()) -> VelocityBodyYawspeed:
    """One action -> the MAVSDK command the runtime sends."""
    return velocity_flu_to_mavsdk(action_to_velocity_flu(action, limits))
