"""`cmnav bench train --quick` runs the whole training step (render, preprocess, encoder, physics,
policy, PPO update) and reports env-steps/s with each stage's share; no timing is asserted."""

import json
import subprocess
import sys

import pytest

from bench.train import FIELD_STAGES, STAGES, TEACHER_STAGES

pytestmark = pytest.mark.timeout(300)


def test_bench_train_quick_reports_rates_and_stage_shares():
    proc = subprocess.run([sys.executable, "-m", "cmnav", "bench", "train", "--quick", "--json"],
                          capture_output=True, text=True, timeout=280)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["device"] == "cpu" and [row["envs"] for row in result["rows"]] == [2, 2]
    assert result["rows"][0]["precision"] == "fp32" and result["rows"][1]["precision"].startswith("auto (")
    for row in result["rows"]:
        assert row["env_steps"] == 2 * result["config"]["rollout_steps"]
        assert 0 < row["env_steps_per_s"] < row["collect_env_steps_per_s"]
        assert set(row["share"]) == set(STAGES)
        assert sum(row["share"].values()) == pytest.approx(1.0, abs=1e-6)
        assert all(row["share"][s] > 0 for s in ("render", "encode", "physics", "ppo_update"))
    teacher = result["teacher"]
    assert teacher["envs"] == result["config"]["teacher_envs"] and teacher["env_steps_per_s"] > 0
    assert set(teacher["share"]) == set(TEACHER_STAGES) and teacher["share"]["privileged"] > 0
    assert [r["path"] for r in result["encoder_speed"]] == ["fp32", "fp32 channels_last", "bf16 channels_last"]
    assert result["encoder_speed"][0]["ratio_to_fp32"] == 1.0 and all(r["frames_per_s"] > 0 for r in result["encoder_speed"])
    assert result["encoder_speed"][2]["parity"]["images"] == result["config"]["encoder_batch"]
    assert [r["path"] for r in result["cmwae_train"]] == ["fp32", "fp32 channels_last", "bf16 channels_last"]
    assert all(r["steps_per_s"] > 0 for r in result["cmwae_train"])
    # The field with the stereo matching and with its stand-in: the stereo stage ran in both.
    assert [r["field_depth"] for r in result["field"]] == ["stereo", "approx"] and result["field"][0]["ratio_to_stereo"] == 1.0
    for row in result["field"]:
        assert set(row["share"]) == set(FIELD_STAGES) and row["share"]["stereo"] > 0 and row["share"]["gray"] > 0


def test_bench_train_table_names_every_stage():
    proc = subprocess.run([sys.executable, "-m", "cmnav", "bench", "train", "--quick"], capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, proc.stderr[-3000:]
    header = next(line for line in proc.stdout.splitlines() if line.startswith("| envs | encoder"))
    assert all(f"{stage} %" in header for stage in STAGES)
    assert "Privileged teacher" in proc.stdout and "CMWAE training" in proc.stdout and "| 2 | approx |" in proc.stdout and "| bf16 channels_last |" in proc.stdout
