"""Batched torch twins of the runtime contract's observation state and action mapping
(``runtime.contract.observation_state`` and ``action_to_velocity_flu``), so the training
environment computes exactly what the runtime computes; ``tests/training/test_policy_env.py``
checks them against the numpy originals on the same states."""

from __future__ import annotations

import torch
from torch import Tensor

from runtime.contract.constants import (
    GOAL_DISTANCE_CLIP_M,
    MAX_INCLINATION_RAD,
    MAX_SPEED_M_S,
    MAX_YAW_RATE_RAD_S,
    STATE_DIM,
)
from runtime.contract.action import ActionLimits
from sim.rotations import euler_from_quat, quat_rotate_inverse, rotate_about_z


def observation_state_batch(
    pos_enu_m: Tensor,
    goal_enu_m: Tensor,
    quat_enu_flu: Tensor,
    vel_enu_m_s: Tensor,
    angvel_body_flu_rad_s: Tensor,
    prev_action: Tensor,
) -> Tensor:
    """[B, 15] float32 state, the layout of ``runtime.contract.observation``; the world-ENU
    velocity is rotated into body FLU as the runtime's telemetry reports it."""
    roll, pitch, yaw = euler_from_quat(quat_enu_flu).unbind(-1)
    to_goal_v = rotate_about_z(goal_enu_m - pos_enu_m, -yaw)
    dist_m = torch.linalg.vector_norm(to_goal_v, dim=-1, keepdim=True)
    goal_dir_v = torch.where(dist_m > 1e-9, to_goal_v / dist_m.clamp_min(1e-9), torch.zeros_like(to_goal_v))
    state = torch.cat(
        [
            goal_dir_v,
            dist_m.clamp_max(GOAL_DISTANCE_CLIP_M) / GOAL_DISTANCE_CLIP_M,
            torch.stack([roll, pitch], dim=-1),
            quat_rotate_inverse(quat_enu_flu, vel_enu_m_s),
            angvel_body_flu_rad_s,
            prev_action,
        ],
        dim=-1,
    ).float()
    assert state.shape[-1] == STATE_DIM
    return state


def action_to_velocity_flu_batch(action: Tensor, limits: ActionLimits | None = None) -> Tensor:
    """Raw actions [B, 3] -> body FLU commands [B, 4] (vx, vy, vz m/s; yaw rate rad/s), clipping
    the action to [-1, 1] first; ``limits``: a deployment's caps on speed and inclination, applied
    as the runtime applies them (``runtime.contract.action_to_velocity_flu``), None = the
    contract's full range."""
    a = action.clamp(-1.0, 1.0)
    speed = (a[:, 0] + 1.0) * (MAX_SPEED_M_S / 2.0)
    incl = a[:, 1] * MAX_INCLINATION_RAD
    if limits is not None:
        speed = speed.clamp_max(limits.max_speed_m_s)
        incl = incl.clamp(-limits.max_inclination_rad, limits.max_inclination_rad)
    return torch.stack([speed * torch.cos(incl), torch.zeros_like(speed), speed * torch.sin(incl), a[:, 2] * MAX_YAW_RATE_RAD_S], dim=-1)
