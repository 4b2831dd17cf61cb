"""The policy's ONNX Runtime session: load, check against the contract, step.

One graph per control step, batch 1 (DESIGN §6): inputs ``gray`` and ``depth``
[1, 1, 224, 224] float32, ``state`` [1, 15] float32, ``hidden`` [1, H] float32 (the GRU state);
outputs ``action`` [1, 3], ``hidden_next`` [1, H], ``latent`` [1, 64], all float32.  A model
whose signature or contract metadata differs is refused with an error naming every difference,
before anything is armed.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import onnxruntime as ort
from onnxruntime.capi import onnxruntime_pybind11_state as _ort_state

from .config import TensorRtConfig
from .contract import check_contract_metadata
from .contract import constants as c
from .contract.images import preprocess_depth, preprocess_gray

log = logging.getLogger(__name__)

_FLOAT = "tensor(float)"
# name -> expected shape; None = the GRU hidden size H (read from the model), "batch" = 1 or symbolic.
_IMAGE_SHAPE = ("batch", 1, c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX)
_INPUTS: dict[str, tuple] = {
    c.ONNX_INPUT_GRAY: _IMAGE_SHAPE,
    c.ONNX_INPUT_DEPTH: _IMAGE_SHAPE,
    c.ONNX_INPUT_STATE: ("batch", c.STATE_DIM),
    c.ONNX_INPUT_HIDDEN: ("batch", None),
}
_OUTPUTS: dict[str, tuple] = {
    c.ONNX_OUTPUT_ACTION: ("batch", c.ACTION_DIM),
    c.ONNX_OUTPUT_HIDDEN: ("batch", None),
    c.ONNX_OUTPUT_LATENT: ("batch", c.LATENT_DIM),
}
_IMAGE_BATCH = (1, 1, c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX)
_LOAD_ERRORS = (
    _ort_state.Fail,
    _ort_state.InvalidGraph,
    _ort_state.InvalidProtobuf,
    _ort_state.InvalidArgument,
    _ort_state.NotImplemented,
)
_FIX = "export the model with `cmnav export` from this cmnav version"
TENSORRT = "TensorrtExecutionProvider"
CUDA = "CUDAExecutionProvider"
CPU = "CPUExecutionProvider"
KEY_VARIANT = "cmnav.variant"  # the export's variant in the model metadata (absent: fp32)


class ModelLoadError(ValueError):
    """The model file is missing, unreadable, or its signature differs from the contract's."""


class ProviderUnavailableError(ModelLoadError):
    """A configured execution provider is not in this ONNX Runtime build."""


@dataclass(frozen=True)
class ModelOutput:
    """One policy step: raw action (3,), next GRU state (H,), CMWAE latent (64,), all float32."""

    action: np.ndarray
    hidden_next: np.ndarray
    latent: np.ndarray


class PolicyModel:
    """An ONNX Runtime session for the policy step, checked against the contract at load."""

    def __init__(
        self,
        path: str | Path,
        providers: Sequence[str] = (CPU,),
        intra_op_threads: int = 0,
        tensorrt: TensorRtConfig | None = None,
        variant: str | None = None,
    ) -> None:
        """Load ``path`` on ``providers`` (in order of preference; TensorRT with the options of
        ``tensorrt``, default :class:`runtime.config.TensorRtConfig`); raise :class:`ModelLoadError`
        or :class:`runtime.contract.ContractMismatchError` if it is not a model for this runtime,
        or, with ``variant``, if its metadata names another variant (``cmnav.variant``)."""
        self.path = Path(path)
        if not self.path.is_file():
            raise ModelLoadError(f"model file {self.path} does not exist: check the path in the config")
        providers = resolve_providers(providers, fallback=False)
        options = ort.SessionOptions()
        options.intra_op_num_threads = intra_op_threads
        options.log_severity_level = 3
        try:
            self._session = ort.InferenceSession(
                str(self.path), sess_options=options, providers=session_providers(providers, tensorrt or TensorRtConfig())
            )
        except _LOAD_ERRORS as err:
            raise ModelLoadError(f"{self.path} is not a loadable ONNX model ({_one_line(err)}): {_FIX}") from err
        metadata = self._session.get_modelmeta().custom_metadata_map
        check_contract_metadata(metadata, source=str(self.path))
        self.variant = metadata.get(KEY_VARIANT, "fp32")
        if variant is not None and self.variant != variant:
            raise ModelLoadError(
                f"{self.path} is the {self.variant} export (its {KEY_VARIANT} metadata), not the {variant} one policy.variant "
                "names: set policy.variant to the model's, or point policy.model_path at the fp32 file the variants sit next to"
            )
        self.hidden_size = self._check_signature()
        self.providers = tuple(self._session.get_providers())
        self.sha256 = file_sha256(self.path)
        self._output_names = [c.ONNX_OUTPUT_ACTION, c.ONNX_OUTPUT_HIDDEN, c.ONNX_OUTPUT_LATENT]
        log.info("loaded %s (%s): hidden size %d, providers %s", self.path, self.variant, self.hidden_size, self.providers)

    def warm_up(self, steps: int) -> list[float]:
        """Run ``steps`` steps on blank inputs and return their durations (ms): the first step of a
        session allocates its buffers, and on TensorRT builds (or loads) the engine, so the
        runtime pays for it here, before it reports READY, not in its first control step."""
        blank = np.zeros((c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX), dtype=np.float32)
        state = np.zeros(c.STATE_DIM, dtype=np.float32)
        durations_ms = []
        for _ in range(steps):
            t0 = time.perf_counter()
            self.step(blank, blank, state, self.initial_hidden())
            durations_ms.append((time.perf_counter() - t0) * 1000.0)
        if durations_ms:
            log.info("warm-up on %s: %d steps, %s ms", self.providers, steps, ", ".join(f"{d:.1f}" for d in durations_ms))
        return durations_ms

    def _check_signature(self) -> int:
        """Compare names, shapes and dtypes with the contract; return the GRU hidden size H."""
        problems: list[str] = []
        hidden_sizes: dict[str, object] = {}
        for kind, expected, actual in (
            ("input", _INPUTS, self._session.get_inputs()),
            ("output", _OUTPUTS, self._session.get_outputs()),
        ):
            by_name = {a.name: a for a in actual}
            for name in sorted(set(by_name) - set(expected)):
                problems.append(f"unexpected {kind} {name!r}")
            for name, shape in expected.items():
                if name not in by_name:
                    problems.append(f"missing {kind} {name!r} (has {sorted(by_name)})")
                    continue
                arg = by_name[name]
                if arg.type != _FLOAT:
                    problems.append(f"{kind} {name!r} has type {arg.type}, expected {_FLOAT}")
                problems.extend(_shape_problems(kind, name, list(arg.shape), shape, hidden_sizes))
        sizes = set(hidden_sizes.values())
        if len(sizes) > 1:
            problems.append(f"GRU hidden sizes differ: {hidden_sizes}")
        if problems:
            raise ModelLoadError(f"{self.path} does not have the contract's step signature: " + "; ".join(problems) + f"; {_FIX}")
        (hidden_size,) = sizes
        assert isinstance(hidden_size, int)
        return hidden_size

    def log_metadata(self) -> dict[str, str]:
        """What a flight log records about this model (``cmnav replay`` finds and checks it by these)."""
        return {"model": str(self.path.resolve()), "model_sha256": self.sha256, "model_providers": ",".join(self.providers),
                "model_variant": self.variant}

    def initial_hidden(self) -> np.ndarray:
        """The GRU state at reset: zeros (H,), float32."""
        return np.zeros(self.hidden_size, dtype=np.float32)

    def step(self, gray: np.ndarray, depth: np.ndarray, state: np.ndarray, hidden: np.ndarray) -> ModelOutput:
        """One policy step.

        ``gray``, ``depth``: (224, 224) float32 from ``runtime.contract.images``; ``state``: (15,)
        float32 from ``observation_state``; ``hidden``: (H,) float32.  Returns the raw action
        (not yet clipped), the next hidden state and the latent.
        """
        feeds = {
            c.ONNX_INPUT_GRAY: _as_input(gray, (c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX), "gray").reshape(_IMAGE_BATCH),
            c.ONNX_INPUT_DEPTH: _as_input(depth, (c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX), "depth").reshape(_IMAGE_BATCH),
            c.ONNX_INPUT_STATE: _as_input(state, (c.STATE_DIM,), "state").reshape(1, c.STATE_DIM),
            c.ONNX_INPUT_HIDDEN: _as_input(hidden, (self.hidden_size,), "hidden").reshape(1, self.hidden_size),
        }
        action, hidden_next, latent = self._session.run(self._output_names, feeds)
        return ModelOutput(action=action[0], hidden_next=hidden_next[0], latent=latent[0])



def check_outputs_finite(model: PolicyModel) -> None:
    """Run two steps before anything flies — all-zero inputs, then a synthetic camera frame
    (textured gray, a depth ramp with invalid pixels, through the contract's preprocessing) with a
    goal ahead and the first step's GRU state — and raise :class:`ModelLoadError` if any output is
    NaN/Inf or the step fails.  The flight watchdog trips on a NaN action too, but in the air;
    this catches a broken export on the ground (``--check``, before arming, before the SITL vehicle)."""
    size = (c.IMAGE_SIZE_PX, c.IMAGE_SIZE_PX)
    rows, cols = np.mgrid[0 : c.SIM_CAMERA_HEIGHT_PX, 0 : c.SIM_CAMERA_WIDTH_PX]
    gray_u8 = ((rows * 7 + cols * 3) % 256).astype(np.uint8)
    depth_m = np.linspace(0.5, 8.0, c.SIM_CAMERA_WIDTH_PX, dtype=np.float32)[None, :].repeat(c.SIM_CAMERA_HEIGHT_PX, axis=0)
    depth_m[:, : c.SIM_CAMERA_WIDTH_PX // 10] = 0.0  # invalid, as the sensor reports it
    state = np.zeros(c.STATE_DIM, np.float32)
    state[0], state[3] = 1.0, 0.5  # goal ahead, 6 m away
    cases = [
        ("all-zero inputs", np.zeros(size, np.float32), np.zeros(size, np.float32), np.zeros(c.STATE_DIM, np.float32), model.initial_hidden()),
        ("a synthetic camera frame", preprocess_gray(gray_u8), preprocess_depth(depth_m), state, None),
    ]  # fmt: skip
    hidden_next = model.initial_hidden()
    for what, gray, depth, step_state, hidden in cases:
        try:
            out = model.step(gray, depth, step_state, hidden_next if hidden is None else hidden)
        except (*_LOAD_ERRORS, _ort_state.RuntimeException) as err:
            raise ModelLoadError(f"{model.path} fails a policy step on {what} ({_one_line(err)}): {_FIX}") from err
        bad = [name for name, value in (("action", out.action), ("hidden_next", out.hidden_next), ("latent", out.latent))
               if not np.all(np.isfinite(value))]  # fmt: skip
        if bad:
            raise ModelLoadError(f"{model.path} outputs NaN/Inf ({', '.join(bad)}) on {what}: a broken export or "
                                 f"checkpoint; nothing is flown with it — re-export it ({_FIX})")  # fmt: skip
        hidden_next = out.hidden_next


def _one_line(err: BaseException) -> str:
    """An error message on one line (ONNX Runtime's can span several)."""
    return " ".join(str(err).split())


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes, lowercase hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def resolve_providers(requested: Sequence[str], fallback: bool) -> tuple[str, ...]:
    """The execution providers to use, in order of preference.

    Without ``fallback`` every requested provider must be in this ONNX Runtime build; with it the
    missing ones are dropped (logged) as long as one remains.  Raises
    :class:`ProviderUnavailableError` naming what is missing and what is available.
    """
    available = ort.get_available_providers()
    present = tuple(p for p in requested if p in available)
    missing = [p for p in requested if p not in available]
    if missing and (not fallback or not present):
        raise ProviderUnavailableError(
            f"execution provider(s) {missing} not in this ONNX Runtime build (available: {available}): "
            "install the onnxruntime build that has them (on a Jetson: NVIDIA's onnxruntime-gpu wheel), "
            "remove them from policy.providers, or set policy.provider_fallback = true"
        )
    if missing:
        log.warning("execution provider(s) %s not available; falling back to %s", missing, list(present))
    return present


def session_providers(providers: Sequence[str], tensorrt: TensorRtConfig) -> list[str | tuple[str, dict]]:
    """ONNX Runtime's provider list for ``providers``: TensorRT with fp16 as configured and its
    engine and timing caches in ``tensorrt.engine_cache_dir`` (created; it must be writable),
    every other provider with its defaults.  ONNX Runtime runs on the next provider in the list
    whatever a provider cannot (CUDA -> CPU)."""
    out: list[str | tuple[str, dict]] = []
    for provider in providers:
        if provider != TENSORRT:
            out.append(provider)
            continue
        cache = tensorrt.engine_cache_dir
        try:
            cache.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ModelLoadError(f"policy.tensorrt.engine_cache_dir {cache} cannot be created ({err}): give the service a "
                                 "writable directory there (systemd/README.md: StateDirectory=cmnav)") from err  # fmt: skip
        if not os.access(cache, os.W_OK | os.X_OK):
            raise ModelLoadError(f"policy.tensorrt.engine_cache_dir {cache} is not writable by this user: chown it to the "
                                 "service user or list it in ReadWritePaths= (systemd/README.md)")  # fmt: skip
        out.append((provider, {
            "trt_fp16_enable": tensorrt.fp16,
            "trt_engine_cache_enable": True,
            "trt_engine_cache_path": str(cache),
            "trt_timing_cache_enable": True,
            "trt_timing_cache_path": str(cache),
            "trt_max_workspace_size": tensorrt.max_workspace_mb * (1 << 20),
        }))  # fmt: skip
    return out


def _as_input(array: np.ndarray, shape: tuple[int, ...], name: str) -> np.ndarray:
    array = np.asarray(array)
    if array.shape != shape:
        raise ValueError(f"policy step input {name!r} has shape {array.shape}, expected {shape}")
    return np.ascontiguousarray(array, dtype=np.float32)


def _shape_problems(kind: str, name: str, actual: list, expected: tuple, hidden_sizes: dict[str, object]) -> list[str]:
    if len(actual) != len(expected):
        return [f"{kind} {name!r} has shape {actual}, expected rank {len(expected)} {_describe(expected)}"]
    problems = []
    for axis, (got, want) in enumerate(zip(actual, expected)):
        if want == "batch":
            if isinstance(got, int) and got != 1:
                problems.append(f"{kind} {name!r} has batch size {got}, expected 1")
        elif want is None:
            hidden_sizes[f"{kind} {name}"] = got
            if not (isinstance(got, int) and got > 0):
                problems.append(f"{kind} {name!r} has hidden size {got!r} on axis {axis}, expected a fixed integer")
        elif got != want:
            problems.append(f"{kind} {name!r} has shape {actual}, expected {_describe(expected)}")
            break
    return problems


def _describe(shape: tuple) -> str:
    return "[" + ", ".join("1" if d == "batch" else "H" if d is None else str(d) for d in shape) + "]"
