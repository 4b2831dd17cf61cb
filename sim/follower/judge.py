"""Ground truth from the followed pose: contact, geofence, goal and timeout.

The autopilot flies on in its own empty world; the room exists only here.  So the judge, not the
autopilot, decides that the vehicle hit something (and the runtime learns it over the camera
link), whether it stayed inside the geofence the runtime's watchdog enforces (the same
defaults, ``runtime.config.WatchdogConfig``), when it first came within GOAL_REACHED_RADIUS_M
of the goal, and whether the flight outlasted its time limit.  The clock of offboard flight
starts when the autopilot first reports OFFBOARD.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from runtime.config import WatchdogConfig
from runtime.contract.constants import GOAL_REACHED_RADIUS_M
from sim.sitl.airframe import floor_crash, room_contact
from sim.sitl.kinematics import Kinematics
from sim.world import WorldBatch

log = logging.getLogger(__name__)


@dataclass
class Verdict:
    """What happened, in time.monotonic seconds; None = did not happen."""

    contact: dict | None = None  # {t_s, pos_enu_m, what}
    geofence: dict | None = None  # {t_s, pos_enu_m, what}
    goal_reached_t_s: float | None = None
    timeout_t_s: float | None = None
    offboard_t_s: float | None = None

    def record(self) -> dict:
        return dict(vars(self))


class Judge:
    """Feed it every followed pose (:meth:`observe`) and the autopilot's mode changes."""

    def __init__(
        self,
        world: WorldBatch,
        goal_world_enu_m: np.ndarray,
        home_world_enu_m: np.ndarray,
        timeout_s: float,
        fence: WatchdogConfig = WatchdogConfig(),
    ) -> None:
        self._world = world
        self._goal = np.asarray(goal_world_enu_m, dtype=np.float64)
        self._home_z_m = float(home_world_enu_m[2])
        self._timeout_s = timeout_s
        self._fence = fence
        self._fence_centre_xy: np.ndarray | None = None
        self.verdict = Verdict()

    def offboard_entered(self, t_s: float, kin: Kinematics | None) -> None:
        """The first OFFBOARD: the flight clock and the geofence centre start here."""
        if self.verdict.offboard_t_s is None:
            self.verdict.offboard_t_s = t_s
            if kin is not None:
                self._fence_centre_xy = kin.pos_enu_m[:2].copy()

    def observe(self, t_s: float, kin: Kinematics) -> dict | None:
        """Judge one pose (world ENU); returns the contact if this pose made the first one."""
        v = self.verdict
        pos = kin.pos_enu_m
        if v.contact is None:
            what = floor_crash(float(pos[2]), float(np.linalg.norm(kin.vel_enu_m_s)))
            what = what or room_contact(self._world, torch.as_tensor(pos, dtype=torch.float32).reshape(1, 3))
            if what is not None:
                v.contact = {"t_s": t_s, "pos_enu_m": [float(x) for x in pos], "what": what}
                log.warning("contact: %s at %s m (world ENU)", what, np.round(pos, 2).tolist())
                return v.contact
        if v.offboard_t_s is None:
            return None
        if v.goal_reached_t_s is None and float(np.linalg.norm(pos - self._goal)) < GOAL_REACHED_RADIUS_M:
            v.goal_reached_t_s = t_s
            log.info("goal reached %.2f s after offboard entry", t_s - v.offboard_t_s)
        if v.timeout_t_s is None and v.goal_reached_t_s is None and t_s - v.offboard_t_s > self._timeout_s:
            v.timeout_t_s = t_s
            log.info("time limit %.1f s passed without reaching the goal", self._timeout_s)
        if v.geofence is None and self._fence_centre_xy is not None and v.goal_reached_t_s is None:
            what = self._fence_breach(pos)
            if what is not None:
                v.geofence = {"t_s": t_s, "pos_enu_m": [float(x) for x in pos], "what": what}
                log.warning("geofence: %s", what)
        return None

    def _fence_breach(self, pos: np.ndarray) -> str | None:
        f = self._fence
        dist_m = float(np.linalg.norm(pos[:2] - self._fence_centre_xy))
        height_m = float(pos[2]) - self._home_z_m
        if dist_m > f.geofence_radius_m:
            return f"{dist_m:.1f} m from the offboard start > {f.geofence_radius_m:.1f} m"
        if height_m > f.altitude_max_m:
            return f"height {height_m:.2f} m above home > {f.altitude_max_m:.2f} m"
        return None
