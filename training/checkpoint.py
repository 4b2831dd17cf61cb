"""Checkpoints: a full training state for resume, and the network alone as fp16 shards of at most
15 MiB each (small enough to commit and to bring back from the GPU machine) with a JSON card.

Layout of a checkpoint directory:
  model.json            {"kind", "config", "step", "meta", "shards": [...]}
  weights-000.pt ...    fp16 (float tensors) state-dict shards, each <= MAX_SHARD_BYTES
  train_state.pt        optimizer, step, RNG states, fp32 weights (resume only; a committed model keeps it so --resume continues it)
  checkpoints/step-N/   with --keep-checkpoints: model.json and shards of each checkpoint kept
"""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path
from typing import Any

import torch
from torch import nn

MAX_SHARD_BYTES = 15 * 1024 * 1024
MODEL_CARD = "model.json"
KEPT_CHECKPOINTS = "checkpoints"  # under a run's out dir: one checkpoint directory per step kept
TRAIN_STATE = "train_state.pt"


class CheckpointError(ValueError):
    """A checkpoint is missing, incomplete, or of another kind; the message says which file."""


def _tensor_bytes(t: torch.Tensor) -> int:
    return t.numel() * t.element_size()


def save_weights(out_dir: str | Path, model: nn.Module, kind: str, config: dict, step: int, meta: dict | None = None) -> Path:
    """Write model.json and fp16 weight shards (replacing older shards)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("weights-*.pt"):
        old.unlink()
    state = {k: (v.detach().half() if v.is_floating_point() else v.detach()).cpu().contiguous() for k, v in model.state_dict().items()}
    shards: list[dict[str, torch.Tensor]] = [{}]
    size = 0
    for name, tensor in state.items():
        if _tensor_bytes(tensor) > MAX_SHARD_BYTES:
            raise CheckpointError(f"tensor {name} alone is {_tensor_bytes(tensor)} bytes, over the {MAX_SHARD_BYTES}-byte shard limit")
        if size + _tensor_bytes(tensor) > MAX_SHARD_BYTES and shards[-1]:
            shards.append({})
            size = 0
        shards[-1][name] = tensor
        size += _tensor_bytes(tensor)
    names = []
    for i, shard in enumerate(shards):
        name = f"weights-{i:03d}.pt"
        torch.save(shard, out / name)
        names.append(name)
    card = {"kind": kind, "config": config, "step": step, "meta": meta or {}, "shards": names, "dtype": "float16"}
    (out / MODEL_CARD).write_text(json.dumps(card, indent=2, sort_keys=True))
    return out / MODEL_CARD


def read_card(ckpt_dir: str | Path, kind: str | None = None) -> dict[str, Any]:
    path = Path(ckpt_dir) / MODEL_CARD
    if not path.is_file():
        raise CheckpointError(f"{path} not found: {ckpt_dir} is not a cmnav checkpoint directory (train one with `cmnav train`)")
    card = json.loads(path.read_text())
    if kind is not None and card.get("kind") != kind:
        raise CheckpointError(f"{ckpt_dir} holds a {card.get('kind')!r} checkpoint, expected {kind!r}")
    return card


def load_weights(ckpt_dir: str | Path, model: nn.Module) -> dict[str, Any]:
    """Load the fp16 shards into ``model`` (cast to its dtype); returns the card."""
    card = read_card(ckpt_dir)
    state: dict[str, torch.Tensor] = {}
    for name in card["shards"]:
        path = Path(ckpt_dir) / name
        if not path.is_file():
            raise CheckpointError(f"weight shard {path} is missing: copy the whole checkpoint directory")
        state.update(torch.load(path, map_location="cpu", weights_only=True))
    reference = model.state_dict()
    state = {k: v.to(reference[k].dtype) if k in reference else v for k, v in state.items()}
    model.load_state_dict(state)
    return card


def keep_checkpoint(out_dir: str | Path) -> Path:
    """Copy the card and weight shards :func:`save_weights` last wrote in ``out_dir`` to
    ``out_dir/checkpoints/step-NNNNNNNNNN`` (its step): a checkpoint directory of its own, without
    the train state, that later saves do not overwrite, so the weights an evaluation chose stay."""
    card = read_card(out_dir)
    kept = Path(out_dir) / KEPT_CHECKPOINTS / f"step-{card['step']:010d}"
    kept.mkdir(parents=True, exist_ok=True)
    for name in [*card["shards"], MODEL_CARD]:  # the card last: a directory with a card is whole
        shutil.copy2(Path(out_dir) / name, kept / name)
    return kept


def save_train_state(out_dir: str | Path, state: dict[str, Any]) -> None:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    tmp = Path(out_dir) / (TRAIN_STATE + ".tmp")
    tmp.write_bytes(buffer.getvalue())
    tmp.replace(Path(out_dir) / TRAIN_STATE)  # atomic: a killed run never leaves half a state


def load_train_state(ckpt_dir: str | Path) -> dict[str, Any] | None:
    path = Path(ckpt_dir) / TRAIN_STATE
    if not path.is_file():
        return None
    return torch.load(path, map_location="cpu", weights_only=False)


def checkpoint_fingerprint(ckpt_dir: str | Path) -> str:
    """SHA-256 (hex, first 16 digits) of a checkpoint's network: its config and weight shards, not
    its step or meta, so a policy can name the exact encoder it was trained on."""
    import hashlib

    card = read_card(ckpt_dir)
    digest = hashlib.sha256(json.dumps({"kind": card["kind"], "config": card["config"]}, sort_keys=True).encode())
    for name in card["shards"]:
        path = Path(ckpt_dir) / name
        if not path.is_file():
            raise CheckpointError(f"weight shard {path} is missing: copy the whole checkpoint directory")
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]
