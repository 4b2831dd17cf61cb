"""`cmnav bench train --quick` runs the whole training step (render, preprocess, encoder, physics,
policy, PPO update) and reports env-steps/s with each stage's share; no timing is asserted."""

import json
import subprocess
import sys

import pytest

from bench.train import STAGES

pytestmark = pytest.mark.timeout(300)


def test_bench_train_quick_reports_rates_and_stage_shares():
    proc = subprocess.run([sys.executable, "-m", "cmnav", "bench", "train", "--quick", "--json"],
                          capture_output=True, text=True, timeout=280)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["device"] == "cpu" and [row["envs"] for row in result["rows"]] == [2]
    for row in result["rows"]:
        assert row["env_steps"] == 2 * result["config"]["rollout_steps"]
        assert 0 < row["env_steps_per_s"] < row["collect_env_steps_per_s"]
        assert set(row["share"]) == set(STAGES)
        assert sum(row["share"].values()) == pytest.approx(1.0, abs=1e-6)
        assert all(row["share"][s] > 0 for s in ("render", "encode", "physics", "ppo_update"))


def test_bench_train_table_names_every_stage():
    proc = subprocess.run([sys.executable, "-m", "cmnav", "bench", "train", "--quick"], capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, proc.stderr[-3000:]
    header = next(line for line in proc.stdout.splitlines() if line.startswith("| envs"))
    assert all(f"{stage} %" in header for stage in STAGES)
