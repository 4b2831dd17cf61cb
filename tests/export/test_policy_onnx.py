"""`cmnav export --encoder --policy`: one ONNX graph equal to the torch networks (random and
recorded inputs), carrying the contract and provenance, accepted by the runtime's loader; a
contract change or an encoder the policy was not trained on is refused; the fp16/int8 variants
load and state their parity cost on held-out recorded flights, and int8 is refused (with the
numbers, nothing written under its name) when it misses its bound or has too few held-out steps.  Small networks (tiny CMWAE, a 32-16 MLP, GRU 8) on the CPU."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from export.policy_onnx import (
    KEY_ENCODER,
    KEY_GIT_COMMIT,
    KEY_HIDDEN_SIZE,
    KEY_PARITY,
    KEY_POLICY,
    KEY_PROVENANCE,
    KEY_VARIANT,
    PARITY_TOLERANCE,
    ParityError,
    VariantBound,
    VariantRefusedError,
    bound_problem,
    export_policy,
    load_networks,
    random_inputs,
    select_nodes,
    torch_outputs,
    variant_path,
)
from runtime.contract import ContractMismatchError, check_contract_metadata
from runtime.contract import constants as c
from runtime.contract.metadata import METADATA_KEY_VALUES
from runtime.model import PolicyModel
from training.checkpoint import checkpoint_fingerprint, save_weights
from training.cmwae.model import Cmwae, make_config
from training.policy.network import CHECKPOINT_KIND, ActorCritic, EncoderMismatchError, PolicyConfig

ROOT = Path(__file__).resolve().parents[2]
GRU_SIZE = 8
# Parity cost the variants may have on these small random networks (action in [-1, 1]-ish units);
# they are measured and stated, not promised to be small: this only catches a broken conversion.
VARIANT_ACTION_BOUND = {"fp16": 1e-2, "int8": 0.2}
# The export's bound for these networks and the few steps the test flights have.
TEST_BOUND = VariantBound(max_action_error=VARIANT_ACTION_BOUND["int8"], min_held_out_steps=10)


def _encoder(out: Path, modalities=("gray", "depth"), seed: int = 0) -> Path:
    torch.manual_seed(seed)
    cmwae = Cmwae(make_config("tiny", modalities))
    save_weights(out, cmwae, "cmwae", asdict(cmwae.config), step=10, meta={"dataset": "tests/generated", "train": {"seed": seed}})
    return out


TABLE2_CELLS = [{"condition": "clean", "level": 5, "episodes": 2, "success_pct": 50.0, "timeout_pct": 0.0, "crash_pct": 50.0}]


def _policy(out: Path, encoder_fingerprint: str | None) -> Path:
    torch.manual_seed(1)
    config = PolicyConfig(mlp_sizes=(32, 16), gru_size=GRU_SIZE)
    policy = ActorCritic(config)
    policy.obs_norm.update(torch.randn(512, c.OBSERVATION_DIM) * 3.0 + 1.0)  # a normaliser that does something
    with torch.no_grad():  # actions of order 1, so parity in action space means something
        policy.action_head.weight.normal_(0.0, 0.5)
    meta = {"seed": 3, "env_steps": 1234, "curriculum_level": 4}
    if encoder_fingerprint is not None:
        meta["encoder_fingerprint"] = encoder_fingerprint
    save_weights(out, policy, CHECKPOINT_KIND, config.to_json(), step=7, meta=meta)
    (out / "eval").mkdir()  # what `cmnav eval policy` leaves next to the checkpoint
    (out / "eval" / "table2.json").write_text(json.dumps({"cells": TABLE2_CELLS}))
    return out


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ckpt")
    encoder = _encoder(tmp / "encoder")
    return encoder, _policy(tmp / "policy", checkpoint_fingerprint(encoder))


def record_flights(tmp: Path, count: int) -> list[Path]:
    """``count`` flight logs recorded by the real flight loop (two episodes each, textured frames)."""
    from tests.runtime.onnx_models import recurrent_step_model, save
    from tests.runtime.test_replay import _fly_two_episodes

    model = save(recurrent_step_model(), tmp / "recurrent.onnx")
    logs = [tmp / f"flight{i}.mcap" for i in range(count)]
    for log_path in logs:
        asyncio.run(_fly_two_episodes(model, log_path))
    return logs


@pytest.fixture(scope="module")
def recorded_logs(tmp_path_factory):
    """Two flight logs: one calibrates int8, the other is held out."""
    return record_flights(tmp_path_factory.mktemp("log"), 2)


@pytest.fixture(scope="module")
def exported(checkpoints, recorded_logs, tmp_path_factory):
    encoder, policy = checkpoints
    out = tmp_path_factory.mktemp("export") / "model.onnx"
    report = export_policy(encoder, policy, out, recorded=recorded_logs, variants=("fp16", "int8"), recorded_samples=12, bound=TEST_BOUND)
    return out, report


def test_parity_on_random_and_recorded_inputs(exported):
    _, report = exported
    assert len(report.parity) == 2
    assert any(source.startswith("random") for source in report.parity)
    assert any(source.startswith("recorded (12 steps") for source in report.parity)
    for errors in report.parity.values():
        assert set(errors) == {c.ONNX_OUTPUT_ACTION, c.ONNX_OUTPUT_HIDDEN, c.ONNX_OUTPUT_LATENT}
        assert max(errors.values()) <= PARITY_TOLERANCE
    assert "parity, ONNX Runtime CPU vs torch" in report.format()


def test_runtime_loader_accepts_it_and_steps_like_torch(exported, checkpoints):
    path, _ = exported
    model = PolicyModel(path)
    assert model.hidden_size == GRU_SIZE
    nets = load_networks(*checkpoints)
    inputs = random_inputs(3, GRU_SIZE, seed=5)
    reference = torch_outputs(nets.step, inputs)
    for i in range(3):
        out = model.step(inputs.gray[i, 0], inputs.depth[i, 0], inputs.state[i], inputs.hidden[i])
        assert np.abs(out.action).max() > 0.05  # not a trivial near-zero action
        np.testing.assert_allclose(out.action, reference[c.ONNX_OUTPUT_ACTION][i], atol=PARITY_TOLERANCE)
        np.testing.assert_allclose(out.hidden_next, reference[c.ONNX_OUTPUT_HIDDEN][i], atol=PARITY_TOLERANCE)
        np.testing.assert_allclose(out.latent, reference[c.ONNX_OUTPUT_LATENT][i], atol=PARITY_TOLERANCE)


def test_metadata_carries_contract_and_provenance(exported, checkpoints):
    path, report = exported
    model = onnx.load(str(path))
    meta = {p.key: p.value for p in model.metadata_props}
    check_contract_metadata(meta)
    assert model.opset_import[0].version >= 17
    assert [i.name for i in model.graph.input] == [c.ONNX_INPUT_GRAY, c.ONNX_INPUT_DEPTH, c.ONNX_INPUT_STATE, c.ONNX_INPUT_HIDDEN]
    assert meta[KEY_VARIANT] == "fp32" and meta[KEY_HIDDEN_SIZE] == str(GRU_SIZE)
    assert meta[KEY_GIT_COMMIT] == report.git_commit and len(meta[KEY_GIT_COMMIT]) in (40, len("unknown"))
    encoder, policy = checkpoints
    assert json.loads(meta[KEY_ENCODER])["fingerprint"] == checkpoint_fingerprint(encoder) == report.encoder_fingerprint
    assert json.loads(meta[KEY_POLICY])["fingerprint"] == checkpoint_fingerprint(policy) == report.policy_fingerprint
    provenance = json.loads(meta[KEY_PROVENANCE])
    assert provenance["policy_seed"] == 3 and provenance["policy_env_steps"] == 1234
    assert provenance["policy_eval"] == TABLE2_CELLS and provenance["encoder_data"] == "tests/generated"
    assert provenance["policy_data"].endswith("curriculum level reached: 4")
    parity = json.loads(meta[KEY_PARITY])
    assert parity["tolerance"] == PARITY_TOLERANCE and parity["max_abs_error"] == report.parity
    for key in ("cmnav.normalisation", "cmnav.action_scaling"):
        assert json.loads(meta[key])
    assert json.loads(meta["cmnav.action_scaling"])["max_speed_m_s"] == c.MAX_SPEED_M_S


def test_altered_contract_is_rejected_naming_the_difference(exported, tmp_path):
    path, _ = exported
    model = onnx.load(str(path))
    for prop in model.metadata_props:
        if prop.key == METADATA_KEY_VALUES:
            values = json.loads(prop.value)
            values["depth_max_m"] = 20.0
            prop.value = json.dumps(values)
    altered = tmp_path / "altered.onnx"
    onnx.save(model, str(altered))
    with pytest.raises(ContractMismatchError, match=r"depth_max_m: .* has 20\.0, runtime has 10\.0"):
        PolicyModel(altered)


def test_variants_load_with_their_parity_stated(exported, recorded_logs):
    path, report = exported
    assert set(report.variants) == {"fp16", "int8"} and report.refused == {}
    for variant, info in report.variants.items():
        assert info["path"] == str(variant_path(path, variant)) and Path(info["path"]).is_file()
        assert not Path(info["path"] + ".candidate").exists()
        model = PolicyModel(info["path"])  # the runtime's loader: fp32 inputs and outputs kept
        assert model.hidden_size == GRU_SIZE
        meta = {p.key: p.value for p in onnx.load(info["path"]).metadata_props}
        assert meta[KEY_VARIANT] == variant
        stated = json.loads(meta[KEY_PARITY])
        assert stated["max_abs_error"] == info["max_abs_error_vs_fp32"] and stated["reference"] == "fp32 graph"
        # Judged on the held-out flight (the second log), which calibration never saw, GRU state carried.
        assert info["inputs"].startswith("held-out recorded flights, GRU state carried") and info["steps"] > 10
        assert stated["fp32_max_abs"] == info["fp32_max_abs"] and stated["steps"] == info["steps"]
        action_error = info["max_abs_error_vs_fp32"][c.ONNX_OUTPUT_ACTION]
        assert 0.0 < action_error <= VARIANT_ACTION_BOUND[variant]
        assert 0.0 <= info["mean_abs_error_vs_fp32"][c.ONNX_OUTPUT_ACTION] <= action_error
    int8 = report.variants["int8"]
    assert int8["calibration"].endswith(f"of 1 flights ({recorded_logs[0].parent.name}/{recorded_logs[0].name})") and report.variants["fp16"]["calibration"] is None
    assert int8["bound"] == {"max_action_error": TEST_BOUND.max_action_error, "min_held_out_steps": TEST_BOUND.min_held_out_steps}
    assert "bound: action <= 0.2, met" in report.format()
    quantised = onnx.load(int8["path"])
    # Only the gray stack's convolutions are quantised: each reads a dequantised weight; the depth
    # stack's convolutions and every Gemm (encoder FC, MLP, GRU, head) stay fp32.
    dequantised = {n.output[0] for n in quantised.graph.node if n.op_type == "DequantizeLinear"}
    convs = [n for n in quantised.graph.node if n.op_type == "Conv"]
    gray = [n for n in convs if n.name.startswith("/encoder/gray/")]
    others = [n for n in quantised.graph.node if n.op_type in ("Conv", "Gemm", "MatMul") and n not in gray]
    assert gray and all(n.input[1] in dequantised for n in gray)
    assert len(others) > len(gray) and not any(i in dequantised for n in others for i in n.input)
    stated = json.loads(meta_of(int8["path"])[KEY_PARITY])
    assert stated["quantised_nodes"] == int8["quantised_nodes"] == [n.name for n in gray]  # every one within budget here
    assert stated["selection"]["budget"] == TEST_BOUND.max_action_error / 2
    assert 0.0 < stated["selection"]["calibration_max_action_error"] <= stated["selection"]["budget"]
    fp16 = onnx.load(report.variants["fp16"]["path"])
    assert any(t.data_type == onnx.TensorProto.FLOAT16 for t in fp16.graph.initializer)


def meta_of(path: str | Path) -> dict[str, str]:
    return {p.key: p.value for p in onnx.load(str(path)).metadata_props}


def test_int8_keeps_only_the_layers_within_its_budget():
    # quantising a layer costs it its own error; together the errors add (the greedy's view)
    alone = {"/encoder/gray/0": 1e-3, "/encoder/gray/3": 5e-2, "/encoder/gray/6": 2e-3}
    calls = []

    def action_error(nodes):
        calls.append(list(nodes))
        return sum(alone[n] for n in nodes)

    # within the budget together: one calibration, every layer
    everything = select_nodes(list(alone), action_error, budget=0.1)
    assert everything.nodes == list(alone) and everything.together == pytest.approx(0.053) and everything.alone == {}
    assert calls == [list(alone)]
    calls.clear()
    selection = select_nodes(list(alone), action_error, budget=4e-3)
    assert selection.nodes == ["/encoder/gray/0", "/encoder/gray/6"] and selection.together == pytest.approx(3e-3)
    assert selection.alone == alone and selection.budget == 4e-3
    assert calls[:4] == [list(alone), *([n] for n in alone)] and ["/encoder/gray/0", "/encoder/gray/6"] in calls
    assert "/encoder/gray/3 5.00e-02" in selection.describe()
    # within a tighter budget the second-best no longer fits beside the best
    assert select_nodes(list(alone), action_error, budget=2.5e-3).nodes == ["/encoder/gray/0"]
    assert select_nodes(list(alone), action_error, budget=1e-4).nodes == []


def test_int8_over_its_bound_is_refused_with_the_numbers(checkpoints, recorded_logs, tmp_path):
    out = tmp_path / "m.onnx"
    variant_path(out, "int8").write_bytes(b"an earlier export's int8")  # must not survive the refusal
    with pytest.raises(VariantRefusedError) as err:
        export_policy(*checkpoints, out, recorded=recorded_logs, variants=("fp16", "int8"), recorded_samples=4,
                      bound=VariantBound(max_action_error=1e-6, min_held_out_steps=10))  # fmt: skip
    message, report = str(err.value), err.value.report
    # no gray convolution stays within half the bound on the calibration steps, even alone
    assert "int8: no Conv node keeps the max action error within 5e-07 on the calibration steps even alone (/encoder/gray/" in message
    assert "not written, fly the fp32 model" in report.refused["int8"]["reason"]
    assert not variant_path(out, "int8").exists() and not list(tmp_path.glob("*.candidate"))
    assert out.is_file() and set(report.variants) == {"fp16"}  # fp32 and fp16 are written
    assert "variant int8: REFUSED, not written" in report.format()

    with pytest.raises(VariantRefusedError, match=r"int8 judged on \d+ held-out recorded steps, fewer than the 100000"):
        export_policy(*checkpoints, out, recorded=recorded_logs, variants=("int8",), recorded_samples=4,
                      bound=VariantBound(min_held_out_steps=100_000))  # fmt: skip
    with pytest.raises(VariantRefusedError, match="int8 needs recorded flights"):
        export_policy(*checkpoints, out, variants=("int8",), random_samples=2)
    assert not variant_path(out, "int8").exists()


def test_a_selected_int8_over_its_bound_on_the_held_out_flights_is_refused():
    errors = {"steps": 400, "max_abs_error": {c.ONNX_OUTPUT_ACTION: 0.03, c.ONNX_OUTPUT_HIDDEN: 0.01, c.ONNX_OUTPUT_LATENT: 0.2},
              "mean_abs_error": {c.ONNX_OUTPUT_ACTION: 0.004}}  # fmt: skip
    problem = bound_problem("int8", errors, VariantBound())
    assert problem == ("int8 max action error 0.0300 > 0.02 over 400 held-out recorded steps (GRU state carried; latent "
                       "error 0.2000, mean action error 0.0040): not written, fly the fp32 model")  # fmt: skip
    assert bound_problem("int8", {**errors, "max_abs_error": {**errors["max_abs_error"], c.ONNX_OUTPUT_ACTION: 0.01}}, VariantBound()) is None
    assert bound_problem("fp16", errors, VariantBound()) is None  # fp16 has no bound


def test_encoder_mismatch_is_refused(checkpoints, tmp_path):
    encoder, _ = checkpoints
    other = _encoder(tmp_path / "other-encoder", seed=9)
    policy = _policy(tmp_path / "policy", checkpoint_fingerprint(other))
    with pytest.raises(EncoderMismatchError) as err:
        export_policy(encoder, policy, tmp_path / "m.onnx")
    message = str(err.value)
    assert checkpoint_fingerprint(other) in message and checkpoint_fingerprint(encoder) in message
    assert "pass --encoder the checkpoint the policy was trained with" in message
    assert not (tmp_path / "m.onnx").exists()


def test_a_parity_failure_leaves_no_model_to_fly(checkpoints, tmp_path):
    out = tmp_path / "m.onnx"
    with pytest.raises(ParityError, match="kept for inspection as .*m.onnx.parity-failed, do not fly it"):
        export_policy(*checkpoints, out, random_samples=1, tolerance=-1.0)  # no error is below -1
    assert not out.exists() and (tmp_path / "m.onnx.parity-failed").is_file()


def test_depth_only_encoder_keeps_the_gray_input(tmp_path):
    encoder = _encoder(tmp_path / "depth-encoder", modalities=("depth",))
    policy = _policy(tmp_path / "policy", checkpoint_fingerprint(encoder))
    report = export_policy(encoder, policy, tmp_path / "depth.onnx", random_samples=2)
    assert max(max(e.values()) for e in report.parity.values()) <= PARITY_TOLERANCE
    model = PolicyModel(tmp_path / "depth.onnx")
    gray = np.random.default_rng(0).random((224, 224), dtype=np.float32)
    state, hidden = np.zeros(c.STATE_DIM, np.float32), np.zeros(GRU_SIZE, np.float32)
    depth = np.full((224, 224), 0.5, np.float32)
    a = model.step(gray, depth, state, hidden).action
    b = model.step(np.zeros_like(gray), depth, state, hidden).action
    np.testing.assert_array_equal(a, b)  # gray is in the signature but read by nothing


def test_cli(checkpoints, tmp_path):
    encoder, policy = checkpoints
    out = tmp_path / "cli.onnx"
    proc = subprocess.run(
        [sys.executable, "-m", "cmnav", "export", "--encoder", str(encoder), "--policy", str(policy), "-o", str(out), "--json"],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"wrote {out}")
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["path"] == str(out) and report["variants"] == {}
    PolicyModel(out)

    mismatched = _policy(tmp_path / "policy-other", "0123456789abcdef")
    proc = subprocess.run(
        [sys.executable, "-m", "cmnav", "export", "--encoder", str(encoder), "--policy", str(mismatched), "-o", str(tmp_path / "x.onnx")],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 2 and "0123456789abcdef" in proc.stderr and "cmnav export:" in proc.stderr

    proc = subprocess.run([sys.executable, "-m", "cmnav", "export", "-o", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2 and "--encoder, --policy required" in proc.stderr


def test_carried_outputs_replay_the_recorded_flight(recorded_logs, tmp_path):
    """A model carrying its own GRU state through a recorded flight (resets where the flight reset
    it) reproduces the actions that flew; without the resets it does not: how the variants are judged."""
    from export.policy_onnx import carried_outputs, cpu_session, flight_inputs
    from runtime.log.topics import STEP_TOPICS
    from runtime.log.reader import FlightLogReader
    from tests.runtime.onnx_models import recurrent_step_model, save

    session = cpu_session(save(recurrent_step_model(), tmp_path / "recurrent.onnx"))
    flight = flight_inputs(recorded_logs[0], hidden_size=8)
    flown = np.stack([s.action_raw for s in FlightLogReader(recorded_logs[0]).records(STEP_TOPICS)])
    assert len(flight) == len(flown) > 10 and flight.resets.sum() == 2  # two episodes
    np.testing.assert_allclose(carried_outputs(session, flight)[c.ONNX_OUTPUT_ACTION], flown, atol=1e-5)
    no_reset = flight.subset(slice(None), "no resets")
    no_reset.resets[1:] = False
    assert np.abs(carried_outputs(session, no_reset)[c.ONNX_OUTPUT_ACTION] - flown).max() > 1e-3


def test_bench_train_measures_bf16_parity_on_recorded_frames(checkpoints, recorded_logs):
    from bench.train import TrainBenchConfig, recorded_parity
    from export.policy_onnx import flight_inputs
    from training.cmwae.train import load_cmwae

    encoder_dir, policy_dir = checkpoints
    encoder = load_cmwae(encoder_dir)[0].encoder
    config = TrainBenchConfig(recorded=tuple(str(p) for p in recorded_logs), policy_dir=str(policy_dir))
    parity = recorded_parity(encoder, config, torch.device("cpu"))
    assert parity["flights"] == 2 and parity["steps"] == sum(len(flight_inputs(p, 1)) for p in recorded_logs)
    assert 0.0 < parity["latent_rms_rel"] <= parity["latent_max_rel"] and parity["action_max_abs"] is not None
