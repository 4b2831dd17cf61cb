"""`cmnav dataset --depth stereo` stores the simulated D455's depth beside the clean depth, and
`cmnav train cmwae --scheme stereo` trains on it (gray + stereo depth -> clean depth)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from runtime.contract.images import preprocess_depth
from training.checkpoint import read_card
from training.cmwae.train import _corrupt
from training.data.generate import DatasetSpec, generate_dataset
from training.data.tartanair import DatasetError, GrayDepthDataset, GrayDepthStereoDataset, find_samples, stereo_depth_path

pytestmark = pytest.mark.timeout(300)


def _cmnav(*args, ok=True):
    proc = subprocess.run([sys.executable, "-m", "cmnav", *args], capture_output=True, text=True, timeout=280)
    assert (proc.returncode == 0) == ok, proc.stderr[-3000:]
    return proc


@pytest.fixture(scope="module")
def stereo_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("stereo") / "data"
    proc = _cmnav("dataset", "--out", str(out), "--count", "12", "--seed", "2", "--levels", "0", "3", "--frames-per-room", "3",
                  "--depth", "stereo", "--stereo-projector-off-fraction", "0.5")  # fmt: skip
    assert "stereo depth" in proc.stdout
    return out


def test_stereo_dataset_stores_the_sensors_depth_beside_the_clean_depth(stereo_dataset):
    manifest = json.loads((stereo_dataset / "manifest.json").read_text())
    assert manifest["spec"]["depth"] == "stereo" and manifest["frames"] == 12
    flags = [on for frames in manifest["stereo"]["projector_on"].values() for on in frames]
    assert len(flags) == 12 and any(flags) and not all(flags)  # both projector states at 50 %
    assert 0.05 < manifest["stereo"]["invalid_depth_frac_mean"] < 0.8
    samples = find_samples(stereo_dataset)
    assert len(samples) == 12
    agree = []
    for sample in samples:
        stereo_m = np.load(stereo_depth_path(sample))
        assert stereo_m.shape == (240, 424) and stereo_m.dtype == np.float32  # the sensor's matching resolution
        clean, stereo = preprocess_depth(np.load(sample.depth_path)), preprocess_depth(stereo_m)
        valid = (stereo > 0) & (clean < 1.0)
        assert 0.05 < 1.0 - float(np.mean(stereo > 0)) < 0.95
        agree.append(float(np.mean(np.abs(stereo - clean)[valid] / clean[valid] < 0.05)))
    assert np.mean(agree) > 0.7  # the stereo depth is the same view's depth, degraded


def test_stereo_dataset_yields_gray_clean_and_stereo_depth(stereo_dataset, tmp_path):
    gray, depth, stereo = GrayDepthStereoDataset(stereo_dataset, "train")[0]
    assert gray.shape == depth.shape == stereo.shape == (1, 224, 224)
    assert float((stereo == 0).float().mean()) > float((depth == 0).float().mean())
    plain = tmp_path / "plain"
    generate_dataset(plain, DatasetSpec(count=6, seed=0, levels=(0,), frames_per_room=2))
    assert len(GrayDepthDataset(plain, "train")[0]) == 2
    with pytest.raises(DatasetError, match="cmnav dataset --depth stereo"):
        GrayDepthStereoDataset(plain, "train")


def test_stereo_scheme_feeds_the_stored_stereo_depth_and_trains(stereo_dataset, tmp_path):
    depth, stereo = torch.rand(3, 1, 8, 8), torch.zeros(3, 1, 8, 8)
    corrupted, was = _corrupt(depth, "stereo", torch.Generator(), stereo)
    assert corrupted is stereo and bool(was.all())
    with pytest.raises(ValueError, match="--depth stereo"):
        _corrupt(depth, "stereo", torch.Generator())

    out = tmp_path / "cmwae"
    _cmnav("train", "cmwae", "--size", "tiny", "--batch-size", "4", "--workers", "0", "--data", str(stereo_dataset),
           "--scheme", "stereo", "--out", str(out), "--steps", "2")  # fmt: skip
    card = read_card(out, "cmwae")
    assert card["step"] == 2 and card["meta"]["train"]["scheme"] == "stereo"
    assert card["meta"]["val/mse_stereo"] > 0.0


def test_stereo_mix_scheme_mixes_stereo_and_clean_bases_under_squares_and_patches(stereo_dataset, tmp_path):
    batch = 600
    depth, stereo = torch.full((batch, 1, 224, 224), 0.5), torch.full((batch, 1, 224, 224), 0.25)
    corrupted, was = _corrupt(depth, "stereo-mix", torch.Generator().manual_seed(0), stereo)
    kept = corrupted != 0.0  # patches hold zero depth, as missing depth does
    base_stereo = (corrupted == 0.25).flatten(1).any(dim=1)
    assert bool(((corrupted == 0.5) | (corrupted == 0.25) | ~kept).all())
    assert 0.4 < float(base_stereo.float().mean()) < 0.6
    lost = 1.0 - kept.flatten(1).float().mean(dim=1)
    patched = lost > 0.0
    assert 0.4 < float(patched.float().mean()) < 0.6  # a quarter squares, a quarter patches
    assert float(lost[patched].max()) <= 0.7 and float(lost[patched].min()) >= 0.15  # a 100 px square is a fifth
    assert torch.equal(was, base_stereo | patched)  # degraded: every stereo image and every patched one, no other
    with pytest.raises(ValueError, match="--depth stereo"):
        _corrupt(depth, "stereo-mix", torch.Generator())
    # --squares-share 1: every overlay is S2's (100 px squares on half the images, none of the small patches).
    corrupted, _ = _corrupt(depth, "stereo-mix", torch.Generator().manual_seed(0), stereo, squares_share=1.0)
    lost = 1.0 - (corrupted != 0.0).flatten(1).float().mean(dim=1)
    assert 0.4 < float((lost > 0.0).float().mean()) < 0.6 and float(lost[lost > 0.0].min()) >= 0.15
    corrupted, _ = _corrupt(depth, "stereo-mix", torch.Generator().manual_seed(0), stereo, squares_share=0.0)
    lost = 1.0 - (corrupted != 0.0).flatten(1).float().mean(dim=1)
    assert 0.4 < float((lost > 0.0).float().mean()) < 0.6 and float(lost[lost > 0.0].max()) <= 0.55  # 1-30 px to 50 %

    out = tmp_path / "cmwae"
    _cmnav("train", "cmwae", "--size", "tiny", "--batch-size", "4", "--workers", "0", "--data", str(stereo_dataset),
           "--scheme", "stereo-mix", "--squares-share", "0.8", "--out", str(out), "--steps", "2")  # fmt: skip
    card = read_card(out, "cmwae")
    assert card["meta"]["val/mse_stereo"] > 0.0 and card["meta"]["train"]["squares_share"] == 0.8
    proc = _cmnav("train", "cmwae", "--data", str(stereo_dataset), "--scheme", "s2", "--squares-share", "0.8",
                  "--out", str(tmp_path / "refused"), "--steps", "2", ok=False)  # fmt: skip
    assert "squares_share applies to scheme 'stereo-mix'" in proc.stderr

    # Table I adds the stored stereo depth as the input, a row per projector state.
    result = json.loads(_cmnav("eval", "cmwae", "--checkpoint", str(out), "--data", str(stereo_dataset), "--split", "train",
                               "--json").stdout.strip().splitlines()[-1])  # fmt: skip
    inputs = [row["input"] for row in result["stereo_rows"]]
    manifest = json.loads((stereo_dataset / "manifest.json").read_text())
    train = GrayDepthStereoDataset(stereo_dataset, "train").samples
    on = sum(manifest["stereo"]["projector_on"][s.trajectory.split("/")[0]][int(s.image_path.name[:6])] for s in train)
    assert {row["input"]: row["images"] for row in result["stereo_rows"]} == {
        k: n for k, n in (("stereo, projector on", on), ("stereo, projector off", len(train) - on)) if n}
    assert all(row["mse_e3"] > 0.0 and row["latent_shift_over_var"] > 0.0 for row in result["stereo_rows"])
    assert all(f"| {name} |" in result["table"] for name in inputs)


def test_cli_refuses_stereo_options_where_they_do_not_apply(tmp_path):
    proc = _cmnav("dataset", "--out", str(tmp_path / "x"), "--count", "2", "--stereo-projector-off-fraction", "0.2", ok=False)
    assert "applies to --depth stereo" in proc.stderr
