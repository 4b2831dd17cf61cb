"""`cmnav sitl`: one SITL episode with the SITL vehicle and the real runtime as separate
processes over loopback, merged into one summary (JSON), an MCAP log and a top-view plot.

The SITL vehicle (``python -m sim.sitl``) owns ground truth: world, trajectory, collisions,
invalid-depth fraction of every served frame.  The runtime (``python -m runtime.sitl_flight``)
owns what it did: outcome as it saw it, step timing, watchdog trips, MCAP log.  A collision in
the ground truth overrides the runtime's view (a crash is a crash, whatever the runtime thinks).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.contract.constants import GOAL_REACHED_RADIUS_M

from .plot import plot_top_view

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
VEHICLE_READY_TIMEOUT_S = 60.0
# Connect + health + arm + take-off + land around the offboard flight itself.
RUNTIME_OVERHEAD_S = 90.0
STOP_TIMEOUT_S = 10.0


class SitlError(RuntimeError):
    """The SITL episode could not be run (a process failed to start or died)."""


@dataclass(frozen=True)
class SitlRequest:
    model_path: Path
    level: int
    seed: int
    timeout_s: float
    out_dir: Path


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


def _stop(proc: subprocess.Popen, name: str) -> None:
    """SIGTERM, then SIGKILL after STOP_TIMEOUT_S, by PID."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        log.warning("%s (pid %d) ignored SIGTERM for %.0f s; killing it", name, proc.pid, STOP_TIMEOUT_S)
        proc.kill()
        proc.wait()


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
    if not request.model_path.is_file():
        raise SitlError(f"model file {request.model_path} not found: export one with `cmnav export goal-seeker -o PATH`")
    run_dir = request.out_dir / f"level{request.level}_seed{request.seed}_{time.strftime('%Y%m%d-%H%M%S')}"
    run_dir.mkdir(parents=True, exist_ok=True)
    episode_path, trace_path, summary_path = run_dir / "episode.json", run_dir / "trace.json", run_dir / "runtime_summary.json"
    sim_log, runtime_log = run_dir / "sim.log", run_dir / "runtime.log"
    mavlink_port, camera_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    env = dict(os.environ, PYTHONUNBUFFERED="1")

    t_launch = time.monotonic()
    with open(sim_log, "w") as sim_out:
        vehicle = subprocess.Popen(
            [sys.executable, "-m", "sim.sitl", "--mavlink-port", str(mavlink_port), "--camera-port", str(camera_port),
             "--level", str(request.level), "--seed", str(request.seed),
             "--episode-json", str(episode_path), "--trace", str(trace_path)],
            stdout=sim_out, stderr=subprocess.STDOUT, env=env,
        )  # fmt: skip
    runtime = None
    try:
        episode = _wait_for_file(episode_path, vehicle, VEHICLE_READY_TIMEOUT_S, "the SITL vehicle", sim_log)
        log.info("SITL vehicle ready (pid %d): level %d seed %d, goal %s m from home",
                 vehicle.pid, request.level, request.seed, episode["goal_rel_home_enu_m"])  # fmt: skip
        with open(runtime_log, "w") as runtime_out:
            runtime = subprocess.Popen(
                [sys.executable, "-m", "runtime.sitl_flight", "--mavlink-port", str(mavlink_port),
                 "--camera-port", str(camera_port), "--model", str(request.model_path),
                 "--goal-rel-home", ",".join(f"{v:.4f}" for v in episode["goal_rel_home_enu_m"]),
                 "--takeoff-alt-m", f"{episode['takeoff_alt_m']:.3f}", "--timeout-s", str(request.timeout_s),
                 "--log-dir", str(run_dir), "--summary", str(summary_path)],
                stdout=runtime_out, stderr=subprocess.STDOUT, env=env,
            )  # fmt: skip
        log.info("runtime started (pid %d); flying", runtime.pid)
        try:
            runtime.wait(timeout=request.timeout_s + RUNTIME_OVERHEAD_S)
        except subprocess.TimeoutExpired:
            log.error("runtime did not finish within %.0f s; stopping it", request.timeout_s + RUNTIME_OVERHEAD_S)
    finally:
        if runtime is not None:
            _stop(runtime, "runtime")
        _stop(vehicle, "SITL vehicle")

    if not summary_path.exists():
        raise SitlError(f"the runtime wrote no summary (exit code {runtime.returncode if runtime else None}); "
                        f"its log ({runtime_log}):\n{_tail(runtime_log)}")  # fmt: skip
    if not trace_path.exists():
        raise SitlError(f"the SITL vehicle wrote no trace; its log ({sim_log}):\n{_tail(sim_log)}")
    flight = json.loads(summary_path.read_text())
    trace = json.loads(trace_path.read_text())
    return merge_summary(request, episode, flight, trace, run_dir, time.monotonic() - t_launch)


def merge_summary(request: SitlRequest, episode: dict, flight: dict, trace: dict, run_dir: Path, wall_s: float) -> dict:
    """One summary from the runtime's view and the vehicle's ground truth; writes the plot."""
    positions = np.asarray(trace["pos_enu_m"], dtype=np.float64).reshape(-1, 3)
    t_s = np.asarray(trace["t_s"], dtype=np.float64)
    offboard = [t for t, mode in trace["mode_log"] if mode == "OFFBOARD"]
    t_offboard = offboard[0] if offboard else None
    t_left = next((t for t, mode in trace["mode_log"] if t_offboard is not None and t > t_offboard and mode != "OFFBOARD"), None)
    in_flight = np.ones(len(t_s), bool) if t_offboard is None else (t_s >= t_offboard) & (t_s <= (t_left if t_left is not None else np.inf))
    flown = positions[in_flight]
    collision = trace.get("collision")
    outcome = "crash" if collision else flight["outcome"]
    goal = np.asarray(episode["goal_enu_m"], dtype=np.float64)
    final_dist_m = float(np.linalg.norm(flown[-1] - goal)) if len(flown) else float("nan")
    if outcome == "success" and final_dist_m > GOAL_REACHED_RADIUS_M + 0.5:
        # The runtime believed it arrived but ground truth disagrees: report what happened.
        log.error("runtime reported success but the vehicle ended %.2f m from the goal", final_dist_m)
        outcome = "aborted"
    frame_fracs = [f for t, f in zip(trace["frame_t_s"], trace["invalid_depth_frac"]) if t_offboard is None or t >= t_offboard]
    plot_path = plot_top_view(
        run_dir / "trajectory.png", episode["room_size_m"], episode["boxes"], episode["start_enu_m"], goal,
        flown if len(flown) >= 2 else positions,
        title=f"{outcome}  level {request.level}  seed {request.seed}  {Path(request.model_path).name}",
        collision_enu_m=collision["pos_enu_m"] if collision else None,
    )  # fmt: skip
    summary = {
        "outcome": outcome,
        "time_s": flight.get("time_s"),
        "path_m": round(_path_length_m(flown), 3),
        "final_distance_m": round(final_dist_m, 3),
        "invalid_depth_pct": _percent_stats(frame_fracs),
        "frames": flight.get("frames"),
        "missed_deadlines": flight.get("missed_deadlines"),
        "step_ms": flight.get("step_ms"),
        "stage_ms": flight.get("stage_ms"),
        "watchdog_trips": flight.get("watchdog_trips", []),
        "t_launch_to_offboard_s": flight.get("t_launch_to_offboard_s"),
        "wall_s": round(wall_s, 2),
        "level": request.level,
        "seed": request.seed,
        "model": str(request.model_path),
        "log": flight.get("log"),
        "plot": str(plot_path),
        "run_dir": str(run_dir),
    }
    if collision:
        summary["collision"] = collision
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def run_sitl_cli(args: argparse.Namespace) -> int:
    """Entry of ``cmnav sitl``: exit 0 on success, 1 on crash/timeout/aborted, 2 if it could not run."""
    request = SitlRequest(Path(args.model), args.level, args.seed, args.timeout, Path(args.out))
    try:
        summary = run_sitl(request)
    except SitlError as err:
        print(f"cmnav sitl: {err}", file=sys.stderr)
        return 2
    print(
        f"{summary['outcome']}: level {summary['level']} seed {summary['seed']}, "
        f"time {summary['time_s']} s, path {summary['path_m']} m, step p50/p99 "
        f"{(summary['step_ms'] or {}).get('p50')}/{(summary['step_ms'] or {}).get('p99')} ms, "
        f"watchdog trips {len(summary['watchdog_trips'])}\nlog {summary['log']}\nplot {summary['plot']}"
    )
    if args.json:
        print(json.dumps(summary))
    return 0 if summary["outcome"] == "success" else 1
