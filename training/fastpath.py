"""The CPU's fast paths for torch, chosen by what the CPU supports and proven by a parity check.

On a CPU with AMX or AVX512-BF16, oneDNN runs bf16 convolutions and matrix products natively:
the paper-size encoder in bf16 + channels_last ran 3.4x its fp32 default layout on an AMD EPYC
with AVX512-BF16 (5.8x on an Intel Xeon with AMX).  Elsewhere bf16 is emulated and slower than
fp32, so the choice is made per machine:

- ``auto`` on a CPU with AMX-BF16 or AVX512-BF16: bf16 compute + channels_last;
- ``auto`` on a CPU with AVX2 (oneDNN's blocked kernels): fp32 channels_last;
- ``auto`` on anything else, and on CUDA: plain fp32 (today's behaviour);
- ``fp32`` / ``bf16``: what is asked (bf16 without the CPU features runs, emulated, with a warning).

A frozen network runs with bf16 weights (:meth:`FastPath.prepare_frozen`); a trained one keeps
fp32 master weights and computes under autocast (:meth:`FastPath.autocast`), its loss in fp32.
Where bf16 changes a frozen encoder's latent by more than :data:`LATENT_PARITY_BOUND` (relative
to the latent's per-dimension spread), :func:`check_latent_parity` refuses it.

The runtime never imports this: it runs ONNX.
"""

from __future__ import annotations

import contextlib
import copy
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor, nn

log = logging.getLogger(__name__)

PRECISIONS = ("auto", "fp32", "bf16")
BF16_FLAGS = ("amx_bf16", "avx512_bf16")
CHANNELS_LAST_FLAGS = ("avx2",)
# bf16 keeps 8 significant bits.  On the committed S2 encoder and 3 x 64 rendered frames (levels 0,
# 5, 15) its latent error was at most 0.019 (RMS 0.0025) of a dimension's std, and the default
# policy's action moved by at most 0.005: the bounds leave 5-10x room above that.  Beyond them the
# network is not the one that was trained.
LATENT_PARITY_BOUND = {"max": 0.1, "rms": 0.02}
ACTION_PARITY_BOUND = 0.03  # max |action_bf16 - action_fp32| over a batch, actions in [-1, 1]


def read_cpu_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> frozenset[str]:
    """The CPU's feature flags as Linux lists them (empty where /proc/cpuinfo is absent)."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return frozenset()
    for line in text.splitlines():
        if line.startswith("flags") and ":" in line:
            return frozenset(line.split(":", 1)[1].split())
    return frozenset()


@dataclass(frozen=True)
class FastPath:
    """What a torch network computes in: ``dtype`` (float32 or bfloat16) and memory layout."""

    dtype: torch.dtype
    channels_last: bool
    reason: str

    @property
    def bf16(self) -> bool:
        return self.dtype == torch.bfloat16

    @property
    def name(self) -> str:
        return ("bf16" if self.bf16 else "fp32") + (" channels_last" if self.channels_last else "")

    def autocast(self, device: torch.device | str) -> contextlib.AbstractContextManager:
        """Autocast to bf16 for a trained network (fp32 master weights); a no-op in fp32."""
        if not self.bf16:
            return contextlib.nullcontext()
        return torch.autocast(torch.device(device).type, dtype=torch.bfloat16)

    def prepare_trained(self, module: nn.Module) -> nn.Module:
        """A network that trains: fp32 weights, in channels_last where chosen (in place)."""
        return module.to(memory_format=torch.channels_last) if self.channels_last else module

    def prepare_frozen(self, module: nn.Module) -> nn.Module:
        """A copy of a frozen network in this path's dtype and layout (the original is untouched)."""
        fast = copy.deepcopy(module).eval()
        if self.channels_last:
            fast = fast.to(memory_format=torch.channels_last)
        return fast.to(self.dtype)

    def image(self, x: Tensor) -> Tensor:
        """An image batch [B, C, H, W] in this path's layout (dtype unchanged: autocast or the
        frozen wrapper casts)."""
        return x.contiguous(memory_format=torch.channels_last) if self.channels_last else x


def choose_fast_path(precision: str = "auto", device: torch.device | str = "cpu",
                     cpu_flags: frozenset[str] | None = None) -> FastPath:  # fmt: skip
    """The fast path for ``precision`` on ``device``; ``cpu_flags`` defaults to this CPU's
    (injectable, so that tests choose for CPUs they do not run on).  Logs the choice and why."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision={precision!r} must be one of {PRECISIONS}")
    device = torch.device(device)
    flags = read_cpu_flags() if cpu_flags is None else cpu_flags
    has_bf16 = [f for f in BF16_FLAGS if f in flags]
    has_avx2 = all(f in flags for f in CHANNELS_LAST_FLAGS)
    if device.type != "cpu":
        path = (FastPath(torch.bfloat16, False, f"--precision bf16 on {device.type}") if precision == "bf16"
                else FastPath(torch.float32, False, f"{device.type}: fp32 unless --precision bf16"))  # fmt: skip
    elif precision == "fp32":
        path = FastPath(torch.float32, has_avx2, "--precision fp32" + (", channels_last on AVX2" if has_avx2 else ""))
    elif precision == "bf16":
        why = f"--precision bf16 ({', '.join(has_bf16)})" if has_bf16 else "--precision bf16 on a CPU without AMX/AVX512-BF16 (emulated: slower than fp32)"
        path = FastPath(torch.bfloat16, True, why)
        if not has_bf16:
            log.warning("%s", why)
    elif has_bf16:
        path = FastPath(torch.bfloat16, True, f"CPU has {', '.join(has_bf16)}")
    elif has_avx2:
        path = FastPath(torch.float32, True, "CPU has AVX2 but no AMX/AVX512-BF16: fp32 channels_last")
    else:
        path = FastPath(torch.float32, False, "CPU has neither AVX2 nor AMX/AVX512-BF16: plain fp32")
    log.info("fast path: %s (%s)", path.name, path.reason)
    return path


class FrozenEncoder(nn.Module):
    """A frozen (gray, depth) -> latent encoder on a fast path: inputs cast to the path's dtype
    and layout, the latent returned in fp32."""

    def __init__(self, encoder: nn.Module, path: FastPath) -> None:
        super().__init__()
        self.path = path
        self.inner = path.prepare_frozen(encoder)
        for p in self.inner.parameters():
            p.requires_grad_(False)

    def forward(self, gray: Tensor, depth: Tensor) -> Tensor:
        cast = lambda x: self.path.image(x).to(self.path.dtype)  # noqa: E731
        return self.inner(cast(gray), cast(depth)).float()


@dataclass(frozen=True)
class LatentParity:
    """Errors of a fast encoder's latent against fp32, relative to fp32's per-dimension std."""

    max_rel: float
    rms_rel: float
    images: int

    @property
    def within_bound(self) -> bool:
        return self.max_rel <= LATENT_PARITY_BOUND["max"] and self.rms_rel <= LATENT_PARITY_BOUND["rms"]

    def to_json(self) -> dict:
        return {"max_rel": self.max_rel, "rms_rel": self.rms_rel, "images": self.images,
                "bound": LATENT_PARITY_BOUND, "within_bound": self.within_bound}  # fmt: skip


@torch.inference_mode()
def latent_parity(reference: nn.Module, fast: nn.Module, gray: Tensor, depth: Tensor,
                  latent_std: Tensor | None = None) -> LatentParity:  # fmt: skip
    """Compare ``fast`` against the fp32 ``reference`` on (gray, depth) [B, 1, 224, 224].  The
    errors are divided by ``latent_std`` [64] (default: the reference latent's std over the batch)."""
    ref = reference.eval()(gray.float(), depth.float()).float()
    out = fast(gray, depth).float()
    std = (ref.std(dim=0) if latent_std is None else latent_std).clamp_min(1e-6)
    rel = (out - ref) / std
    return LatentParity(float(rel.abs().max()), float(rel.square().mean().sqrt()), int(gray.shape[0]))


class ParityError(RuntimeError):
    """A fast path changed a network's output beyond its bound."""


def check_latent_parity(reference: nn.Module, fast: nn.Module, gray: Tensor, depth: Tensor,
                        latent_std: Tensor | None = None) -> LatentParity:  # fmt: skip
    """:func:`latent_parity`, raising :class:`ParityError` beyond :data:`LATENT_PARITY_BOUND`."""
    parity = latent_parity(reference, fast, gray, depth, latent_std)
    if not parity.within_bound:
        raise ParityError(
            f"the bf16 encoder's latent differs from fp32 by max {parity.max_rel:.3f} / RMS {parity.rms_rel:.3f} "
            f"of the latent's std on {parity.images} images (bound: max {LATENT_PARITY_BOUND['max']}, RMS "
            f"{LATENT_PARITY_BOUND['rms']}): this network is not safe in bf16; run with --precision fp32"
        )
    return parity


def check_action_parity(action_fp32: Tensor, action_fast: Tensor) -> float:
    """The largest action difference [-1, 1] units that a fast encoder's latent causes;
    :class:`ParityError` beyond :data:`ACTION_PARITY_BOUND`."""
    error = float((action_fast.float() - action_fp32.float()).abs().max())
    if not error <= ACTION_PARITY_BOUND:
        raise ParityError(f"with the bf16 encoder's latent the policy's action moves by {error:.4f} (bound "
                          f"{ACTION_PARITY_BOUND}): run with --precision fp32")  # fmt: skip
    return error


def frozen_encoder(encoder: nn.Module, precision: str, device: torch.device | str,
                   parity_inputs: Callable[[], tuple[Tensor, Tensor]], cpu_flags: frozenset[str] | None = None) -> nn.Module:  # fmt: skip
    """The frozen ``encoder`` on the fast path ``precision`` chooses: unchanged in fp32 default
    layout, else a :class:`FrozenEncoder`.  In bf16 the latent's parity against fp32 is checked
    first on ``parity_inputs()`` (a (gray, depth) batch of real frames): beyond the bound, an
    explicit ``bf16`` is refused (:class:`ParityError`) and ``auto`` falls back to fp32."""
    path = choose_fast_path(precision, device, cpu_flags)
    if path.bf16:
        fast = FrozenEncoder(encoder, path)
        gray, depth = parity_inputs()
        try:
            parity = check_latent_parity(encoder, fast, gray, depth)
        except ParityError as err:
            if precision == "bf16":
                raise
            log.warning("%s; auto falls back to fp32", err)
            path = FastPath(torch.float32, path.channels_last, "bf16 refused by the parity bound")
        else:
            log.info("bf16 encoder parity on %d frames: max %.3f, RMS %.4f of the latent std", parity.images,
                     parity.max_rel, parity.rms_rel)  # fmt: skip
            return fast
    return FrozenEncoder(encoder, path) if path.channels_last else encoder
