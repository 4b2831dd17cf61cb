"""The identification sequence flown offline on ``sim.dynamics`` (no MAVLink, no processes): the
same run record :mod:`.flight` writes, for comparing a parameter set with a recorded autopilot
(:func:`fit_params`) and for the test that holds our vehicle to PX4's recorded response.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from runtime.contract import CONTROL_PERIOD_S
from runtime.contract.frames import vehicle_to_world_enu
from sim.dynamics import CommandDelay, DynamicsParams, QuadrotorDynamics, QuadState

from .identify import identify, vehicle_frame_response
from .sequence import command_schedule, identification_sequence

PHYSICS_DT_S = 0.01
SAMPLE_DT_S = 0.02
START_HEIGHT_M = 2.5


def fly_offline(params: DynamicsParams, heading_rad: float = math.pi / 2) -> dict:
    """The sequence on the dynamics ``params`` from a hover at START_HEIGHT_M facing ``heading_rad``
    (ENU; PX4 SIH starts facing north).  Returns a run record as :func:`.flight.fly_sequence`'s
    (without a landing)."""
    t_cmd, cmd_v, steps = command_schedule(identification_sequence())
    dynamics = QuadrotorDynamics(params)
    delay = CommandDelay(params)
    state = QuadState.at_rest(torch.tensor([[0.0, 0.0, START_HEIGHT_M]], dtype=torch.float64), heading_rad)
    samples: dict[str, list] = {"t_s": [], "pos_enu_m": [], "vel_enu_m_s": [], "yaw_enu_rad": [], "mode": [], "in_air": []}
    n_steps = int(round((t_cmd[-1] + 1.0) / PHYSICS_DT_S))
    every = int(round(SAMPLE_DT_S / PHYSICS_DT_S))
    for i in range(n_steps):
        t_s = i * PHYSICS_DT_S
        k = int(np.searchsorted(t_cmd, t_s + 1e-9, side="right")) - 1
        command = cmd_v[k] if k >= 0 else np.zeros(4)
        yaw = float(state.yaw_enu_rad()[0])
        vel_cmd = torch.as_tensor(vehicle_to_world_enu(command[:3], yaw), dtype=torch.float64).reshape(1, 3)
        vel_cmd, yaw_cmd = delay.push(t_s, vel_cmd, torch.tensor([float(command[3])], dtype=torch.float64))
        state = dynamics.step(state, vel_cmd, yaw_cmd, PHYSICS_DT_S)
        if i % every == 0:
            samples["t_s"].append(t_s)
            samples["pos_enu_m"].append(state.pos_enu_m[0].tolist())
            samples["vel_enu_m_s"].append(state.vel_enu_m_s[0].tolist())
            samples["yaw_enu_rad"].append(float(state.yaw_enu_rad()[0]))
            samples["mode"].append("OFFBOARD")
            samples["in_air"].append(True)
    return {"control_period_s": CONTROL_PERIOD_S, "commands": {"t_s": t_cmd.tolist(), "command_v": cmd_v.tolist()},
            "steps": steps, "samples": samples, "end": None}  # fmt: skip


def response_error(run: dict, reference: dict, axes: tuple[int, ...]) -> float:
    """RMS difference of the vehicle-frame responses (forward, left, up m/s; yaw rate rad/s) on
    ``axes`` over the step part of the sequence, both read at the reference's sample times
    relative to its first command."""
    t_ref, r_ref = vehicle_frame_response(reference["samples"])
    t_run, r_run = vehicle_frame_response(run["samples"])
    t0_ref, t0_run = reference["commands"]["t_s"][0], run["commands"]["t_s"][0]
    last_step_s = max(s["t_end_s"] for s in reference["steps"])
    keep = (t_ref - t0_ref >= 0.0) & (t_ref - t0_ref <= last_step_s)
    errors = [np.interp(t_ref[keep] - t0_ref, t_run - t0_run, r_run[:, k]) - r_ref[keep, k] for k in axes]
    return float(np.sqrt(np.mean(np.square(errors))))


# Which parameters shape which axes' response.
_AXIS_PARAMS = {
    (0, 1): ("command_delay_xy_s", "velocity_gain_1_s", "linear_drag_kg_s", "velocity_integral_gain_1_s2",
             "max_accel_horizontal_m_s2", "attitude_tau_s"),
    (2,): ("command_delay_z_s", "vertical_velocity_gain_1_s"),
    (3,): ("command_delay_yaw_s", "yaw_rate_tau_s", "yaw_rate_gain", "max_yaw_accel_rad_s2"),
}  # fmt: skip


def fit_params(reference: dict, start: DynamicsParams, rounds: int = 3) -> tuple[DynamicsParams, dict]:
    """Coordinate descent of ``start`` toward the recorded ``reference`` run: each parameter in
    turn scaled by the factors that lower :func:`response_error` on its axes.  Returns the fitted
    parameters and the error per axis group before and after."""
    params = start
    before = {str(axes): round(response_error(fly_offline(params), reference, axes), 4) for axes in _AXIS_PARAMS}
    for _ in range(rounds):
        for axes, names in _AXIS_PARAMS.items():
            best = response_error(fly_offline(params), reference, axes)
            for name in names:
                for factor in (0.6, 0.8, 0.9, 1.1, 1.25, 1.6):
                    value = getattr(params, name)
                    value = 0.05 if value == 0.0 and factor > 1.0 else value * factor
                    if not math.isfinite(value):
                        continue
                    try:
                        trial = dataclasses.replace(params, **{name: value})
                        trial.validate()
                    except ValueError:
                        continue
                    error = response_error(fly_offline(trial), reference, axes)
                    if error < best:
                        params, best = trial, error
    after = {str(axes): round(response_error(fly_offline(params), reference, axes), 4) for axes in _AXIS_PARAMS}
    return params, {"rms_before": before, "rms_after": after, "identified": identify(fly_offline(params))}
