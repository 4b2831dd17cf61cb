"""`cmnav bench runtime`: the real command as a subprocess in its quick mode on a small exported
model (with its variants and checkpoints), checking the JSON structure and the table; the FLOP
counter on a graph whose FLOPs are known.  Never timings."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from onnx import TensorProto, helper, numpy_helper

from bench.runtime import count_flops, cpu_peak, format_runtime_bench
from export.policy_onnx import export_policy
from export.variants import VARIANTS, variant_path
from tests.export.test_policy_onnx import TEST_BOUND, _encoder, _policy, record_flights
from training.checkpoint import checkpoint_fingerprint

ROOT = Path(__file__).resolve().parents[2]
STATS = {"p50_ms", "p99_ms", "best_ms", "n"}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bench")
    encoder = _encoder(tmp / "encoder")
    policy = _policy(tmp / "policy", checkpoint_fingerprint(encoder))
    export_policy(encoder, policy, tmp / "model.onnx", recorded=record_flights(tmp, 2), variants=VARIANTS, random_samples=2,
                  recorded_samples=4, bound=TEST_BOUND)  # fmt: skip
    return tmp / "model.onnx", encoder, policy


def _bench(*args: str) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "cmnav", "bench", "runtime", "--quick", "--json", "--no-sitl", *args],
        capture_output=True, text=True, timeout=240, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_bench_runtime_quick_json(exported):
    model, encoder, policy = exported
    result = _bench("--model", str(model), "--encoder", str(encoder), "--policy", str(policy))
    assert result["model"] == str(model) and result["variant"] == "fp32" and result["hidden_size"] == 8
    assert result["flops"]["total"] > 0 and result["flops"]["uncounted_nodes"] == []
    assert set(result["flops"]["by_op"]) <= {"Conv", "Gemm", "MatMul"}
    assert result["cpu"]["cores"] >= 1 and result["cpu"]["flop_per_cycle_per_core"] >= 2
    gemm = {(g["library"].split()[0], g["threads"]) for g in result["gemm"]}
    cores = result["cpu"]["cores"]
    assert gemm == {("onnxruntime", 1), ("onnxruntime", cores), ("torch", cores)} and all(g["gflop_s"] > 0 for g in result["gemm"])
    assert isinstance(result["warnings"], list)
    assert [r["frame"] for r in result["preprocess"]] == ["d455 848x480", "sim 212x120"]

    cpu_rows = [r for r in result["onnx"] if r["provider"] == "CPUExecutionProvider"]
    assert {(r["variant"], r["threads"]) for r in cpu_rows} == {(v, t) for v in ("fp32", *VARIANTS) for t in (1, 2)}
    assert result["variant_files"] == {v: str(variant_path(model, v)) for v in VARIANTS}
    assert {(s["variant"], s["threads"]) for s in result["variant_speedup"] if s["provider"] == "CPUExecutionProvider"} == {
        (v, t) for v in VARIANTS for t in (1, 2)
    }
    for row in result["onnx"] + result["torch"] + result["preprocess"]:
        assert STATS <= set(row) and row["best_ms"] <= row["p50_ms"] <= row["p99_ms"]
    assert {(r["device"], r["threads"]) for r in result["torch"] if r["device"] == "cpu"} == {("cpu", 1), ("cpu", 2)}
    assert result["torch_skipped"] is None

    assert result["sitl"] == {"skipped": "--no-sitl"}
    assert result["ideal_ms"] > 0 and result["ratios"]["onnx_over_eager_2t"] > 0 and result["ratios"]["onnx_over_ideal"] > 0
    targets = {t["name"].split(" (")[0]: t for t in result["targets"]}
    assert len(targets) == 4
    for name in ("ONNX step / torch eager", "ONNX step / ideal"):
        assert targets[name]["status"] in ("PASS", "MISS") and targets[name]["measured"] > 0
    for name in ("grab->command minus ONNX step", "end to end, capture->command"):
        assert targets[name]["status"] == "SKIP" and targets[name]["why_skipped"] == "--no-sitl"

    table = format_runtime_bench(result)
    assert "| ONNX step fp32, CPU, 2 threads |" in table and "| torch eager, cpu, 1 thread |" in table
    assert "| int8 | CPU | 2 |" in table and "| target | measured | target | result |" in table


def test_torch_rows_skipped_without_checkpoints(exported):
    model, _, _ = exported
    result = _bench("--model", str(model), "--no-variants")
    assert result["torch"] == [] and "--encoder/--policy" in result["torch_skipped"]
    assert {r["variant"] for r in result["onnx"]} == {"fp32"} and result["variant_speedup"] == []
    eager = next(t for t in result["targets"] if t["name"].startswith("ONNX step / torch eager"))
    assert eager["status"] == "SKIP" and eager["measured"] is None


def test_variants_of_another_export_are_not_timed(exported, tmp_path):
    model, _, _ = exported
    encoder = _encoder(tmp_path / "encoder", seed=9)
    other = tmp_path / "other.onnx"
    export_policy(encoder, _policy(tmp_path / "policy", checkpoint_fingerprint(encoder)), other, random_samples=1)
    shutil.copy(variant_path(model, "int8"), variant_path(other, "int8"))  # a leftover of another export
    result = _bench("--model", str(other))
    assert {r["variant"] for r in result["onnx"]} == {"fp32"} and result["variant_files"] == {}
    assert "exported from another checkpoint (cmnav.encoder fingerprint" in result["variants_skipped"]["int8"]


def test_count_flops_on_a_known_graph():
    # Conv 3->8, 3x3, stride 1, pad 1 on 1x3x10x10: 2 * (8*10*10) * (3*3*3) = 43200;
    # Gemm [1, 800] x [800, 5]^T: 2 * 5 * 800 = 8000; MatMul [1, 5] x [5, 4]: 2 * 4 * 5 = 40.
    rng = np.random.default_rng(0)
    inits = [
        numpy_helper.from_array(rng.random((8, 3, 3, 3), dtype=np.float32), "w"),
        numpy_helper.from_array(rng.random((5, 800), dtype=np.float32), "g"),
        numpy_helper.from_array(rng.random((5, 4), dtype=np.float32), "m"),
    ]
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["y"], pads=[1, 1, 1, 1]),
        helper.make_node("Flatten", ["y"], ["f"]),
        helper.make_node("Gemm", ["f", "g"], ["z"], transB=1),
        helper.make_node("MatMul", ["z", "m"], ["out"]),
    ]
    graph = helper.make_graph(
        nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 10, 10])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 4])], inits,
    )  # fmt: skip
    flops = count_flops(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]))
    assert flops["by_op"] == {"Conv": 43200, "Gemm": 8000, "MatMul": 40}
    assert flops["total"] == 51240


def test_cpu_peak_states_its_assumptions():
    peak = cpu_peak(2)
    assert peak["cores"] == 2 and peak["flop_per_cycle_per_core"] in (2, 8, 16, 32, 64)
    assert peak["vector_units"] and peak["clock_source"]
    if peak["clock_ghz"]:
        assert peak["peak_gflop_s"] == pytest.approx(2 * peak["flop_per_cycle_per_core"] * peak["clock_ghz"], rel=1e-3)


@pytest.mark.flight
def test_sitl_flights_per_variant_with_the_runtime_pinned(exported):
    """The quick SITL path flies fp32 and int8 (not fp16) with the runtime on a core of its own and
    reports the overhead split by stage: structure only, never the times."""
    import os

    model, _, _ = exported
    result = _bench_sitl("--model", str(model), "--level", "0", "--seed", "1")
    sitl = result["sitl"]
    allowed = sorted(os.sched_getaffinity(0))
    assert set(sitl["flights"]) == {"fp32", "int8"}
    if len(allowed) >= 2:
        assert sitl["pinning"]["runtime_cpus"] == allowed[-1:] and sitl["pinning"]["vehicle_cpus"] == allowed[:-1]
    for variant, flight in sitl["flights"].items():
        assert "skipped" not in flight, flight
        assert flight["model"] == str(model if variant == "fp32" else variant_path(model, variant)) and flight["steps"] > 0
        if len(allowed) >= 2:  # the runtime pinned itself (runtime.cpu_affinity) and said so in its summary
            assert flight["pinning"]["runtime_cpus"] == allowed[-1:] and flight["pinning"]["runtime_intra_op_threads"] == 1
        assert set(flight["stages"]) == {"pickup", "executor_in", "preprocess", "observation", "executor_out", "checks", "send"}
        assert set(flight["frame_age"]) == {"delivery", "frame_age_at_step"}
        for stats in (flight["end_to_end"], flight["grab_to_command"], flight["overhead"], *flight["stages"].values(),
                      *flight["frame_age"].values()):  # fmt: skip
            assert STATS <= set(stats)
        # the SITL camera link stamps receipt: the frame reaches the runtime after its capture, and the
        # runtime's share (grab -> command) is the end to end less the delivery
        assert flight["frame_age"]["delivery"]["best_ms"] > 0.0
        assert flight["grab_to_command"]["p50_ms"] < flight["end_to_end"]["p50_ms"]
    names = [t["name"] for t in result["targets"] if t["name"].startswith(("grab->command", "end to end"))]
    assert len(names) == 4 and all(any(f", {v};" in n for n in names) for v in ("fp32", "int8"))
    table = format_runtime_bench(result)
    assert "| SITL int8 stage executor_out |" in table and "SITL flight fp32:" in table


def _bench_sitl(*args: str) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "cmnav", "bench", "runtime", "--quick", "--json", *args],
        capture_output=True, text=True, timeout=400, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)
