"""The policy's 15-value state vector (the 64-d latent is appended inside the ONNX graph).

Layout (float32): [0:3] unit vector to the goal in the vehicle frame V; [3] min(dist, 12 m)/12 m;
[4:6] roll, pitch (rad, ENU/FLU convention of ``frames``); [6:9] body linear velocity FLU (m/s);
[9:12] body angular velocity FLU (rad/s); [12:15] previous raw policy action in [-1, 1].
"""

from __future__ import annotations

import numpy as np

from .constants import GOAL_DISTANCE_CLIP_M, STATE_DIM
from .frames import euler_from_quat, world_enu_to_vehicle


def observation_state(
    pos_enu_m: np.ndarray,
    goal_enu_m: np.ndarray,
    quat_enu_flu: np.ndarray,
    vel_body_flu_m_s: np.ndarray,
    angvel_body_flu_rad_s: np.ndarray,
    prev_action: np.ndarray,
) -> np.ndarray:
    """State vector(s) of shape (..., 15), float32.  Positions in the same ENU world frame."""
    roll, pitch, yaw = np.moveaxis(euler_from_quat(quat_enu_flu), -1, 0)
    to_goal_v = world_enu_to_vehicle(np.asarray(goal_enu_m) - np.asarray(pos_enu_m), yaw)
    dist_m = np.linalg.norm(to_goal_v, axis=-1, keepdims=True)
    goal_dir_v = np.divide(to_goal_v, dist_m, out=np.zeros_like(to_goal_v), where=dist_m > 1e-9)
    state = np.concatenate(
        [
            goal_dir_v,
            np.minimum(dist_m, GOAL_DISTANCE_CLIP_M) / GOAL_DISTANCE_CLIP_M,
            np.stack([roll, pitch], axis=-1),
            np.broadcast_to(vel_body_flu_m_s, to_goal_v.shape),
            np.broadcast_to(angvel_body_flu_rad_s, to_goal_v.shape),
            np.broadcast_to(prev_action, to_goal_v.shape),
        ],
        axis=-1,
    ).astype(np.float32)
    assert state.shape[-1] == STATE_DIM
    return state
