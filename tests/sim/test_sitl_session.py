"""The `cmnav sitl` orchestrator's own logic: merging the runtime's view with ground truth."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from sim.sitl_session import SitlError, SitlRequest, merge_summary, run_sitl

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
