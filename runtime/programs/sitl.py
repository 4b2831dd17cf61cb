"""``python -m runtime.programs.sitl``: fly one SITL episode with the runtime (the SITL dry run).

Connects to the SITL vehicle (MAVSDK ``udpin://127.0.0.1:PORT``) and its camera link (TCP
127.0.0.1) and flies the episode script (``runtime.programs.episode``, the same as ``cmnav fly``'s dry
run): waits for health (armable, local position, home) and a first frame, arms, takes off to
``--takeoff-alt-m`` and waits for Hold there, sets a hover setpoint, starts offboard, flies the
policy (:class:`runtime.flight.FlightLoop`) until within GOAL_REACHED_RADIUS_M of the goal, the
time limit or an abort, hovers, Holds, lands, waits for disarm and writes the summary JSON.  If
the autopilot refuses offboard, it records the trip (``offboard_refused``), commands Hold and
lands without flying; if the pilot takes over, it stops commanding and does nothing more; after
a ``vehicle_fault`` trip with the vehicle disarmed (a crash), there is nothing to land.
``--inject`` (tests only) injects the runtime's faults of ``runtime.faults.catalogue``.

Unlike the field program this one arms and takes off by itself: that is what a SITL dry run is.

Exit codes: 0 success; 1 timeout or aborted in flight; 2 the episode could not be run (model
refused, no autopilot, not healthy, takeoff failed, ...).  The summary is written in every case
it can be: ``{outcome: success|timeout|aborted, abort_reason, time_s, frames, missed_deadlines,
step_ms {p50, p99}, stage_ms {stage: {p50, p99}}, watchdog_trips [...], log,
t_launch_to_offboard_s, takeoff_climb, goal_rel_home_enu_m, final_distance_m, tracking_error_peak_m_s,
approach_cap, t_episode_start_s, injections, ...}``; ``approach_cap`` is {capped_steps, least_cap_m_s}
of the approach to the goal (``runtime.watchdog.cap_approach``); ``takeoff_climb`` is the climb in offboard that finishes the
autopilot's take-off (``FlightLoop.climb``: {ended, from_m, to_m, drift_m, duration_s});
``time_s`` runs from offboard start to the goal, ``t_launch_to_offboard_s`` from this process's
start to offboard confirmed by telemetry; ``t_episode_start_s`` is when the episode started (the
zero of the trips' ``t_s``) and ``injections`` ``[{kind, t_s}]`` when each injected fault first
acted, both time.monotonic seconds (the host's clock, shared with the SITL vehicle's trace).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from ..camera.sim_source import SimCameraSource
from ..config import MissionConfig, PolicyModelConfig, ProcessConfig, RecorderConfig, RuntimeConfig, VehicleConfig
from ..tracking import VELOCITY_BIAS_MODES
from ..contract import ContractMismatchError
from ..faults.catalogue import FaultKind, FaultSite, Injection, InjectionError, parse_injection
from ..faults.injection import FaultyPolicy, shrink_geofence, shrink_geofence_at
from ..flight import EpisodeResult, FlightLoop, log_task_failure, settle_heap
from ..log.recorder import Recorder, RecorderError
from ..model import ModelLoadError, PolicyModel, check_outputs_finite
from ..service.affinity import prepare_control_process
from ..service.shutdown import close_step, in_daemon_thread, run_bounded
from ..service.signals import StopSignals, cancel_on_stop_signals, ignore_stop_signals
from ..state import VehicleError, VehicleState
from ..vehicle import Vehicle
from .episode import EpisodeError, EpisodeScript
from .stop import FlightPhase, stop_on_signal

log = logging.getLogger("runtime.programs.sitl")

T_IMPORT_NS = time.monotonic_ns()
FIRST_FRAME_TIMEOUT_S = 10.0
LOG_NAME = "flight.mcap"
APPROACH_CAP_MODES = ("on", "off")  # --approach-cap: mission.approach_cap true or false


def process_age_s() -> float:
    """Seconds since this process started (Linux /proc; elsewhere since this module's import)."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
    except (OSError, IndexError, ValueError):
        return (time.monotonic_ns() - T_IMPORT_NS) / 1e9
    return time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK")


class FlightError(EpisodeError):
    """The episode could not be run (or landed); the message says why."""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m runtime.programs.sitl", description=__doc__.split("\n\n")[0])
    parser.add_argument("--mavlink-port", type=int, required=True, help="UDP port MAVSDK listens on (127.0.0.1)")
    parser.add_argument("--camera-port", type=int, required=True, help="the SITL vehicle's camera TCP port (127.0.0.1)")
    parser.add_argument("--model", type=Path, required=True, help="ONNX model with the runtime's contract")
    parser.add_argument("--goal-rel-home", required=True, help="goal relative to home, ENU metres: x,y,z")
    parser.add_argument("--takeoff-alt-m", type=float, required=True, help="takeoff height above home (m)")
    parser.add_argument("--timeout-s", type=float, default=60.0, help="offboard flight time limit (s, default 60)")
    parser.add_argument("--log-dir", type=Path, required=True, help=f"directory for the MCAP log ({LOG_NAME})")
    parser.add_argument("--summary", type=Path, required=True, help="where to write the summary JSON")
    parser.add_argument("--providers", default="CPUExecutionProvider", help="ONNX Runtime execution providers, comma-separated")
    parser.add_argument("--cpu-affinity", default="", metavar="CPU,...",
                        help="pin this process to these CPU ids (runtime.cpu_affinity of cmnav fly); default: no pinning")
    parser.add_argument("--intra-op-threads", type=int, default=0, help="ONNX Runtime intra-op threads (0 = its default)")
    parser.add_argument("--velocity-bias", choices=VELOCITY_BIAS_MODES, default="correct",
                        help="vehicle.velocity_bias_correction: correct the autopilot's velocity error (default) or off")
    parser.add_argument("--approach-cap", choices=APPROACH_CAP_MODES, default="on",
                        help="mission.approach_cap: slow the approach to the goal to what the brake stops in (default) or off")
    parser.add_argument("--inject", action="append", default=[], metavar="KIND@SECONDS",
                        help="fault injection for tests (repeatable): inference-overrun, nan-action or geofence, "
                        "SECONDS after offboard start")  # fmt: skip
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    args = parser.parse_args(argv)
    try:
        args.inject = [parse_injection(text, [FaultSite.RUNTIME]) for text in args.inject]
    except InjectionError as err:
        parser.error(str(err))
    try:
        goal = [float(v) for v in args.goal_rel_home.split(",")]
    except ValueError:
        goal = []
    if len(goal) != 3 or not np.all(np.isfinite(goal)):
        parser.error(f"--goal-rel-home {args.goal_rel_home!r}: expected three numbers x,y,z (ENU metres from home)")
    args.goal_rel_home = np.array(goal)
    if not (0.0 < args.takeoff_alt_m < 50.0):
        parser.error(f"--takeoff-alt-m {args.takeoff_alt_m}: expected a height in (0, 50) m above home")
    if args.timeout_s <= 0.0:
        parser.error(f"--timeout-s {args.timeout_s}: expected a positive number of seconds")
    try:
        args.process = ProcessConfig(cpu_affinity=tuple(int(v) for v in args.cpu_affinity.split(",") if v.strip()))
        args.policy = PolicyModelConfig(model_path=args.model, providers=tuple(args.providers.split(",")), intra_op_threads=args.intra_op_threads)
    except ValueError as err:  # ConfigError names the key
        parser.error(f"--cpu-affinity {args.cpu_affinity!r} / --intra-op-threads {args.intra_op_threads}: {err}")
    return args


def runtime_config(args: argparse.Namespace) -> RuntimeConfig:
    """The runtime's configuration for one SITL episode (``parse_args``' namespace)."""
    return RuntimeConfig(
        policy=args.policy,
        vehicle=VehicleConfig(url=f"udpin://127.0.0.1:{args.mavlink_port}",
                              velocity_bias_correction=args.velocity_bias == "correct"),
        mission=MissionConfig(approach_cap=args.approach_cap == "on"),
        recorder=RecorderConfig(log_dir=args.log_dir),
        runtime=args.process,
    )


async def fly_episode(args: argparse.Namespace, summary: dict, signals: StopSignals | None = None) -> EpisodeResult:
    """Everything between process start and disarm; fills ``summary`` as it goes.  On a stop
    signal (``signals``) it commands the safe state of the phase it interrupted (``runtime.programs.stop``),
    records ``summary["stop"]`` and what was flown, and re-raises the cancellation."""
    flight = FlightPhase()
    config = runtime_config(args)
    pinned = prepare_control_process(config.runtime.cpu_affinity)  # before ONNX Runtime's and MAVSDK's threads
    if pinned is not None:
        summary["cpu_affinity"] = list(pinned)
    try:
        model = PolicyModel(config.policy.model_path, config.policy.providers, config.policy.intra_op_threads)
        check_outputs_finite(model)
    except (ModelLoadError, ContractMismatchError) as err:
        raise FlightError(f"model refused, nothing armed: {err}") from err
    summary["model"] = {"path": str(model.path), "hidden_size": model.hidden_size, "providers": list(model.providers)}
    log_path = args.log_dir / LOG_NAME
    try:
        recorder = Recorder(log_path, config.recorder, metadata={**model.log_metadata(), "entry": "sitl_flight"})
    except RecorderError as err:
        raise FlightError(str(err)) from err
    summary["log"] = str(log_path)
    vehicle = Vehicle(config.vehicle)
    camera = SimCameraSource(args.camera_port)
    step_faults = [i for i in args.inject if i.kind in (FaultKind.INFERENCE_OVERRUN, FaultKind.NAN_ACTION)]
    policy = FaultyPolicy(model, step_faults) if step_faults else None
    loop = FlightLoop(config, policy or model, vehicle, camera, recorder)
    script = EpisodeScript(vehicle, loop, flight)

    async def fly(state: VehicleState) -> EpisodeResult:
        summary["t_launch_to_offboard_s"] = round(process_age_s(), 3)
        summary["takeoff_climb"] = script.takeoff_climb
        goal_enu_m = state.home_enu_m + args.goal_rel_home
        result = await _fly_with_faults(loop, policy, args.inject, goal_enu_m, args.timeout_s, summary)
        summary.update(result.summary())
        log.info("episode %s in %.2f s (%d steps, final distance %.2f m)", result.outcome, result.time_s,
                 result.steps, result.final_distance_m)  # fmt: skip
        return result

    async def refused(result: EpisodeResult, t_request_ns: int) -> None:
        summary["t_episode_start_s"] = t_request_ns / 1e9
        summary.update(result.summary())

    try:
        await script.start(FIRST_FRAME_TIMEOUT_S, "sim",
                           lambda: f"is the SITL vehicle serving frames on 127.0.0.1:{args.camera_port} (camera link: {camera.stats})?")  # fmt: skip
        return await script.dry_run(args.takeoff_alt_m, fly, before_offboard=lambda: None, on_refused=refused)
    except VehicleError as err:
        raise FlightError(f"vehicle: {err}") from err
    except asyncio.CancelledError:
        if signals is not None:
            summary["stop"] = await stop_on_signal(signals, flight, loop, vehicle, T_IMPORT_NS)
        if loop.interrupted is not None and "time_s" not in summary:
            summary.update(loop.interrupted.summary())
        raise
    finally:
        summary["camera"] = vars(camera.stats).copy()
        await close_step("the flight loop and camera", loop.close)
        await close_step("the flight log", lambda: in_daemon_thread("recorder-close", recorder.close))
        summary["recorder"] = vars(recorder.stats).copy()
        await close_step("MAVSDK", vehicle.close)


async def _fly_with_faults(
    loop: FlightLoop, policy: FaultyPolicy | None, injections: list[Injection], goal_enu_m: np.ndarray, timeout_s: float,
    summary: dict,
) -> EpisodeResult:  # fmt: skip
    """``loop.fly`` with the runtime's injected faults armed (none: just ``loop.fly``); a goal reached
    is followed by the dry run's retreat and landing (``FlightLoop.fly``'s ``landing_next``)."""
    settle_heap()  # here, not only in loop.fly: the faults' clock and the episode's start together
    t0_ns = time.monotonic_ns()
    summary["t_episode_start_s"] = t0_ns / 1e9
    if not injections:
        return await loop.fly(goal_enu_m, timeout_s, landing_next=True)
    injected: dict[FaultKind, float] = {}
    if policy is not None:
        policy.start(t0_ns)
    fence = next((i for i in injections if i.kind == FaultKind.GEOFENCE), None)
    fence_task = None
    if fence is not None and fence.at_s == 0.0:
        shrink_geofence(loop.watchdog, loop.vehicle.state().pos_enu_m, goal_enu_m)
        injected[FaultKind.GEOFENCE] = time.monotonic()
    elif fence is not None:
        fence_task = asyncio.create_task(shrink_geofence_at(loop.watchdog, fence.at_s, t0_ns, loop.vehicle.state))
        fence_task.add_done_callback(log_task_failure)
    try:
        return await loop.fly(goal_enu_m, timeout_s, landing_next=True)
    finally:
        if fence_task is not None:
            if fence_task.done() and not fence_task.cancelled() and fence_task.exception() is None:
                injected[FaultKind.GEOFENCE] = fence_task.result()
            fence_task.cancel()
        injected.update(policy.injected if policy is not None else {})
        summary["injections"] = [{"kind": kind.value, "t_s": t_s} for kind, t_s in injected.items()]


async def _main(args: argparse.Namespace, summary: dict) -> int:
    signals = cancel_on_stop_signals()
    try:
        result = await fly_episode(args, summary, signals)
    except EpisodeError as err:
        log.error("%s", err)
        summary["error"] = str(err)
        if "time_s" in summary:  # it flew; landing (or after) failed
            return 1
        summary["abort_reason"] = str(err)
        return 2
    except asyncio.CancelledError:
        cause = signals.received or "cancelled"
        log.error("terminated by %s", cause)
        summary.update(outcome="aborted", abort_reason=f"stopped by {cause}")
        if summary.get("stop") is None:  # before the vehicle existed (model load, log): nothing to command
            summary["stop"] = await stop_on_signal(signals, FlightPhase(), None, None, T_IMPORT_NS)
        return 1
    return 0 if result.outcome == "success" else 1


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    summary: dict = {
        "outcome": "aborted",
        "abort_reason": None,
        "goal_rel_home_enu_m": args.goal_rel_home.tolist(),
        "takeoff_alt_m": args.takeoff_alt_m,
        "log": None,
        "t_launch_to_offboard_s": None,
        "watchdog_trips": [],
    }
    try:
        code = run_bounded(_main(args, summary))
    finally:
        ignore_stop_signals()
    args.summary.parent.mkdir(parents=True, exist_ok=True)
    args.summary.write_text(json.dumps(summary, indent=2))
    log.info("summary written to %s (outcome %s, exit %d)", args.summary, summary["outcome"], code)
    return code


if __name__ == "__main__":
    sys.exit(main())
