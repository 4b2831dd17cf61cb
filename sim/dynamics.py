"""Batched quadrotor point-mass dynamics behind a PX4-like velocity-tracking controller.

The controller plays the autopilot's role: it tracks a world-ENU velocity setpoint and a yaw-rate
setpoint.  Desired acceleration = P-gain x velocity error + drag feed-forward, vertical part
clamped to the vertical-acceleration limits, horizontal part clamped so the thrust axis stays
within the tilt limit.  The thrust axis follows its setpoint with a first-order lag (time
constant ``attitude_tau_s``), the yaw rate follows its setpoint with another (``yaw_rate_tau_s``);
collective thrust is the desired specific force projected on the actual thrust axis.  Linear
drag, gravity and an optional external (kick) force act on the body; integration is
semi-implicit Euler (velocity first, then position with the new velocity).

Frames: world ENU (z up), body FLU; quaternions (w, x, y, z) rotate body FLU into world ENU,
Euler angles are intrinsic Z-Y-X as in ``runtime.contract.frames`` (positive yaw rate turns
left, i.e. counter-clockwise seen from above).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from .rotations import (
    euler_from_quat,
    quat_conjugate,
    quat_from_euler,
    quat_log,
    quat_multiply,
    quat_rotate,
    quat_rotate_inverse,
    rotate_about_z,
)

GRAVITY_M_S2 = 9.81


@dataclass(frozen=True)
class DynamicsParams:
    """Vehicle and controller parameters (SI units)."""

    mass_kg: float = 1.0
    max_tilt_rad: float = math.radians(35.0)
    max_accel_up_m_s2: float = 4.0
    max_accel_down_m_s2: float = 4.0
    velocity_gain_1_s: float = 3.0
    attitude_tau_s: float = 0.1
    yaw_rate_tau_s: float = 0.1
    linear_drag_kg_s: float = 0.1
    # The body origin cannot sink below the floor (z = 0): the ground pushes back.
    ground_contact: bool = True

    def validate(self) -> None:
        """Raise ValueError naming the parameter that is out of range."""
        positive = ("mass_kg", "max_accel_up_m_s2", "max_accel_down_m_s2", "velocity_gain_1_s",
                    "attitude_tau_s", "yaw_rate_tau_s")
        for key in positive:
            if not getattr(self, key) > 0.0:
                raise ValueError(f"DynamicsParams.{key}={getattr(self, key)} must be > 0")
        if not 0.0 < self.max_tilt_rad < math.pi / 2:
            raise ValueError(f"DynamicsParams.max_tilt_rad={self.max_tilt_rad} must be in (0, pi/2)")
        if self.max_accel_down_m_s2 >= GRAVITY_M_S2:
            raise ValueError(
                f"DynamicsParams.max_accel_down_m_s2={self.max_accel_down_m_s2} must be below g={GRAVITY_M_S2}"
            )
        if self.linear_drag_kg_s < 0.0:
            raise ValueError(f"DynamicsParams.linear_drag_kg_s={self.linear_drag_kg_s} must be >= 0")


@dataclass
class QuadState:
    """Vehicle state of B envs: pos_enu_m [B, 3], vel_enu_m_s [B, 3] (world ENU),
    quat_enu_flu [B, 4] (w, x, y, z; body FLU -> world ENU), angvel_body_flu_rad_s [B, 3]."""

    pos_enu_m: Tensor
    vel_enu_m_s: Tensor
    quat_enu_flu: Tensor
    angvel_body_flu_rad_s: Tensor

    @classmethod
    def at_rest(cls, pos_enu_m: Tensor, yaw_enu_rad: Tensor | float = 0.0) -> QuadState:
        """Level and still at pos_enu_m [B, 3], heading yaw_enu_rad (scalar or [B])."""
        yaw = torch.as_tensor(yaw_enu_rad, dtype=pos_enu_m.dtype, device=pos_enu_m.device)
        yaw = yaw.expand(pos_enu_m.shape[0])
        zeros = torch.zeros_like(yaw)
        return cls(
            pos_enu_m=pos_enu_m.clone(),
            vel_enu_m_s=torch.zeros_like(pos_enu_m),
            quat_enu_flu=quat_from_euler(zeros, zeros, yaw),
            angvel_body_flu_rad_s=torch.zeros_like(pos_enu_m),
        )

    @property
    def batch_size(self) -> int:
        return int(self.pos_enu_m.shape[0])

    def vel_body_flu_m_s(self) -> Tensor:
        """[B, 3] linear velocity in the body FLU frame (m/s)."""
        return vel_body_flu(self.quat_enu_flu, self.vel_enu_m_s)

    def euler_rad(self) -> Tensor:
        """[B, 3] roll, pitch, yaw (rad), the contract's Z-Y-X convention (pitch + = nose down)."""
        return euler_from_quat(self.quat_enu_flu)

    def roll_pitch_rad(self) -> Tensor:
        """[B, 2] roll, pitch (rad) as the observation carries them."""
        return self.euler_rad()[:, :2]

    def yaw_enu_rad(self) -> Tensor:
        """[B] heading (rad), counter-clockwise from east."""
        return self.euler_rad()[:, 2]

    def tilt_rad(self) -> Tensor:
        """[B] angle between the body up axis (thrust axis) and world up (rad)."""
        up_enu = quat_rotate(self.quat_enu_flu, _unit_z_like(self.pos_enu_m))
        return torch.acos(up_enu[:, 2].clamp(-1.0, 1.0))

    def to(self, device: torch.device | str) -> QuadState:
        return QuadState(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})

    def select(self, idx: int | slice | list[int] | Tensor) -> QuadState:
        """The envs at idx, as a batch (an int index keeps the batch axis: B = 1)."""
        if isinstance(idx, int):
            idx = [idx]
        return QuadState(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})


def vel_body_flu(quat_enu_flu: Tensor, vel_enu_m_s: Tensor) -> Tensor:
    """World-ENU velocity (..., 3) -> body FLU (..., 3) for attitude(s) quat_enu_flu (..., 4)."""
    return quat_rotate_inverse(quat_enu_flu, vel_enu_m_s)


class QuadrotorDynamics:
    """Steps a batch of quadrotors under velocity + yaw-rate setpoints (see the module doc)."""

    def __init__(self, params: DynamicsParams = DynamicsParams()) -> None:
        params.validate()
        self.params = params

    def step(
        self,
        state: QuadState,
        vel_cmd_enu_m_s: Tensor,
        yaw_rate_cmd_rad_s: Tensor,
        dt_s: float,
        kick_force_n: Tensor | None = None,
    ) -> QuadState:
        """Advance by dt_s seconds.

        vel_cmd_enu_m_s [B, 3]: velocity setpoint, world ENU (m/s).  yaw_rate_cmd_rad_s [B]:
        yaw-rate setpoint (rad/s, + = counter-clockwise from above).  kick_force_n [B, 3]:
        external force in world ENU (N) acting during this step, or None.
        """
        p = self.params
        up = _unit_z_like(state.pos_enu_m)

        # Controller: desired acceleration, then desired thrust axis within the tilt cone.
        accel_des = p.velocity_gain_1_s * (vel_cmd_enu_m_s - state.vel_enu_m_s)
        accel_des = accel_des + (p.linear_drag_kg_s / p.mass_kg) * vel_cmd_enu_m_s
        accel_z = accel_des[:, 2].clamp(-p.max_accel_down_m_s2, p.max_accel_up_m_s2)
        force_z = accel_z + GRAVITY_M_S2  # specific force, > 0 since max_accel_down < g
        accel_xy = accel_des[:, :2]
        max_xy = force_z * math.tan(p.max_tilt_rad)
        norm_xy = torch.linalg.vector_norm(accel_xy, dim=-1)
        accel_xy = accel_xy * (max_xy / norm_xy.clamp_min(1e-9)).clamp(max=1.0).unsqueeze(-1)
        force_des = torch.cat([accel_xy, force_z.unsqueeze(-1)], dim=-1)
        axis_des = force_des / torch.linalg.vector_norm(force_des, dim=-1, keepdim=True)

        # Attitude: thrust axis and yaw rate follow their setpoints with first-order lags.
        axis = quat_rotate(state.quat_enu_flu, up)
        axis_new = _slerp_unit(axis, axis_des, 1.0 - math.exp(-dt_s / p.attitude_tau_s))
        roll, pitch, yaw = euler_from_quat(state.quat_enu_flu).unbind(-1)
        yaw_rate = _yaw_rate_from_body_rates(roll, pitch, state.angvel_body_flu_rad_s)
        yaw_rate_new = yaw_rate + (yaw_rate_cmd_rad_s - yaw_rate) * (1.0 - math.exp(-dt_s / p.yaw_rate_tau_s))
        quat_new = _quat_from_axis_yaw(axis_new, yaw + yaw_rate_new * dt_s)
        angvel_new = quat_log(quat_multiply(quat_conjugate(state.quat_enu_flu), quat_new)) / dt_s

        # Translation: thrust along the new axis, gravity, drag, kick; semi-implicit Euler.
        thrust = (force_des * axis_new).sum(dim=-1).clamp_min(0.0)
        accel = thrust.unsqueeze(-1) * axis_new - GRAVITY_M_S2 * up
        accel = accel - (p.linear_drag_kg_s / p.mass_kg) * state.vel_enu_m_s
        if kick_force_n is not None:
            accel = accel + kick_force_n / p.mass_kg
        vel_new = state.vel_enu_m_s + accel * dt_s
        pos_new = state.pos_enu_m + vel_new * dt_s
        if p.ground_contact:
            on_ground = pos_new[:, 2] <= 0.0
            pos_new = torch.cat([pos_new[:, :2], pos_new[:, 2:].clamp_min(0.0)], dim=-1)
            vel_z = torch.where(on_ground, vel_new[:, 2].clamp_min(0.0), vel_new[:, 2])
            vel_new = torch.cat([vel_new[:, :2], vel_z.unsqueeze(-1)], dim=-1)
        return QuadState(pos_new, vel_new, quat_new, angvel_new)


def _unit_z_like(v: Tensor) -> Tensor:
    up = torch.zeros_like(v)
    up[..., 2] = 1.0
    return up


def _slerp_unit(a: Tensor, b: Tensor, fraction: float) -> Tensor:
    """Move unit vector(s) a towards b along the great circle by ``fraction`` of the angle."""
    cos_angle = (a * b).sum(dim=-1, keepdim=True).clamp(-1.0, 1.0)
    angle = torch.acos(cos_angle)
    sin_angle = torch.sin(angle)
    small = sin_angle < 1e-6
    safe_sin = torch.where(small, torch.ones_like(sin_angle), sin_angle)
    wa = torch.where(small, torch.full_like(angle, 1.0 - fraction), torch.sin((1.0 - fraction) * angle) / safe_sin)
    wb = torch.where(small, torch.full_like(angle, fraction), torch.sin(fraction * angle) / safe_sin)
    out = wa * a + wb * b
    return out / torch.linalg.vector_norm(out, dim=-1, keepdim=True)


def _yaw_rate_from_body_rates(roll: Tensor, pitch: Tensor, angvel_body_flu: Tensor) -> Tensor:
    """Z-Y-X Euler yaw rate (rad/s) from body rates: (sin(roll) q + cos(roll) r) / cos(pitch)."""
    _, q, r = angvel_body_flu.unbind(-1)
    return (torch.sin(roll) * q + torch.cos(roll) * r) / torch.cos(pitch)


def _quat_from_axis_yaw(axis_enu: Tensor, yaw_rad: Tensor) -> Tensor:
    """Attitude whose body up axis is axis_enu (unit, world ENU) and whose Z-Y-X yaw is yaw_rad.

    In the yaw-rotated frame the body up axis of R = Rz(yaw) Ry(pitch) Rx(roll) is
    (cos(roll) sin(pitch), -sin(roll), cos(roll) cos(pitch)); invert that for roll and pitch.
    """
    axis_v = rotate_about_z(axis_enu, -yaw_rad)
    roll = -torch.asin(axis_v[:, 1].clamp(-1.0, 1.0))
    pitch = torch.atan2(axis_v[:, 0], axis_v[:, 2])
    return quat_from_euler(roll, pitch, yaw_rad)
