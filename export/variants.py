"""The exported model's variants and where they are written (torch-free, so ``cmnav bench
runtime`` finds them on a machine without torch, e.g. the Jetson)."""

from __future__ import annotations

from pathlib import Path

VARIANTS = ("fp16", "int8")


def variant_path(path: str | Path, variant: str) -> Path:
    """Where a variant of ``path`` is written: ``model.onnx`` -> ``model.fp16.onnx``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.{variant}{path.suffix or '.onnx'}")
