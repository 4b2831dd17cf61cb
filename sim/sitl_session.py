"""`cmnav sitl`: one SITL episode with the SITL vehicle and the real runtime as separate
processes over loopback, merged into one summary (JSON), an MCAP log and a top-view plot.

The SITL vehicle (``python -m sim.sitl``) owns ground truth: world, trajectory, collisions,
invalid-depth fraction of every served frame.  The runtime (``python -m runtime.programs.sitl``)
owns what it did: outcome as it saw it, step timing, watchdog trips, MCAP log.  A collision in
the ground truth overrides the runtime's view (a crash is a crash, whatever the runtime thinks): the summary's ``time_s`` is
then the crash time in ground truth, and ``crash_detect_ms`` how long the runtime took to trip
on it (its ``tracking`` or ``vehicle_fault`` trip; null if it never did).

Fault injection (``--inject KIND@SECONDS``, ``runtime.faults.catalogue``): each fault goes to the process
where it happens (vehicle or runtime; with ``--autopilot`` the camera faults go to the world
follower, which serves the frames); ``runtime-kill`` and ``runtime-stop`` are done here, SIGKILL
resp. SIGTERM to the runtime's PID SECONDS after the vehicle entered OFFBOARD (read from the live
status file of the vehicle or the follower).  SIGKILL leaves the vehicle to its offboard-loss
failsafe; on SIGTERM the runtime stops as it would under systemd (hover, then Hold) and writes
its summary.  When a faulted flight does not end in a landing, the vehicle runs FAULT_OBSERVE_S
longer, so ground truth covers the response even when the runtime stopped early (pilot takeover,
kill, stop, lost link); the summary gets a ``faults`` list measured on ground truth (:func:`fault_records`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from runtime.contract import ContractMismatchError
from runtime.contract.constants import GOAL_REACHED_RADIUS_M
from runtime.faults.catalogue import FaultKind, FaultSite, Injection, InjectionError, parse_injection
from runtime.model import ModelLoadError, PolicyModel, check_outputs_finite
from runtime.service.paths import directory_problem

from .episode_args import check_level_seed
from .fault_report import RuntimeSignal, fault_records, runtime_trip_after, vehicle_failsafe_trip
from .follower.faults import follower_injection_problem
from .follower.url import AutopilotUrlError, parse_autopilot_url
from .plot import plot_top_view

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
VEHICLE_READY_TIMEOUT_S = 60.0
# Connect + health + arm + take-off + land around the offboard flight itself.
RUNTIME_OVERHEAD_S = 90.0
STOP_TIMEOUT_S = 10.0
POLL_S = 0.02
# After a faulted flight that did not end in a landing, keep the vehicle running this long after
# the runtime exited (s).
FAULT_OBSERVE_S = 2.0


class SitlError(RuntimeError):
    """The SITL episode could not be run (a process failed to start or died)."""


class SitlStopped(Exception):
    """SIGTERM / SIGINT reached ``cmnav sitl`` (raised by its handler in the main thread)."""


class _StopSignals:
    """SIGTERM / SIGINT while ``cmnav sitl`` runs: the first one interrupts the wait (raises
    :class:`SitlStopped`) so that the children are stopped by PID — the runtime with SIGTERM, so it
    commands hover then Hold and writes its summary, then the vehicle.  The children run in their
    own sessions, so a Ctrl-C in the terminal reaches only this process, which stops them in that
    order (the vehicle must still be there to take the runtime's Hold).  Further signals, and any
    that come once the children are being stopped, are logged and ignored: they must not cut the
    stop short (each child is SIGKILLed after STOP_TIMEOUT_S if it ignores SIGTERM)."""

    def __init__(self) -> None:
        self.received: str | None = None
        self.may_raise = True
        self._previous: dict[int, object] = {}

    def install(self) -> None:
        if threading.current_thread() is threading.main_thread():  # signal handlers live there only
            self._previous = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    @contextlib.contextmanager
    def deferred(self) -> Iterator[None]:
        """A signal in this block is raised at its end (not half way through starting a child)."""
        self.may_raise = False
        try:
            yield
        finally:
            self.may_raise = True
        if self.received is not None:
            raise SitlStopped(self.received)

    def _on_signal(self, signum: int, _frame: object) -> None:
        name = signal.Signals(signum).name
        if self.received is not None:
            log.warning("%s received while stopping: ignored, the runtime and the vehicle are being stopped", name)
            return
        if not self.may_raise:
            self.received = name
            log.warning("%s received: stopping the runtime and the SITL vehicle", name)
            return
        self.received = name
        log.warning("%s received: stopping the runtime (it commands Hold) and the SITL vehicle", name)
        raise SitlStopped(name)


@dataclass(frozen=True)
class SitlRequest:
    model_path: Path
    level: int
    seed: int
    timeout_s: float
    out_dir: Path
    injections: tuple[Injection, ...] = ()
    degrade: str = "none"
    estimate: str = "exact"  # our SITL vehicle's state estimate (sim.sitl.estimate.ESTIMATES)
    velocity_bias: str = "correct"  # the runtime's vehicle.velocity_bias_correction: correct | off
    approach_cap: str = "on"  # the runtime's mission.approach_cap: on | off
    # Pinning (cmnav bench runtime): the runtime process pins itself (runtime.cpu_affinity) and
    # runs ONNX Runtime with runtime_threads intra-op threads; the vehicle is started pinned.
    runtime_cpus: tuple[int, ...] = ()
    vehicle_cpus: tuple[int, ...] = ()
    runtime_threads: int = 0
    # An external autopilot (PX4 SITL): the world follows its pose from this URL (sim.follower)
    # and the runtime flies it on its offboard link, 127.0.0.1:offboard_port (PX4: 14540).
    autopilot_url: str | None = None
    offboard_port: int = 14540
    allow_remote: bool = False

    def injections_at(self, site: FaultSite) -> list[str]:
        """``--inject`` arguments for the process at ``site``."""
        return [arg for i in self.injections if i.site == site for arg in ("--inject", str(i))]

    @property
    def runtime_signal(self) -> Injection | None:
        """The orchestrator's fault, sent SECONDS after the vehicle's OFFBOARD entry: runtime-kill
        (SIGKILL) or runtime-stop (SIGTERM), or None."""
        return next((i for i in self.injections if i.site == FaultSite.ORCHESTRATOR), None)


def free_port(kind: int) -> int:
    """A free loopback port for ``socket.SOCK_DGRAM`` or ``socket.SOCK_STREAM``."""
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind((LOOPBACK, 0))
        return int(sock.getsockname()[1])


def _tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def stop_process(proc: subprocess.Popen, name: str, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
    """SIGTERM, then SIGKILL after ``timeout_s``, by PID; returns the exit code."""
    if proc.poll() is not None:
        return proc.returncode
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        log.warning("%s (pid %d) ignored SIGTERM for %.0f s; killing it", name, proc.pid, timeout_s)
        proc.kill()
        proc.wait()
    return proc.returncode


def _wait_for_file(path: Path, proc: subprocess.Popen, timeout_s: float, what: str, log_path: Path) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SitlError(f"{what} exited with code {proc.returncode} before it was ready; its log ({log_path}):\n{_tail(log_path)}")
        if path.exists():
            try:
                return json.loads(path.read_text())
            except json.JSONDecodeError:
                pass  # written but not complete yet
        time.sleep(0.05)
    raise SitlError(f"{what} was not ready within {timeout_s:.0f} s; its log ({log_path}):\n{_tail(log_path)}")


def _path_length_m(positions: np.ndarray) -> float:
    if len(positions) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum())


def _percent_stats(fractions: list[float]) -> dict[str, float]:
    if not fractions:
        return {"avg": 0.0, "min": 0.0, "max": 0.0}
    arr = 100.0 * np.asarray(fractions, dtype=np.float64)
    return {"avg": round(float(arr.mean()), 3), "min": round(float(arr.min()), 3), "max": round(float(arr.max()), 3)}


def run_sitl(request: SitlRequest) -> dict:
    """Fly one episode and return the merged summary (see ``cmnav sitl --help``)."""
    if (problem := directory_problem(request.out_dir)) is not None:
        raise SitlError(f"--out {request.out_dir}: {problem}: pass a writable directory")
    if not request.model_path.is_file():
        raise SitlError(f"model file {request.model_path} not found: export one with `cmnav export goal-seeker -o PATH`")
    try:  # the runtime's own load and first steps, before any process starts
        check_outputs_finite(PolicyModel(request.model_path))
    except (ModelLoadError, ContractMismatchError) as err:
        raise SitlError(f"model refused, nothing started: {err}") from err
    run_dir = request.out_dir / f"level{request.level}_seed{request.seed}_{time.strftime('%Y%m%d-%H%M%S')}"
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise SitlError(f"--out {request.out_dir}: cannot create {run_dir} ({err.strerror or err}): "
                        "pass a writable directory") from err  # fmt: skip
    mavlink_port = free_port(socket.SOCK_DGRAM) if request.autopilot_url is None else request.offboard_port
    camera_port = free_port(socket.SOCK_STREAM)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    t_launch = time.monotonic()
    signals = _StopSignals()
    signals.install()
    try:
        return _run_processes(request, run_dir, mavlink_port, camera_port, env, signals, t_launch)
    finally:
        signals.restore()


def _run_processes(
    request: SitlRequest, run_dir: Path, mavlink_port: int, camera_port: int, env: dict, signals: _StopSignals,
    t_launch: float,
) -> dict:  # fmt: skip
    episode_path, trace_path, summary_path = run_dir / "episode.json", run_dir / "trace.json", run_dir / "runtime_summary.json"
    status_path = run_dir / "vehicle_status.json"
    sim_log, runtime_log = run_dir / "sim.log", run_dir / "runtime.log"
    if request.autopilot_url is None:
        world_name, ready_timeout_s = "the SITL vehicle", VEHICLE_READY_TIMEOUT_S
    else:  # the follower waits for the autopilot to be armable; its own error names what is missing
        world_name, ready_timeout_s = "the world follower", VEHICLE_READY_TIMEOUT_S + 5.0
    signalled = None
    vehicle = runtime = None
    try:
        with signals.deferred():  # a child started is a child whose PID we hold
            vehicle = _start_world(request, mavlink_port, camera_port, episode_path, trace_path, status_path, sim_log, env)
        episode = _wait_for_file(episode_path, vehicle, ready_timeout_s, world_name, sim_log)
        log.info("%s ready (pid %d): level %d seed %d, goal %s m from home", world_name,
                 vehicle.pid, request.level, request.seed, episode["goal_rel_home_enu_m"])  # fmt: skip
        with open(runtime_log, "w") as runtime_out, signals.deferred():
            runtime = subprocess.Popen(
                [sys.executable, "-m", "runtime.programs.sitl", "--mavlink-port", str(mavlink_port),
                 "--camera-port", str(camera_port), "--model", str(request.model_path),
                 "--goal-rel-home=" + ",".join(f"{v:.4f}" for v in episode["goal_rel_home_enu_m"]),  # "=": may start with "-"
                 "--takeoff-alt-m", f"{episode['takeoff_alt_m']:.3f}", "--timeout-s", str(request.timeout_s),
                 "--log-dir", str(run_dir), "--summary", str(summary_path), *request.injections_at(FaultSite.RUNTIME),
                 "--velocity-bias", request.velocity_bias, "--approach-cap", request.approach_cap,
                 "--cpu-affinity", ",".join(map(str, request.runtime_cpus)), "--intra-op-threads", str(request.runtime_threads)],
                stdout=runtime_out, stderr=subprocess.STDOUT, env=env, start_new_session=True,
            )  # fmt: skip
        log.info("runtime started (pid %d); flying", runtime.pid)
        signalled = _wait_runtime(runtime, request, status_path)
        if request.injections and [mode for _, mode in _vehicle_mode_log(status_path)][-1:] != ["LAND"]:
            time.sleep(FAULT_OBSERVE_S)  # still flying: ground truth of the response, whatever the runtime did
    except SitlStopped:
        pass  # the children are stopped below, the runtime first; what it recorded makes the summary
    finally:
        signals.may_raise = False
        if runtime is not None:
            stop_process(runtime, "runtime")  # SIGTERM: hover, then Hold, summary written
        if vehicle is not None:
            stop_process(vehicle, world_name)
    if signals.received is not None and runtime is None:
        raise SitlError(f"stopped by {signals.received} before the flight started; nothing was armed")
    if not trace_path.exists():
        raise SitlError(f"{world_name} wrote no trace; its log ({sim_log}):\n{_tail(sim_log)}")
    if signalled is not None and signalled.kind == FaultKind.RUNTIME_KILL:
        # Killed: the runtime could write no summary; its MCAP log is cut short but readable.
        log_path = next(run_dir.glob("*.mcap"), None)
        flight = {"outcome": "aborted", "abort_reason": "runtime_killed", "log": log_path and str(log_path), "watchdog_trips": []}
    elif summary_path.exists():
        flight = json.loads(summary_path.read_text())
        if runtime is not None and runtime.returncode == 2:  # refused before the flight (sitl_flight's exit 2)
            raise SitlError(f"the runtime could not run the episode: {flight.get('error')} (its log: {runtime_log})")
        if signals.received is not None and flight.get("stop") is not None:
            flight["abort_reason"] = f"stopped by {signals.received}"  # forwarded to the runtime as SIGTERM
        elif signalled is not None and flight.get("stop") is not None:
            flight["abort_reason"] = "runtime_stopped"  # runtime-stop: our SIGTERM, not an operator's
    else:
        raise SitlError(f"the runtime wrote no summary (exit code {runtime.returncode if runtime else None}); "
                        f"its log ({runtime_log}):\n{_tail(runtime_log)}")  # fmt: skip
    trace = json.loads(trace_path.read_text())
    return merge_summary(request, episode, flight, trace, run_dir, time.monotonic() - t_launch, signalled)


def _start_world(
    request: SitlRequest, mavlink_port: int, camera_port: int, episode_path: Path, trace_path: Path, status_path: Path,
    sim_log: Path, env: dict,
) -> subprocess.Popen:  # fmt: skip
    """The camera world: our SITL vehicle, or the follower of the autopilot at ``request.autopilot_url``."""
    world_files = ["--level", str(request.level), "--seed", str(request.seed), "--degrade", request.degrade,
                   "--episode-json", str(episode_path), "--trace", str(trace_path), "--status-json", str(status_path)]  # fmt: skip
    if request.autopilot_url is None:
        command = [sys.executable, "-m", "sim.sitl", "--mavlink-port", str(mavlink_port), "--camera-port", str(camera_port),
                   "--estimate", request.estimate, *world_files, *request.injections_at(FaultSite.VEHICLE)]  # fmt: skip
    else:  # the vehicle's faults that reach the follower are the camera's (autopilot_request refuses the rest)
        command = [sys.executable, "-m", "sim.follower", "--autopilot", request.autopilot_url,
                   *(["--allow-remote"] if request.allow_remote else []), "--camera-port", str(camera_port), *world_files,
                   "--timeout-s", str(request.timeout_s), "--ready-timeout-s", str(VEHICLE_READY_TIMEOUT_S),
                   *request.injections_at(FaultSite.VEHICLE)]  # fmt: skip
    with open(sim_log, "w") as sim_out:
        return subprocess.Popen(
            command, stdout=sim_out, stderr=subprocess.STDOUT, env=env, start_new_session=True,
            # In the child before exec: every thread the vehicle starts inherits the set.
            preexec_fn=(lambda: os.sched_setaffinity(0, request.vehicle_cpus)) if request.vehicle_cpus else None,
        )  # fmt: skip


def _wait_runtime(runtime: subprocess.Popen, request: SitlRequest, status_path: Path) -> RuntimeSignal | None:
    """Wait for the runtime to finish (stopping it after the time limit); with a runtime-kill or
    runtime-stop injection, SIGKILL / SIGTERM it on time (after SIGTERM it stops itself: hover,
    Hold, summary).  Returns the signal sent, or None."""
    limit_s = request.timeout_s + RUNTIME_OVERHEAD_S
    deadline = time.monotonic() + limit_s
    fault = request.runtime_signal
    sent = None
    while runtime.poll() is None:
        if time.monotonic() > deadline:
            log.error("runtime did not finish within %.0f s; stopping it", limit_s)
            return sent
        t_offboard_s = _vehicle_offboard_entry(status_path) if fault is not None and sent is None else None
        if t_offboard_s is not None and time.monotonic() >= t_offboard_s + fault.at_s:
            # Stamped before it is sent: the runtime's handler can run (and stamp its own time)
            # before this process is scheduled again, which on loaded cores took seconds.
            sent = RuntimeSignal(fault.kind, time.monotonic(), time.time())
            if fault.kind == FaultKind.RUNTIME_KILL:
                runtime.kill()  # SIGKILL by PID: no handler runs, MAVSDK's setpoint re-sending dies with it
            else:
                runtime.send_signal(signal.SIGTERM)  # by PID: what systemd sends; the runtime's stop handling runs
            log.warning("runtime (pid %d) sent %s %.2f s after the vehicle entered OFFBOARD (%s)", runtime.pid,
                        "SIGKILL" if fault.kind == FaultKind.RUNTIME_KILL else "SIGTERM", sent.t_s - t_offboard_s, fault)  # fmt: skip
            if fault.kind == FaultKind.RUNTIME_KILL:
                runtime.wait()
                return sent
        time.sleep(POLL_S)
    return sent


def _vehicle_mode_log(status_path: Path) -> list[tuple[float, str]]:
    """The vehicle's mode log so far (time.monotonic s, mode) from its live status file."""
    try:
        return [(t, mode) for t, mode in json.loads(status_path.read_text())["mode_log"]]
    except (OSError, json.JSONDecodeError, KeyError):
        return []  # not written yet


def _vehicle_offboard_entry(status_path: Path) -> float | None:
    """The vehicle's first OFFBOARD entry (time.monotonic s), or None."""
    return next((t for t, mode in _vehicle_mode_log(status_path) if mode == "OFFBOARD"), None)


def flight_end_t_s(trace: dict, t_offboard: float | None) -> float | None:
    """When the flight that began at ``t_offboard`` ended in ground truth: the first mode other than
    offboard after it, or the disarm (a dry run lands in offboard: ``mission.land_in_offboard``);
    None if neither came (or it never entered offboard)."""
    if t_offboard is None:
        return None
    ends = [t for t, mode in trace["mode_log"] if t > t_offboard and mode != "OFFBOARD"][:1]
    ends += [t for t, armed in trace.get("armed_log", []) if t > t_offboard and not armed][:1]
    return min(ends, default=None)


def merge_summary(
    request: SitlRequest, episode: dict, flight: dict, trace: dict, run_dir: Path, wall_s: float,
    signalled: RuntimeSignal | None = None,
) -> dict:  # fmt: skip
    """One summary from the runtime's view and the vehicle's ground truth; writes the plot.

    With injections it adds ``faults`` (:func:`sim.fault_report.fault_records`); a killed
    runtime's trip (``signalled``: runtime-kill), the vehicle's own failsafe, is added to
    ``watchdog_trips`` from the trace.  A stopped runtime's (runtime-stop) is its ``stop`` record.
    """
    positions = np.asarray(trace["pos_enu_m"], dtype=np.float64).reshape(-1, 3)
    t_s = np.asarray(trace["t_s"], dtype=np.float64)
    offboard = [t for t, mode in trace["mode_log"] if mode == "OFFBOARD"]
    t_offboard = offboard[0] if offboard else None
    t_left = flight_end_t_s(trace, t_offboard)
    in_flight = np.ones(len(t_s), bool) if t_offboard is None else (t_s >= t_offboard) & (t_s <= (t_left if t_left is not None else np.inf))
    flown = positions[in_flight]
    collision = trace.get("collision")
    outcome = "crash" if collision else flight["outcome"]
    goal = np.asarray(episode["goal_enu_m"], dtype=np.float64)
    # Where offboard ended (after the brake and the dry run's retreat) and the closest it came.
    final_dist_m = float(np.linalg.norm(flown[-1] - goal)) if len(flown) else float("nan")
    closest_m = float(np.linalg.norm(flown - goal, axis=1).min()) if len(flown) else float("nan")
    if outcome == "success" and not closest_m <= GOAL_REACHED_RADIUS_M + 0.5:
        # The runtime believed it arrived but ground truth disagrees: report what happened.
        log.error("runtime reported success but the vehicle came no nearer than %.2f m to the goal", closest_m)
        outcome = "aborted"
    # The frames served from the episode's start (the dry run's climb in offboard comes first) to offboard's end.
    t_frames_from = flight.get("t_episode_start_s", t_offboard)
    frame_fracs = [f for t, f in zip(trace["frame_t_s"], trace["invalid_depth_frac"])
                   if (t_frames_from is None or t >= t_frames_from) and (t_left is None or t <= t_left)]  # fmt: skip
    plot_path = plot_top_view(
        run_dir / "trajectory.png", episode["room_size_m"], episode["boxes"], episode["start_enu_m"], goal,
        flown if len(flown) >= 2 else positions,
        title=f"{outcome}  level {request.level}  seed {request.seed}  {Path(request.model_path).name}",
        collision_enu_m=collision["pos_enu_m"] if collision else None,
    )  # fmt: skip
    trips = list(flight.get("watchdog_trips", []))
    if signalled is not None and signalled.kind == FaultKind.RUNTIME_KILL:
        failsafe, _ = vehicle_failsafe_trip([(t, m) for t, m in trace["mode_log"]], signalled.t_s)
        trips += [failsafe] if failsafe is not None else []
    time_s = flight.get("time_s")
    if collision:
        time_s, crash_detect_ms = crash_timing(collision, flight, t_offboard)
    summary = {
        "outcome": outcome,
        "abort_reason": flight.get("abort_reason"),
        "time_s": time_s,
        "path_m": round(_path_length_m(flown), 3),
        "final_distance_m": round(final_dist_m, 3),
        "closest_distance_m": round(closest_m, 3),
        "invalid_depth_pct": _percent_stats(frame_fracs),
        "frames": flight.get("frames"),
        "missed_deadlines": flight.get("missed_deadlines"),
        "step_ms": flight.get("step_ms"),
        "stage_ms": flight.get("stage_ms"),
        "watchdog_trips": trips,
        "tracking_error_peak_m_s": flight.get("tracking_error_peak_m_s"),
        "brake": flight.get("brake"),
        "approach_cap": flight.get("approach_cap"),
        "t_launch_to_offboard_s": flight.get("t_launch_to_offboard_s"),
        "takeoff_climb": flight.get("takeoff_climb"),
        "wall_s": round(wall_s, 2),
        "level": request.level,
        "seed": request.seed,
        "model": str(request.model_path),
        "log": flight.get("log"),
        "log_error": (flight.get("recorder") or {}).get("log_error"),
        "log_records_dropped": (flight.get("recorder") or {}).get("dropped"),
        "stop": flight.get("stop"),
        "plot": str(plot_path),
        "run_dir": str(run_dir),
    }
    if collision:
        summary["collision"] = collision
        summary["crash_detect_ms"] = crash_detect_ms
    if request.runtime_cpus or request.vehicle_cpus:
        summary["pinning"] = {"runtime_cpus": flight.get("cpu_affinity"), "vehicle_cpus": list(request.vehicle_cpus),
                              "runtime_intra_op_threads": request.runtime_threads}  # fmt: skip
    from .tracking import flight_tracking_error  # reads the MCAP log: mcap and the recorder's topics, which only SITL needs

    summary["tracking_error_m_s"] = flight_tracking_error(flight.get("log"), trace)
    if request.autopilot_url is not None:
        summary["autopilot"] = request.autopilot_url
        summary["ground_truth"] = trace.get("verdict")
        summary["pose_stream"] = trace.get("pose_stream")
    if request.injections:
        summary["faults"] = fault_records(request.injections, trace, flight, signalled)
    from runtime.report import write_report_quietly  # matplotlib (the extra `report`), only where a report is drawn

    # Before summary.json, which names it; a report that cannot be drawn only costs a warning.
    report = write_report_quietly(summary["log"], summary, episode)
    summary["report"] = None if report is None else str(report)
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def crash_timing(collision: dict, flight: dict, t_offboard: float | None) -> tuple[float | None, float | None]:
    """A crash's ``time_s`` (ground truth: the collision, s after the episode started, as the
    runtime counts ``time_s``; else after the vehicle's OFFBOARD entry) and ``crash_detect_ms``:
    collision -> the runtime's first trip at or after it (ms), None if it never tripped."""
    t_crash = float(collision["t_s"])
    t0 = flight.get("t_episode_start_s", t_offboard)
    time_s = None if t0 is None else round(t_crash - t0, 3)
    trip, t_trip = runtime_trip_after(flight, t_crash)
    return time_s, None if trip is None else round(1000.0 * (t_trip - t_crash), 1)


def autopilot_request(request: SitlRequest, url: str, offboard_port: int | None, allow_remote: bool) -> SitlRequest:
    """``request`` flown against an external autopilot: ValueError (naming the option) for a URL
    it refuses (another host without ``allow_remote``), a bad port, a fault only our vehicle can
    inject (the world follower injects the camera faults: ``sim.follower.faults``), or our
    vehicle's ``estimate``."""
    parse_autopilot_url(url, allow_remote)
    port = SitlRequest.offboard_port if offboard_port is None else offboard_port
    if not 0 < port < 65536:
        raise ValueError(f"--offboard-port {port} must be a UDP port in 1..65535 (PX4 SITL's offboard link: 14540)")
    for injection in request.injections:
        if (problem := follower_injection_problem(injection)) is not None:
            raise ValueError(problem)
    if request.estimate != "exact":
        raise ValueError("--estimate is our SITL vehicle's; with --autopilot the autopilot has its own")
    return replace(request, autopilot_url=url, offboard_port=port, allow_remote=allow_remote)


def run_sitl_cli(args: argparse.Namespace) -> int:
    """Entry of ``cmnav sitl``: exit 0 on success, 1 on crash/timeout/aborted, 2 if it could not run."""
    try:
        injections = tuple(parse_injection(text) for text in args.inject)
    except InjectionError as err:
        print(f"cmnav sitl: {err}", file=sys.stderr)
        return 2
    try:  # before any process starts: the children would refuse them with a traceback
        check_level_seed(args.level, args.seed)
        signalled = [str(i) for i in injections if i.site == FaultSite.ORCHESTRATOR]
        if len(signalled) > 1:
            raise ValueError(f"--inject {', '.join(signalled)}: the runtime gets one signal per flight (runtime-kill "
                             "or runtime-stop); fly them one at a time")  # fmt: skip
        if not (math.isfinite(args.timeout) and args.timeout > 0.0):
            raise ValueError(f"--timeout {args.timeout} must be a positive number of seconds")
    except ValueError as err:
        print(f"cmnav sitl: {err}", file=sys.stderr)
        return 2
    request = SitlRequest(Path(args.model), args.level, args.seed, args.timeout, Path(args.out), injections, args.degrade,
                          estimate=getattr(args, "estimate", "exact"),
                          velocity_bias=getattr(args, "velocity_bias", "correct"),
                          approach_cap=getattr(args, "approach_cap", "on"))  # fmt: skip
    if getattr(args, "autopilot", None) is not None:
        try:
            request = autopilot_request(request, args.autopilot, args.offboard_port, args.allow_remote)
        except (AutopilotUrlError, ValueError) as err:
            print(f"cmnav sitl: {err}", file=sys.stderr)
            return 2
    try:
        summary = run_sitl(request)
    except SitlError as err:
        print(f"cmnav sitl: {err}", file=sys.stderr)
        return 2
    print(
        f"{summary['outcome']}: level {summary['level']} seed {summary['seed']}, "
        f"time {summary['time_s']} s, path {summary['path_m']} m, step p50/p99 "
        f"{(summary['step_ms'] or {}).get('p50')}/{(summary['step_ms'] or {}).get('p99')} ms, "
        f"watchdog trips {len(summary['watchdog_trips'])}"
        + (f", crash detected after {summary['crash_detect_ms']} ms" if "crash_detect_ms" in summary else "")
        + f"\nlog {summary['log']}\nplot {summary['plot']}"
        + (f"\nreport {summary['report']}" if summary.get("report") else "")
    )
    for fault in summary.get("faults", []):
        if not fault["injected"]:
            print(f"fault {fault['kind']}@{fault['at_s']:g}: not injected (the flight ended before its time)")
            continue
        print(f"fault {fault['kind']}@{fault['at_s']:g}: trip {fault['cause']} detected in {fault['detect_ms']} ms, "
              f"{fault['trip_after_inject_ms']} ms after injection; {fault['response']}; stopped "
              f"{fault['stopped_within_s']} s after injection; Hold after {fault['hold_entered_s']} s "
              f"(commanded by the runtime after {fault['hold_commanded_s']} s)")  # fmt: skip
    if args.json:
        print(json.dumps(summary))
    return 0 if summary["outcome"] == "success" else 1
