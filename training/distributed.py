"""torch.distributed set-up for `torchrun` (one process per GPU; gloo on CPU for tests)."""

from __future__ import annotations

import hashlib
import logging
import os
import time
from dataclasses import dataclass
from typing import Callable, TypeVar

import torch
import torch.distributed as dist

T = TypeVar("T")
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DistInfo:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1


def init_distributed(device: str) -> tuple[DistInfo, torch.device]:
    """Join the process group torchrun describes (env RANK/WORLD_SIZE/LOCAL_RANK), if any, and
    pick this process's device (cuda:LOCAL_RANK under torchrun with CUDA)."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    info = DistInfo(int(os.environ.get("RANK", "0")), world_size, int(os.environ.get("LOCAL_RANK", "0")))
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError("--device cuda but torch sees no CUDA device: use --device cpu or check the driver")
    if info.enabled and not dist.is_initialized():
        dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")
    if device.startswith("cuda"):
        torch.cuda.set_device(info.local_rank)
        return info, torch.device("cuda", info.local_rank)
    return info, torch.device(device)


def all_reduce_mean(value: torch.Tensor, info: DistInfo) -> torch.Tensor:
    if info.enabled:
        value = value.clone()
        dist.all_reduce(value, op=dist.ReduceOp.SUM)
        value /= info.world_size
    return value


def wall_budget_spent(max_wall_s: float | None, t_start: float, info: DistInfo, device: torch.device) -> bool:
    """True once ``max_wall_s`` seconds have passed since ``t_start`` (time.monotonic) on any
    process, so that every process stops at the same step."""
    if max_wall_s is None:
        return False
    over = torch.tensor([1.0 if time.monotonic() - t_start >= max_wall_s else 0.0], device=device)
    return bool(all_reduce_mean(over, info) > 0)


def run_distributed(device: str, train: Callable[[DistInfo, torch.device], T]) -> T:
    """``train(info, device)`` inside the process group torchrun describes (if any), left after."""
    info, torch_device = init_distributed(device)
    try:
        return train(info, torch_device)
    finally:
        shutdown(info)


def shutdown(info: DistInfo) -> None:
    if info.enabled and dist.is_initialized():
        dist.destroy_process_group()


def log_weights_digest(model: torch.nn.Module, info: DistInfo) -> str:
    """Log (on every process) and return a SHA-256 of the network's weights: under torchrun every
    rank must end with the same digest, or the processes trained different networks."""
    digest = hashlib.sha256()
    for name, tensor in model.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().float().cpu().contiguous().numpy().tobytes())
    hexdigest = digest.hexdigest()[:16]
    log.info("rank %d of %d: final weights sha256 %s", info.rank, info.world_size, hexdigest)
    return hexdigest
