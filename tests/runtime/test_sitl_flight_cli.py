"""``python -m runtime.programs.sitl``: refusals before anything is armed (no vehicle needed)."""

import json
import subprocess
import sys
from pathlib import Path

from tests.runtime.onnx_models import save, step_model

ROOT = Path(__file__).resolve().parents[2]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "runtime.programs.sitl", *args], capture_output=True, text=True,
                          timeout=60, cwd=ROOT)  # fmt: skip


def _args(tmp_path: Path, model: Path, goal: str = "9,1,0.5") -> list[str]:
    return ["--mavlink-port", "9", "--camera-port", "9", "--model", str(model), "--goal-rel-home", goal,
            "--takeoff-alt-m", "1.5", "--timeout-s", "5", "--log-dir", str(tmp_path / "logs"),
            "--summary", str(tmp_path / "summary.json")]  # fmt: skip


def test_wrong_model_is_refused_before_connecting(tmp_path):
    model = save(step_model(metadata={}), tmp_path / "old.onnx")
    proc = _run(*_args(tmp_path, model))
    assert proc.returncode == 2, proc.stderr[-2000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["outcome"] == "aborted"
    assert "model refused, nothing armed" in summary["abort_reason"]
    assert "carries no cmnav contract metadata" in summary["abort_reason"]
    assert summary["goal_rel_home_enu_m"] == [9.0, 1.0, 0.5] and summary["watchdog_trips"] == []


def test_bad_goal_argument_is_named(tmp_path):
    proc = _run(*_args(tmp_path, tmp_path / "m.onnx", goal="9,1"))
    assert proc.returncode == 2
    assert "--goal-rel-home '9,1': expected three numbers" in proc.stderr


def test_vehicle_faults_are_not_injected_by_the_runtime(tmp_path):
    proc = _run(*_args(tmp_path, tmp_path / "m.onnx"), "--inject", "camera-stall@2")
    assert proc.returncode == 2
    assert "unknown fault kind 'camera-stall' here; expected one of geofence, inference-overrun, nan-action" in proc.stderr


def test_the_runtime_switches_reach_its_configuration(tmp_path):
    from runtime.programs.sitl import parse_args, runtime_config

    default = runtime_config(parse_args(_args(tmp_path, tmp_path / "m.onnx")))
    assert default.mission.approach_cap and default.vehicle.velocity_bias_correction
    off = runtime_config(parse_args([*_args(tmp_path, tmp_path / "m.onnx"), "--approach-cap", "off", "--velocity-bias", "off"]))
    assert not off.mission.approach_cap and not off.vehicle.velocity_bias_correction
