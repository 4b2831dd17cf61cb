"""Gray/depth pairs on disk in the TartanAir layouts, with splits by trajectory.

V1: ``ENV/{Easy,Hard}/P000/image_left/000000_left.png`` and
    ``ENV/{Easy,Hard}/P000/depth_left/000000_left_depth.npy`` (float32 metres).
V2: ``ENV/Data_{easy,hard}/P000/image_lcam_front/000000_lcam_front.png`` and
    ``ENV/Data_{easy,hard}/P000/depth_lcam_front/000000_lcam_front_depth.png`` (float32 metres
    stored as the bytes of a 4-channel uint8 PNG).

``cmnav dataset`` writes the V1 layout, so one loader reads ours and TartanAir's.  Images go
through the contract's preprocessing (runtime.contract.images), exactly as in flight.  Without
OpenCV (the offline GPU machine) PNGs are read by ``pngio``'s numpy reader and preprocessed by the
contract's torch twin (``sim.preprocess_torch``, as the RL env does): gray within one level (1/255)
of the contract's, depth equal except where an output pixel centre falls exactly between two source
pixels (input sides that are multiples of 64 px, e.g. TartanAir's 640 px width), and the colour to
gray conversion bit-exact.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from runtime.contract.images import gray_from_bgr, preprocess_depth, preprocess_gray
from sim.preprocess_torch import preprocess_depth_batch, preprocess_gray_batch

from .pngio import PngError, opencv, read_png, write_png

SPLITS = ("train", "val", "test")


class DatasetError(ValueError):
    """A dataset folder or file is missing or unreadable; the message names it and the fix."""


@dataclass(frozen=True)
class Sample:
    image_path: Path
    depth_path: Path
    layout: str  # "v1" | "v2"
    trajectory: str  # "ENV/Easy/P000"


@dataclass(frozen=True)
class _Layout:
    name: str
    difficulty_glob: str
    image_dir: str
    depth_dir: str
    image_suffix: str
    depth_suffix: str


V1 = _Layout("v1", "[EH][a-z]*", "image_left", "depth_left", "_left.png", "_left_depth.npy")
V2 = _Layout("v2", "Data_*", "image_lcam_front", "depth_lcam_front", "_lcam_front.png", "_lcam_front_depth.png")


def v1_paths(root: Path, env: str, difficulty: str, trajectory: int, index: int) -> tuple[Path, Path]:
    """Where sample ``index`` of a V1 trajectory lives (used by the writer and the tests)."""
    base = root / env / difficulty / f"P{trajectory:03d}"
    return base / V1.image_dir / f"{index:06d}{V1.image_suffix}", base / V1.depth_dir / f"{index:06d}{V1.depth_suffix}"


# `cmnav dataset --depth stereo` stores the simulated D455's depth of each frame beside the clean
# one (V1 layout only): ENV/Easy/P000/depth_stereo/000000_stereo_depth.npy, float32 metres at the
# sensor's matching resolution, 0 = invalid.
STEREO_DEPTH_DIR = "depth_stereo"
STEREO_DEPTH_SUFFIX = "_stereo_depth.npy"


def _v1_frame(sample: Sample) -> str:
    """A V1 sample's frame name ("000000")."""
    return sample.image_path.name[: -len(V1.image_suffix)]


def stereo_depth_path(sample: Sample) -> Path:
    """Where the stereo depth of a V1 sample lives (it may not exist)."""
    return sample.image_path.parent.parent / STEREO_DEPTH_DIR / f"{_v1_frame(sample)}{STEREO_DEPTH_SUFFIX}"


def stereo_projector_on(root: str | Path, samples: list[Sample]) -> list[bool]:
    """Whether the IR projector was on for each sample's stereo depth, as the manifest of a
    `cmnav dataset --depth stereo` dataset records it per room (the trajectory's ENV) and frame."""
    projector = json.loads((Path(root) / "manifest.json").read_text())["stereo"]["projector_on"]
    return [projector[s.trajectory.split("/")[0]][int(_v1_frame(s))] for s in samples]


def find_samples(root: str | Path) -> list[Sample]:
    """Every gray/depth pair under ``root`` in either layout, sorted by trajectory and frame."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"dataset folder {root} not found: create one with `cmnav dataset --out {root} ...`")
    samples = []
    for layout in (V1, V2):
        for traj_dir in sorted(root.glob(f"*/{layout.difficulty_glob}/P[0-9][0-9][0-9]")):
            image_dir, depth_dir = traj_dir / layout.image_dir, traj_dir / layout.depth_dir
            if not image_dir.is_dir():
                continue
            trajectory = str(traj_dir.relative_to(root))
            for image_path in sorted(image_dir.glob(f"*{layout.image_suffix}")):
                frame = image_path.name[: -len(layout.image_suffix)]
                depth_path = depth_dir / f"{frame}{layout.depth_suffix}"
                if depth_path.is_file():
                    samples.append(Sample(image_path, depth_path, layout.name, trajectory))
    if not samples:
        raise DatasetError(
            f"no gray/depth pairs under {root}: expected the TartanAir V1 layout "
            "(ENV/Easy/P000/image_left/000000_left.png + depth_left/000000_left_depth.npy) or V2 "
            "(ENV/Data_easy/P000/image_lcam_front/... + depth_lcam_front/..._depth.png)"
        )
    return samples


def assign_splits(trajectories: list[str], val_fraction: float = 0.1, test_fraction: float = 0.1) -> dict[str, str]:
    """Trajectory -> split.  Frames of one trajectory never straddle splits.  Trajectories are
    ranked by a hash of their name (deterministic, independent of listing order); the first
    round(test_fraction * n) go to test, the next round(val_fraction * n) to val, each at least
    one when there are three or more trajectories."""
    unique = sorted(set(trajectories), key=lambda t: hashlib.sha256(t.encode()).digest())
    n = len(unique)
    n_test = max(1 if n >= 3 and test_fraction > 0 else 0, round(test_fraction * n))
    n_val = max(1 if n >= 3 and val_fraction > 0 else 0, round(val_fraction * n))
    return {t: "test" if i < n_test else "val" if i < n_test + n_val else "train" for i, t in enumerate(unique)}


def split_samples(samples: list[Sample], split: str, val_fraction: float = 0.1, test_fraction: float = 0.1) -> list[Sample]:
    if split not in SPLITS:
        raise ValueError(f"split={split!r} must be one of {SPLITS}")
    splits = assign_splits([s.trajectory for s in samples], val_fraction, test_fraction)
    return [s for s in samples if splits[s.trajectory] == split]


def read_gray_u8(path: Path) -> np.ndarray:
    try:
        image = read_png(path)
    except PngError as err:
        raise DatasetError(f"{err}; re-generate or remove it") from err
    if image.dtype != np.uint8:
        raise DatasetError(f"image {path} is {image.dtype}, expected 8-bit gray or color")
    if image.ndim == 3 and image.shape[2] == 4:
        image = image[..., :3]
    if image.ndim == 3:
        image = _gray_from_bgr(np.ascontiguousarray(image))
    return image


def _gray_from_bgr(bgr_u8: np.ndarray) -> np.ndarray:
    """The contract's BGR -> gray, or without OpenCV its exact integer equivalent: OpenCV rounds
    the BT.601 weights to 15-bit fixed point (checked equal over all 2^24 colours, OpenCV 5.0)."""
    if opencv() is not None:
        return gray_from_bgr(bgr_u8)
    b, g, r = (bgr_u8[..., i].astype(np.uint32) for i in range(3))
    return ((b * 3735 + g * 19235 + r * 9798 + (1 << 14)) >> 15).astype(np.uint8)


def read_depth_m(path: Path, layout: str) -> np.ndarray:
    try:
        if layout == "v1":
            depth = np.load(path, allow_pickle=False)
        else:
            rgba = read_png(path)
            if rgba.ndim != 3 or rgba.shape[2] != 4 or rgba.dtype != np.uint8:
                raise DatasetError(f"{path} is not a 4-channel 8-bit PNG holding float32 depth (TartanAir V2)")
            depth = np.ascontiguousarray(rgba).view("<f4")[..., 0]
    except (OSError, ValueError) as err:  # PngError is a ValueError
        if isinstance(err, DatasetError):
            raise
        raise DatasetError(f"cannot read depth {path} ({err}); re-generate or remove it") from err
    if depth.ndim != 2:
        raise DatasetError(f"depth {path} has shape {depth.shape}, expected (H, W)")
    return depth.astype(np.float32, copy=False)


def write_v2_depth_png(path: Path, depth_m: np.ndarray) -> None:
    """float32 metres -> TartanAir V2's 4-channel PNG (for tests and conversions)."""
    rgba = np.ascontiguousarray(depth_m.astype("<f4")).view(np.uint8).reshape(*depth_m.shape, 4)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_png(path, rgba)


class GrayDepthDataset(Dataset):
    """Preprocessed (gray [1, 224, 224], depth [1, 224, 224]) float32 tensors of one split."""

    def __init__(self, root: str | Path, split: str = "train", val_fraction: float = 0.1, test_fraction: float = 0.1) -> None:
        self.samples = split_samples(find_samples(root), split, val_fraction, test_fraction)
        if not self.samples:
            raise DatasetError(
                f"the {split!r} split of {root} is empty: it needs more trajectories "
                f"(splits are by trajectory: val {val_fraction:.0%}, test {test_fraction:.0%})"
            )

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        sample = self.samples[i]
        gray_u8, depth_m = read_gray_u8(sample.image_path), read_depth_m(sample.depth_path, sample.layout)
        if opencv() is None:  # the contract's functions resize with cv2; its torch twin does not
            return preprocess_gray_batch(torch.from_numpy(gray_u8)[None]), preprocess_depth_batch(torch.from_numpy(depth_m)[None])
        return torch.from_numpy(preprocess_gray(gray_u8)).unsqueeze(0), torch.from_numpy(preprocess_depth(depth_m)).unsqueeze(0)


class GrayDepthStereoDataset(GrayDepthDataset):
    """Preprocessed (gray, clean depth, stereo depth) [1, 224, 224] float32 triples of one split
    of a `cmnav dataset --depth stereo` dataset: the stereo depth is the degraded input, the clean
    rendered depth the target."""

    def __init__(self, root: str | Path, split: str = "train", val_fraction: float = 0.1, test_fraction: float = 0.1) -> None:
        super().__init__(root, split, val_fraction, test_fraction)
        missing = next((s for s in self.samples if s.layout != "v1" or not stereo_depth_path(s).is_file()), None)
        if missing is not None:
            raise DatasetError(
                f"{root} has no stereo depth for {missing.image_path} (expected {stereo_depth_path(missing)}): "
                f"render the dataset with `cmnav dataset --depth stereo --out {root} ...`"
            )

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        gray, depth = super().__getitem__(i)
        stereo_m = read_depth_m(stereo_depth_path(self.samples[i]), "v1")
        if opencv() is None:
            return gray, depth, preprocess_depth_batch(torch.from_numpy(stereo_m)[None])
        return gray, depth, torch.from_numpy(preprocess_depth(stereo_m)).unsqueeze(0)
