"""Where the room sits in the autopilot's local frame, and the followed pose in the room.

An external autopilot (PX4 SIH) knows no room: it reports its pose in its local NED frame
(origin where its estimator started) and body FRD.  The follower places the room so that the
autopilot's home is the room's start point on the floor (at the landing-gear height, as our own
vehicle rests) and the autopilot's heading at placement is the room's +x (the goal side, as in
training).  Conversions between the sides go through ``runtime.contract.frames`` only.

Frames: local ENU = ``ned_to_enu`` of the autopilot's local NED (the runtime's local ENU too);
world ENU = the room's frame: ``world = origin + Rz(-heading) (local - home)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.contract.frames import (
    frd_to_flu,
    ned_to_enu,
    quat_from_euler,
    quat_multiply,
    quat_ned_frd_to_enu_flu,
    vehicle_to_world_enu,
    world_enu_to_vehicle,
    wrap_angle,
)
from sim.sitl.kinematics import Kinematics


@dataclass(frozen=True)
class AutopilotPose:
    """One pose as the autopilot sends it: LOCAL_POSITION_NED (position m, velocity m/s, local
    NED) and ATTITUDE_QUATERNION (quat FRD -> NED (w, x, y, z), body rates FRD rad/s); t_ns is
    when it was received (time.monotonic_ns)."""

    t_ns: int
    pos_ned_m: np.ndarray
    vel_ned_m_s: np.ndarray
    quat_ned_frd: np.ndarray
    rates_frd_rad_s: np.ndarray


@dataclass(frozen=True)
class Placement:
    """The room in the autopilot's local frame.

    home_local_enu_m: the autopilot's home (local ENU, m); heading_local_enu_rad: its heading at
    placement (counter-clockwise from local east); origin_world_enu_m: where home lies in the room
    (world ENU, m).
    """

    home_local_enu_m: np.ndarray
    heading_local_enu_rad: float
    origin_world_enu_m: np.ndarray

    def world_from_local(self, v_local_enu: np.ndarray) -> np.ndarray:
        """Direction/velocity (local ENU) -> world ENU."""
        return vehicle_to_world_enu(v_local_enu, -self.heading_local_enu_rad)

    def local_from_world(self, v_world_enu: np.ndarray) -> np.ndarray:
        """Direction/velocity (world ENU) -> local ENU."""
        return world_enu_to_vehicle(v_world_enu, -self.heading_local_enu_rad)

    def world_position(self, pos_local_enu_m: np.ndarray) -> np.ndarray:
        return self.origin_world_enu_m + self.world_from_local(np.asarray(pos_local_enu_m) - self.home_local_enu_m)

    def local_position(self, pos_world_enu_m: np.ndarray) -> np.ndarray:
        return self.home_local_enu_m + self.local_from_world(np.asarray(pos_world_enu_m) - self.origin_world_enu_m)

    def world_quat(self, quat_local_enu_flu: np.ndarray) -> np.ndarray:
        """Attitude FLU -> local ENU into FLU -> world ENU (w, x, y, z)."""
        return quat_multiply(quat_from_euler(0.0, 0.0, -self.heading_local_enu_rad), quat_local_enu_flu)

    def world_yaw(self, yaw_local_enu_rad: float) -> float:
        return float(wrap_angle(yaw_local_enu_rad - self.heading_local_enu_rad))

    def kinematics(self, pose: AutopilotPose, on_ground: bool) -> Kinematics:
        """The followed pose in the room (world ENU, body FLU)."""
        pos_local_enu = ned_to_enu(pose.pos_ned_m)
        return Kinematics(
            t_ns=pose.t_ns,
            pos_enu_m=self.world_position(pos_local_enu),
            vel_enu_m_s=self.world_from_local(ned_to_enu(pose.vel_ned_m_s)),
            quat_enu_flu=self.world_quat(quat_ned_frd_to_enu_flu(pose.quat_ned_frd)),
            angvel_body_flu_rad_s=frd_to_flu(pose.rates_frd_rad_s),
            on_ground=on_ground,
        )

    def record(self) -> dict:
        """JSON-ready."""
        return {
            "home_local_enu_m": [float(v) for v in self.home_local_enu_m],
            "heading_local_enu_rad": float(self.heading_local_enu_rad),
            "origin_world_enu_m": [float(v) for v in self.origin_world_enu_m],
        }


def place_room(home_local_enu_m: np.ndarray, heading_local_enu_rad: float, start_world_enu_m: np.ndarray, floor_height_m: float) -> Placement:
    """Home at the room's start point (x, y) at ``floor_height_m`` (the body origin's height when
    landed); the current heading along the room's +x."""
    start = np.asarray(start_world_enu_m, dtype=np.float64)
    return Placement(
        np.asarray(home_local_enu_m, dtype=np.float64).copy(),
        float(heading_local_enu_rad),
        np.array([start[0], start[1], floor_height_m], dtype=np.float64),
    )
