"""The SITL vehicle's own state estimate (``--estimate px4``): what PX4's EKF2 reports is not the
truth, and PX4 flies what it reports.  The autopilot logic (commander, flight tasks) and the
MAVLink telemetry see the estimate; the camera, the trace and the contacts see the truth; every
velocity setpoint reaches the airframe less the estimate's velocity error, so the vehicle slides
by it as PX4 SIH's did (docs/px4-sitl.md §5).  The error model is the batched sim's
(``sim.estimate``, measured on PX4 SIH flights), one vehicle at the physics rate.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from sim.dynamics import QuadState
from sim.estimate import StateEstimateConfig, StateEstimator

from .flight_tasks import VelocityCommand
from .kinematics import Kinematics

ESTIMATES = ("exact", "px4")  # SitlConfig.estimate / --estimate


def _state(kin: Kinematics) -> QuadState:
    def row(values: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(values, dtype=torch.float32).reshape(1, -1)

    return QuadState(row(kin.pos_enu_m), row(kin.vel_enu_m_s), row(kin.quat_enu_flu), row(kin.angvel_body_flu_rad_s))


class SitlEstimate:
    """One vehicle's estimate: :meth:`update` after every physics step with the truth, then
    :attr:`kinematics` is what the autopilot knows and :meth:`flown` the command the airframe gets."""

    def __init__(self, truth: Kinematics, physics_dt_s: float, seed: int, config: StateEstimateConfig = StateEstimateConfig()) -> None:
        self._estimator = StateEstimator(config, 1, physics_dt_s)
        self._generator = torch.Generator().manual_seed(seed)
        self._estimator.reset(torch.tensor([0]), _state(truth), self._generator)
        self.kinematics = truth

    def update(self, truth: Kinematics) -> Kinematics:
        """Record the truth after a physics step; returns (and keeps) the estimate now."""
        self._estimator.record(_state(truth), self._generator)
        est = self._estimator.estimate(self._generator)
        self.kinematics = dataclasses.replace(
            truth,
            pos_enu_m=est.pos_enu_m[0].double().numpy(),
            vel_enu_m_s=est.vel_enu_m_s[0].double().numpy(),
            quat_enu_flu=est.quat_enu_flu[0].double().numpy(),
            angvel_body_flu_rad_s=est.angvel_body_flu_rad_s[0].double().numpy(),
        )
        return self.kinematics

    def velocity_error_m_s(self) -> np.ndarray:
        """(3,) world ENU: the estimate's velocity error now (bias + drift)."""
        return self._estimator.velocity_error_m_s()[0].double().numpy()

    def flown(self, command: VelocityCommand) -> VelocityCommand:
        """The setpoint as the truth follows it: the autopilot holds its estimate at ``command``."""
        return dataclasses.replace(command, vel_enu_m_s=np.asarray(command.vel_enu_m_s, dtype=np.float64) - self.velocity_error_m_s())
