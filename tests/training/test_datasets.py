"""Datasets: our generator writes TartanAir V1; one loader reads V1 and V2; splits by trajectory."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from training.data.generate import DatasetSpec, generate_dataset
from training.data.tartanair import (
    SPLITS,
    DatasetError,
    GrayDepthDataset,
    assign_splits,
    find_samples,
    read_depth_m,
    split_samples,
    v1_paths,
    write_v2_depth_png,
)


def _write_v1(root, env="office", trajectories=3, frames=2):
    rng = np.random.default_rng(0)
    for p in range(trajectories):
        for i in range(frames):
            image_path, depth_path = v1_paths(root, env, "Hard", p, i)
            image_path.parent.mkdir(parents=True, exist_ok=True)
            depth_path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(image_path), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))  # RGB, as TartanAir
            np.save(depth_path, rng.uniform(0.5, 30.0, (48, 64)).astype(np.float32))


def _write_v2(root, env="hospital", trajectories=3, frames=2):
    rng = np.random.default_rng(1)
    depths = {}
    for p in range(trajectories):
        base = root / env / "Data_easy" / f"P{p:03d}"
        for i in range(frames):
            (base / "image_lcam_front").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(base / "image_lcam_front" / f"{i:06d}_lcam_front.png"), rng.integers(0, 256, (40, 40, 3), dtype=np.uint8))
            depth = rng.uniform(0.5, 12.0, (40, 40)).astype(np.float32)
            write_v2_depth_png(base / "depth_lcam_front" / f"{i:06d}_lcam_front_depth.png", depth)
            depths[(p, i)] = depth
    return depths


def test_v1_and_v2_are_read_by_one_loader(tmp_path):
    _write_v1(tmp_path)
    depths = _write_v2(tmp_path)
    samples = find_samples(tmp_path)
    assert {s.layout for s in samples} == {"v1", "v2"} and len(samples) == 12
    v2 = next(s for s in samples if s.layout == "v2" and s.trajectory.endswith("P001") and s.image_path.name.startswith("000000"))
    np.testing.assert_array_equal(read_depth_m(v2.depth_path, "v2"), depths[(1, 0)])
    dataset = GrayDepthDataset(tmp_path, "train")
    gray, depth = dataset[0]
    assert gray.shape == depth.shape == (1, 224, 224)
    assert 0 <= float(gray.min()) and float(depth.max()) <= 1.0


def test_splits_are_by_trajectory_and_cover_everything(tmp_path):
    _write_v1(tmp_path, trajectories=12, frames=3)
    samples = find_samples(tmp_path)
    parts = {split: split_samples(samples, split) for split in SPLITS}
    assert sum(len(p) for p in parts.values()) == len(samples)
    trajectories = {split: {s.trajectory for s in p} for split, p in parts.items()}
    assert all(trajectories[a].isdisjoint(trajectories[b]) for a in SPLITS for b in SPLITS if a < b)
    assert all(trajectories[split] for split in SPLITS)
    # Deterministic and independent of listing order.
    names = [f"e/Easy/P{i:03d}" for i in range(20)]
    assert assign_splits(names) == assign_splits(list(reversed(names)))


def test_missing_and_corrupt_inputs_are_named(tmp_path):
    with pytest.raises(DatasetError, match="not found: create one with `cmnav dataset"):
        find_samples(tmp_path / "nope")
    with pytest.raises(DatasetError, match="no gray/depth pairs"):
        find_samples(tmp_path)
    _write_v1(tmp_path, trajectories=3, frames=1)
    sample = find_samples(tmp_path)[0]
    sample.depth_path.write_bytes(b"not a numpy file")
    with pytest.raises(DatasetError, match="cannot read depth"):
        read_depth_m(sample.depth_path, "v1")


def test_generated_dataset_is_tartanair_v1_and_deterministic(tmp_path):
    spec = DatasetSpec(count=12, seed=3, levels=(0, 6), frames_per_room=4)
    manifest = generate_dataset(tmp_path / "a", spec)
    generate_dataset(tmp_path / "b", spec)
    assert manifest["frames"] == 12 and manifest["rooms"] == 3
    samples = find_samples(tmp_path / "a")
    assert len(samples) == 12 and all(s.layout == "v1" for s in samples)
    assert {s.trajectory.split("/")[0][:7] for s in samples} == {"sim_L00", "sim_L06"}
    for s in samples:
        other = tmp_path / "b" / s.depth_path.relative_to(tmp_path / "a")
        np.testing.assert_array_equal(np.load(s.depth_path), np.load(other))
        gray = cv2.imread(str(s.image_path), cv2.IMREAD_UNCHANGED)
        assert gray.dtype == np.uint8 and gray.ndim == 2 and gray.std() > 5  # textured, not flat
        depth = np.load(s.depth_path)
        assert depth.dtype == np.float32 and np.all(depth > 0.05)


def test_cli(tmp_path):
    out = tmp_path / "ds"
    subprocess.run([sys.executable, "-m", "cmnav", "dataset", "--out", str(out), "--count", "5", "--seed", "1",
                    "--levels", "0", "3", "--frames-per-room", "5"], check=True, capture_output=True)  # fmt: skip
    assert json.loads((out / "manifest.json").read_text())["frames"] == 5
    assert len(find_samples(out)) == 5
