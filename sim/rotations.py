"""Batched torch twins of the quaternion and Euler helpers in ``runtime.contract.frames``.

Same conventions as the contract: quaternions are (w, x, y, z) and rotate body-frame vectors into
the world frame (here body FLU -> world ENU); Euler angles are intrinsic Z-Y-X (yaw, pitch, roll),
so on the ENU/FLU side positive pitch is nose *down*.  Leading axes are batch axes.
"""

from __future__ import annotations

import torch
from torch import Tensor


def quat_multiply(q1: Tensor, q2: Tensor) -> Tensor:
    """Hamilton product q1 * q2 (apply q2 first, then q1)."""
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        dim=-1,
    )


def quat_conjugate(q: Tensor) -> Tensor:
    """Inverse rotation of a unit quaternion."""
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def quat_rotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vector(s) v (..., 3) by unit quaternion(s) q (..., 4)."""
    u = q[..., 1:]
    t = 2.0 * torch.linalg.cross(u, v, dim=-1)
    return v + q[..., :1] * t + torch.linalg.cross(u, t, dim=-1)


def quat_rotate_inverse(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vector(s) v by the inverse of unit quaternion(s) q (world -> body)."""
    return quat_rotate(quat_conjugate(q), v)


def quat_from_euler(roll_rad: Tensor, pitch_rad: Tensor, yaw_rad: Tensor) -> Tensor:
    """Quaternion of intrinsic Z-Y-X Euler angles (yaw, then pitch, then roll), rad."""
    cr, sr = torch.cos(roll_rad / 2), torch.sin(roll_rad / 2)
    cp, sp = torch.cos(pitch_rad / 2), torch.sin(pitch_rad / 2)
    cy, sy = torch.cos(yaw_rad / 2), torch.sin(yaw_rad / 2)
    return torch.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        dim=-1,
    )


def euler_from_quat(q: Tensor) -> Tensor:
    """Intrinsic Z-Y-X Euler angles (..., 3) = (roll, pitch, yaw) in rad of unit quaternion(s)."""
    w, x, y, z = q.unbind(-1)
    roll = torch.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = torch.asin(torch.clamp(2 * (w * y - z * x), -1.0, 1.0))
    yaw = torch.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return torch.stack([roll, pitch, yaw], dim=-1)


def quat_from_yaw(yaw_rad: Tensor) -> Tensor:
    """Quaternion of a rotation by yaw_rad about the world z axis."""
    zeros = torch.zeros_like(yaw_rad)
    return torch.stack([torch.cos(yaw_rad / 2), zeros, zeros, torch.sin(yaw_rad / 2)], dim=-1)


def quat_log(q: Tensor) -> Tensor:
    """Rotation vector (axis * angle, rad) of unit quaternion(s), taking the short way round."""
    q = torch.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    sin_half = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(sin_half, q[..., :1])
    # angle / sin(angle/2) -> 2 as the angle -> 0.
    scale = torch.where(sin_half > 1e-12, angle / sin_half.clamp_min(1e-12), torch.full_like(angle, 2.0))
    return v * scale


def rotate_about_z(v: Tensor, angle_rad: Tensor) -> Tensor:
    """Rotate vector(s) v (..., 3) by angle_rad (...) about the z axis (counter-clockwise from above)."""
    c, s = torch.cos(angle_rad), torch.sin(angle_rad)
    x, y, z = v.unbind(-1)
    return torch.stack([c * x - s * y, s * x + c * y, z], dim=-1)
