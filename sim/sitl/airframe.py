"""The simulated airframe in its room: ``sim.dynamics`` behind the commanded velocity, plus what
the point-mass model leaves to us: standing on landing gear, falling when the motors are off,
touch-down versus crash on the floor, and collisions with walls, ceiling and obstacles.

Frames: world ENU, body FLU.  The body origin rests LANDING_GEAR_HEIGHT_M above the floor, so a
landed camera still sees the room; the floor is ground, not an obstacle, unless it is hit faster
than TOUCHDOWN_MAX_SPEED_M_S.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import torch

from sim.collision import DEFAULT_VEHICLE_RADIUS_M, box_signed_distance_m
from sim.dynamics import GRAVITY_M_S2, PX4_SIH_V1_16, CommandDelay, DynamicsParams, QuadrotorDynamics, QuadState
from sim.world import WorldBatch

from .flight_tasks import VelocityCommand
from .kinematics import Kinematics

log = logging.getLogger(__name__)

LANDING_GEAR_HEIGHT_M = 0.15
# Faster than this at floor contact is a crash (PX4 lands at MPC_LAND_SPEED = 0.7 m/s).
TOUCHDOWN_MAX_SPEED_M_S = 1.0
# A commanded climb faster than this lifts a landed vehicle off; anything less keeps it sitting.
LIFTOFF_MIN_CLIMB_M_S = 0.05


class Airframe:
    """One vehicle in one world, stepped under velocity commands (None = motors off)."""

    def __init__(
        self,
        world: WorldBatch,
        spawn_xy_enu_m: np.ndarray,
        yaw_enu_rad: float = 0.0,
        params: DynamicsParams = PX4_SIH_V1_16,
        radius_m: float = DEFAULT_VEHICLE_RADIUS_M,
        world_contact: bool = True,
    ) -> None:
        """``params``: the velocity response (default PX4 v1.16 SIH's, as identified; its command
        delays are applied here); the floor is this class's to handle, not the dynamics'.
        ``world_contact`` False: walls, ceiling and obstacles are not there for this vehicle
        (only the floor is), as for an external autopilot that knows no room."""
        params = dataclasses.replace(params, ground_contact=False)
        if world.batch_size != 1:
            raise ValueError(f"an airframe flies in one world, got a batch of {world.batch_size}")
        self._world = world
        self._dynamics = QuadrotorDynamics(params)
        self._delay = CommandDelay(params)
        self._t_s = 0.0  # the airframe's own clock, for the command delay
        self._radius_m = radius_m
        self._world_contact = world_contact
        home = np.array([spawn_xy_enu_m[0], spawn_xy_enu_m[1], LANDING_GEAR_HEIGHT_M], dtype=np.float64)
        self.home_enu_m = home
        self._state = QuadState.at_rest(torch.as_tensor(home, dtype=torch.float32).reshape(1, 3), yaw_enu_rad)
        self.on_ground = True
        self.crashed = False

    def kinematics(self, t_ns: int | None = None) -> Kinematics:
        """Current state as numpy, stamped t_ns (default: time.monotonic_ns() now)."""
        s = self._state
        return Kinematics(
            t_ns=time.monotonic_ns() if t_ns is None else t_ns,
            pos_enu_m=s.pos_enu_m[0].double().numpy().copy(),
            vel_enu_m_s=s.vel_enu_m_s[0].double().numpy().copy(),
            quat_enu_flu=s.quat_enu_flu[0].double().numpy().copy(),
            angvel_body_flu_rad_s=s.angvel_body_flu_rad_s[0].double().numpy().copy(),
            on_ground=self.on_ground,
        )

    def step(self, command: VelocityCommand | None, dt_s: float) -> str | None:
        """Advance dt_s under ``command`` (None: motors off).  Returns what was hit if this step
        crashed the vehicle (it then stays frozen where it hit), else None."""
        if self.crashed:
            return None
        if command is None:
            if self.on_ground:
                return None
            self._fall(dt_s)
        else:
            if self.on_ground and command.vel_enu_m_s[2] <= LIFTOFF_MIN_CLIMB_M_S:
                return None
            self.on_ground = False
            vel_cmd, yaw_rate_cmd = self._delay.push(
                self._t_s,
                torch.as_tensor(command.vel_enu_m_s, dtype=torch.float32).reshape(1, 3),
                torch.tensor([command.yaw_rate_enu_rad_s], dtype=torch.float32),
            )
            self._state = self._dynamics.step(self._state, vel_cmd, yaw_rate_cmd, dt_s)
        self._t_s += dt_s
        hit = self._contact()
        if hit is not None:
            self.crashed = True
            self._state = QuadState(
                self._state.pos_enu_m,
                torch.zeros_like(self._state.vel_enu_m_s),
                self._state.quat_enu_flu,
                torch.zeros_like(self._state.angvel_body_flu_rad_s),
            )
            log.warning("crash: %s at %s m ENU", hit, np.round(self._state.pos_enu_m[0].numpy(), 2).tolist())
        return hit

    def _fall(self, dt_s: float) -> None:
        """Motors off in the air: gravity only (attitude frozen)."""
        s = self._state
        vel = s.vel_enu_m_s.clone()
        vel[:, 2] -= GRAVITY_M_S2 * dt_s
        self._state = QuadState(s.pos_enu_m + vel * dt_s, vel, s.quat_enu_flu, torch.zeros_like(s.angvel_body_flu_rad_s))

    def _contact(self) -> str | None:
        """Floor touch-down (or crash), then walls, ceiling and obstacles."""
        pos = self._state.pos_enu_m
        if float(pos[0, 2]) <= LANDING_GEAR_HEIGHT_M:
            crash = floor_crash(float(pos[0, 2]), float(torch.linalg.vector_norm(self._state.vel_enu_m_s[0])))
            if crash is not None:
                return crash
            yaw = float(self._state.yaw_enu_rad()[0])
            rest = pos.clone()
            rest[0, 2] = LANDING_GEAR_HEIGHT_M
            self._state = QuadState.at_rest(rest, yaw)
            self.on_ground = True
        return self._obstacle_hit()

    def _obstacle_hit(self) -> str | None:
        if not self._world_contact:
            return None
        return room_contact(self._world, self._state.pos_enu_m, self._radius_m)


def room_contact(world: WorldBatch, pos_enu_m: torch.Tensor, radius_m: float = DEFAULT_VEHICLE_RADIUS_M) -> str | None:
    """What a vehicle of ``radius_m`` at ``pos_enu_m`` [1, 3] (world ENU, m) touches: a wall, the
    ceiling or an obstacle (its name), or None.  The floor is ground, judged apart
    (:func:`floor_crash`)."""
    size = world.room_size_m
    faces = {
        "wall x=0": pos_enu_m[0, 0],
        f"wall x={float(size[0, 0]):.1f}": size[0, 0] - pos_enu_m[0, 0],
        "wall y=0": pos_enu_m[0, 1],
        f"wall y={float(size[0, 1]):.1f}": size[0, 1] - pos_enu_m[0, 1],
        "ceiling": size[0, 2] - pos_enu_m[0, 2],
    }
    for name, clearance_m in faces.items():
        if float(clearance_m) < radius_m:
            return name
    if world.num_slots:
        distances = box_signed_distance_m(world, pos_enu_m)[0]
        nearest = int(torch.argmin(distances))
        if float(distances[nearest]) < radius_m:
            return f"obstacle {nearest}"
    return None


def floor_crash(height_m: float, speed_m_s: float) -> str | None:
    """A floor contact (body origin at or below LANDING_GEAR_HEIGHT_M) faster than
    TOUCHDOWN_MAX_SPEED_M_S is a crash (its name); slower is a touch-down (None)."""
    if height_m <= LANDING_GEAR_HEIGHT_M and speed_m_s > TOUCHDOWN_MAX_SPEED_M_S:
        return f"floor at {speed_m_s:.1f} m/s"
    return None
