"""Batched quadrotor point-mass dynamics behind a PX4-like velocity-tracking controller.

The controller plays the autopilot's role: it tracks a world-ENU velocity setpoint and a yaw-rate
setpoint.  Desired acceleration = P-gain x velocity error (its own gain vertically) + an integral
of the horizontal error (PX4's MPC_XY_VEL_I_ACC) + drag feed-forward (a fraction of it), vertical
part clamped to the vertical-acceleration limits, horizontal part clamped to its own limit and so
the thrust axis stays within the tilt limit.  The defaults are the ideal vehicle the shipped
policies were trained on; :data:`PX4_SIH_V1_16` is PX4 v1.16 SIH as identified
(``sim.response``, docs/px4-sitl.md): with no drag feed-forward and a slow integrator, a
commanded speed is reached at ~0.8 within seconds and the vehicle still creeps after a stop.
The command delay of an autopilot is not stepped here: ``CommandDelay`` holds the commands back.  The thrust axis follows its setpoint with a first-order lag (time
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
    # PX4-like controller terms; the defaults leave the ideal vehicle as it was.
    vertical_velocity_gain_1_s: float | None = None  # None: velocity_gain_1_s
    velocity_integral_gain_1_s2: float = 0.0  # horizontal integral of the velocity error
    velocity_integral_max_m_s2: float = 2.0  # the integral's acceleration, at most (anti-windup)
    drag_feedforward: float = 1.0  # fraction of the horizontal linear drag the controller anticipates
    max_accel_horizontal_m_s2: float = math.inf
    yaw_rate_gain: float = 1.0  # steady yaw rate / commanded
    max_yaw_accel_rad_s2: float = math.inf
    # Command delays of the autopilot (s): setpoint received -> the controller acts on it
    # (CommandDelay holds the commands back; QuadrotorDynamics.step takes them as given).
    command_delay_xy_s: float = 0.0
    command_delay_z_s: float = 0.0
    command_delay_yaw_s: float = 0.0
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
        if self.vertical_velocity_gain_1_s is not None and not self.vertical_velocity_gain_1_s > 0.0:
            raise ValueError(f"DynamicsParams.vertical_velocity_gain_1_s={self.vertical_velocity_gain_1_s} must be > 0")
        for key in ("velocity_integral_gain_1_s2", "velocity_integral_max_m_s2"):
            if not getattr(self, key) >= 0.0:
                raise ValueError(f"DynamicsParams.{key}={getattr(self, key)} must be >= 0")
        if not 0.0 <= self.drag_feedforward <= 1.0:
            raise ValueError(f"DynamicsParams.drag_feedforward={self.drag_feedforward} must be in [0, 1]")
        for key in ("command_delay_xy_s", "command_delay_z_s", "command_delay_yaw_s"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise ValueError(f"DynamicsParams.{key}={getattr(self, key)} must be in [0, 1] s")
        for key in ("max_accel_horizontal_m_s2", "yaw_rate_gain", "max_yaw_accel_rad_s2"):
            if not getattr(self, key) > 0.0:
                raise ValueError(f"DynamicsParams.{key}={getattr(self, key)} must be > 0")


@dataclass
class QuadState:
    """Vehicle state of B envs: pos_enu_m [B, 3], vel_enu_m_s [B, 3] (world ENU),
    quat_enu_flu [B, 4] (w, x, y, z; body FLU -> world ENU), angvel_body_flu_rad_s [B, 3]."""

    pos_enu_m: Tensor
    vel_enu_m_s: Tensor
    quat_enu_flu: Tensor
    angvel_body_flu_rad_s: Tensor
    # The controller's integral of the horizontal velocity error, world ENU (m) [B, 2]; None = zero.
    vel_error_integral_m: Tensor | None = None

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

    def integral(self) -> Tensor:
        """[B, 2] the controller's horizontal velocity-error integral (zeros when never set)."""
        if self.vel_error_integral_m is None:
            return torch.zeros_like(self.pos_enu_m[:, :2])
        return self.vel_error_integral_m

    def to(self, device: torch.device | str) -> QuadState:
        return QuadState(**{f.name: None if getattr(self, f.name) is None else getattr(self, f.name).to(device) for f in fields(self)})

    def select(self, idx: int | slice | list[int] | Tensor) -> QuadState:
        """The envs at idx, as a batch (an int index keeps the batch axis: B = 1)."""
        if isinstance(idx, int):
            idx = [idx]
        return QuadState(**{f.name: None if getattr(self, f.name) is None else getattr(self, f.name)[idx] for f in fields(self)})


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
        per_env: dict[str, Tensor] | None = None,
    ) -> QuadState:
        """Advance by dt_s seconds.

        vel_cmd_enu_m_s [B, 3]: velocity setpoint, world ENU (m/s).  yaw_rate_cmd_rad_s [B]:
        yaw-rate setpoint (rad/s, + = counter-clockwise from above).  kick_force_n [B, 3]:
        external force in world ENU (N) acting during this step, or None.  per_env: a value [B]
        per env for any of :data:`PER_ENV_PARAMS` (e.g. from :func:`sample_dynamics`), in place of
        ``params``' scalar; the others stay ``params``'.
        """
        p = self.params
        if per_env:
            return self._step_per_env(state, vel_cmd_enu_m_s, yaw_rate_cmd_rad_s, dt_s, kick_force_n, per_env)
        up = _unit_z_like(state.pos_enu_m)

        # Controller: desired acceleration, then desired thrust axis within the tilt cone.
        error = vel_cmd_enu_m_s - state.vel_enu_m_s
        accel_des = p.velocity_gain_1_s * error
        if p.vertical_velocity_gain_1_s is not None:
            accel_des[:, 2] = p.vertical_velocity_gain_1_s * error[:, 2]
        # The drag feed-forward: a fraction horizontally, all of it vertically (the autopilot's
        # hover-thrust estimate and vertical integrator hold a commanded climb rate).
        feedforward = torch.tensor([p.drag_feedforward, p.drag_feedforward, 1.0], dtype=vel_cmd_enu_m_s.dtype, device=vel_cmd_enu_m_s.device)
        accel_des = accel_des + (p.linear_drag_kg_s / p.mass_kg) * feedforward * vel_cmd_enu_m_s
        integral = state.integral()
        if p.velocity_integral_gain_1_s2 > 0.0:
            limit_m = p.velocity_integral_max_m_s2 / p.velocity_integral_gain_1_s2
            integral = (integral + error[:, :2] * dt_s).clamp(-limit_m, limit_m)
            accel_des = accel_des + torch.cat([p.velocity_integral_gain_1_s2 * integral, torch.zeros_like(integral[:, :1])], dim=-1)
        accel_z = accel_des[:, 2].clamp(-p.max_accel_down_m_s2, p.max_accel_up_m_s2)
        force_z = accel_z + GRAVITY_M_S2  # specific force, > 0 since max_accel_down < g
        accel_xy = accel_des[:, :2]
        max_xy = (force_z * math.tan(p.max_tilt_rad)).clamp(max=p.max_accel_horizontal_m_s2)
        norm_xy = torch.linalg.vector_norm(accel_xy, dim=-1)
        accel_xy = accel_xy * (max_xy / norm_xy.clamp_min(1e-9)).clamp(max=1.0).unsqueeze(-1)
        force_des = torch.cat([accel_xy, force_z.unsqueeze(-1)], dim=-1)
        axis_des = force_des / torch.linalg.vector_norm(force_des, dim=-1, keepdim=True)

        # Attitude: thrust axis and yaw rate follow their setpoints with first-order lags.
        axis = quat_rotate(state.quat_enu_flu, up)
        axis_new = _slerp_unit(axis, axis_des, 1.0 - math.exp(-dt_s / p.attitude_tau_s))
        roll, pitch, yaw = euler_from_quat(state.quat_enu_flu).unbind(-1)
        yaw_rate = _yaw_rate_from_body_rates(roll, pitch, state.angvel_body_flu_rad_s)
        yaw_rate_step = (p.yaw_rate_gain * yaw_rate_cmd_rad_s - yaw_rate) * (1.0 - math.exp(-dt_s / p.yaw_rate_tau_s))
        yaw_rate_step = yaw_rate_step.clamp(-p.max_yaw_accel_rad_s2 * dt_s, p.max_yaw_accel_rad_s2 * dt_s)
        yaw_rate_new = yaw_rate + yaw_rate_step
        quat_new = _quat_from_axis_yaw(axis_new, yaw + yaw_rate_new * dt_s)
        angvel_new = quat_log(quat_multiply(quat_conjugate(state.quat_enu_flu), quat_new)) / dt_s

        pos_new, vel_new = _translate(state, force_des, axis_new, p.linear_drag_kg_s / p.mass_kg, kick_force_n, p, dt_s)
        return QuadState(pos_new, vel_new, quat_new, angvel_new,
                         integral if p.velocity_integral_gain_1_s2 > 0.0 else state.vel_error_integral_m)


    def _step_per_env(self, state: QuadState, vel_cmd_enu_m_s: Tensor, yaw_rate_cmd_rad_s: Tensor, dt_s: float,
                      kick_force_n: Tensor | None, per_env: dict[str, Tensor]) -> QuadState:  # fmt: skip
        """:meth:`step` with some parameters given per env ([B] tensors): the same controller and
        vehicle, each scalar replaced by a column (a second copy of the arithmetic so that the
        scalar path, which the SITL vehicle and the fit use, stays exactly as it was)."""
        p = self.params
        unknown = set(per_env) - set(PER_ENV_PARAMS)
        if unknown:
            raise ValueError(f"per-env dynamics parameters {sorted(unknown)} are not supported: choose from {PER_ENV_PARAMS}")
        like = vel_cmd_enu_m_s

        def col(name: str) -> Tensor:
            """[B, 1] the per-env value, or the scalar broadcast."""
            if name in per_env:
                return per_env[name].to(dtype=like.dtype, device=like.device).reshape(-1, 1)
            value = getattr(p, name)
            if name == "vertical_velocity_gain_1_s" and value is None:
                return col("velocity_gain_1_s")
            return torch.full((like.shape[0], 1), float(value), dtype=like.dtype, device=like.device)

        up = _unit_z_like(state.pos_enu_m)
        error = vel_cmd_enu_m_s - state.vel_enu_m_s
        gain = torch.cat([col("velocity_gain_1_s").expand(-1, 2), col("vertical_velocity_gain_1_s")], dim=-1)
        accel_des = gain * error
        feedforward = torch.tensor([p.drag_feedforward, p.drag_feedforward, 1.0], dtype=like.dtype, device=like.device)
        drag_per_kg = col("linear_drag_kg_s") / p.mass_kg
        accel_des = accel_des + drag_per_kg * feedforward * vel_cmd_enu_m_s
        integral = state.integral()
        gain_i = col("velocity_integral_gain_1_s2")
        keeps_integral = "velocity_integral_gain_1_s2" in per_env or p.velocity_integral_gain_1_s2 > 0.0
        if keeps_integral:
            limit_m = p.velocity_integral_max_m_s2 / gain_i.clamp_min(1e-9)
            integral = torch.minimum(torch.maximum(integral + error[:, :2] * dt_s, -limit_m), limit_m)
            accel_des = accel_des + torch.cat([gain_i * integral, torch.zeros_like(integral[:, :1])], dim=-1)
        accel_z = accel_des[:, 2].clamp(-p.max_accel_down_m_s2, p.max_accel_up_m_s2)
        force_z = accel_z + GRAVITY_M_S2
        accel_xy = accel_des[:, :2]
        max_xy = torch.minimum(force_z * math.tan(p.max_tilt_rad), col("max_accel_horizontal_m_s2")[:, 0])
        norm_xy = torch.linalg.vector_norm(accel_xy, dim=-1)
        accel_xy = accel_xy * (max_xy / norm_xy.clamp_min(1e-9)).clamp(max=1.0).unsqueeze(-1)
        force_des = torch.cat([accel_xy, force_z.unsqueeze(-1)], dim=-1)
        axis_des = force_des / torch.linalg.vector_norm(force_des, dim=-1, keepdim=True)

        axis = quat_rotate(state.quat_enu_flu, up)
        axis_new = _slerp_unit(axis, axis_des, 1.0 - torch.exp(-dt_s / col("attitude_tau_s")))
        roll, pitch, yaw = euler_from_quat(state.quat_enu_flu).unbind(-1)
        yaw_rate = _yaw_rate_from_body_rates(roll, pitch, state.angvel_body_flu_rad_s)
        yaw_follow = 1.0 - torch.exp(-dt_s / col("yaw_rate_tau_s")[:, 0])
        yaw_rate_step = (col("yaw_rate_gain")[:, 0] * yaw_rate_cmd_rad_s - yaw_rate) * yaw_follow
        max_step = col("max_yaw_accel_rad_s2")[:, 0] * dt_s
        yaw_rate_new = yaw_rate + torch.minimum(torch.maximum(yaw_rate_step, -max_step), max_step)
        quat_new = _quat_from_axis_yaw(axis_new, yaw + yaw_rate_new * dt_s)
        angvel_new = quat_log(quat_multiply(quat_conjugate(state.quat_enu_flu), quat_new)) / dt_s

        pos_new, vel_new = _translate(state, force_des, axis_new, drag_per_kg, kick_force_n, p, dt_s)
        return QuadState(pos_new, vel_new, quat_new, angvel_new, integral if keeps_integral else state.vel_error_integral_m)


def _translate(state: QuadState, force_des: Tensor, axis_new: Tensor, drag_per_kg: float | Tensor,
               kick_force_n: Tensor | None, p: DynamicsParams, dt_s: float) -> tuple[Tensor, Tensor]:
    """Translation, shared by the scalar and the per-env step: thrust along the new axis, gravity,
    linear drag (``drag_per_kg``, 1/s: a float or [B, 1]), kick; semi-implicit Euler; the floor
    pushes back when ``ground_contact``.  Returns (pos [B, 3], vel [B, 3]), world ENU."""
    thrust = (force_des * axis_new).sum(dim=-1).clamp_min(0.0)
    accel = thrust.unsqueeze(-1) * axis_new - GRAVITY_M_S2 * _unit_z_like(state.pos_enu_m) - drag_per_kg * state.vel_enu_m_s
    if kick_force_n is not None:
        accel = accel + kick_force_n / p.mass_kg
    vel_new = state.vel_enu_m_s + accel * dt_s
    pos_new = state.pos_enu_m + vel_new * dt_s
    if p.ground_contact:
        on_ground = pos_new[:, 2] <= 0.0
        pos_new = torch.cat([pos_new[:, :2], pos_new[:, 2:].clamp_min(0.0)], dim=-1)
        vel_z = torch.where(on_ground, vel_new[:, 2].clamp_min(0.0), vel_new[:, 2])
        vel_new = torch.cat([vel_new[:, :2], vel_z.unsqueeze(-1)], dim=-1)
    return pos_new, vel_new


def _unit_z_like(v: Tensor) -> Tensor:
    up = torch.zeros_like(v)
    up[..., 2] = 1.0
    return up


def _slerp_unit(a: Tensor, b: Tensor, fraction: float | Tensor) -> Tensor:
    """Move unit vector(s) a towards b along the great circle by ``fraction`` of the angle."""
    cos_angle = (a * b).sum(dim=-1, keepdim=True).clamp(-1.0, 1.0)
    angle = torch.acos(cos_angle)
    sin_angle = torch.sin(angle)
    small = sin_angle < 1e-6
    safe_sin = torch.where(small, torch.ones_like(sin_angle), sin_angle)
    if isinstance(fraction, Tensor):  # per env [B, 1]
        wa = torch.where(small, (1.0 - fraction).expand_as(angle), torch.sin((1.0 - fraction) * angle) / safe_sin)
        wb = torch.where(small, fraction.expand_as(angle), torch.sin(fraction * angle) / safe_sin)
    else:
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


class CommandDelay:
    """The autopilot's command delays (``DynamicsParams.command_delay_*_s``): commands pushed with
    their time come out ``delay`` later, per axis (horizontal, vertical, yaw).  Before the first
    command is due, the first one pushed holds.  Batched: vel [B, 3] world ENU, yaw rate [B]."""

    def __init__(self, params: DynamicsParams) -> None:
        self._delays_s = (params.command_delay_xy_s, params.command_delay_z_s, params.command_delay_yaw_s)
        self._history: list[tuple[float, Tensor, Tensor]] = []

    @property
    def active(self) -> bool:
        return any(d > 0.0 for d in self._delays_s)

    def push(self, t_s: float, vel_cmd_enu_m_s: Tensor, yaw_rate_cmd_rad_s: Tensor) -> tuple[Tensor, Tensor]:
        """Record the command given at ``t_s``; return the one acting at ``t_s``."""
        if not self.active:
            return vel_cmd_enu_m_s, yaw_rate_cmd_rad_s
        self._history.append((t_s, vel_cmd_enu_m_s, yaw_rate_cmd_rad_s))
        oldest_needed_s = t_s - max(self._delays_s)
        while len(self._history) > 1 and self._history[1][0] <= oldest_needed_s:
            self._history.pop(0)
        d_xy, d_z, d_yaw = self._delays_s
        vel_xy = self._at(t_s - d_xy)[1][:, :2]
        vel_z = self._at(t_s - d_z)[1][:, 2:]
        return torch.cat([vel_xy, vel_z], dim=-1), self._at(t_s - d_yaw)[2]

    def _at(self, t_s: float) -> tuple[float, Tensor, Tensor]:
        """The newest command given at or before ``t_s`` (the oldest kept if none)."""
        for entry in reversed(self._history):
            if entry[0] <= t_s + 1e-9:
                return entry
        return self._history[0]


# PX4 v1.16 SITL with its SIH quadrotor (airframe 10040): the parameters that reproduce its
# offboard response to the identification sequence, fitted by ``sim.response.offline.fit_params``
# to a recorded flight (RMS velocity error 0.10 m/s horizontal, 0.05 vertical, 0.045 rad/s yaw;
# docs/px4-sitl.md has the identified numbers and the comparison).  What they make: delays of
# 0.18 s horizontal, 0.07-0.1 s vertical, 0.12 s yaw; ~0.8 of a commanded horizontal speed
# within seconds (no drag feed-forward, a slow integrator) and a creep after a stop; a horizontal
# acceleration limit of 3.6 m/s^2; yaw rate at 0.93 of the command with a 0.3 s lag.
PX4_SIH_V1_16 = DynamicsParams(
    velocity_gain_1_s=1.96,
    attitude_tau_s=0.083,
    linear_drag_kg_s=0.77,
    drag_feedforward=0.0,
    velocity_integral_gain_1_s2=0.30,
    max_accel_horizontal_m_s2=3.63,
    vertical_velocity_gain_1_s=5.5,
    yaw_rate_tau_s=0.30,
    yaw_rate_gain=0.93,
    max_yaw_accel_rad_s2=2.64,
    command_delay_xy_s=0.076,
    command_delay_z_s=0.099,
    command_delay_yaw_s=0.124,
)


# The parameters QuadrotorDynamics.step takes per env (``per_env``), and the command delays
# (applied outside the dynamics, by CommandDelay or the batched env's delay line).
PER_ENV_PARAMS = ("velocity_gain_1_s", "vertical_velocity_gain_1_s", "velocity_integral_gain_1_s2", "linear_drag_kg_s",
                  "max_accel_horizontal_m_s2", "attitude_tau_s", "yaw_rate_tau_s", "yaw_rate_gain",
                  "max_yaw_accel_rad_s2")  # fmt: skip
COMMAND_DELAY_PARAMS = ("command_delay_xy_s", "command_delay_z_s", "command_delay_yaw_s")


@dataclass(frozen=True)
class DynamicsRandomization:
    """Per-episode spread of a vehicle around its identified parameters (training's domain
    randomization): each value is drawn uniformly in nominal x [1 - r, 1 + r] with r the
    relative half-range of its group.  The ranges are assumptions, not measurements: one PX4
    flight was fitted (``PX4_SIH_V1_16``), so how much a real airframe's response differs from
    it (battery, mass, props, wind) is not known here; +-20 % on gains and limits and +-30 % on
    lags and delays cover the spread one expects between a SIH fit and real vehicles."""

    gain_fraction: float = 0.2  # velocity gains, integral gain, drag, yaw-rate gain, acceleration limits
    lag_fraction: float = 0.3  # attitude and yaw-rate time constants
    delay_fraction: float = 0.3  # command_delay_*_s

    def validate(self) -> None:
        for key in ("gain_fraction", "lag_fraction", "delay_fraction"):
            if not 0.0 <= getattr(self, key) < 1.0:
                raise ValueError(f"DynamicsRandomization.{key}={getattr(self, key)} must be in [0, 1): a relative half-range")

    def fraction(self, name: str) -> float:
        if name in COMMAND_DELAY_PARAMS:
            return self.delay_fraction
        if name in ("attitude_tau_s", "yaw_rate_tau_s"):
            return self.lag_fraction
        return self.gain_fraction


def sample_dynamics(params: DynamicsParams, randomization: DynamicsRandomization, batch_size: int,
                    generator: torch.Generator) -> dict[str, Tensor]:  # fmt: skip
    """{name: [batch_size] float32} per-env values of :data:`PER_ENV_PARAMS` and
    :data:`COMMAND_DELAY_PARAMS` drawn around ``params`` (see :class:`DynamicsRandomization`),
    in a fixed order from ``generator`` (CPU).  A parameter at infinity (no limit) stays there;
    a command delay stays within DynamicsParams' [0, 1] s."""
    randomization.validate()
    names = PER_ENV_PARAMS + COMMAND_DELAY_PARAMS
    u = torch.rand((len(names), batch_size), generator=generator, dtype=torch.float32) * 2.0 - 1.0
    out = {}
    for row, name in zip(u, names):
        nominal = getattr(params, name)
        if name == "vertical_velocity_gain_1_s" and nominal is None:
            nominal = params.velocity_gain_1_s
        value = nominal * (1.0 + randomization.fraction(name) * row) if math.isfinite(nominal) else torch.full_like(row, nominal)
        out[name] = value.clamp(0.0, 1.0) if name in COMMAND_DELAY_PARAMS else value
    return out
