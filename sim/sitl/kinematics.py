"""Ground-truth state of the one SITL vehicle as plain numpy: what the autopilot logic, the
telemetry and the camera read.  Nothing here knows where the state comes from (our dynamics
today, a PX4 SIH pose over MAVLink later)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.contract.frames import euler_from_quat


@dataclass(frozen=True)
class Kinematics:
    """One vehicle's state at ``t_ns`` (time.monotonic_ns).

    pos_enu_m (3,) world ENU of the body origin; vel_enu_m_s (3,) world ENU; quat_enu_flu (4,)
    (w, x, y, z), body FLU -> world ENU; angvel_body_flu_rad_s (3,); on_ground: resting on the
    floor (landed).
    """

    t_ns: int
    pos_enu_m: np.ndarray
    vel_enu_m_s: np.ndarray
    quat_enu_flu: np.ndarray
    angvel_body_flu_rad_s: np.ndarray
    on_ground: bool

    @property
    def yaw_enu_rad(self) -> float:
        """Heading, counter-clockwise from east (rad)."""
        return float(euler_from_quat(self.quat_enu_flu)[2])
