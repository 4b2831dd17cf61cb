"""The world follower flown end to end without PX4: our SITL vehicle stands in for the external
autopilot (``--stand-in``: no camera, no room to hit, a second MAVLink link streaming its pose)
and ``cmnav sitl --autopilot`` runs the follower and the runtime against it — two MAVLink
consumers (the runtime's MAVSDK offboard link, the follower's pose link), the camera rendered at
the followed pose, crash reporting over the camera link, and the PX4 campaign's fault scenarios
(a camera stall injected by the follower, a SIGTERM to the runtime).  Real processes over loopback."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from runtime.programs.replay import replay_log
from sim.sitl_session import free_port, stop_process

pytestmark = pytest.mark.timeout(300)


def _fly(
    model: Path, out: Path, level: int, seed: int, *stand_in_args: str, inject: tuple[str, ...] = ()
) -> tuple[int, dict, str, dict]:
    """Stand-in vehicle + ``cmnav sitl --autopilot`` (with ``--inject`` each of ``inject``);
    returns (exit code, summary, stderr, the stand-in's own trace)."""
    offboard_port, pose_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    trace_path = out / "stand_in_trace.json"
    with open(out / "stand_in.log", "w") as log:
        stand_in = subprocess.Popen(
            [sys.executable, "-m", "sim.sitl", "--stand-in", "--mavlink-port", str(offboard_port), "--pose-port",
             str(pose_port), "--level", "0", "--seed", "99", "--episode-json", str(out / "stand_in_episode.json"),
             "--trace", str(trace_path), *stand_in_args],
            stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "cmnav", "sitl", "--model", str(model), "--out", str(out / "runs"), "--json",
             "--autopilot", f"udp://127.0.0.1:{pose_port}", "--offboard-port", str(offboard_port),
             "--level", str(level), "--seed", str(seed), "--timeout", "30", *(a for i in inject for a in ("--inject", i))],
            capture_output=True, text=True, timeout=240,
        )  # fmt: skip
    finally:
        assert stop_process(stand_in, "stand-in vehicle") == 0, (out / "stand_in.log").read_text()[-2000:]
    lines = proc.stdout.strip().splitlines()
    summary = json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}
    return proc.returncode, summary, proc.stderr, json.loads(trace_path.read_text())


def _modes_after_offboard(trace: dict) -> list[str]:
    modes = [mode for _, mode in trace["mode_log"]]
    return modes[modes.index("OFFBOARD") :]


def test_follower_flies_the_stand_in_autopilot_to_the_goal(goal_seeker, tmp_path):
    # Spawned facing north, as PX4 SIH starts: the room is placed along the autopilot's heading.
    code, summary, stderr, stand_in = _fly(goal_seeker, tmp_path, 0, 1, "--heading-deg", "90")
    assert code == 0, f"exit {code}; summary {summary}; stderr:\n{stderr[-3000:]}"
    assert summary["outcome"] == "success" and summary["watchdog_trips"] == []
    assert summary["closest_distance_m"] <= 1.5 and summary["path_m"] > 5.0
    # Then back along its path before the landing (the landing site): it lands clear of the goal's wall.
    assert summary["brake"]["retreat"]["ended"] == "arrived" and summary["final_distance_m"] > summary["closest_distance_m"] + 1.0
    truth = summary["ground_truth"]
    assert truth["contact"] is None and truth["geofence"] is None and truth["timeout_t_s"] is None
    assert truth["goal_reached_t_s"] > truth["offboard_t_s"]
    episode = json.loads((Path(summary["run_dir"]) / "episode.json").read_text())
    assert abs(episode["placement"]["heading_local_enu_rad"] - math.pi / 2) < 0.01
    # Offboard flight went north in the autopilot's frame: the room's +x is its north.
    start_local = np.asarray(stand_in["pos_enu_m"][0])
    end_local = np.asarray(stand_in["pos_enu_m"][-1])
    assert end_local[1] - start_local[1] > 5.0 and abs(end_local[0] - start_local[0]) < 0.5 * (end_local[1] - start_local[1])
    # The follower followed the pose at the requested rate: frames were rendered and served in flight.
    assert summary["frames"] > 0.5 * 15 * summary["time_s"]
    assert summary["pose_stream"]["position_messages"] > summary["frames"]  # poses came faster than frames
    tracking = summary["tracking_error_m_s"]
    assert tracking["n"] > 0.5 * summary["frames"] and 0.0 <= tracking["p50"] <= tracking["p99"]
    # The stand-in (the autopilot) flew offboard to the ground, where its land detector disarmed it:
    # the runtime flew it, the landing too (mission.land_in_offboard), with no Hold or Land of its own.
    assert summary["brake"]["descent"]["ended"] == "disarmed", summary["brake"]
    assert not {"HOLD", "LAND"} & set(_modes_after_offboard(stand_in)), stand_in["mode_log"]
    assert stand_in["collision"] is None  # it knows no room
    report = replay_log(summary["log"])
    assert report.same_model and report.steps == summary["frames"] and report.max_abs_diff <= 1e-5


def test_a_contact_in_the_followed_world_ends_the_flight_in_hold(goal_seeker, tmp_path):
    # Level 3, seed 1: the goal-seeker flies straight into obstacle 0.
    code, summary, stderr, stand_in = _fly(goal_seeker, tmp_path, level=3, seed=1)
    assert code == 1, f"exit {code}; summary {summary}; stderr:\n{stderr[-3000:]}"
    assert summary["outcome"] == "crash" and summary["collision"]["what"].startswith("obstacle")
    (trip,) = summary["watchdog_trips"]
    assert trip["cause"] == "sim_contact" and trip["response"] == "hover_then_hold" and trip["hold_t_s"] is not None
    assert summary["ground_truth"]["contact"] == summary["collision"]
    # The autopilot itself never knew: it was commanded to Hold, then landed by the runtime.
    assert _modes_after_offboard(stand_in)[:3] == ["OFFBOARD", "HOLD", "LAND"]
    modes = stand_in["mode_log"]
    i_offboard = next(i for i, (_, mode) in enumerate(modes) if mode == "OFFBOARD")
    assert modes[i_offboard][0] < summary["collision"]["t_s"] < modes[i_offboard + 1][0]  # Hold came after the contact
    report = replay_log(summary["log"])
    assert report.same_model and report.steps == summary["frames"] and report.max_abs_diff <= 1e-5


def _no_failsafe(stand_in: dict) -> None:
    """The autopilot stopped in the runtime's Hold, never in its own offboard-loss failsafe."""
    assert "POSCTL" not in _modes_after_offboard(stand_in), stand_in["mode_log"]
    assert not any("ailsafe" in text for _, text in stand_in["events"]), stand_in["events"]


def test_a_camera_stall_injected_by_the_follower_ends_in_hover_and_hold(goal_seeker, tmp_path):
    code, summary, stderr, stand_in = _fly(goal_seeker, tmp_path, 0, 1, inject=("camera-stall@2",))
    assert code == 1, f"exit {code}; summary {summary}; stderr:\n{stderr[-3000:]}"
    assert summary["outcome"] == "aborted" and summary["abort_reason"] == "stale_frame"
    (fault,) = summary["faults"]
    assert fault["injected"] and fault["t_inject_s"] >= 2.0, fault
    assert (fault["cause"], fault["response"]) == ("stale_frame", "hover_then_hold"), fault
    # The follower's mode log comes from the 1 Hz HEARTBEAT and misses the runtime's Hold, which
    # lasts until its landing command: the record takes Hold from the runtime's accepted command.
    assert fault["trip_after_inject_ms"] is not None and fault["hold_commanded_s"] is not None, fault
    assert fault["stopped_after_trip_s"] is not None, fault
    # The follower's trace says when the stall began; no frame captured after it was served.
    trace = json.loads((Path(summary["run_dir"]) / "trace.json").read_text())
    (stall,) = trace["injections"]
    assert stall["kind"] == "camera-stall" and max(trace["frame_t_s"]) < stall["t_s"]
    # The autopilot: offboard, the runtime's Hold after the trip, then the runtime's landing.
    assert _modes_after_offboard(stand_in)[:3] == ["OFFBOARD", "HOLD", "LAND"]
    _no_failsafe(stand_in)


def test_a_sigterm_to_the_runtime_ends_in_its_own_stop_and_hold(goal_seeker, tmp_path):
    code, summary, stderr, stand_in = _fly(goal_seeker, tmp_path, 0, 1, inject=("runtime-stop@2",))
    assert code == 1, f"exit {code}; summary {summary}; stderr:\n{stderr[-3000:]}"
    assert summary["outcome"] == "aborted" and summary["abort_reason"] == "runtime_stopped"
    stop = summary["stop"]
    assert (stop["cause"], stop["phase"], stop["action"]) == ("SIGTERM", "episode", "hover_then_hold"), stop
    (fault,) = summary["faults"]
    assert fault["injected"] and fault["stop"] == stop, fault
    assert (fault["cause"], fault["response"]) == ("stop_signal", "hover_then_hold"), fault
    assert fault["hold_entered_s"] is not None and fault["stopped_within_s"] is not None, fault
    runtime_log = (Path(summary["run_dir"]) / "runtime.log").read_text()
    assert "stopped on SIGTERM while episode: hover_then_hold" in runtime_log and "Traceback" not in runtime_log
    # The runtime's Hold is the last word: it exits without landing, the autopilot hovers in Hold.
    assert _modes_after_offboard(stand_in) == ["OFFBOARD", "HOLD"], stand_in["mode_log"]
    _no_failsafe(stand_in)
