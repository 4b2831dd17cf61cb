"""Frame conversions between the policy side (world ENU, body FLU, vehicle frame V) and the
autopilot side (world NED, body FRD), as one module (DESIGN §2).

Vectors are numpy arrays whose last axis holds (x, y, z); leading axes are batch axes.
Quaternions are (w, x, y, z) and rotate body-frame vectors into the world frame.
Euler angles are intrinsic Z-Y-X (yaw, pitch, roll) of the body-to-world rotation of the
frame pair named in the function.  On the policy side (ENU/FLU) positive pitch is nose *down*
(a right-handed rotation about the left-pointing y axis); on the PX4 side (NED/FRD) positive
pitch is nose *up*.  Roll is positive right-wing-down in both.
"""

from __future__ import annotations

import numpy as np

_SQRT_HALF = np.sqrt(0.5)

# Fixed rotations between the conventions, as quaternions (w, x, y, z).
# ENU <- NED: swap x/y and negate z; a rotation of pi about the axis (1, 1, 0)/sqrt(2).
_Q_ENU_FROM_NED = np.array([0.0, _SQRT_HALF, _SQRT_HALF, 0.0])
# FRD <- FLU (and FLU <- FRD): negate y and z; a rotation of pi about x.
_Q_FRD_FROM_FLU = np.array([0.0, 1.0, 0.0, 0.0])


def enu_to_ned(v_enu: np.ndarray) -> np.ndarray:
    """World vector ENU (east, north, up) -> NED (north, east, down)."""
    v = np.asarray(v_enu, dtype=np.float64)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


def ned_to_enu(v_ned: np.ndarray) -> np.ndarray:
    """World vector NED -> ENU (the map is its own inverse)."""
    return enu_to_ned(v_ned)


def flu_to_frd(v_flu: np.ndarray) -> np.ndarray:
    """Body vector FLU (forward, left, up) -> FRD (forward, right, down)."""
    v = np.asarray(v_flu, dtype=np.float64)
    return np.stack([v[..., 0], -v[..., 1], -v[..., 2]], axis=-1)


def frd_to_flu(v_frd: np.ndarray) -> np.ndarray:
    """Body vector FRD -> FLU (the map is its own inverse)."""
    return flu_to_frd(v_frd)


def quat_multiply(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Hamilton product q1 * q2 (apply q2 first, then q1)."""
    q1 = np.asarray(q1, dtype=np.float64)
    q2 = np.asarray(q2, dtype=np.float64)
    w1, x1, y1, z1 = np.moveaxis(q1, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(q2, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vector(s) v by unit quaternion(s) q."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    u = q[..., 1:]
    w = q[..., :1]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_ned_frd_to_enu_flu(q_ned_frd: np.ndarray) -> np.ndarray:
    """Attitude as PX4 reports it (FRD body -> NED world) -> policy side (FLU body -> ENU world)."""
    q = quat_multiply(quat_multiply(_Q_ENU_FROM_NED, q_ned_frd), _Q_FRD_FROM_FLU)
    return _canonical(q)


def quat_enu_flu_to_ned_frd(q_enu_flu: np.ndarray) -> np.ndarray:
    """Attitude FLU body -> ENU world into PX4's FRD body -> NED world."""
    q = quat_multiply(quat_multiply(quat_conjugate(_Q_ENU_FROM_NED), q_enu_flu), _Q_FRD_FROM_FLU)
    return _canonical(q)


def _canonical(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with w >= 0 (q and -q are the same rotation)."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def quat_from_euler(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """Quaternion of intrinsic Z-Y-X Euler angles (yaw, then pitch, then roll)."""
    r = np.asarray(roll_rad, dtype=np.float64) / 2.0
    p = np.asarray(pitch_rad, dtype=np.float64) / 2.0
    y = np.asarray(yaw_rad, dtype=np.float64) / 2.0
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def euler_from_quat(q: np.ndarray) -> np.ndarray:
    """Intrinsic Z-Y-X Euler angles (roll, pitch, yaw) in rad of unit quaternion(s) q."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = np.moveaxis(q, -1, 0)
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def yaw_ned_to_enu(yaw_ned_rad):
    """Heading clockwise from north (NED) -> counter-clockwise from east (ENU), wrapped to (-pi, pi]."""
    return wrap_angle(np.pi / 2.0 - np.asarray(yaw_ned_rad, dtype=np.float64))


def yaw_enu_to_ned(yaw_enu_rad):
    """Inverse of :func:`yaw_ned_to_enu` (the map is its own inverse)."""
    return yaw_ned_to_enu(yaw_enu_rad)


def wrap_angle(angle_rad):
    """Wrap to (-pi, pi]."""
    a = np.asarray(angle_rad, dtype=np.float64)
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def world_enu_to_vehicle(v_enu: np.ndarray, yaw_enu_rad) -> np.ndarray:
    """World ENU vector -> vehicle frame V (ENU rotated by the vehicle's yaw only)."""
    v = np.asarray(v_enu, dtype=np.float64)
    yaw = np.asarray(yaw_enu_rad, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1], v[..., 2]], axis=-1)


def vehicle_to_world_enu(v_vehicle: np.ndarray, yaw_enu_rad) -> np.ndarray:
    """Vehicle frame V -> world ENU."""
    return world_enu_to_vehicle(v_vehicle, -np.asarray(yaw_enu_rad, dtype=np.float64))
