"""Trained checkpoints -> the runtime's ONNX file (DESIGN §6, issue 6).

``cmnav export --encoder CKPT --policy CKPT -o model.onnx`` builds one graph for the runtime's
control step from the CMWAE encoder (not its decoder) and the policy::

    latent = encoder(gray, depth)                        # [1, 64]
    obs = concat(state, latent)                          # [1, 79], the contract's layout
    action, _, hidden_next = policy.step(obs, hidden)    # action = the Gaussian's mean [1, 3]

with the runtime's step signature (``runtime.contract.constants``: inputs gray, depth, state,
hidden; outputs action, hidden_next, latent; batch 1), opset 17, exported by torch's TorchScript
exporter (``dynamo=False``: the dynamo exporter needs onnxscript, which neither this machine nor
the GPU machine has).  The policy's observation normaliser is inside the graph.

The file carries the contract (``runtime.contract.contract_metadata``) and, under ``cmnav.*``
keys: normalisation, action scaling, latent and GRU sizes, and provenance (git commit, both
checkpoints' fingerprints and cards' meta: data, seed, steps, eval tables), plus the parity
measured at export.  A policy trained on another encoder (its card's ``meta.encoder_fingerprint``
differs from the given encoder's) is refused.

Parity: ONNX Runtime (CPU) against the torch networks on random inputs and, with ``recorded``, on
the camera frames and states of a flight log, the GRU state carried from step to step as in
flight; max abs error of action, hidden_next and latent, bounded by ``PARITY_TOLERANCE`` (fp32).
Then the runtime's own loader (:class:`runtime.model.PolicyModel`) must accept the file.

Variants (``variants``): ``fp16`` (weights and activations in float16, inputs and outputs kept
float32: for GPU execution providers) and ``int8`` (static QDQ quantisation of the gray AlexNet
stack's convolutions, per-channel int8 weights, uint8 activations calibrated on recorded frames;
the depth stack, which the latent is most sensitive to, and the MLP/GRU head stay fp32: see
``INT8_NODE_PREFIXES`` for the per-layer errors measured); of the gray convolutions only those
that keep the action within half the bound on the calibration steps are quantised
(:func:`select_nodes`).  With several ``recorded`` flight logs the first half of them calibrate
int8 and the rest are held out; every variant is measured there against the fp32 graph, each
model carrying its own GRU state through each flight as it would fly.  int8 is written only if
its max action error over at least ``VARIANT_MIN_HELD_OUT_STEPS`` (300) held-out steps is at most
``VARIANT_MAX_ACTION_ERROR`` (0.02); its latent error is stated with it.  Otherwise it is refused
with the numbers (:class:`VariantRefusedError`, kept as ``model.int8.onnx.refused`` for
inspection).  Each written variant sits next to the fp32 file (``model.fp16.onnx``,
``model.int8.onnx``) with its parity cost in its metadata; ``cmnav bench runtime`` times every
variant it finds next to the model, and ``cmnav fly`` selects one with ``policy.variant``.
"""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import Tensor, nn

from runtime.contract import constants as c
from runtime.contract import contract_metadata
from training.checkpoint import CheckpointError, checkpoint_fingerprint
from training.cmwae.train import load_cmwae
from training.policy.network import ActorCritic, check_trained_on, load_policy

from .variants import VARIANTS, variant_path

log = logging.getLogger(__name__)

OPSET = 17
PARITY_TOLERANCE = 1e-4  # max abs error of any output, fp32 ONNX Runtime vs torch
RANDOM_SAMPLES = 8
RECORDED_SAMPLES = 64
INPUT_NAMES = (c.ONNX_INPUT_GRAY, c.ONNX_INPUT_DEPTH, c.ONNX_INPUT_STATE, c.ONNX_INPUT_HIDDEN)
OUTPUT_NAMES = (c.ONNX_OUTPUT_ACTION, c.ONNX_OUTPUT_HIDDEN, c.ONNX_OUTPUT_LATENT)
# Metadata keys besides the contract's (all values are strings; JSON where structured).
KEY_MODEL = "cmnav.model"
KEY_VARIANT = "cmnav.variant"
KEY_NORMALISATION = "cmnav.normalisation"
KEY_ACTION_SCALING = "cmnav.action_scaling"
KEY_LATENT_DIM = "cmnav.latent_dim"
KEY_HIDDEN_SIZE = "cmnav.gru_hidden_size"
KEY_GIT_COMMIT = "cmnav.git_commit"
KEY_GIT_DIRTY = "cmnav.git_dirty"
KEY_ENCODER = "cmnav.encoder"
KEY_POLICY = "cmnav.policy"
KEY_PROVENANCE = "cmnav.provenance"
KEY_PARITY = "cmnav.parity"
_REPO_ROOT = Path(__file__).resolve().parent.parent


class ExportError(ValueError):
    """The checkpoints cannot be exported, or the exported graph failed a check; the message says why."""


class ParityError(ExportError):
    """ONNX Runtime's outputs differ from torch's by more than the tolerance."""


class RuntimeStep(nn.Module):
    """The runtime's control step as one module: (gray, depth [B, 1, 224, 224], state [B, 15],
    hidden [B, H]) -> (action mean [B, 3], hidden_next [B, H], latent [B, 64])."""

    def __init__(self, encoder: nn.Module, policy: ActorCritic) -> None:
        super().__init__()
        self.encoder = encoder
        self.policy = policy

    def forward(self, gray: Tensor, depth: Tensor, state: Tensor, hidden: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        latent = self.encoder(gray, depth)
        action, _value, hidden_next = self.policy.step(torch.cat([state, latent], dim=1), hidden)
        return action, hidden_next, latent


@dataclass
class Networks:
    """The two checkpoints as one step module (eval mode, fp32, CPU) with what the metadata needs."""

    step: RuntimeStep
    encoder_dir: Path
    policy_dir: Path
    encoder_card: dict
    policy_card: dict
    encoder_fingerprint: str
    policy_fingerprint: str

    @property
    def hidden_size(self) -> int:
        return self.step.policy.hidden_size


def load_networks(encoder_dir: str | Path, policy_dir: str | Path) -> Networks:
    """Load the CMWAE encoder and the policy; raise :class:`~training.policy.network.EncoderMismatchError`
    when the policy's card names another encoder (``meta.encoder_fingerprint``), :class:`ExportError`
    when a checkpoint is missing or of the wrong kind."""
    encoder_dir, policy_dir = Path(encoder_dir), Path(policy_dir)
    try:
        policy_fp = checkpoint_fingerprint(policy_dir)
        policy, policy_card = load_policy(policy_dir)
        if policy.config.obs_dim != c.OBSERVATION_DIM:
            raise ExportError(f"{policy_dir} observes {policy.config.obs_dim} values, not the contract's {c.OBSERVATION_DIM}: "
                              f"it is a privileged teacher ({policy_card.get('meta', {}).get('role')}), which never flies; "
                              f"export the student distilled from it (cmnav train policy --teacher {policy_dir} ...)")  # fmt: skip
        encoder_fp = check_trained_on(policy_card, policy_dir, encoder_dir)
        cmwae, encoder_card = load_cmwae(encoder_dir)
    except CheckpointError as err:
        raise ExportError(str(err)) from err
    step = RuntimeStep(cmwae.encoder, policy).float().eval()
    return Networks(step, encoder_dir, policy_dir, encoder_card, policy_card, encoder_fp, policy_fp)


def git_commit() -> tuple[str, bool | None]:
    """(HEAD commit of this repository, whether the working tree has changes); ("unknown", None)
    outside a git checkout."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=_REPO_ROOT, capture_output=True, text=True, check=True, timeout=10)
        status = subprocess.run(["git", "status", "--porcelain"], cwd=_REPO_ROOT, capture_output=True, text=True, check=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return "unknown", None
    return head.stdout.strip(), bool(status.stdout.strip())


def export_metadata(nets: Networks, variant: str = "fp32") -> dict[str, str]:
    """Every ``metadata_props`` entry of an exported policy (strings; JSON where structured)."""
    commit, dirty = git_commit()
    policy_meta = nets.policy_card.get("meta", {})
    encoder_meta = nets.encoder_card.get("meta", {})
    metadata = contract_metadata()
    metadata.update({
        KEY_MODEL: "policy",
        KEY_VARIANT: variant,
        KEY_NORMALISATION: json.dumps({
            "gray": "uint8 (BGR -> BT.601 luma) resized bilinear to 224x224, / 255",
            "gray_range": [0.0, 1.0],
            "depth": "metres, resized nearest to 224x224, / depth_max_m clipped to [0, 1], invalid (0, NaN) = depth_invalid_value",
            "depth_max_m": c.DEPTH_MAX_M,
            "depth_invalid_value": c.DEPTH_INVALID_VALUE,
            "image_size_px": c.IMAGE_SIZE_PX,
            "observation": "state (15) then latent (64); the policy's running normaliser is inside the graph",
        }, sort_keys=True),
        KEY_ACTION_SCALING: json.dumps({
            "clip": [-1.0, 1.0],
            "speed_m_s": "(a1 + 1) * max_speed_m_s / 2",
            "inclination_rad": "a2 * max_inclination_rad",
            "yaw_rate_rad_s": "a3 * max_yaw_rate_rad_s",
            "max_speed_m_s": c.MAX_SPEED_M_S,
            "max_inclination_rad": c.MAX_INCLINATION_RAD,
            "max_yaw_rate_rad_s": c.MAX_YAW_RATE_RAD_S,
        }, sort_keys=True),
        KEY_LATENT_DIM: str(c.LATENT_DIM),
        KEY_HIDDEN_SIZE: str(nets.hidden_size),
        KEY_GIT_COMMIT: commit,
        KEY_GIT_DIRTY: json.dumps(dirty),
        KEY_ENCODER: json.dumps(_card_summary(nets.encoder_card, nets.encoder_fingerprint, nets.encoder_dir), sort_keys=True),
        KEY_POLICY: json.dumps(_card_summary(nets.policy_card, nets.policy_fingerprint, nets.policy_dir), sort_keys=True),
        KEY_PROVENANCE: json.dumps({
            "policy_data": "simulated rooms (sim.world), curriculum level reached: "
                           f"{policy_meta.get('curriculum_level')}",
            "policy_seed": policy_meta.get("seed"),
            "policy_env_steps": policy_meta.get("env_steps"),
            "policy_eval": _eval_table(nets.policy_dir / "eval" / "table2.json", "cells"),
            "encoder_data": encoder_meta.get("dataset"),
            "encoder_seed": encoder_meta.get("train", {}).get("seed"),
            "encoder_steps": nets.encoder_card.get("step"),
            "encoder_eval": _eval_table(nets.encoder_dir / "eval" / "table1.json", "rows")
                            or {k: v for k, v in encoder_meta.items() if k.startswith("val/")} or None,
        }, sort_keys=True),
    })  # fmt: skip
    return metadata


def _eval_table(path: Path, key: str) -> list | None:
    """The rows of a Table I/II file written by `cmnav eval` next to a checkpoint, if any."""
    try:
        return json.loads(path.read_text())[key]
    except (OSError, ValueError, KeyError):
        return None


def _card_summary(card: dict, fingerprint: str, path: Path) -> dict:
    return {"path": str(path), "fingerprint": fingerprint, "kind": card.get("kind"), "step": card.get("step"),
            "config": card.get("config"), "meta": card.get("meta", {})}  # fmt: skip


def export_step_onnx(step: RuntimeStep, path: str | Path, hidden_size: int) -> onnx.ModelProto:
    """Trace ``step`` to ONNX (opset 17, batch 1, fp32) and write it to ``path``; returns the model.

    The TorchScript exporter drops graph inputs the computation does not read (gray, for a
    depth-only encoder); they are put back, so every model has the runtime's four inputs."""
    args = (
        torch.zeros(1, 1, c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX),
        torch.zeros(1, 1, c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX),
        torch.zeros(1, c.STATE_DIM),
        torch.zeros(1, hidden_size),
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        # The TorchScript exporter is deprecated in favour of dynamo, which needs onnxscript.
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            step, args, str(path), input_names=list(INPUT_NAMES), output_names=list(OUTPUT_NAMES),
            opset_version=OPSET, do_constant_folding=True, dynamo=False,
        )  # fmt: skip
    model = onnx.load(str(path))
    _restore_inputs(model, hidden_size)
    model.producer_name = "cmnav"
    onnx.checker.check_model(model, full_check=True)
    onnx.save(model, str(path))
    return model


def _restore_inputs(model: onnx.ModelProto, hidden_size: int) -> None:
    shapes = {
        c.ONNX_INPUT_GRAY: [1, 1, c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX],
        c.ONNX_INPUT_DEPTH: [1, 1, c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX],
        c.ONNX_INPUT_STATE: [1, c.STATE_DIM],
        c.ONNX_INPUT_HIDDEN: [1, hidden_size],
    }
    present = {i.name: i for i in model.graph.input}
    if set(present) == set(INPUT_NAMES):
        return
    ordered = [present.get(name) or onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, shapes[name]) for name in INPUT_NAMES]
    log.info("inputs %s are not read by the networks; kept in the signature", sorted(set(INPUT_NAMES) - set(present)))
    del model.graph.input[:]
    model.graph.input.extend(ordered)


def set_metadata(model: onnx.ModelProto, metadata: dict[str, str]) -> None:
    """Replace ``model``'s ``metadata_props`` with ``metadata``."""
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, metadata)


# ---------------------------------------------------------------------------- parity inputs


@dataclass
class ParityInputs:
    """N step inputs, float32: gray, depth [N, 1, 224, 224], state [N, 15], hidden [N, H]; for a
    recorded flight, where its GRU state was reset."""

    gray: np.ndarray
    depth: np.ndarray
    state: np.ndarray
    hidden: np.ndarray
    source: str
    resets: np.ndarray | None = None  # [N] bool: the GRU state resets before this step (recorded flights)

    def __len__(self) -> int:
        return len(self.state)

    def feeds(self) -> Iterator[dict[str, np.ndarray]]:
        """One batch-1 ONNX Runtime feed per sample."""
        for i in range(len(self)):
            yield {
                c.ONNX_INPUT_GRAY: self.gray[i : i + 1], c.ONNX_INPUT_DEPTH: self.depth[i : i + 1],
                c.ONNX_INPUT_STATE: self.state[i : i + 1], c.ONNX_INPUT_HIDDEN: self.hidden[i : i + 1],
            }  # fmt: skip

    def subset(self, rows: slice | np.ndarray, source: str) -> ParityInputs:
        """The steps ``rows`` (a slice or an index array); a recorded subset starts with a reset
        (its first step has no earlier step in the subset to carry the GRU state from)."""
        resets = None
        if self.resets is not None:
            resets = self.resets[rows].copy()
            resets[:1] = True
        return ParityInputs(self.gray[rows], self.depth[rows], self.state[rows], self.hidden[rows], source, resets)

    def halves(self) -> tuple[ParityInputs, ParityInputs]:
        """(first half, second half) of the steps."""
        half = max(1, len(self) // 2)
        return (self.subset(slice(0, half), f"{self.source}, first {half}"),
                self.subset(slice(half, None), f"{self.source}, last {len(self) - half}"))  # fmt: skip


def random_inputs(count: int, hidden_size: int, seed: int = 0) -> ParityInputs:
    """Inputs in the contract's ranges: gray in [0, 1]; depth in [0, 1] with about 20% invalid
    (0) pixels; state: unit goal vector, distance in [0, 1], roll/pitch within 0.3 rad, velocities
    and rates within 2, previous action in [-1, 1]; hidden in (-1, 1) like a GRU's."""
    rng = np.random.default_rng(seed)
    size = (count, 1, c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX)
    gray = rng.random(size, dtype=np.float32)
    depth = rng.random(size, dtype=np.float32)
    depth[rng.random(size) < 0.2] = c.DEPTH_INVALID_VALUE
    state = np.concatenate([
        _unit_rows(rng, count), rng.random((count, 1)), rng.uniform(-0.3, 0.3, (count, 2)),
        rng.uniform(-2.0, 2.0, (count, 6)), rng.uniform(-1.0, 1.0, (count, 3)),
    ], axis=1).astype(np.float32)  # fmt: skip
    hidden = rng.uniform(-0.9, 0.9, (count, hidden_size)).astype(np.float32)
    return ParityInputs(gray, depth, state, hidden, source=f"random (seed {seed})")


def _unit_rows(rng: np.random.Generator, count: int) -> np.ndarray:
    v = rng.normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def recorded_steps(log_path: str | Path) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, int]]:
    """The policy steps of a flight log (``cmnav fly`` / ``cmnav sitl``) in order: (gray, depth
    [1, 1, 224, 224] through the contract's preprocessing, the recorded 15-value state [1, 15],
    the step's GRU epoch: it changes where the flight reset the hidden state).  Raises
    :class:`runtime.log.reader.ReplayError` for a file that is not a cmnav flight log or holds no
    step with its camera frame."""
    from runtime.contract import preprocess_depth, preprocess_gray
    from runtime.log.topics import FRAME_TOPICS, STEP_TOPICS
    from runtime.log.reader import FlightLogReader, LoggedFrame, ReplayError

    reader = FlightLogReader(log_path)
    frames: dict[int, LoggedFrame] = {}
    found = 0
    for item in reader.records(FRAME_TOPICS + STEP_TOPICS):
        if isinstance(item, LoggedFrame):
            frames[item.t_capture_ns] = item
            continue
        frame = frames.pop(item.t_capture_ns, None)
        if frame is None:
            continue
        found += 1
        yield (
            preprocess_gray(frame.gray_u8)[None, None], preprocess_depth(frame.depth_m)[None, None],
            item.observation[: c.STATE_DIM].astype(np.float32)[None], item.hidden_epoch,
        )  # fmt: skip
        frames = {t: f for t, f in frames.items() if t > item.t_capture_ns}  # skipped frames: never a step's
    if not found:
        reader.check_topics(FRAME_TOPICS + STEP_TOPICS, "export parity needs recorded camera frames and policy steps")
        raise ReplayError(f"{reader.path} holds no policy step with its camera frame")


def recorded_inputs(log_path: str | Path, step: RuntimeStep, count: int = RECORDED_SAMPLES) -> ParityInputs:
    """The first ``count`` policy steps of a flight log (:func:`recorded_steps`) with the GRU state
    carried from step to step by ``step`` (torch), reset where the flight reset it."""
    gray, depth, state, hidden = [], [], [], []
    h = torch.zeros(1, step.policy.hidden_size)
    epoch = None
    for g, d, s, step_epoch in recorded_steps(log_path):
        if step_epoch != epoch:
            h, epoch = torch.zeros_like(h), step_epoch
        gray.append(g)
        depth.append(d)
        state.append(s)
        hidden.append(h.numpy().copy())
        with torch.no_grad():
            _, h, _ = step(torch.from_numpy(g), torch.from_numpy(d), torch.from_numpy(s), h)
        if len(state) >= count:
            break
    return ParityInputs(
        np.concatenate(gray), np.concatenate(depth), np.concatenate(state), np.concatenate(hidden).astype(np.float32),
        source=f"recorded ({len(state)} steps of {Path(log_path)})",
    )  # fmt: skip


def _log_name(path: str | Path) -> str:
    """A flight log's folder and name (cmnav sitl names every log flight.mcap in its run folder)."""
    path = Path(path)
    return f"{path.parent.name}/{path.name}"


def flight_inputs(log_path: str | Path, hidden_size: int) -> ParityInputs:
    """Every policy step of one flight log (:func:`recorded_steps`), hidden state zero and
    ``resets`` marking the steps where the flight reset it: for :func:`carried_outputs`, where each
    model carries its own GRU state as it would in flight."""
    gray, depth, state, resets = [], [], [], []
    epoch = None
    for g, d, s, step_epoch in recorded_steps(log_path):
        gray.append(g)
        depth.append(d)
        state.append(s)
        resets.append(step_epoch != epoch)
        epoch = step_epoch
    return ParityInputs(
        np.concatenate(gray), np.concatenate(depth), np.concatenate(state),
        np.zeros((len(state), hidden_size), dtype=np.float32), source=f"{len(state)} steps of {_log_name(log_path)}",
        resets=np.asarray(resets),
    )  # fmt: skip


# ---------------------------------------------------------------------------- parity


def torch_outputs(step: RuntimeStep, inputs: ParityInputs) -> dict[str, np.ndarray]:
    """The torch step's outputs per sample (batch 1, as the runtime runs), stacked: name -> [N, ...]."""
    out: dict[str, list[np.ndarray]] = {name: [] for name in OUTPUT_NAMES}
    with torch.no_grad():
        for feed in inputs.feeds():
            values = step(*(torch.from_numpy(feed[name]) for name in INPUT_NAMES))
            for name, value in zip(OUTPUT_NAMES, values):
                out[name].append(value.numpy())
    return {name: np.concatenate(v) for name, v in out.items()}


def onnx_outputs(session: ort.InferenceSession, inputs: ParityInputs) -> dict[str, np.ndarray]:
    """An ONNX Runtime session's outputs per sample, stacked: name -> [N, ...]."""
    out: dict[str, list[np.ndarray]] = {name: [] for name in OUTPUT_NAMES}
    for feed in inputs.feeds():
        for name, value in zip(OUTPUT_NAMES, session.run(list(OUTPUT_NAMES), feed)):
            out[name].append(value)
    return {name: np.concatenate(v) for name, v in out.items()}


def carried_outputs(session: ort.InferenceSession, inputs: ParityInputs) -> dict[str, np.ndarray]:
    """A session's outputs over a recorded flight as it would fly it: the GRU state it returns
    feeds its next step, and is zeroed where the flight reset it (``inputs.resets``); the
    ``hidden`` of ``inputs`` is not read.  name -> [N, ...]."""
    assert inputs.resets is not None, "carried outputs need a recorded flight (flight_inputs)"
    out: dict[str, list[np.ndarray]] = {name: [] for name in OUTPUT_NAMES}
    hidden = np.zeros_like(inputs.hidden[:1])
    for i, feed in enumerate(inputs.feeds()):
        if inputs.resets[i]:
            hidden = np.zeros_like(hidden)
        feed[c.ONNX_INPUT_HIDDEN] = hidden
        values = session.run(list(OUTPUT_NAMES), feed)
        for name, value in zip(OUTPUT_NAMES, values):
            out[name].append(value)
        hidden = values[OUTPUT_NAMES.index(c.ONNX_OUTPUT_HIDDEN)]
    return {name: np.concatenate(v) for name, v in out.items()}


def max_abs_errors(reference: dict[str, np.ndarray], outputs: dict[str, np.ndarray]) -> dict[str, float]:
    """name -> max |output - reference| (inf where either is not finite)."""
    errors = {}
    for name in OUTPUT_NAMES:
        diff = np.abs(outputs[name].astype(np.float64) - reference[name].astype(np.float64))
        errors[name] = float(np.nan_to_num(diff, nan=np.inf).max())
    return errors


def cpu_session(model: str | Path | bytes, threads: int = 0) -> ort.InferenceSession:
    """An ONNX Runtime CPU session (quiet; ``threads`` intra-op threads, 0 = ORT's default)."""
    options = ort.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = threads
    source = model if isinstance(model, bytes) else str(model)
    return ort.InferenceSession(source, sess_options=options, providers=["CPUExecutionProvider"])


# ---------------------------------------------------------------------------- variants

# What int8 quantises: the convolutions of the gray AlexNet stack (half of the step's FLOPs).
# Measured on the default model (policy-s2 on cmwae-s2) over held-out recorded SITL frames, max
# action error of one quantised layer at a time against fp32 (issue 15): every gray convolution
# <= 2e-4 (all five together 3e-4); the depth stack's 0.26 (depth.0, its input's uint8 steps),
# 0.045, 0.040, 0.030, 0.012 (min/max calibration; percentile calibration brings one layer to
# 0.003 but the five together still to 0.065, and gray + the last depth convolution to 0.023).
# The depth stack carries the latent and stays fp32, as do the MLP/GRU head (quantised too, the
# action error was ~0.3 whether the weights were per-tensor or per-channel) and every Gemm.
# Activation ranges: entropy calibration (the range that keeps the histogram's KL divergence
# least), not min/max.  On student-near / cmwae-near, whose latent leans harder on gray, min/max
# put each gray convolution alone at 1.3e-2..2.7e-2 max action error on 240 calibration steps (the
# five: 0.098 held out); a few outlier activations stretched the ranges.  Entropy: one layer
# (gray.3) 1.1e-4, all five 5.3e-4; percentile 99.999 %: 7.8e-4 (99.99 %: 3.6e-3).
INT8_OP_TYPES = ("Conv",)
INT8_NODE_PREFIXES = ("/encoder/gray/",)
# The bound a quantised variant must meet to be written: max |action - fp32 action| over at least
# this many held-out recorded steps, each model carrying its own GRU state through each flight.
VARIANT_MAX_ACTION_ERROR = 0.02
VARIANT_MIN_HELD_OUT_STEPS = 300
BOUNDED_VARIANTS = ("int8",)
# Calibration: at most this many recorded steps (evenly spread over the calibration flights), and
# activation ranges folded every CALIBRATION_BATCH steps so the calibrator's memory stays bounded.
CALIBRATION_MAX_STEPS = 240
CALIBRATION_BATCH = 32


@dataclass(frozen=True)
class VariantBound:
    """When a bounded variant (int8) is written: its max action error against the fp32 graph, on
    at least ``min_held_out_steps`` recorded steps calibration never saw, is at most
    ``max_action_error`` (action units: the policy's raw output, [-1, 1] after the clip)."""

    max_action_error: float = VARIANT_MAX_ACTION_ERROR
    min_held_out_steps: int = VARIANT_MIN_HELD_OUT_STEPS


class VariantRefusedError(ExportError):
    """A variant missed its bound (or had too few held-out steps to be judged): not written.  The
    fp32 model and the other variants were; ``report`` says what was done, with the numbers."""

    def __init__(self, message: str, report: ExportReport) -> None:
        super().__init__(message)
        self.report = report


def make_fp16(model: onnx.ModelProto) -> onnx.ModelProto:
    """Weights and activations in float16, graph inputs and outputs kept float32 (the runtime's
    signature); for GPU execution providers (ONNX Runtime's CPU kernels mostly run fp16 through casts)."""
    from onnxruntime.transformers.float16 import convert_float_to_float16

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "the model has values beyond fp16 range": clamped, reported by parity
        return convert_float_to_float16(model, keep_io_types=True, disable_shape_infer=False)


# Layer selection: all candidate convolutions are quantised and scored on the calibration steps
# (max action error against fp32); over this share of the variant's bound, each is scored alone
# and they are added in order of that error while the ones chosen together stay within it.  The
# held-out flights, which selection never sees, judge the result against the whole bound.
INT8_SELECTION_SHARE = 0.5


@dataclass
class Int8Selection:
    """What :func:`make_int8` quantised: the nodes chosen, the chosen set's max action error on the
    calibration steps, the budget it was held to, and (when the whole set missed it) each
    candidate's error alone."""

    nodes: list[str]
    together: float
    budget: float
    alone: dict[str, float] = field(default_factory=dict)

    def describe(self) -> str:
        return ", ".join(f"{name} {error:.2e}" for name, error in self.alone.items())


def select_nodes(candidates: list[str], action_error: Callable[[list[str]], float], budget: float) -> Int8Selection:
    """The layer selection (``INT8_SELECTION_SHARE``): ``action_error(nodes)`` is the max action
    error with ``nodes`` quantised.  All candidates when they stay within ``budget`` together;
    otherwise each is scored alone and, in order of that score, kept when the set with it stays
    within ``budget``."""
    together = action_error(candidates)
    if together <= budget:
        return Int8Selection(list(candidates), together, budget)
    alone = {name: action_error([name]) for name in candidates}
    chosen: list[str] = []
    together = 0.0
    for name in sorted(candidates, key=alone.__getitem__):
        if alone[name] > budget:
            break
        error = alone[name] if not chosen else action_error([*chosen, name])
        if error <= budget:
            chosen.append(name)
            together = error
    return Int8Selection([n for n in candidates if n in chosen], together, budget, alone)


def make_int8(
    fp32_path: str | Path, out_path: str | Path, calibration: ParityInputs, budget: float,
    op_types: tuple[str, ...] = INT8_OP_TYPES, node_prefixes: tuple[str, ...] = INT8_NODE_PREFIXES,
) -> Int8Selection:  # fmt: skip
    """Static int8 QDQ quantisation of the ``op_types`` nodes whose names start with one of
    ``node_prefixes`` (default: the gray stack's convolutions; uint8 activations, int8
    per-channel weights), activation ranges calibrated (entropy) on ``calibration``, after ONNX
    Runtime's recommended pre-processing (shape inference and graph optimisation).  Of those nodes,
    the ones :func:`select_nodes` keeps within ``budget`` (max action error on the calibration
    steps) are quantised; every other node stays fp32.  Raises :class:`ExportError` when no node
    matches (a depth-only encoder has no gray stack: nothing to quantise) or none is kept (the
    message gives each one's error)."""
    import tempfile

    from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Calibration(CalibrationDataReader):
        def __init__(self) -> None:
            self._feeds = calibration.feeds()

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self._feeds, None)

    with tempfile.TemporaryDirectory() as tmp:
        prepared = Path(tmp) / "prepared.onnx"
        quant_pre_process(str(fp32_path), str(prepared), skip_symbolic_shape=True)
        nodes = [n.name for n in onnx.load(str(prepared)).graph.node if n.op_type in op_types and n.name.startswith(node_prefixes)]
        if not nodes:
            raise ExportError(f"int8: no {'/'.join(op_types)} node under {list(node_prefixes)} in the graph: nothing to quantise")

        def quantise(chosen: list[str], path: Path) -> None:
            quantize_static(
                str(prepared), str(path), Calibration(), quant_format=QuantFormat.QDQ,
                op_types_to_quantize=list(op_types), nodes_to_quantize=chosen, per_channel=True,
                activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, calibrate_method=CalibrationMethod.Entropy,
                extra_options={"CalibMaxIntermediateOutputs": CALIBRATION_BATCH},
            )  # fmt: skip

        reference = onnx_outputs(cpu_session(fp32_path), calibration)[c.ONNX_OUTPUT_ACTION]
        trials: dict[frozenset[str], Path] = {}  # every set scored, so the chosen one is not calibrated again

        def action_error(chosen: list[str]) -> float:
            trial = trials.setdefault(frozenset(chosen), Path(tmp) / f"trial{len(trials)}.onnx")
            quantise(chosen, trial)
            action = onnx_outputs(cpu_session(trial), calibration)[c.ONNX_OUTPUT_ACTION]
            error = float(np.nan_to_num(np.abs(action.astype(np.float64) - reference), nan=np.inf).max())
            log.info("int8 %s: max action error %.2e on the calibration steps", chosen, error)
            return error

        selection = select_nodes(nodes, action_error, budget)
        if not selection.nodes:
            raise ExportError(f"int8: no {'/'.join(op_types)} node keeps the max action error within {budget:g} on the "
                              f"calibration steps even alone ({selection.describe()})")  # fmt: skip
        shutil.copyfile(trials[frozenset(selection.nodes)], out_path)
    return selection


def with_carried_hidden(session: ort.InferenceSession, inputs: ParityInputs) -> ParityInputs:
    """``inputs`` (a recorded flight) with the hidden state ``session`` carries into each step."""
    hidden_next = carried_outputs(session, inputs)[c.ONNX_OUTPUT_HIDDEN]
    hidden = np.concatenate([np.zeros_like(hidden_next[:1]), hidden_next[:-1]])
    hidden[inputs.resets] = 0.0
    return ParityInputs(inputs.gray, inputs.depth, inputs.state, hidden, inputs.source, inputs.resets)


def concat_inputs(parts: list[ParityInputs], source: str) -> ParityInputs:
    """Several step sets as one (resets kept)."""
    resets = None if any(p.resets is None for p in parts) else np.concatenate([p.resets for p in parts])
    return ParityInputs(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("gray", "depth", "state", "hidden")),
                      source=source, resets=resets)  # fmt: skip


@dataclass
class RecordedSplit:
    """Recorded flights split for the variants: calibration steps (fp32's GRU state carried into
    them) and the held-out flights, loaded one at a time (:meth:`held_out`)."""

    calibration: ParityInputs
    held_out_logs: list[Path]
    held_out_part: ParityInputs | None = None  # one log: its second half
    description: str = ""

    def held_out(self, hidden_size: int) -> Iterator[ParityInputs]:
        if self.held_out_part is not None:
            yield self.held_out_part
        for path in self.held_out_logs:
            yield flight_inputs(path, hidden_size)


def split_recorded(logs: list[Path], session: ort.InferenceSession, hidden_size: int) -> RecordedSplit:
    """Calibration and held-out flights: with several logs the first half of them (at least one)
    calibrate and the rest are held out; with one log, the first half of its steps calibrate and
    the second half is held out.  Calibration keeps at most CALIBRATION_MAX_STEPS steps, evenly
    spread over its flights."""
    if len(logs) == 1:
        first, second = flight_inputs(logs[0], hidden_size).halves()
        calibration = with_carried_hidden(session, first)
        every = max(1, -(-len(calibration) // CALIBRATION_MAX_STEPS))
        calibration = calibration.subset(slice(None, None, every), f"{first.source} (every {every})")
        return RecordedSplit(calibration, [], second, f"one flight split in halves: calibration {calibration.source}, held out {second.source}")
    n_calibration = len(logs) // 2
    per_flight = max(1, CALIBRATION_MAX_STEPS // n_calibration)
    parts = []
    for path in logs[:n_calibration]:
        flight = with_carried_hidden(session, flight_inputs(path, hidden_size))
        rows = np.unique(np.linspace(0, len(flight) - 1, min(per_flight, len(flight))).round().astype(int))
        parts.append(flight.subset(rows, flight.source))
    names = ", ".join(_log_name(p) for p in logs[:n_calibration])
    calibration = concat_inputs(parts, f"{sum(len(p) for p in parts)} steps of {n_calibration} flights ({names})")
    held = ", ".join(str(p) for p in logs[n_calibration:])
    return RecordedSplit(calibration, logs[n_calibration:], None,
                         f"calibration: {calibration.source}; held out: {len(logs) - n_calibration} flights ({held})")  # fmt: skip


def held_out_errors(reference: ort.InferenceSession, sessions: dict[str, ort.InferenceSession], flights: Iterator[ParityInputs]) -> dict[str, dict]:
    """Each session against ``reference`` over recorded ``flights``, every model carrying its own
    GRU state (:func:`carried_outputs`): variant -> {steps, flights, max_abs_error, mean_abs_error,
    fp32_max_abs} (per output)."""
    steps, names = 0, []
    worst = {v: dict.fromkeys(OUTPUT_NAMES, 0.0) for v in sessions}
    total = {v: dict.fromkeys(OUTPUT_NAMES, 0.0) for v in sessions}
    scale = dict.fromkeys(OUTPUT_NAMES, 0.0)
    for flight in flights:
        fp32 = carried_outputs(reference, flight)
        for name in OUTPUT_NAMES:
            scale[name] = max(scale[name], float(np.abs(fp32[name]).max()))
        for variant, session in sessions.items():
            out = carried_outputs(session, flight)
            for name in OUTPUT_NAMES:
                diff = np.nan_to_num(np.abs(out[name].astype(np.float64) - fp32[name]), nan=np.inf).max(axis=-1)
                worst[variant][name] = max(worst[variant][name], float(diff.max()))
                total[variant][name] += float(diff.sum())
        steps += len(flight)
        names.append(flight.source)
        log.info("held out %s: %s", flight.source, {v: worst[v][c.ONNX_OUTPUT_ACTION] for v in sessions})
    return {v: {"steps": steps, "flights": names, "max_abs_error": worst[v],
                "mean_abs_error": {n: total[v][n] / max(steps, 1) for n in OUTPUT_NAMES}, "fp32_max_abs": scale}
            for v in sessions}  # fmt: skip


def bound_problem(variant: str, errors: dict, bound: VariantBound) -> str | None:
    """Why a bounded variant may not be written (with the numbers), or None."""
    if variant not in BOUNDED_VARIANTS:
        return None
    action = errors["max_abs_error"][c.ONNX_OUTPUT_ACTION]
    latent = errors["max_abs_error"][c.ONNX_OUTPUT_LATENT]
    if errors["steps"] < bound.min_held_out_steps:
        return (f"{variant} judged on {errors['steps']} held-out recorded steps, fewer than the {bound.min_held_out_steps} "
                "its bound needs: pass more --recorded flight logs (record them with `cmnav sitl --model MODEL --level 3 "
                "--seed N`; the second half of the logs is held out)")  # fmt: skip
    if not action <= bound.max_action_error:
        return (f"{variant} max action error {action:.4f} > {bound.max_action_error:g} over {errors['steps']} held-out "
                f"recorded steps (GRU state carried; latent error {latent:.4f}, mean action error "
                f"{errors['mean_abs_error'][c.ONNX_OUTPUT_ACTION]:.4f}): not written, fly the fp32 model")  # fmt: skip
    return None


# ---------------------------------------------------------------------------- the command


@dataclass
class ExportReport:
    """What ``cmnav export`` did: files, fingerprints, parity (max abs error per output and input
    set), variants with their parity cost against the fp32 graph, and the variants refused."""

    path: str
    encoder_fingerprint: str
    policy_fingerprint: str
    hidden_size: int
    git_commit: str
    tolerance: float
    parity: dict[str, dict[str, float]] = field(default_factory=dict)
    variants: dict[str, dict] = field(default_factory=dict)
    refused: dict[str, dict] = field(default_factory=dict)
    runtime_loader: str = ""

    def format(self) -> str:
        lines = [
            f"wrote {self.path} (GRU hidden {self.hidden_size}; encoder {self.encoder_fingerprint}, policy "
            f"{self.policy_fingerprint}, commit {self.git_commit[:12]})",
            f"parity, ONNX Runtime CPU vs torch, max abs error (bound {self.tolerance:g}):",
        ]
        for source, errors in self.parity.items():
            lines.append(f"  {source}: " + ", ".join(f"{name} {errors[name]:.2e}" for name in OUTPUT_NAMES))
        for name, variant in self.variants.items():
            errors, scale = variant["max_abs_error_vs_fp32"], variant["fp32_max_abs"]
            calibrated = f", calibrated on {variant['calibration']}" if variant.get("calibration") else ""
            if variant.get("quantised_nodes"):
                calibrated += f", quantised {', '.join(variant['quantised_nodes'])}"
            bound = f"; bound: action <= {variant['bound']['max_action_error']:g}, met" if variant.get("bound") else ""
            lines.append(
                f"variant {name}: {variant['path']}{calibrated}; max abs error vs fp32 on {variant['inputs']} "
                "(and the fp32 outputs' max abs): "
                + ", ".join(f"{n} {errors[n]:.2e} ({scale[n]:.2e})" for n in OUTPUT_NAMES)
                + bound + "; time it with `cmnav bench runtime` and keep it only where it is faster"
            )
        for name, refused in self.refused.items():
            lines.append(f"variant {name}: REFUSED, not written: {refused['reason']}")
        lines.append(f"runtime loader: {self.runtime_loader}")
        return "\n".join(lines)

    def to_json(self) -> dict:
        return dict(self.__dict__)


def export_policy(
    encoder_dir: str | Path,
    policy_dir: str | Path,
    out_path: str | Path,
    recorded: str | Path | list[str | Path] | tuple[str | Path, ...] | None = None,
    variants: tuple[str, ...] = (),
    random_samples: int = RANDOM_SAMPLES,
    recorded_samples: int = RECORDED_SAMPLES,
    tolerance: float = PARITY_TOLERANCE,
    bound: VariantBound = VariantBound(),
) -> ExportReport:
    """Export, check parity, write the variants, and load the result with the runtime's loader.

    ``recorded``: one or more flight logs.  The fp32 parity against torch runs on the first
    ``recorded_samples`` steps of the first; the variants are calibrated and judged on all of them
    (:func:`split_recorded`).  A bounded variant (int8) that misses ``bound`` (or has no recorded
    flights to be judged on) is not written.

    Raises :class:`~training.policy.network.EncoderMismatchError`, :class:`ExportError` (bad
    checkpoint), :class:`ParityError` (the file is renamed ``*.parity-failed``, named in the
    message, for inspection), the runtime loader's error, or, after everything else was written,
    :class:`VariantRefusedError` naming each refused variant with its numbers.
    """
    from runtime.model import PolicyModel

    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ExportError(f"unknown variant(s) {unknown}: choose from {list(VARIANTS)}")
    logs = [Path(p) for p in ([recorded] if isinstance(recorded, (str, Path)) else (recorded or []))]
    nets = load_networks(encoder_dir, policy_dir)
    out_path = Path(out_path)
    log.info("exporting encoder %s + policy %s to %s", nets.encoder_dir, nets.policy_dir, out_path)
    model = export_step_onnx(nets.step, out_path, nets.hidden_size)

    input_sets = [random_inputs(random_samples, nets.hidden_size)]
    if logs:
        input_sets.append(recorded_inputs(logs[0], nets.step, recorded_samples))
    session = cpu_session(out_path)
    parity: dict[str, dict[str, float]] = {}
    for inputs in input_sets:
        errors = max_abs_errors(torch_outputs(nets.step, inputs), onnx_outputs(session, inputs))
        parity[inputs.source] = errors
        log.info("parity on %s: %s", inputs.source, errors)
    worst = max(max(e.values()) for e in parity.values())

    metadata = export_metadata(nets)
    metadata[KEY_PARITY] = json.dumps({"tolerance": tolerance, "max_abs_error": parity}, sort_keys=True)
    set_metadata(model, metadata)
    onnx.save(model, str(out_path))
    commit = metadata[KEY_GIT_COMMIT]
    report = ExportReport(str(out_path), nets.encoder_fingerprint, nets.policy_fingerprint, nets.hidden_size, commit, tolerance, parity)
    if not worst <= tolerance:
        failed = out_path.with_name(out_path.name + ".parity-failed")
        out_path.replace(failed)  # not under a name anything would fly
        raise ParityError(
            f"ONNX Runtime differs from torch by {worst:.3e} > {tolerance:g} ({parity}): the graph does not compute "
            f"what the networks do; kept for inspection as {failed}, do not fly it (report it with the checkpoints)"
        )

    PolicyModel(out_path)  # the runtime's own loader: signature and contract
    report.runtime_loader = "runtime.model.PolicyModel accepts " + str(out_path)

    for stale in (v for v in VARIANTS if v not in variants and variant_path(out_path, v).exists()):
        log.warning("%s is from an earlier export, not of this model: delete it (cmnav bench runtime skips it)",
                    variant_path(out_path, stale))  # fmt: skip
    if not variants:
        return report
    write_variants(nets, model, out_path, session, logs, variants, random_samples, bound, report)
    if report.refused:
        raise VariantRefusedError("; ".join(f"variant {v} refused: {r['reason']}" for v, r in report.refused.items()), report)
    return report


def write_variants(
    nets: Networks, model: onnx.ModelProto, out_path: Path, session: ort.InferenceSession, logs: list[Path],
    variants: tuple[str, ...], random_samples: int, bound: VariantBound, report: ExportReport,
) -> None:  # fmt: skip
    """Build each variant next to ``out_path``, measure it against the fp32 graph (``session``)
    and write it with its parity in the metadata, or refuse it (``report.refused``).

    With recorded flights: int8 is calibrated on the calibration flights and every variant is
    judged on the held-out flights, carrying its own GRU state.  Without: fp16 is judged per step
    on random inputs; int8 is refused (its bound needs recorded steps)."""
    from runtime.model import PolicyModel

    split = split_recorded(logs, session, nets.hidden_size) if logs else None
    candidates: dict[str, Path] = {}
    selection: Int8Selection | None = None
    for variant in variants:
        path = variant_path(out_path, variant)
        path.unlink(missing_ok=True)  # an earlier export's file must not survive a refusal
        candidate = path.with_name(path.name + ".candidate")
        if variant == "fp16":
            onnx.save(make_fp16(model), str(candidate))
        elif split is None:
            report.refused[variant] = {"reason": f"{variant} needs recorded flights to be calibrated and judged on: pass "
                                       "--recorded LOG.mcap (several flights; record them with `cmnav sitl`)"}  # fmt: skip
            continue
        else:
            try:
                selection = make_int8(out_path, candidate, split.calibration, INT8_SELECTION_SHARE * bound.max_action_error)
            except ExportError as err:
                report.refused[variant] = {"reason": f"{err}: not written, fly the fp32 model"}
                continue
        candidates[variant] = candidate
    sessions = {v: cpu_session(p) for v, p in candidates.items()}
    if split is not None:
        measured = held_out_errors(session, sessions, split.held_out(nets.hidden_size))
        inputs = f"held-out recorded flights, GRU state carried ({next(iter(measured.values()))['steps'] if measured else 0} steps)"
    else:
        held_out = random_inputs(random_samples, nets.hidden_size)
        reference = onnx_outputs(session, held_out)
        scale = {name: float(np.abs(v).max()) for name, v in reference.items()}
        measured = {v: {"steps": len(held_out), "max_abs_error": max_abs_errors(reference, onnx_outputs(s, held_out)),
                        "fp32_max_abs": scale} for v, s in sessions.items()}  # fmt: skip
        inputs = held_out.source
    for variant, candidate in candidates.items():
        errors = measured[variant]
        problem = bound_problem(variant, errors, bound)
        if problem is not None:
            refused = candidate.with_name(variant_path(out_path, variant).name + ".refused")
            candidate.replace(refused)  # for inspection, under a name nothing flies
            report.refused[variant] = {"reason": problem + f" (kept for inspection as {refused})", "path": str(refused),
                                       "inputs": inputs, **errors}  # fmt: skip
            log.error("variant %s refused: %s", variant, problem)
            continue
        path = variant_path(out_path, variant)
        variant_model = onnx.load(str(candidate))
        variant_metadata = export_metadata(nets, variant)
        parity_info = {"reference": "fp32 graph", "inputs": inputs, "steps": errors["steps"],
                       "max_abs_error": errors["max_abs_error"], "fp32_max_abs": errors["fp32_max_abs"]}  # fmt: skip
        if "mean_abs_error" in errors:
            parity_info["mean_abs_error"] = errors["mean_abs_error"]
        if variant in BOUNDED_VARIANTS:
            parity_info["bound"] = {"max_action_error": bound.max_action_error, "min_held_out_steps": bound.min_held_out_steps}
            parity_info["quantised_nodes"] = selection.nodes
            parity_info["selection"] = {"calibration_max_action_error": selection.together, "budget": selection.budget,
                                        "calibration_max_action_error_alone": selection.alone}  # fmt: skip
        if variant == "int8" and split is not None:
            parity_info["calibration"] = split.calibration.source
            parity_info["split"] = split.description
        variant_metadata[KEY_PARITY] = json.dumps(parity_info, sort_keys=True)
        set_metadata(variant_model, variant_metadata)
        onnx.save(variant_model, str(path))
        candidate.unlink()
        PolicyModel(path)
        report.variants[variant] = {"path": str(path), "inputs": inputs, "max_abs_error_vs_fp32": errors["max_abs_error"],
                                    "mean_abs_error_vs_fp32": errors.get("mean_abs_error"), "steps": errors["steps"],
                                    "fp32_max_abs": errors["fp32_max_abs"], "calibration": parity_info.get("calibration"),
                                    "bound": parity_info.get("bound"), "quantised_nodes": parity_info.get("quantised_nodes")}  # fmt: skip
        log.info("variant %s: %s, max abs error vs fp32 %s", variant, path, errors["max_abs_error"])
