"""`cmnav bench runtime`: how fast the runtime's control step is, measured in one run and reported
as ratios against targets (issue 6).

What it times (p50 / p99 / best over repeated calls, in milliseconds):
- **preprocess**: the contract's ``preprocess_gray`` + ``preprocess_depth`` on one D455-size
  frame (848x480) and one sim-size frame (212x120), as the runtime does per step;
- **ONNX step**: :meth:`runtime.model.PolicyModel.step` (the runtime's own session and call) on
  the CPU with 1 and 2 intra-op threads, and with the CUDA and TensorRT providers when this ONNX
  Runtime build has them; also the fp16 / int8 variants found next to the model
  (``model.fp16.onnx``, ``model.int8.onnx``, written by ``cmnav export --variants``), each with
  its speed relative to the fp32 model on the same provider and threads;
- **torch eager**: the same networks from their checkpoints (``--encoder`` / ``--policy``; their
  fingerprints must be the ones the model's metadata names) under ``torch.inference_mode``,
  numpy in and numpy out as the runtime would, with 1 and 2 threads (and on CUDA when present);
  skipped, with the reason, without checkpoints;
- **SITL end to end**: one short ``cmnav sitl`` flight per CPU model file (fp32, and the int8
  variant when it is next to the model), with the runtime on a core of its own as on the Jetson:
  the runtime process pinned to the last CPU this process may use (``runtime.cpu_affinity``,
  every thread) with 1 ONNX Runtime intra-op thread, the SITL vehicle (renderer, physics,
  MAVLink) pinned to the others (``--no-pin``: neither pinned, ORT's default threads).  From each
  MCAP log's per-step timing records: end to end (``frame_age``: the frame's capture by the SITL
  camera to the velocity command sent); grab -> command (``grab_to_command``: the runtime's
  receipt of the frame off the camera link to the command sent, its share of the latency), the
  ONNX step inside it (``inference``), the overhead around the step (grab -> command minus
  inference, per step); the frame's age when the step began (``frame_age_at_step``) and its part
  before the runtime had it (``delivery``: the SITL camera's render and the link); and where the
  overhead goes, stage by stage: from receipt to the step's start (``pickup``: asyncio waking the
  loop), the hop to the worker thread (``executor_in``), preprocessing, the observation, the hop
  back to the event loop (``executor_out``), the checks, and the MAVSDK send with its own
  executor hop (``send``).

The rows compared with each other (every model file and torch at one thread count, or on one GPU
provider) are timed in interleaved blocks of calls, the first call of each block untimed (it pays
for the switch from the other library's thread pool), so load from other work on the machine
falls on all of them alike; the load average at the start is reported, with a warning when it
says the machine was busy.

What it computes: the model's FLOPs (2 x multiply-adds of Conv, Gemm, MatMul, GRU/LSTM from the
ONNX graph's shapes; elementwise ops and pooling are not counted), this CPU's theoretical FP32
peak (cores x FLOP/cycle of its vector units x clock, from /proc/cpuinfo; see :func:`cpu_peak`
for the assumptions), the achieved rate of a large fp32 GEMM (ONNX Runtime's MatMul, the kernels
the runtime uses, and torch's), and the ratios against the targets of issue 6, on 2 CPU threads:
ONNX step <= 0.65x torch eager, <= 1.3x ideal (FLOPs / theoretical peak), grab -> command minus
the step <= 3 ms at p99, grab -> command <= 25 ms at p99.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

from export.variants import VARIANTS, variant_path
from runtime.contract import constants as c
from runtime.contract import preprocess_depth, preprocess_gray
from runtime.model import PolicyModel

log = logging.getLogger(__name__)

CPU = "CPUExecutionProvider"
CUDA = "CUDAExecutionProvider"
TENSORRT = "TensorrtExecutionProvider"
# Targets of issue 6, on 2 CPU threads.
TARGET_ONNX_OVER_EAGER = 0.65
TARGET_ONNX_OVER_IDEAL = 1.3
TARGET_OVERHEAD_P99_MS = 3.0
TARGET_E2E_P99_MS = 25.0
TARGET_THREADS = 2
# A 1-minute load average above this fraction of the CPUs means other work competed.
BUSY_LOAD_PER_CPU = 0.25


@dataclass(frozen=True)
class RuntimeBenchConfig:
    """What `cmnav bench runtime` measures and for how long: per row at least ``min_calls``
    timed calls and ``step_time_s`` seconds, in blocks of ``block_calls``."""

    model: Path
    encoder: Path | None = None
    policy: Path | None = None
    threads: tuple[int, ...] = (1, TARGET_THREADS)
    step_time_s: float = 5.0
    preprocess_time_s: float = 2.0
    min_calls: int = 50
    block_calls: int = 10
    warmup_calls: int = 5
    gemm_size: int = 2048
    variants: bool = True
    sitl: bool = True
    sitl_level: int = 0
    sitl_seed: int = 0
    sitl_timeout_s: float = 20.0
    pin: bool = True  # the SITL runtime on a core of its own (1 intra-op thread), the vehicle on the others
    out_dir: Path = Path("runs/bench-runtime")


def quick(config: RuntimeBenchConfig) -> RuntimeBenchConfig:
    """`--quick`: a smoke run of every path (seconds), not a measurement."""
    return replace(config, step_time_s=0.0, preprocess_time_s=0.0, min_calls=3, block_calls=3, warmup_calls=1,
                   gemm_size=256, sitl_timeout_s=3.0)  # fmt: skip


# ---------------------------------------------------------------------------- timing


def latency_stats(times_ms: list[float] | np.ndarray) -> dict:
    """{p50_ms, p99_ms, best_ms, n} of samples in ms."""
    values = np.asarray(times_ms, dtype=np.float64)
    p50, p99 = np.percentile(values, [50, 99])
    return {"p50_ms": round(float(p50), 4), "p99_ms": round(float(p99), 4), "best_ms": round(float(values.min()), 4), "n": len(values)}


def time_calls(call: Callable[[], object], min_time_s: float, min_calls: int, warmup_calls: int) -> dict:
    """:func:`latency_stats` of ``call`` over at least ``min_calls`` calls and ``min_time_s``."""
    return time_interleaved({"call": call}, min_time_s, min_calls, warmup_calls, block_calls=max(min_calls, 1))["call"]


def time_interleaved(
    calls: dict[str, Callable[[], object]], min_time_s: float, min_calls: int, warmup_calls: int, block_calls: int
) -> dict[str, dict]:
    """Time several calls against each other: after ``warmup_calls`` each, rounds of one block per
    call (one untimed call, then ``block_calls`` timed ones) until every call has ``min_calls``
    timed calls and ``min_time_s`` seconds of them.  Returns name -> :func:`latency_stats`."""
    for call in calls.values():
        for _ in range(warmup_calls):
            call()
    samples: dict[str, list[float]] = {name: [] for name in calls}
    spent_s = dict.fromkeys(calls, 0.0)

    def wanting() -> list[str]:
        return [n for n in calls if len(samples[n]) < min_calls or spent_s[n] < min_time_s]

    while pending := wanting():  # a call that has enough drops out: a slow one does not hold up the rest
        for name in pending:
            call = calls[name]
            call()  # untimed: the other library's threads may still be spinning
            for _ in range(block_calls):
                t0 = time.perf_counter()
                call()
                dt = time.perf_counter() - t0
                samples[name].append(dt * 1000.0)
                spent_s[name] += dt
    return {name: latency_stats(values) for name, values in samples.items()}


# ---------------------------------------------------------------------------- FLOPs, peak, GEMM


_COUNTED = {"Conv", "QLinearConv", "ConvInteger", "Gemm", "MatMul", "MatMulInteger", "QLinearMatMul", "GRU", "LSTM"}


def count_flops(model: onnx.ModelProto) -> dict:
    """FLOPs of one step (batch 1): 2 x multiply-adds of Conv, Gemm, MatMul, GRU and LSTM nodes,
    by op type, from the shapes ONNX shape inference gives (the exported graphs are static).
    Their quantised forms (QLinearConv, ConvInteger, MatMulInteger, QLinearMatMul) count like
    the float ops.  Elementwise, pooling and normalisation ops are not counted."""
    inferred = onnx.shape_inference.infer_shapes(model)
    shapes: dict[str, list[int]] = {}
    for info in [*inferred.graph.value_info, *inferred.graph.input, *inferred.graph.output]:
        dims = info.type.tensor_type.shape.dim
        shapes[info.name] = [d.dim_value if d.HasField("dim_value") else 1 for d in dims]
    for init in inferred.graph.initializer:
        shapes[init.name] = list(init.dims)
    by_op: dict[str, int] = {}
    uncounted: list[str] = []
    for node in inferred.graph.node:
        if node.op_type not in _COUNTED:
            continue
        try:
            flops = _node_flops(node, shapes)
        except (KeyError, IndexError):
            uncounted.append(node.name or node.op_type)  # a shape inference could not give
            continue
        by_op[node.op_type] = by_op.get(node.op_type, 0) + flops
    return {"total": int(sum(by_op.values())), "by_op": by_op, "uncounted_nodes": uncounted}


def _attr(node: onnx.NodeProto, name: str, default: int) -> int:
    return next((onnx.helper.get_attribute_value(a) for a in node.attribute if a.name == name), default)


def _node_flops(node: onnx.NodeProto, shapes: dict[str, list[int]]) -> int:
    op = node.op_type
    if op in ("Conv", "ConvInteger", "QLinearConv"):
        y = shapes[node.output[0]]
        w = shapes[node.input[3 if op == "QLinearConv" else 1]]  # [Cout, Cin/group, k...]
        return 2 * math.prod(y) * math.prod(w[1:])
    if op == "Gemm":
        a, b = shapes[node.input[0]], shapes[node.input[1]]
        m, k = (a[1], a[0]) if _attr(node, "transA", 0) else (a[0], a[1])
        n = b[0] if _attr(node, "transB", 0) else b[1]
        return 2 * m * n * k
    if op in ("MatMul", "MatMulInteger", "QLinearMatMul"):
        a = shapes[node.input[0]]
        return 2 * math.prod(shapes[node.output[0]]) * a[-1]
    # GRU / LSTM: X [T, B, I], W [directions, gates x H, I]; per step gates x H x (I + H) multiply-adds.
    x, w = shapes[node.input[0]], shapes[node.input[1]]
    hidden = w[1] // (3 if op == "GRU" else 4)
    return 2 * x[0] * x[1] * w[0] * w[1] * (w[2] + hidden)


def _cpuinfo() -> list[dict[str, str]]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return []
    blocks: list[dict[str, str]] = [{}]
    for line in text.splitlines():
        if not line.strip():
            blocks.append({})
            continue
        key, _, value = line.partition(":")
        blocks[-1][key.strip()] = value.strip()
    return [b for b in blocks if b]


def cpu_peak(cores: int) -> dict:
    """Theoretical FP32 peak of ``cores`` cores: cores x FLOP/cycle x clock (GFLOP/s).

    FLOP/cycle per core from the vector units /proc/cpuinfo's flags name, assuming two FMA
    pipes (as on every recent x86 core), each FMA counting 2 FLOP:
    avx512f: 2 x 16 lanes x 2 = 64, except AMD family 25 (Zen 4), which runs 512-bit ops as
    two 256-bit halves: 32; avx2 + fma: 2 x 8 x 2 = 32; avx without fma: 16 (one add and one
    multiply pipe of 8 lanes); aarch64 asimd (e.g. the Jetson Orin's Cortex-A78AE, two 128-bit
    FMA pipes): 16; sse2: 8.  Clock: cpufreq's cpuinfo_max_freq when the kernel exposes it, else
    the highest "cpu MHz" in /proc/cpuinfo (in a VM often the nominal clock: the cores may turbo
    above it, and then measured rates can exceed this "peak").  SMT siblings share a core's
    pipes, so ``cores`` should count physical cores.
    """
    blocks = _cpuinfo()
    first = blocks[0] if blocks else {}
    flags = set((first.get("flags") or first.get("Features") or "").split())
    vendor, family = first.get("vendor_id", ""), first.get("cpu family", "")
    if "avx512f" in flags:
        zen4 = vendor == "AuthenticAMD" and family == "25"
        flop_per_cycle, vector = (32, "avx512f (Zen 4: 2x256-bit datapath)") if zen4 else (64, "avx512f")
    elif "avx2" in flags and "fma" in flags:
        flop_per_cycle, vector = 32, "avx2+fma"
    elif "avx" in flags:
        flop_per_cycle, vector = 16, "avx"
    elif "asimd" in flags:
        flop_per_cycle, vector = 16, "asimd"
    elif "sse2" in flags:
        flop_per_cycle, vector = 8, "sse2"
    else:
        flop_per_cycle, vector = 2, "scalar (no vector flags found)"
    clock_ghz, clock_source = None, "unknown"
    max_freq = Path("/sys/devices/system/cpu/cpu0/cpufreq/cpuinfo_max_freq")
    try:
        clock_ghz, clock_source = int(max_freq.read_text().strip()) / 1e6, str(max_freq)
    except (OSError, ValueError):
        mhz = [float(b["cpu MHz"]) for b in blocks if "cpu MHz" in b]
        if mhz:
            clock_ghz, clock_source = max(mhz) / 1000.0, "/proc/cpuinfo cpu MHz, may be below turbo"
    smt = "siblings" in first and "cpu cores" in first and int(first["siblings"]) > int(first["cpu cores"])
    return {
        "model_name": first.get("model name", "unknown"),
        "vendor": vendor,
        "family": family,
        "vector_units": vector,
        "flop_per_cycle_per_core": flop_per_cycle,
        "clock_ghz": clock_ghz and round(clock_ghz, 4),
        "clock_source": clock_source,
        "cores": cores,
        "smt": smt,
        "peak_gflop_s": round(cores * flop_per_cycle * clock_ghz, 2) if clock_ghz else None,
    }


def gemm_rates(size: int, threads: tuple[int, ...]) -> list[dict]:
    """Achieved fp32 GEMM rates (GFLOP/s, best of 5) of a ``size`` x ``size`` product: ONNX
    Runtime's MatMul (MLAS, the runtime's kernels) at each thread count, and torch's matmul
    (its BLAS) at the largest, when torch is installed."""
    rng = np.random.default_rng(0)
    a = rng.random((size, size), dtype=np.float32)
    b = numpy_helper.from_array(rng.random((size, size), dtype=np.float32), "b")
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["a", "b"], ["y"])], "gemm",
        [helper.make_tensor_value_info("a", TensorProto.FLOAT, [size, size])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [size, size])], [b],
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    rows = []
    for n in threads:
        options = ort.SessionOptions()
        options.intra_op_num_threads = n
        session = ort.InferenceSession(model.SerializeToString(), options, providers=[CPU])
        stats = time_calls(lambda: session.run(None, {"a": a}), 0.0, 5, 1)
        rows.append(_gemm_row(size, n, f"onnxruntime {ort.__version__} MatMul (MLAS)", stats["best_ms"]))
    try:
        import torch
    except ImportError:
        return rows
    previous = torch.get_num_threads()
    torch.set_num_threads(max(threads))
    try:
        ta, tb = torch.from_numpy(a), torch.from_numpy(numpy_helper.to_array(b).copy())
        stats = time_calls(lambda: ta @ tb, 0.0, 5, 1)
    finally:
        torch.set_num_threads(previous)
    rows.append(_gemm_row(size, max(threads), f"torch {torch.__version__} matmul", stats["best_ms"]))
    return rows


def _gemm_row(size: int, threads: int, library: str, best_ms: float) -> dict:
    return {"size": size, "threads": threads, "library": library, "best_ms": best_ms,
            "gflop_s": round(2.0 * size**3 / (best_ms / 1000.0) / 1e9, 2)}  # fmt: skip


# ---------------------------------------------------------------------------- the rows


def bench_frames() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """One synthetic frame per camera size: gray uint8, depth (m) in [0.3, 12] with 10% invalid."""
    rng = np.random.default_rng(0)
    frames = {}
    for name, (w, h) in {"d455": (c.CAMERA_WIDTH_PX, c.CAMERA_HEIGHT_PX), "sim": (c.SIM_CAMERA_WIDTH_PX, c.SIM_CAMERA_HEIGHT_PX)}.items():
        gray = rng.integers(0, 256, (h, w), dtype=np.uint8)
        depth = rng.uniform(0.3, 12.0, (h, w)).astype(np.float32)
        depth[rng.random((h, w)) < 0.1] = 0.0
        frames[f"{name} {w}x{h}"] = (gray, depth)
    return frames


def preprocess_rows(config: RuntimeBenchConfig) -> list[dict]:
    rows = []
    for name, (gray, depth) in bench_frames().items():
        stats = time_calls(lambda: (preprocess_gray(gray), preprocess_depth(depth)), config.preprocess_time_s, config.min_calls, config.warmup_calls)
        rows.append({"frame": name, **stats})
    return rows


def step_inputs(hidden_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One step's inputs as the runtime passes them: gray, depth (224, 224), state (15,), hidden (H,)."""
    gray_u8, depth_m = next(iter(bench_frames().values()))
    state = np.zeros(c.STATE_DIM, np.float32)
    state[0], state[3] = 1.0, 0.5
    return preprocess_gray(gray_u8), preprocess_depth(depth_m), state, np.zeros(hidden_size, np.float32)


def _torch_networks(config: RuntimeBenchConfig, model_meta: dict[str, str]):
    """(the torch step module, None) from the checkpoints, or (None, why not)."""
    if config.encoder is None or config.policy is None:
        return None, "no --encoder/--policy checkpoints given: the torch eager rows need the networks the model was exported from"
    from export.policy_onnx import KEY_ENCODER, KEY_POLICY, load_networks

    nets = load_networks(config.encoder, config.policy)
    for key, given in ((KEY_ENCODER, nets.encoder_fingerprint), (KEY_POLICY, nets.policy_fingerprint)):
        recorded = json.loads(model_meta.get(key, "{}")).get("fingerprint")
        if recorded is not None and recorded != given:
            return None, (f"the model was exported from a checkpoint with fingerprint {recorded} ({key}), not {given}: "
                          "pass the checkpoints it was exported from")  # fmt: skip
    return nets.step, None


def _torch_call(step, device: str, args: tuple[np.ndarray, ...]) -> Callable[[], object]:
    import torch

    size = c.IMAGE_SIZE_PX
    gray, depth, state, hidden = args

    def call() -> object:
        # As the runtime would: numpy in, numpy out (host <-> device copies included).
        with torch.inference_mode():
            out = step(
                torch.from_numpy(gray).view(1, 1, size, size).to(device), torch.from_numpy(depth).view(1, 1, size, size).to(device),
                torch.from_numpy(state).view(1, -1).to(device), torch.from_numpy(hidden).view(1, -1).to(device),
            )  # fmt: skip
            return [o.cpu().numpy() for o in out]

    return call


def step_rows(config: RuntimeBenchConfig, files: dict[str, Path], torch_step) -> tuple[list[dict], list[dict]]:
    """(ONNX rows, torch rows): every model file on every provider (the CPU at each thread count),
    and torch eager alongside, each group timed interleaved (:func:`time_interleaved`)."""
    available = ort.get_available_providers()
    groups: list[tuple[str, tuple[str, ...], int]] = [(CPU, (CPU,), t) for t in config.threads]
    if CUDA in available:
        groups.append((CUDA, (CUDA, CPU), 0))
    if TENSORRT in available:
        groups.append((TENSORRT, (TENSORRT, CUDA, CPU) if CUDA in available else (TENSORRT, CPU), 0))
    torch_device = {CPU: "cpu", CUDA: "cuda"}
    onnx_out, torch_out = [], []
    for provider, providers, threads in groups:
        calls: dict[str, Callable[[], object]] = {}
        models = []
        for variant, path in files.items():
            model = PolicyModel(path, providers, intra_op_threads=threads)
            if model.providers[0] != provider:
                log.warning("%s: %s did not take the session (got %s); row skipped", path, provider, model.providers)
                continue
            args = step_inputs(model.hidden_size)
            calls[variant] = lambda model=model, args=args: model.step(*args)
            models.append(model)
        device = torch_device.get(provider)
        if torch_step is not None and device is not None and (device == "cpu" or _cuda_available()):
            import torch

            if device == "cpu":
                torch.set_num_threads(threads)
            calls["torch"] = _torch_call(torch_step.to(device), device, step_inputs(torch_step.policy.hidden_size))
        stats = time_interleaved(calls, config.step_time_s, config.min_calls, config.warmup_calls, config.block_calls)
        for name, s in stats.items():
            if name == "torch":
                torch_out.append({"device": device, "threads": threads, **s})
            else:
                onnx_out.append({"provider": provider, "threads": threads, "variant": name, "model": str(files[name]), **s})
            log.info("%s %s threads=%d: p50 %.3f ms", name, provider, threads, s["p50_ms"])
        del models, calls
    return onnx_out, torch_out


def _cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


# Stages of a step as the flight loop records them (runtime.flight), in order: they add up to
# grab -> command minus the ONNX step.  The frame's delivery (capture -> receipt) comes before
# them and is reported on its own, with the frame's age when the step began.
OVERHEAD_STAGES = ("pickup", "executor_in", "preprocess", "observation", "executor_out", "checks", "send")
FRAME_AGE_STAGES = ("delivery", "frame_age_at_step")


def sitl_pinning(pin: bool) -> dict:
    """Where the SITL runtime and vehicle run: {runtime_cpus, vehicle_cpus, runtime_threads, note}."""
    allowed = sorted(os.sched_getaffinity(0))
    if not pin:
        return {"runtime_cpus": [], "vehicle_cpus": [], "runtime_threads": 0, "note": "not pinned (--no-pin)"}
    if len(allowed) < 2:
        return {"runtime_cpus": [], "vehicle_cpus": [], "runtime_threads": 1,
                "note": f"one CPU ({allowed}): the runtime cannot have a core of its own; not pinned"}  # fmt: skip
    return {"runtime_cpus": allowed[-1:], "vehicle_cpus": allowed[:-1], "runtime_threads": 1,
            "note": f"runtime pinned to CPU {allowed[-1]} with 1 intra-op thread, SITL vehicle to CPUs {allowed[:-1]}"}  # fmt: skip


def sitl_result(config: RuntimeBenchConfig, files: dict[str, Path]) -> dict:
    """One SITL flight per CPU model file (fp32 and int8, not fp16, which is for GPUs), the runtime
    pinned as :func:`sitl_pinning` says; per variant, grab -> command, the step, the overhead and
    each stage's share from its log."""
    from sim.sitl_session import SitlError, SitlRequest, run_sitl

    pinning = sitl_pinning(config.pin)
    flights: dict[str, dict] = {}
    for variant, path in files.items():
        if variant == "fp16":
            continue
        request = SitlRequest(
            path, config.sitl_level, config.sitl_seed, config.sitl_timeout_s, config.out_dir / "sitl" / variant,
            runtime_cpus=tuple(pinning["runtime_cpus"]), vehicle_cpus=tuple(pinning["vehicle_cpus"]),
            runtime_threads=pinning["runtime_threads"],
        )  # fmt: skip
        try:
            summary = run_sitl(request)
        except SitlError as err:
            flights[variant] = {"skipped": f"the SITL flight could not run: {err}"}
            continue
        stages = read_step_timing(Path(summary["log"])) if summary.get("log") else {}
        if not stages.get("grab_to_command"):
            flights[variant] = {"skipped": f"the SITL flight recorded no policy step (outcome {summary['outcome']}, log {summary.get('log')})"}
            continue
        e2e, grab, inference, loop = (np.asarray(stages[k]) for k in ("frame_age", "grab_to_command", "inference", "step"))
        flights[variant] = {
            "model": str(path),
            "outcome": summary["outcome"],
            "steps": len(e2e),
            "missed_deadlines": summary.get("missed_deadlines"),
            "log": summary.get("log"),
            "pinning": summary.get("pinning"),
            "end_to_end": latency_stats(e2e),
            "grab_to_command": latency_stats(grab),
            "step_onnx": latency_stats(inference),
            "overhead": latency_stats(grab - inference),
            "loop_step": latency_stats(loop),
            "loop_overhead": latency_stats(loop - inference),
            "stages": {name: latency_stats(stages[name]) for name in OVERHEAD_STAGES if stages.get(name)},
            "frame_age": {name: latency_stats(stages[name]) for name in FRAME_AGE_STAGES if stages.get(name)},
        }
    if not flights:
        return {"skipped": "no CPU model file to fly"}
    return {"level": config.sitl_level, "seed": config.sitl_seed, "pinning": pinning, "flights": flights}


def read_step_timing(log_path: Path) -> dict[str, list[float]]:
    """Per-step stage times (ms) from a flight log's /timing channel: stage -> [ms per step]."""
    from mcap.reader import make_reader

    from runtime.log.topics import TOPIC_TIMING

    stages: dict[str, list[float]] = {}
    with open(log_path, "rb") as f:
        for _schema, _channel, message in make_reader(f).iter_messages(topics=[TOPIC_TIMING]):
            for name, ms in json.loads(message.data)["stages_ms"].items():
                stages.setdefault(name, []).append(float(ms))
    return stages


# ---------------------------------------------------------------------------- the bench


def run_runtime_bench(config: RuntimeBenchConfig) -> dict:
    """Measure everything; returns a JSON-able dict (see :func:`format_runtime_bench`)."""
    load_average = os.getloadavg()[0]
    cpus = len(os.sched_getaffinity(0))
    model = PolicyModel(config.model)  # refuses a model that is not the runtime's
    proto = onnx.load(str(config.model))
    meta = {p.key: p.value for p in proto.metadata_props}
    flops = count_flops(proto)
    del proto
    variant = meta.get("cmnav.variant", "fp32")
    files = {variant: config.model}
    skipped_variants = {}
    for v in VARIANTS if config.variants else ():
        path = variant_path(config.model, v)
        if path.is_file():
            why = _not_a_variant_of(path, meta)
            if why:
                skipped_variants[v] = why
                log.warning("%s skipped: %s", path, why)
            else:
                files[v] = path
    cores = min(cpus, TARGET_THREADS)
    result: dict = {
        "model": str(config.model),
        "model_sha256": model.sha256,
        "hidden_size": model.hidden_size,
        "variant": variant,
        "ort": ort.__version__,
        "providers_available": ort.get_available_providers(),
        "cpus_available": cpus,
        "load_average_1min": load_average,
        "flops": flops,
        "cpu": cpu_peak(cores),
        "gemm": gemm_rates(config.gemm_size, tuple(sorted({1, cores}))),
        "preprocess": preprocess_rows(config),
        "variant_files": {v: str(p) for v, p in files.items() if v != variant},
        "variants_skipped": skipped_variants,
    }
    del model
    correct_clock(result["cpu"], result["gemm"])
    torch_step, result["torch_skipped"] = _torch_networks(config, meta)
    result["onnx"], result["torch"] = step_rows(config, files, torch_step)
    result["variant_speedup"] = variant_speedups(result["onnx"], variant)
    result["sitl"] = sitl_result(config, files) if config.sitl else {"skipped": "--no-sitl"}
    peak = result["cpu"]["peak_gflop_s"]
    result["ideal_ms"] = round(flops["total"] / (peak * 1e9) * 1000.0, 4) if peak else None
    result["ratios"] = ratios(result)
    result["targets"] = targets(result)
    result["warnings"] = bench_warnings(result)
    return result


def _not_a_variant_of(path: Path, model_meta: dict[str, str]) -> str | None:
    """Why ``path`` is not a variant of the model with ``model_meta`` (another export's leftover),
    or None: its encoder and policy fingerprints must be the model's."""
    meta = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    for key in ("cmnav.encoder", "cmnav.policy"):
        theirs, ours = (json.loads(m.get(key, "{}")).get("fingerprint") for m in (meta, model_meta))
        if theirs != ours:
            return f"exported from another checkpoint ({key} fingerprint {theirs}, the model's {ours}); re-export the variants"
    return None


def variant_speedups(rows: list[dict], base_variant: str) -> list[dict]:
    """Each variant's p50 against the base model's on the same provider and threads (> 1 = faster)."""
    base = {(r["provider"], r["threads"]): r for r in rows if r["variant"] == base_variant}
    out = []
    for r in rows:
        ref = base.get((r["provider"], r["threads"]))
        if r["variant"] != base_variant and ref is not None:
            out.append({"variant": r["variant"], "provider": r["provider"], "threads": r["threads"],
                        "speedup_p50": round(ref["p50_ms"] / r["p50_ms"], 3), "speedup_best": round(ref["best_ms"] / r["best_ms"], 3)})  # fmt: skip
    return out


def _row(rows: list[dict], **match) -> dict | None:
    return next((r for r in rows if all(r.get(k) == v for k, v in match.items())), None)


def ratios(result: dict) -> dict:
    """p50 ratios of the model's ONNX step on the CPU: over torch eager at each thread count, over
    the ideal (FLOPs / theoretical peak) and over the GEMM ideal (FLOPs / best achieved GEMM rate)
    at 2 threads; and the SITL overhead and end to end at p99 (ms)."""
    out: dict[str, float | None] = {}
    for r in result["onnx"]:
        if r["provider"] == CPU and r["variant"] == result["variant"]:
            eager = _row(result["torch"], device="cpu", threads=r["threads"])
            out[f"onnx_over_eager_{r['threads']}t"] = eager and round(r["p50_ms"] / eager["p50_ms"], 4)
    onnx2 = _row(result["onnx"], provider=CPU, threads=TARGET_THREADS, variant=result["variant"])
    best_gemm = max((g["gflop_s"] for g in result["gemm"] if g["threads"] == result["cpu"]["cores"]), default=None)
    out["onnx_over_ideal"] = onnx2 and result["ideal_ms"] and round(onnx2["p50_ms"] / result["ideal_ms"], 4)
    out["onnx_over_gemm_ideal"] = onnx2 and best_gemm and round(onnx2["p50_ms"] / (result["flops"]["total"] / best_gemm / 1e6), 4)
    for variant, flight in _flown(result["sitl"]).items():
        out[f"overhead_p99_ms_{variant}"] = flight["overhead"]["p99_ms"]
        out[f"e2e_p99_ms_{variant}"] = flight["end_to_end"]["p99_ms"]
    return out


def _flown(sitl: dict) -> dict[str, dict]:
    """variant -> its SITL flight's result, for the flights that recorded steps."""
    return {v: f for v, f in sitl.get("flights", {}).items() if "skipped" not in f}


def targets(result: dict) -> list[dict]:
    """The issue's targets with the measured value and PASS / MISS (or SKIP with why)."""
    ratio, sitl = result["ratios"], result["sitl"]
    rows = []

    def add(name: str, measured: float | None, target: float, unit: str, why_skipped: str | None) -> None:
        status = "SKIP" if measured is None else ("PASS" if measured <= target else "MISS")
        rows.append({"name": name, "measured": None if measured is None else round(measured, 3), "target": target,
                     "unit": unit, "status": status, "why_skipped": why_skipped if measured is None else None})  # fmt: skip

    add(f"ONNX step / torch eager (p50, CPU, {TARGET_THREADS} threads)", ratio.get(f"onnx_over_eager_{TARGET_THREADS}t"),
        TARGET_ONNX_OVER_EAGER, "x", result["torch_skipped"] or f"no {TARGET_THREADS}-thread rows")  # fmt: skip
    add(f"ONNX step / ideal (p50 over FLOPs / peak of {result['cpu']['cores']} cores)", ratio["onnx_over_ideal"],
        TARGET_ONNX_OVER_IDEAL, "x", "no clock found for the peak")  # fmt: skip
    flown = _flown(sitl)
    where = (sitl.get("pinning") or {}).get("note", "")
    for variant, flight in flown.items():
        add(f"grab->command minus ONNX step (SITL p99, {variant}; {where})", flight["overhead"]["p99_ms"], TARGET_OVERHEAD_P99_MS, "ms", None)
        add(f"end to end, capture->command (SITL p99, {variant}; {where})", flight["end_to_end"]["p99_ms"], TARGET_E2E_P99_MS, "ms", None)
    if not flown:
        why = sitl.get("skipped") or "; ".join(f"{v}: {f['skipped']}" for v, f in sitl.get("flights", {}).items())
        add("grab->command minus ONNX step (SITL, p99)", None, TARGET_OVERHEAD_P99_MS, "ms", why)
        add("end to end, capture->command (SITL, p99)", None, TARGET_E2E_P99_MS, "ms", why)
    return rows


def correct_clock(cpu: dict, gemm: list[dict]) -> None:
    """When one thread's GEMM beats one core's peak at the clock read, the clock read is below the
    running one (turbo; a VM's nominal "cpu MHz"): the running clock is at least that GEMM rate /
    FLOP per cycle.  Use that lower bound for the peak (the stricter ideal) and keep the other."""
    single = max((g["gflop_s"] for g in gemm if g["threads"] == 1), default=0.0)
    bound_ghz = single / cpu["flop_per_cycle_per_core"]
    cpu["peak_gflop_s_clock_read"] = cpu["peak_gflop_s"]
    cpu["clock_ghz_lower_bound_from_gemm"] = round(bound_ghz, 4)
    if cpu["clock_ghz"] is None or bound_ghz > cpu["clock_ghz"]:
        cpu["clock_ghz"] = round(bound_ghz, 4)
        cpu["clock_source"] += f"; below one thread's GEMM, so the clock is taken as >= {bound_ghz:.2f} GHz from it"
        cpu["peak_gflop_s"] = round(cpu["cores"] * cpu["flop_per_cycle_per_core"] * bound_ghz, 2)


def bench_warnings(result: dict) -> list[str]:
    """What makes this run's numbers less than clean: a busy machine, a peak below measured rates."""
    out = []
    if result["load_average_1min"] > BUSY_LOAD_PER_CPU * result["cpus_available"]:
        out.append(
            f"load average {result['load_average_1min']:.2f} on {result['cpus_available']} CPUs at the start: other work "
            "competed for the cores, so times (above all at 2 threads and in SITL) are inflated and p99s are the other "
            "work's; rerun on an idle machine for the targets"
        )
    if result["variant"] != "fp32":
        out.append(
            f"the model is the {result['variant']} variant: its ONNX / ideal compares it with the FP32 peak, which does not "
            "bound it (int8 runs on the integer dot-product units); compare the fp32 model's for the target"
        )
    cpu = result["cpu"]
    if cpu["peak_gflop_s"] != cpu["peak_gflop_s_clock_read"]:
        out.append(
            f"the clock read from the machine gives a peak of {cpu['peak_gflop_s_clock_read']} GFLOP/s, below what one "
            f"thread's GEMM reaches: the peak and the ideal step use the clock that GEMM implies ({cpu['clock_ghz']} GHz, "
            "a lower bound: the real peak may be higher still)"
        )
    return out


def _threads(n: int) -> str:
    return f"{n} thread" + ("" if n == 1 else "s")


def format_runtime_bench(result: dict) -> str:
    """The result of :func:`run_runtime_bench` as markdown tables."""
    cpu, flops, peak = result["cpu"], result["flops"], result["cpu"]["peak_gflop_s"]
    lines = [
        f"Model {result['model']} ({result['variant']}, GRU hidden {result['hidden_size']}); ONNX Runtime {result['ort']}; "
        f"{result['cpus_available']} CPUs available, load average {result['load_average_1min']:.2f} at the start.",
        f"FLOPs per step: {flops['total'] / 1e9:.3f} G ({', '.join(f'{k} {v / 1e9:.3f} G' for k, v in flops['by_op'].items())}).",
        f"CPU: {cpu['model_name']}, {cpu['vector_units']} -> {cpu['flop_per_cycle_per_core']} FP32 FLOP/cycle/core (assumed: "
        f"2 FMA pipes) x {cpu['clock_ghz']} GHz ({cpu['clock_source']}) x {cpu['cores']} cores = peak {peak} GFLOP/s; "
        f"ideal step {result['ideal_ms']} ms.",
        "GEMM " + "; ".join(f"{g['size']}² fp32 {g['library']}, {_threads(g['threads'])}: {g['gflop_s']} GFLOP/s"
                            + (f" ({g['gflop_s'] / (peak * g['threads'] / cpu['cores']):.2f}x peak)" if peak else "")
                            for g in result["gemm"]) + ".",  # fmt: skip
        "",
        "| what | p50 ms | p99 ms | best ms | n |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in result["preprocess"]:
        lines.append(f"| preprocess {r['frame']} | {r['p50_ms']:.3f} | {r['p99_ms']:.3f} | {r['best_ms']:.3f} | {r['n']} |")
    for r in result["onnx"]:
        threads = f", {_threads(r['threads'])}" if r["provider"] == CPU else ""
        lines.append(f"| ONNX step {r['variant']}, {r['provider'].replace('ExecutionProvider', '')}{threads} "
                     f"| {r['p50_ms']:.3f} | {r['p99_ms']:.3f} | {r['best_ms']:.3f} | {r['n']} |")  # fmt: skip
    for r in result["torch"]:
        threads = f", {_threads(r['threads'])}" if r["device"] == "cpu" else ""
        lines.append(f"| torch eager, {r['device']}{threads} | {r['p50_ms']:.3f} | {r['p99_ms']:.3f} | {r['best_ms']:.3f} | {r['n']} |")
    if result["torch_skipped"]:
        lines.append(f"| torch eager: skipped ({result['torch_skipped']}) | | | | |")
    sitl = result["sitl"]
    if "skipped" in sitl:
        lines.append(f"| SITL: skipped ({sitl['skipped']}) | | | | |")
    for variant, flight in sitl.get("flights", {}).items():
        if "skipped" in flight:
            lines.append(f"| SITL {variant}: skipped ({flight['skipped']}) | | | | |")
            continue
        rows = [("end_to_end", "end to end (capture->command)"), ("grab_to_command", "grab->command"),
                ("step_onnx", "ONNX step inside"), ("overhead", "grab->command minus step"),
                ("loop_step", "loop: frame taken->command")]  # fmt: skip
        for key, label in rows:
            r = flight[key]
            lines.append(f"| SITL {variant} {label} | {r['p50_ms']:.3f} | {r['p99_ms']:.3f} | {r['best_ms']:.3f} | {r['n']} |")
        for stage, r in {**flight["stages"], **flight["frame_age"]}.items():
            lines.append(f"| SITL {variant} stage {stage} | {r['p50_ms']:.3f} | {r['p99_ms']:.3f} | {r['best_ms']:.3f} | {r['n']} |")
    if result["variant_speedup"]:
        lines += ["", "| variant | provider | threads | speed vs fp32, p50 (best) |", "|---|---|---:|---:|"]
        for s in result["variant_speedup"]:
            lines.append(f"| {s['variant']} | {s['provider'].replace('ExecutionProvider', '')} | {s['threads']} "
                         f"| {s['speedup_p50']:.2f}x ({s['speedup_best']:.2f}x) |")  # fmt: skip
    for v, why in result["variants_skipped"].items():
        lines.append(f"variant {v}: not timed ({why})")
    ratio = result["ratios"]
    lines += ["", "Ratios (p50): " + ", ".join(f"{k} {v}" for k, v in ratio.items()), ""]
    lines += ["| target | measured | target | result |", "|---|---:|---:|---|"]
    for t in result["targets"]:
        measured = "-" if t["measured"] is None else f"{t['measured']:.3f} {t['unit']}"
        status = t["status"] + (f" ({t['why_skipped']})" if t["status"] == "SKIP" else "")
        lines.append(f"| {t['name']} | {measured} | <= {t['target']:g} {t['unit']} | {status} |")
    if "pinning" in sitl:
        lines.append(f"\nSITL: level {sitl['level']} seed {sitl['seed']}; {sitl['pinning']['note']}")
    for variant, flight in _flown(sitl).items():
        lines.append(f"SITL flight {variant}: {flight['outcome']}, {flight['steps']} steps, log {flight['log']}")
    lines += [f"WARNING: {w}" for w in result["warnings"]]
    return "\n".join(lines)
