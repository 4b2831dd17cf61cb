"""The `cmnav sitl` orchestrator's own logic: merging the runtime's view with ground truth."""

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from runtime.faults.catalogue import FaultKind, FaultSite, Injection, parse_injection
from sim.fault_report import RuntimeSignal
from sim.sitl_session import SitlError, SitlRequest, flight_end_t_s, merge_summary, run_sitl, run_sitl_cli

EPISODE = {
    "room_size_m": [11.0, 6.0, 5.0],
    "boxes": [{"center_m": [5.0, 3.0, 2.0], "half_extent_m": [0.05, 0.6, 1.5], "yaw_rad": 0.3}],
    "start_enu_m": [1.0, 3.0, 1.5],
    "goal_enu_m": [10.5, 3.0, 1.5],
}
FLIGHT = {
    "outcome": "success",
    "time_s": 9.8,
    "frames": 147,
    "missed_deadlines": 0,
    "step_ms": {"p50": 1.0, "p99": 2.0},
    "stage_ms": {},
    "watchdog_trips": [],
    "t_launch_to_offboard_s": 7.0,
    "log": "flight.mcap",
}


def _trace(collision=None):
    t = np.arange(0.0, 20.0, 0.1)
    x = np.interp(t, [0, 5, 15, 20], [1.0, 1.0, 10.5, 10.5])
    pos = np.stack([x, np.full_like(t, 3.0), np.full_like(t, 1.5)], axis=1)
    return {
        "t_s": t.tolist(),
        "pos_enu_m": pos.tolist(),
        "mode_log": [[0.0, "HOLD"], [5.0, "OFFBOARD"], [15.0, "HOLD"], [17.0, "LAND"]],
        "collision": collision,
        "frame_t_s": t[::2].tolist(),
        "invalid_depth_frac": np.where(t[::2] < 5.0, 0.9, 0.1).tolist(),
        "frames_served": len(t[::2]),
    }


def _request(tmp_path):
    return SitlRequest(Path("m.onnx"), 1, 7, 30.0, tmp_path)


def test_merge_success(tmp_path):
    summary = merge_summary(_request(tmp_path), EPISODE, FLIGHT, _trace(), tmp_path, 30.0)
    assert summary["outcome"] == "success"
    assert summary["path_m"] == pytest.approx(9.5, abs=0.05)  # offboard part only
    assert summary["invalid_depth_pct"] == {"avg": 10.0, "min": 10.0, "max": 10.0}  # frames in flight only
    image = cv2.imread(summary["plot"])
    assert image is not None and image.shape[0] > 100
    assert json.loads((tmp_path / "summary.json").read_text())["outcome"] == "success"


def test_ground_truth_collision_overrides(tmp_path):
    collision = {"t_s": 9.0, "pos_enu_m": [4.9, 3.0, 1.5]}
    summary = merge_summary(_request(tmp_path), EPISODE, dict(FLIGHT, outcome="timeout"), _trace(collision), tmp_path, 30.0)
    assert summary["outcome"] == "crash" and summary["collision"] == collision


def test_success_far_from_goal_is_not_success(tmp_path):
    trace = _trace()
    trace["pos_enu_m"] = [[1.0, 3.0, 1.5]] * len(trace["t_s"])
    summary = merge_summary(_request(tmp_path), EPISODE, FLIGHT, trace, tmp_path, 30.0)
    assert summary["outcome"] == "aborted"


def test_missing_model_is_named(tmp_path):
    with pytest.raises(SitlError, match="model file .*nope.onnx not found.*cmnav export goal-seeker"):
        run_sitl(SitlRequest(tmp_path / "nope.onnx", 0, 0, 10.0, tmp_path))


def test_killed_runtime_gets_the_vehicles_failsafe_trip_and_fault_record(tmp_path):
    trace = _trace()
    trace["mode_log"] = [[0.0, "HOLD"], [5.0, "OFFBOARD"], [8.05, "HOLD"]]
    trace["vel_enu_m_s"] = [[1.0 if t < 8.5 else 0.0, 0.0, 0.0] for t in trace["t_s"]]
    request = SitlRequest(Path("m.onnx"), 1, 7, 30.0, tmp_path, (Injection(FaultKind.RUNTIME_KILL, 2.0),))
    flight = {"outcome": "aborted", "abort_reason": "runtime_killed", "log": None, "watchdog_trips": []}
    summary = merge_summary(request, EPISODE, flight, trace, tmp_path, 30.0, RuntimeSignal(FaultKind.RUNTIME_KILL, 7.0, 1e9))
    assert summary["abort_reason"] == "runtime_killed"
    (trip,) = summary["watchdog_trips"]
    assert trip["cause"] == "offboard_loss_failsafe" and trip["detect_ms"] == pytest.approx(1050.0)
    (fault,) = summary["faults"]
    assert fault["t_inject_s"] == pytest.approx(2.0) and fault["hold_entered_s"] == pytest.approx(1.05)
    assert fault["stopped_within_s"] == pytest.approx(1.5)


def test_injections_go_to_the_process_where_the_fault_happens(tmp_path):
    request = SitlRequest(Path("m.onnx"), 0, 1, 10.0, tmp_path, tuple(
        parse_injection(t) for t in ("camera-stall@2", "nan-action@3", "runtime-kill@4")))  # fmt: skip
    assert request.injections_at(FaultSite.VEHICLE) == ["--inject", "camera-stall@2"]
    assert request.injections_at(FaultSite.RUNTIME) == ["--inject", "nan-action@3"]
    assert request.runtime_signal == parse_injection("runtime-kill@4")
    stop = SitlRequest(Path("m.onnx"), 0, 1, 10.0, tmp_path, (parse_injection("runtime-stop@2"),))
    assert stop.runtime_signal == parse_injection("runtime-stop@2")
    assert stop.injections_at(FaultSite.VEHICLE) == stop.injections_at(FaultSite.RUNTIME) == []


def test_one_signal_per_flight(tmp_path, capsys):
    args = argparse.Namespace(model="m.onnx", level=0, seed=0, timeout=10.0, out=str(tmp_path), json=False,
                              inject=["runtime-kill@3", "runtime-stop@2"])  # fmt: skip
    assert run_sitl_cli(args) == 2
    err = capsys.readouterr().err
    assert "runtime-kill@3, runtime-stop@2: the runtime gets one signal per flight" in err
    assert not any(tmp_path.iterdir())


def test_bad_injection_is_refused_before_anything_starts(tmp_path, capsys):
    args = argparse.Namespace(model="m.onnx", level=0, seed=0, timeout=10.0, out=str(tmp_path), json=False,
                              inject=["camera-stal@2"])  # fmt: skip
    assert run_sitl_cli(args) == 2
    assert "unknown fault kind 'camera-stal'" in capsys.readouterr().err


def test_a_crash_takes_its_time_from_ground_truth_with_the_runtimes_detection_delay(tmp_path):
    collision = {"t_s": 9.0, "pos_enu_m": [4.9, 3.0, 1.5], "what": "obstacle 0"}
    trips = [{"cause": "vehicle_fault", "detail": "autopilot CRITICAL: collision: obstacle 0", "t_s": 4.012,
              "detect_ms": 4.0, "response": "hover_then_hold", "hold_t_s": 5.012}]  # fmt: skip
    flight = dict(FLIGHT, outcome="aborted", abort_reason="vehicle_fault", time_s=5.1, t_episode_start_s=5.0,
                  watchdog_trips=trips)  # fmt: skip
    summary = merge_summary(_request(tmp_path), EPISODE, flight, _trace(collision), tmp_path, 30.0)
    assert summary["outcome"] == "crash" and summary["abort_reason"] == "vehicle_fault"
    assert summary["time_s"] == pytest.approx(4.0)  # collision at 9.0, episode from 5.0; not the runtime's 5.1
    assert summary["crash_detect_ms"] == pytest.approx(12.0)
    # A runtime that never noticed: the time is still the crash's, the detection delay null.
    unnoticed = dict(FLIGHT, outcome="timeout", time_s=15.0, t_episode_start_s=5.0)
    summary = merge_summary(_request(tmp_path), EPISODE, unnoticed, _trace(collision), tmp_path, 30.0)
    assert summary["time_s"] == pytest.approx(4.0) and summary["crash_detect_ms"] is None


def test_a_nan_model_is_refused_before_any_process_starts(tmp_path, capsys):
    from tests.runtime.onnx_models import save, step_model

    model = save(step_model(action_offset=float("nan")), tmp_path / "nan.onnx")
    out = tmp_path / "runs"
    args = argparse.Namespace(model=str(model), level=0, seed=0, timeout=10.0, out=str(out), json=False, inject=[],
                              degrade="none")  # fmt: skip
    assert run_sitl_cli(args) == 2
    err = capsys.readouterr().err
    assert "model refused, nothing started" in err and "outputs NaN/Inf (action)" in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()  # no run directory: neither the vehicle nor the runtime was started


def test_the_flight_ends_at_the_first_mode_out_of_offboard_or_the_disarm():
    trace = {"mode_log": [[0.0, "HOLD"], [5.0, "OFFBOARD"], [15.0, "HOLD"], [17.0, "LAND"]],
             "armed_log": [[1.0, True], [20.0, False]]}  # fmt: skip
    assert flight_end_t_s(trace, 5.0) == 15.0
    landed_in_offboard = {"mode_log": [[0.0, "HOLD"], [5.0, "OFFBOARD"]], "armed_log": [[1.0, True], [18.0, False]]}
    assert flight_end_t_s(landed_in_offboard, 5.0) == 18.0
    assert flight_end_t_s({"mode_log": [[5.0, "OFFBOARD"]]}, 5.0) is None  # a trace from before armed_log: to its end
    assert flight_end_t_s(trace, None) is None
