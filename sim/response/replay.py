"""Recorded autopilot flights read back: the autopilot's estimate against the ground truth, and a
``sim.dynamics`` parameter set replayed on the commands that were sent.

A run of ``cmnav sitl --autopilot`` (one flight of ``scripts/px4-campaign.sh``) keeps the
runtime's flight log (``flight.mcap``: ``/vehicle/state`` is what the autopilot reported, its
estimate; ``/vehicle/command`` what was sent) and the world follower's ``trace.json`` (the ground
truth in the room, and the placement that maps the autopilot's local frame into the room).  In
offboard and in the air only:

- :func:`estimate_error`: estimate minus truth, position and velocity, world axes (x, y: the
  room's horizontal axes; z up): the spread of each flight's mean over the flights (the
  per-episode bias of ``sim.estimate``), the spread about it within a flight (the drift), its
  autocorrelation; of the autopilot's estimate as it reported it, or (``corrected``) as the
  runtime used it, less the velocity bias it measured (``runtime.tracking.VelocityBias``);
- :func:`replay_error`: the logged commands flown through ``sim.dynamics``, the flight held to
  the record until a window starts (every ``every_s``), then free; the velocity (vehicle frame:
  forward, left, up) and heading ``horizon_s`` later against the truth's, or against the
  autopilot's own estimate (what its controller holds at the setpoint).

``python -m sim.response replay RUN_DIR...`` prints both.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from runtime.contract.frames import world_enu_to_vehicle, wrap_angle
from runtime.log.reader import FlightLogReader, ReplayError
from sim.dynamics import CommandDelay, DynamicsParams, QuadrotorDynamics, QuadState
from sim.follower.placement import Placement
from sim.rotations import quat_from_euler, quat_multiply, rotate_about_z

log = logging.getLogger(__name__)

REFERENCES = ("truth", "estimate")
AUTOCORRELATION_LAGS_S = (0.5, 1.0, 2.0)
PHYSICS_DT_S = 0.01
COMMAND_DELAY_LEAD_S = 0.3  # a window's held lead-in: longer than the autopilot's command delays


class FlightRecordError(ValueError):
    """A run directory cannot be read as a recorded flight; the message names the file and the fix."""


class NeverFlewError(FlightRecordError):
    """The run is readable but never flew the policy in offboard (e.g. a contact at take-off)."""


@dataclass(frozen=True)
class Track:
    """Samples in the room's frame: t_s [N] (this host's CLOCK_MONOTONIC, s), pos_enu_m [N, 3],
    vel_enu_m_s [N, 3], yaw_enu_rad [N] (unwrapped)."""

    t_s: np.ndarray
    pos_enu_m: np.ndarray
    vel_enu_m_s: np.ndarray
    yaw_enu_rad: np.ndarray

    def at(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(pos [K, 3], vel [K, 3], yaw [K]) interpolated at times t_s [K]."""
        def interp(values: np.ndarray) -> np.ndarray:
            return np.stack([np.interp(t_s, self.t_s, values[:, i]) for i in range(values.shape[1])], axis=-1)

        return interp(self.pos_enu_m), interp(self.vel_enu_m_s), np.interp(t_s, self.t_s, self.yaw_enu_rad)


@dataclass(frozen=True)
class RecordedFlight:
    """One flight: the truth, the estimate (in offboard, in the air) as the autopilot reported it
    and as the runtime corrected it (its velocity less the bias the runtime measured; the same as
    ``estimate`` in logs from before the correction), and the commands sent in offboard,
    ``commands`` [M, 5]: t_s, forward, left, up (m/s, vehicle frame), yaw rate (rad/s, + =
    counter-clockwise)."""

    name: str
    truth: Track
    estimate: Track
    corrected_estimate: Track
    commands: np.ndarray


def _track(t_s: list, pos: list, vel: list, yaw: list) -> Track:
    t = np.asarray(t_s, dtype=np.float64)
    order = np.argsort(t, kind="stable")
    keep = np.r_[True, np.diff(t[order]) > 0.0]
    pick = order[keep]
    return Track(t[pick], np.asarray(pos, dtype=np.float64)[pick], np.asarray(vel, dtype=np.float64)[pick],
                 np.unwrap(np.asarray(yaw, dtype=np.float64)[pick]))  # fmt: skip


def load_flight(run_dir: str | Path) -> RecordedFlight:
    """A run directory of ``cmnav sitl --autopilot`` (``trace.json`` and ``flight.mcap``)."""
    run_dir = Path(run_dir)
    trace_path, log_path = run_dir / "trace.json", run_dir / "flight.mcap"
    try:
        trace = json.loads(trace_path.read_text())
        placement = Placement(np.asarray(trace["placement"]["home_local_enu_m"], dtype=np.float64),
                              float(trace["placement"]["heading_local_enu_rad"]),
                              np.asarray(trace["placement"]["origin_world_enu_m"], dtype=np.float64))  # fmt: skip
        truth = _track(trace["t_s"], trace["pos_enu_m"], trace["vel_enu_m_s"], trace["yaw_enu_rad"])
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise FlightRecordError(f"{trace_path}: not a world follower's trace ({type(err).__name__}: {err}): pass the run "
                                "directory of a `cmnav sitl --autopilot` flight (it writes trace.json)") from err  # fmt: skip
    est: dict[str, list] = {"t": [], "pos": [], "vel": [], "corrected_vel": [], "yaw": []}
    commands, mode, in_air = [], "UNKNOWN", False
    try:
        reader = FlightLogReader(log_path)
        for topic, log_time_ns, m in reader.messages(("/vehicle/state", "/vehicle/command")):
            if topic == "/vehicle/state":
                mode, in_air = m["flight_mode"], bool(m["in_air"])
                if mode == "OFFBOARD" and in_air and m["pos_enu_m"][0] is not None and m["vel_enu_m_s"][0] is not None:
                    est["t"].append(m["t_posvel_ns"] * 1e-9)
                    est["pos"].append(placement.world_position(np.asarray(m["pos_enu_m"], dtype=np.float64)))
                    # The runtime logs the autopilot's velocity less the bias it measured
                    # (runtime.tracking.VelocityBias); logs from before that have no bias.
                    bias = np.asarray(m.get("vel_bias_enu_m_s") or [0.0, 0.0, 0.0], dtype=np.float64)
                    corrected = np.asarray(m["vel_enu_m_s"], dtype=np.float64)
                    est["vel"].append(placement.world_from_local(corrected + bias))
                    est["corrected_vel"].append(placement.world_from_local(corrected))
                    est["yaw"].append(placement.world_yaw(float(m["yaw_enu_rad"])))
            elif mode == "OFFBOARD" and m["sent"]:
                commands.append(((log_time_ns - reader.offset_ns) * 1e-9, m["forward_m_s"], -m["right_m_s"], -m["down_m_s"],
                                 -math.radians(m["yawspeed_deg_s"])))  # fmt: skip
    except (ReplayError, KeyError, TypeError) as err:
        raise FlightRecordError(f"{log_path}: {err}: pass the run directory of a `cmnav sitl --autopilot` flight") from err
    if len(est["t"]) < 2 or len(commands) < 2:
        raise NeverFlewError(f"{log_path}: {len(est['t'])} estimates and {len(commands)} commands in offboard: "
                                "the flight never flew the policy (see its runtime.log)")  # fmt: skip
    return RecordedFlight(run_dir.name, truth, _track(est["t"], est["pos"], est["vel"], est["yaw"]),
                          _track(est["t"], est["pos"], est["corrected_vel"], est["yaw"]), np.asarray(commands))  # fmt: skip


def load_flights(paths: list[str | Path]) -> list[RecordedFlight]:
    """Run directories, or campaign directories (their ``runs/*``, in name order; a run in one
    that never flew the policy is left out, with a warning)."""
    flights = []
    for path in map(Path, paths):
        if not (path / "runs").is_dir():
            flights.append(load_flight(path))
            continue
        for run_dir in sorted(p for p in (path / "runs").iterdir() if p.is_dir()):
            try:
                flights.append(load_flight(run_dir))
            except NeverFlewError as err:
                log.warning("left out: %s", err)
    if not flights:
        raise FlightRecordError(f"no flight in {', '.join(map(str, paths))} flew the policy in offboard")
    return flights


def _within_truth(flight: RecordedFlight) -> np.ndarray:
    t = flight.estimate.t_s
    return (t >= flight.truth.t_s[0]) & (t <= flight.truth.t_s[-1])


def estimate_error(flights: list[RecordedFlight], corrected: bool = False) -> dict:
    """Estimate minus truth at the estimate's times; per axis x, y, z (see the module doc).
    ``corrected``: the estimate as the runtime used it (velocity less its measured bias)."""
    per_flight = []
    for f in flights:
        keep = _within_truth(f)
        estimate = f.corrected_estimate if corrected else f.estimate
        pos, vel, _ = f.truth.at(estimate.t_s[keep])
        error = np.concatenate([estimate.pos_enu_m[keep] - pos, estimate.vel_enu_m_s[keep] - vel], axis=1)
        if len(error) >= 2:
            per_flight.append((estimate.t_s[keep], error))
    if not per_flight:
        raise FlightRecordError("no flight has estimates within its ground truth's time span")
    means = np.stack([e.mean(axis=0) for _, e in per_flight])
    centred = [(t, e - e.mean(axis=0)) for t, e in per_flight]
    within = np.concatenate([e for _, e in centred]).std(axis=0)
    period_s = float(np.median(np.concatenate([np.diff(t) for t, _ in per_flight])))
    autocorrelation = {}
    for lag_s in AUTOCORRELATION_LAGS_S:
        k = max(1, int(round(lag_s / period_s)))
        num = sum((e[k:] * e[:-k]).sum(axis=0) for _, e in centred if len(e) > k)
        den = sum((e * e).sum(axis=0) for _, e in centred)
        autocorrelation[lag_s] = np.round(num / np.maximum(den, 1e-12), 2).tolist()

    def split(values: np.ndarray) -> dict:
        return {"position_m": np.round(values[:3], 3).tolist(), "velocity_m_s": np.round(values[3:], 3).tolist()}

    return {"flights": len(per_flight), "samples": int(sum(len(e) for _, e in per_flight)), "sample_period_s": round(period_s, 4),
            "bias_sd": split(means.std(axis=0)), "within_flight_sd": split(within),
            "autocorrelation": {str(lag): split(np.asarray(v)) for lag, v in autocorrelation.items()}}  # fmt: skip


def _commands_at(flight: RecordedFlight, t_s: np.ndarray) -> np.ndarray:
    """[K, 4] the command acting at each of t_s (the last one sent before it)."""
    index = np.clip(np.searchsorted(flight.commands[:, 0], t_s, side="right") - 1, 0, None)
    return flight.commands[index, 1:5]


def _held_flight(params: DynamicsParams, commands: np.ndarray, reference: tuple[np.ndarray, ...], held_steps: int,
                 snapshots_at: range | tuple[int, ...], state: QuadState | None = None) -> list[QuadState]:  # fmt: skip
    """Fly B flights at once under ``commands`` [B, T, 4] (forward, left, up, yaw rate), for the
    first ``held_steps`` steps put back after every physics step at ``reference`` (pos [B, T+1, 3],
    vel [B, T+1, 3], yaw [B, T+1]; index 0 is the start) in position, velocity and heading, free
    after: the controller's integral, the tilt and the yaw rate stay the model's own answer to the
    commands.  Returns the state after each number of steps in ``snapshots_at`` (ascending)."""
    pos, vel, yaw = (torch.as_tensor(x, dtype=torch.float64) for x in reference)
    cmd = torch.as_tensor(commands, dtype=torch.float64)
    if state is None:
        zeros = torch.zeros_like(yaw[:, 0])
        state = QuadState(pos[:, 0], vel[:, 0], quat_from_euler(zeros, zeros, yaw[:, 0]), torch.zeros_like(pos[:, 0]))
    dynamics, delay = QuadrotorDynamics(params), CommandDelay(params)
    wanted, snapshots = set(snapshots_at), []
    for k in range(max(snapshots_at)):
        heading = state.yaw_enu_rad()
        vel_cmd, yaw_rate_cmd = delay.push(k * PHYSICS_DT_S, rotate_about_z(cmd[:, k, :3], heading), cmd[:, k, 3])
        state = dynamics.step(state, vel_cmd, yaw_rate_cmd, PHYSICS_DT_S)
        if k < held_steps:
            zeros = torch.zeros_like(heading)
            turn = quat_from_euler(zeros, zeros, yaw[:, k + 1] - state.yaw_enu_rad())
            state = replace(state, pos_enu_m=pos[:, k + 1], vel_enu_m_s=vel[:, k + 1], quat_enu_flu=quat_multiply(turn, state.quat_enu_flu))
        if k + 1 in wanted:
            snapshots.append(state)
    return snapshots


def _select(states: list[tuple[QuadState, int]]) -> QuadState:
    """One batch of the states[j][0]'s row states[j][1]."""
    def pick(name: str) -> torch.Tensor | None:
        rows = [getattr(state, name) for state, _ in states]
        if any(r is None for r in rows):
            return None
        return torch.stack([r[i] for r, (_, i) in zip(rows, states)])

    return QuadState(*(pick(f.name) for f in fields(QuadState)))


def replay_error(flights: list[RecordedFlight], params: DynamicsParams, reference: str = "truth",
                 horizon_s: float = 1.0, every_s: float = 0.25) -> dict:  # fmt: skip
    """The logged commands through ``params`` in windows that start from ``reference`` (see the
    module doc).  Every flight is first flown from the start of offboard held to the reference
    (:func:`_held_flight`); every ``every_s`` a window takes its flight's model state, flies
    COMMAND_DELAY_LEAD_S more held (its command delays filled) and then ``horizon_s`` free.
    Returns the RMS and mean of (model - reference) at half the horizon and at the horizon:
    forward, left, up (m/s, vehicle frame of the reference's heading) and heading (rad)."""
    if reference not in REFERENCES:
        raise ValueError(f"reference {reference!r}: choose from {REFERENCES}")
    tracks = [f.truth if reference == "truth" else f.estimate for f in flights]
    first = np.array([max(f.commands[0, 0], f.estimate.t_s[0], f.truth.t_s[0]) for f in flights])
    last = np.array([min(f.commands[-1, 0], f.estimate.t_s[-1], f.truth.t_s[-1]) for f in flights])
    lead, steps, every = (int(round(x / PHYSICS_DT_S)) for x in (COMMAND_DELAY_LEAD_S, horizon_s, every_s))
    # Phase 1: every flight held to its reference from the start of offboard (a flight that ends
    # sooner than the longest holds its last command and reference).
    length = int(round((last - first).max() / PHYSICS_DT_S))
    t_all = [first[i] + np.minimum(np.arange(length + 1) * PHYSICS_DT_S, last[i] - first[i]) for i in range(len(flights))]
    reference_all = [track.at(t) for track, t in zip(tracks, t_all)]
    snapshots = _held_flight(params, np.stack([_commands_at(f, t[:-1]) for f, t in zip(flights, t_all)]),
                             tuple(np.stack([r[j] for r in reference_all]) for j in range(3)), length, range(every, length + 1, every))  # fmt: skip
    starts = [(i, first[i] + (n + 1) * every * PHYSICS_DT_S, snapshot) for n, snapshot in enumerate(snapshots)
              for i in range(len(flights)) if first[i] + ((n + 1) * every + lead + steps) * PHYSICS_DT_S <= last[i]]  # fmt: skip
    if not starts:
        raise FlightRecordError(f"no flight is longer than the {horizon_s} s horizon plus {COMMAND_DELAY_LEAD_S} s")
    # Phase 2: the windows together, from their flights' held states.
    t_windows = [t0 + np.arange(lead + steps + 1) * PHYSICS_DT_S for _, t0, _ in starts]
    reference_windows = [tracks[i].at(t) for (i, _, _), t in zip(starts, t_windows)]
    ref_pos, ref_vel, ref_yaw = (np.stack([r[j] for r in reference_windows]) for j in range(3))
    checks = {round(horizon_s / 2, 3): lead + steps // 2, round(horizon_s, 3): lead + steps}
    flown = _held_flight(params, np.stack([_commands_at(flights[i], t[:-1]) for (i, _, _), t in zip(starts, t_windows)]),
                         (ref_pos, ref_vel, ref_yaw), lead, tuple(checks.values()), state=_select([(s, i) for i, _, s in starts]))  # fmt: skip
    out = {}
    for (h, at_step), state in zip(checks.items(), flown):
        yaw_ref = ref_yaw[:, at_step]
        vel_error = world_enu_to_vehicle(state.vel_enu_m_s.numpy(), yaw_ref) - world_enu_to_vehicle(ref_vel[:, at_step], yaw_ref)
        yaw_error = wrap_angle(state.yaw_enu_rad().numpy() - yaw_ref)
        error = np.column_stack([vel_error, yaw_error])
        out[str(h)] = {"rms": np.round(np.sqrt((error**2).mean(axis=0)), 3).tolist(), "mean": np.round(error.mean(axis=0), 3).tolist()}
    return {"reference": reference, "windows": len(starts), "axes": ["forward_m_s", "left_m_s", "up_m_s", "yaw_rad"], "at_s": out}
