"""The device helpers the torch benchmarks share: wait for queued GPU work before reading a
clock, and name the device in a result."""

from __future__ import annotations

import torch


def synchronize(device: str | torch.device) -> None:
    """Wait until ``device`` has finished its queued work (a no-op on the CPU)."""
    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def device_name(device: str | torch.device) -> str:
    """'cpu', or 'cuda (<GPU name>)'."""
    device = torch.device(device)
    return f"cuda ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else "cpu"
