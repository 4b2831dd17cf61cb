"""`cmnav train cmwae` and `cmnav eval cmwae` for a few steps on tiny data the test generates."""

import dataclasses
import json
import os
import subprocess
import sys

import pytest
import torch

from training.checkpoint import MAX_SHARD_BYTES, load_train_state, read_card, save_weights
from training.cmwae.loss import TEACHER_GRID, cmwae_loss, hidden_pixels, near_surface_mask, nearest_per_cell, pooled_nearest_error
from training.cmwae.model import Cmwae, make_config
from training.cmwae.train import CmwaeTrainConfig, _pixel_weights, learning_rate, load_cmwae
from sim.degradation import SCHEMES, PatchScheme, corrupt_depth, corrupt_with_scheme, patch_masks
from training.data.generate import DatasetSpec, generate_dataset
from training.data.tartanair import GrayDepthDataset
from tests.training.test_fastpath import torchrun_digests

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    generate_dataset(root, DatasetSpec(count=40, seed=0, levels=(0, 6), frames_per_room=4))
    return root


def _cmnav(*args):
    proc = subprocess.run([sys.executable, "-m", "cmnav", *args], capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


TRAIN = ["train", "cmwae", "--size", "tiny", "--batch-size", "4", "--workers", "0", "--checkpoint-every", "2"]


def test_train_checkpoint_resume_and_eval(dataset, tmp_path):
    out = tmp_path / "s2"
    _cmnav(*TRAIN, "--data", str(dataset), "--scheme", "s2", "--out", str(out), "--steps", "3")
    card = read_card(out, "cmwae")
    assert card["step"] == 3 and card["meta"]["train"]["scheme"] == "s2"
    assert all((out / shard).stat().st_size <= MAX_SHARD_BYTES for shard in card["shards"])
    assert list((out / "tensorboard").glob("events.out.tfevents.*"))
    first = {k: v.clone() for k, v in load_cmwae(out)[0].state_dict().items()}

    _cmnav(*TRAIN, "--data", str(dataset), "--scheme", "s2", "--out", str(out), "--steps", "5", "--resume")
    assert read_card(out, "cmwae")["step"] == 5 and load_train_state(out)["step"] == 5
    # the validation curve: a point per checkpoint (2, 3; the resumed run's 4, 5), drawn against the step
    curve = json.loads((out / "val_curve.json").read_text())
    assert [p["step"] for p in curve] == [2, 3, 4, 5]
    assert all(p["ratio_50_over_0"] == pytest.approx(p["mse_50pct"] / p["mse_0pct"]) for p in curve)
    assert (out / "val_curve.png").stat().st_size > 1000
    resumed = load_cmwae(out)[0].state_dict()
    assert any(not torch.equal(first[k], resumed[k]) for k in first)

    stdout = _cmnav("eval", "cmwae", "--checkpoint", str(out), "--data", str(dataset), "--max-images", "3", "--json")
    result = json.loads(stdout.strip().splitlines()[-1])
    assert [r["corruption_pct"] for r in result["rows"]] == [0, 20, 30, 40, 50]
    assert all(r["images"] == 3 for r in result["rows"])
    assert all(0 < r["mse_e3"] for r in result["rows"]) and all(-100 <= r["ssim_e2"] <= 100 for r in result["rows"])
    assert result["rows"][4]["actual_coverage_pct"] >= 50.0
    assert "| 50% |" in result["table"]
    for plot in result["plots"].values():
        assert os.path.getsize(plot) > 1000
    assert result["patch_sides_px"] == [1, 50]
    # the near-surface column: below 1000 m every pixel of these closed rooms is near, so it is the
    # whole-frame MSE; below 1 cm none is
    for near_m, expected in (("1000", [r["mse_e3"] for r in result["rows"]]), ("0.01", [None] * 5)):
        stdout = _cmnav("eval", "cmwae", "--checkpoint", str(out), "--data", str(dataset), "--max-images", "3",
                        "--near-m", near_m, "--out", str(tmp_path / f"near{near_m}"), "--json")  # fmt: skip
        near = json.loads(stdout.strip().splitlines()[-1])
        got = [r["near_mse_e3"] for r in near["rows"]]
        assert got == expected if expected[0] is None else got == pytest.approx(expected, rel=1e-3)
        assert [r["near_images"] for r in near["rows"]] == [3 if expected[0] else 0] * 5
        assert f"MSE < {float(near_m):g} m" in near["table"]
    assert 0.0 < result["rows"][0]["near_pixels_pct"] < 100.0 and result["near_m"] == 1.5
    # the latent shift: none without corruption, some at 50 %
    assert result["rows"][0]["latent_shift_over_var"] == 0.0 and result["rows"][4]["latent_shift_over_var"] > 0.0
    assert result["latent_var"] > 0.0 and "latent shift / var" in result["table"]
    # the teacher's-view column: nearest surface per cell of the 18 x 32 grid, coarser than the frame
    assert all(0 < r["teacher_view_mse_e3"] for r in result["rows"]) and "teacher's view MSE" in result["table"]

    # S2's own 100 px squares instead of Table I's 1-50 px patches: other masks, same coverages.
    stdout = _cmnav("eval", "cmwae", "--checkpoint", str(out), "--data", str(dataset), "--max-images", "3",
                    "--patch-sides", "100-100", "--out", str(tmp_path / "eval100"), "--json")  # fmt: skip
    squares = json.loads(stdout.strip().splitlines()[-1])
    assert squares["patch_sides_px"] == [100, 100] and "patches of side 100-100 px" in stdout
    assert squares["rows"][0]["mse_e3"] == result["rows"][0]["mse_e3"]  # 0 %: no patches either way
    assert squares["rows"][4]["actual_coverage_pct"] >= 50.0
    bad = subprocess.run([sys.executable, "-m", "cmnav", "eval", "cmwae", "--checkpoint", str(out), "--data", str(dataset),
                          "--patch-sides", "0-5"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert bad.returncode == 2 and "patch sides 0..5 px must lie in 1..224" in bad.stderr


def test_learning_rate_schedule_and_minutes_limit(dataset, tmp_path):
    config = CmwaeTrainConfig(data_dir="d", out_dir="o", steps=11, lr=1e-3, lr_final=1e-4)
    rates = [learning_rate(config, step, 11) for step in range(11)]
    assert rates[0] == pytest.approx(1e-3) and rates[-1] == pytest.approx(1e-4) and rates[5] == pytest.approx(5.5e-4)
    assert all(a > b for a, b in zip(rates, rates[1:]))
    assert learning_rate(CmwaeTrainConfig(data_dir="d", out_dir="o", steps=11, lr=3e-4), 7, 11) == 3e-4
    with pytest.raises(ValueError, match="lr_final"):
        CmwaeTrainConfig(data_dir="d", out_dir="o", steps=11, lr=1e-4, lr_final=1e-3).validate()

    out = tmp_path / "lr"
    _cmnav(*TRAIN, "--data", str(dataset), "--out", str(out), "--steps", "3", "--lr", "1e-3")
    assert load_train_state(out)["optimizer"]["param_groups"][0]["lr"] == pytest.approx(1e-3)
    # --resume applies the new rate (the optimizer state alone would keep 1e-3) and decays it to --lr-final.
    _cmnav(*TRAIN, "--data", str(dataset), "--out", str(out), "--steps", "5", "--lr", "5e-4", "--lr-final", "1e-4", "--resume")
    assert load_train_state(out)["optimizer"]["param_groups"][0]["lr"] == pytest.approx(1e-4)

    # --minutes stops early, with a checkpoint.
    _cmnav(*TRAIN, "--data", str(dataset), "--out", str(tmp_path / "short"), "--steps", "500", "--minutes", "0.0001")
    assert 1 <= read_card(tmp_path / "short", "cmwae")["step"] < 500


def test_depth_only_baseline_uses_the_same_command(dataset, tmp_path):
    out = tmp_path / "dce"
    _cmnav(*TRAIN, "--data", str(dataset), "--scheme", "none", "--modalities", "depth", "--out", str(out), "--steps", "2")
    model, card = load_cmwae(out)
    assert tuple(card["config"]["modalities"]) == ("depth",) and "gray" not in model.encoder.features


def test_policy_scheme_corrupts_half_the_images_with_the_policys_patches(dataset, tmp_path):
    out = tmp_path / "policy"
    _cmnav(*TRAIN, "--data", str(dataset), "--scheme", "policy", "--out", str(out), "--steps", "2")
    assert read_card(out, "cmwae")["meta"]["train"]["scheme"] == "policy"
    depth = torch.rand(64, 1, 224, 224) * 0.9 + 0.05
    corrupted, masks = corrupt_with_scheme(depth, SCHEMES["policy"], torch.Generator().manual_seed(0))
    lost, hit = (corrupted == 0).flatten(1).float().mean(dim=1), masks.flatten(1).any(dim=1)
    assert 20 <= int(hit.sum()) <= 44 and torch.all(lost[~hit] == 0)
    assert lost[hit].min() >= 0.2 and lost[hit].max() <= 0.55  # the last patch may overshoot the target a little


def _latent_gap(encoder, base, gray, depth, corrupted) -> float:
    """Mean square distance of ``encoder``'s latent of corrupted depth from ``base``'s of clean depth."""
    with torch.no_grad():
        return float(((encoder(gray, corrupted) - base(gray, depth)) ** 2).mean())


def test_latent_anchoring_pulls_corrupted_latents_to_clean_ones_with_the_decoder_fixed(dataset, tmp_path):
    base_dir, out = tmp_path / "base", tmp_path / "anchored"
    # The anchor: a tiny CMWAE whose latent responds to depth (a tiny one trained a few steps hardly
    # does), so that corruption moves it.  A small MMD weight: the toy's latent is not the prior's.
    torch.manual_seed(0)
    config = make_config("tiny")
    base = Cmwae(config)
    with torch.no_grad():
        base.encoder.features["depth"][0].weight.mul_(3.0)
        base.encoder.embed["depth"][1].weight.mul_(30.0)
    save_weights(base_dir, base, "cmwae", dataclasses.asdict(config), 0, {})
    _cmnav(*TRAIN, "--data", str(dataset), "--scheme", "s2", "--out", str(out), "--steps", "80", "--lr", "1e-3",
           "--anchor", str(base_dir), "--anchor-weight", "20", "--mmd-weight", "0.01", "--precision", "fp32",
           "--val-images", "4")  # fmt: skip
    base, _ = load_cmwae(base_dir)
    anchored, card = load_cmwae(out)
    assert card["meta"]["train"]["anchor_from"] == str(base_dir) and card["meta"]["train"]["anchor_weight"] == 20.0
    assert card["meta"]["train"]["val_images"] == 4 and card["meta"]["val/mse_50pct"] > 0
    # the decoder is the anchor's, bit for bit; the encoder learnt
    for key, value in base.decoder.state_dict().items():
        assert torch.equal(anchored.decoder.state_dict()[key], value), key
    assert any(not torch.equal(anchored.encoder.state_dict()[k], v) for k, v in base.encoder.state_dict().items())
    # On the images it trained on, with squares at 50 % coverage, the latent of corrupted depth came
    # closer to the anchor's latent of the clean pair; the clean latent stayed near the anchor's.
    gray, depth = (torch.stack(t) for t in zip(*[GrayDepthDataset(dataset, "train")[i] for i in range(16)]))
    masks = patch_masks(torch.full((16,), 0.5), PatchScheme(40, 40, 0.5, 0.5), torch.Generator().manual_seed(0))
    corrupted = corrupt_depth(depth, masks)
    before = _latent_gap(base.encoder, base.encoder, gray, depth, corrupted)
    after = _latent_gap(anchored.encoder, base.encoder, gray, depth, corrupted)
    clean_drift = _latent_gap(anchored.encoder, base.encoder, gray, depth, depth)
    assert after < 0.5 * before and clean_drift < before, (before, after, clean_drift)
    # `cmnav eval cmwae`'s latent shift sees it too, on S2's squares at 50 % (80 steps: at 40 this toy
    # stopped at 0.60 of the anchor's shift on an Intel Xeon with AMX, below 0.5 on AMD EPYC; at 80, 0.16)
    shifts = []
    for checkpoint in (base_dir, out):
        stdout = _cmnav("eval", "cmwae", "--checkpoint", str(checkpoint), "--data", str(dataset), "--split", "train",
                        "--max-images", "16", "--patch-sides", "100-100", "--precision", "fp32", "--json")  # fmt: skip
        shifts.append(json.loads(stdout.strip().splitlines()[-1])["rows"][4]["latent_shift_over_var"])
    assert shifts[1] < 0.5 * shifts[0], shifts


def test_consistency_fine_tune_on_two_datasets_pulls_corrupted_latents_to_its_own_clean_ones(dataset, tmp_path):
    base_dir, out, second = tmp_path / "base", tmp_path / "tuned", tmp_path / "second"
    generate_dataset(second, DatasetSpec(count=24, seed=5, levels=(10,), frames_per_room=4))
    torch.manual_seed(0)
    config = make_config("tiny")
    base = Cmwae(config)
    with torch.no_grad():  # a latent that responds to depth, as in the anchoring test
        base.encoder.features["depth"][0].weight.mul_(3.0)
        base.encoder.embed["depth"][1].weight.mul_(30.0)
    save_weights(base_dir, base, "cmwae", dataclasses.asdict(config), 0, {})
    _cmnav(*TRAIN, "--data", str(dataset), str(second), "--scheme", "s2", "--out", str(out), "--steps", "80", "--lr", "1e-3",
           "--init-from", str(base_dir), "--consistency-weight", "20", "--mmd-weight", "0.01", "--precision", "fp32",
           "--val-images", "4")  # fmt: skip
    base, _ = load_cmwae(base_dir)
    tuned, card = load_cmwae(out)
    assert card["meta"]["extra_datasets"] == [str(second)] and card["meta"]["train"]["consistency_weight"] == 20.0
    # encoder and decoder both learnt (nothing frozen, unlike anchoring)
    for part in ("encoder", "decoder"):
        before, after = getattr(base, part).state_dict(), getattr(tuned, part).state_dict()
        assert any(not torch.equal(after[k], v) for k, v in before.items()), part
    # the corrupted latent came closer to the encoder's own latent of the clean pair, on images of both datasets
    for root in (dataset, second):
        gray, depth = (torch.stack(t) for t in zip(*[GrayDepthDataset(root, "train")[i] for i in range(12)]))
        masks = patch_masks(torch.full((12,), 0.5), PatchScheme(40, 40, 0.5, 0.5), torch.Generator().manual_seed(0))
        corrupted = corrupt_depth(depth, masks)
        before = _latent_gap(base.encoder, base.encoder, gray, depth, corrupted)
        after = _latent_gap(tuned.encoder, tuned.encoder, gray, depth, corrupted)
        assert after < 0.5 * before, (root, before, after)


def test_near_surface_weighting_is_a_weighted_mean_over_each_images_pixels():
    target = torch.full((2, 1, 4, 4), 0.5)
    target[0, 0, 0, :2] = 0.1  # two pixels 1 m away, one invalid (0): only the valid near ones weigh more
    target[0, 0, 1, 0] = 0.0
    recon = target + 0.1
    recon[0, 0, 0, :2] += 0.2  # the near pixels are 0.3 off, the rest 0.1
    z = torch.randn(2, 3, generator=torch.Generator().manual_seed(0))
    weights = 1.0 + 9.0 * near_surface_mask(target, 1.5)
    assert int(near_surface_mask(target, 1.5).sum()) == 2
    losses = cmwae_loss(recon, target, z, 0.0, pixel_weights=weights)
    near_image = (2 * 10 * 0.3**2 + 14 * 0.1**2) / (2 * 10 + 14)
    assert float(losses["loss"]) == pytest.approx((near_image + 0.1**2) / 2, rel=1e-5)
    assert float(losses["recon_mse"]) == pytest.approx(((2 * 0.3**2 + 14 * 0.1**2) / 16 + 0.1**2) / 2, rel=1e-5)
    with pytest.raises(ValueError, match="near_m=12.0 must lie in"):
        CmwaeTrainConfig(data_dir="d", out_dir="o", steps=1, near_weight=1.0, near_m=12.0).validate()


def test_the_pooled_loss_sees_the_depth_as_the_teacher_does():
    from training.policy.env import NavEnvConfig

    width, height = NavEnvConfig().privileged_depth_px
    assert TEACHER_GRID == (height, width)  # rows x columns of the teacher's privileged depth
    far = torch.full((1, 1, 224, 224), 0.8)  # the contract's image: cells of 7 columns x 12.4 rows
    pole = far.clone()
    pole[0, 0, :, 35] = 0.1  # a pole one pixel wide at 1 m, in grid column 5 (px 35-41)
    pole[0, 0, 0, :] = 0.0  # an invalid row reads far, not as a surface at 0 m
    cells = nearest_per_cell(pole)
    assert cells.shape == (1, 1, *TEACHER_GRID)
    assert torch.allclose(cells[0, 0, :, 5], torch.full((18,), 0.1)) and float(cells[0, 0, :, 6:].min()) == pytest.approx(0.8)
    # the pole missing from the reconstruction: the frame's MSE barely sees it, the teacher's view does
    frame_mse = float(((far - pole)[pole > 0] ** 2).mean())
    missed = float(pooled_nearest_error(far, pole)[0])
    assert missed == pytest.approx(0.7**2 / 32, rel=1e-5) and missed > 6 * frame_mse
    # shifted by a pixel inside its cell it is what the teacher sees; the invalid row is not scored
    shifted = far.clone()
    shifted[0, 0, :, 36] = 0.1
    shifted[0, 0, 0, :] = 0.3
    assert float(pooled_nearest_error(shifted, pole)[0]) == 0.0
    # near cells (the pole's, at 1 m < 1.5 m) weigh 1 + near_weight
    assert float(pooled_nearest_error(far, pole, near_weight=9.0)[0]) == pytest.approx(18 * 10 * 0.7**2 / (18 * 10 + 558), rel=1e-5)
    with pytest.raises(ValueError, match="pooled_weight=-1.0 must lie in"):
        CmwaeTrainConfig(data_dir="d", out_dir="o", steps=1, pooled_weight=-1.0).validate()


def test_the_pooled_term_pulls_the_reconstruction_toward_the_teachers_view():
    # plain gradient steps on a free image: the frame's mean spreads a thin pole's error over every
    # pixel, the teacher's-view term puts it on one cell; the pole comes back only with the term
    target = torch.full((1, 1, 224, 224), 0.8)
    target[0, 0, :, 35] = target[0, 0, :, 120] = 0.1
    errors = {}
    for pooled_weight in (0.0, 30.0):
        recon = torch.full_like(target, 0.8).requires_grad_(True)
        for _ in range(20):
            loss = ((recon - target) ** 2).mean() + pooled_weight * pooled_nearest_error(recon, target).mean()
            (grad,) = torch.autograd.grad(loss, recon)
            recon = (recon - 5.0 * grad).detach().requires_grad_(True)
        errors[pooled_weight] = float(pooled_nearest_error(recon.detach(), target)[0])
    assert errors[0.0] > 0.9 * pooled_nearest_error(torch.full_like(target, 0.8), target)[0] and errors[30.0] < 0.01 * errors[0.0], errors


def test_hidden_far_weighting_weighs_only_hidden_surfaces_read_too_far():
    target = torch.full((1, 1, 224, 224), 0.8)
    target[0, 0, :, 35] = target[0, 0, :, 120] = 0.1  # two poles at 1 m, in grid columns 5 and 17
    target[0, 0, 0, :] = 0.0  # an invalid row: never hidden (the target has nothing there)
    corrupted = target.clone()
    corrupted[0, 0, :, 28:42] = 0.0  # a square hides the first pole (and its cells' far wall)
    hidden = hidden_pixels(corrupted, target)
    assert int(hidden[0, 0, 0].sum()) == 0 and bool(hidden[0, 0, 1:, 35].all()) and not bool(hidden[0, 0, :, 120].any())
    both_missed = torch.full_like(target, 0.8)  # neither pole reconstructed: both read too far
    plain = float(pooled_nearest_error(both_missed, target)[0])
    tilted = float(pooled_nearest_error(both_missed, target, hidden=hidden, hidden_far_weight=9.0)[0])
    # the 18 cells of 576 that hold the hidden pole weigh 10
    assert plain == pytest.approx(36 * 0.7**2 / 576, rel=1e-5)
    assert tilted == pytest.approx((36 + 18 * 9) * 0.7**2 / (576 + 18 * 9), rel=1e-5)
    # read too near, the same hidden pole weighs as before: the term is pessimism, not accuracy
    too_near = target.clone()
    too_near[0, 0, :, 35] = 0.05
    too_near[0, 0, :, 120] = 0.8
    assert float(pooled_nearest_error(too_near, target, hidden=hidden, hidden_far_weight=9.0)[0]) == pytest.approx(
        (18 * 0.05**2 + 18 * 0.7**2) / 576, rel=1e-5)
    with pytest.raises(ValueError, match="hidden_far_weight=-1.0 must lie in"):
        CmwaeTrainConfig(data_dir="d", out_dir="o", steps=1, hidden_far_weight=-1.0).validate()


def test_the_hidden_far_term_tilts_the_guess_under_a_square_near():
    # one guess for two hidden pixels of an image, one near and one far: the plain mean's optimum
    # is their mean; with the term the guess moves to the 10 : 1 weighted mean
    target = torch.tensor([0.1, 0.9]).view(1, 1, 1, 2)
    hidden = torch.ones_like(target, dtype=torch.bool)
    guesses = {}
    for weight in (0.0, 9.0):
        config = CmwaeTrainConfig(data_dir="d", out_dir="o", steps=1, hidden_far_weight=weight)
        guess = torch.tensor(0.5, requires_grad=True)
        for _ in range(400):
            recon = guess.expand_as(target)
            loss = cmwae_loss(recon, target, torch.randn(2, 3), 0.0, pixel_weights=_pixel_weights(config, recon, target, hidden))
            (grad,) = torch.autograd.grad(loss["loss"], guess)
            guess = (guess - 0.2 * grad).detach().requires_grad_(True)
        guesses[weight] = float(guess.detach())
    assert guesses[0.0] == pytest.approx(0.5, abs=1e-3)
    assert guesses[9.0] == pytest.approx((0.9 + 0.1 * 10) / 11, abs=1e-2)


def test_train_cmwae_with_the_hidden_far_term(dataset, tmp_path):
    weights = {}
    for hidden_far_weight in ("0", "9"):
        out = tmp_path / f"hidden{hidden_far_weight}"
        _cmnav(*TRAIN, "--data", str(dataset), "--scheme", "s2", "--out", str(out), "--steps", "3", "--seed", "1",
               "--pooled-weight", "30", "--hidden-far-weight", hidden_far_weight, "--precision", "fp32", "--val-images", "4")
        model, card = load_cmwae(out)
        assert card["meta"]["train"]["hidden_far_weight"] == float(hidden_far_weight)
        weights[hidden_far_weight] = model.state_dict()
    # the same seed, squares and start: the term reached the gradient
    assert any(not torch.allclose(weights["0"][k], weights["9"][k]) for k in weights["0"])


def test_train_cmwae_with_the_pooled_term(dataset, tmp_path):
    weights = {}
    for pooled_weight in ("0", "30"):
        out = tmp_path / f"pooled{pooled_weight}"
        _cmnav(*TRAIN, "--data", str(dataset), "--scheme", "none", "--out", str(out), "--steps", "3", "--seed", "1",
               "--pooled-weight", pooled_weight, "--precision", "fp32", "--val-images", "4")
        model, card = load_cmwae(out)
        assert card["meta"]["train"]["pooled_weight"] == float(pooled_weight)
        weights[pooled_weight] = model.state_dict()
    # the same seed, batches and start: the term reached the gradient
    assert any(not torch.allclose(weights["0"][k], weights["30"][k]) for k in weights["0"])


def test_near_surface_weighting_lowers_the_near_error_more_than_the_plain_mean(dataset, tmp_path):
    base_dir = tmp_path / "base"
    _cmnav(*TRAIN, "--data", str(dataset), "--scheme", "none", "--out", str(base_dir), "--steps", "2", "--precision", "fp32")
    near_m = 3.0
    errors = {}
    for near_weight in ("0", "30"):
        out = tmp_path / f"near{near_weight}"
        _cmnav(*TRAIN, "--data", str(dataset), "--scheme", "none", "--out", str(out), "--steps", "25", "--lr", "1e-3",
               "--init-from", str(base_dir), "--near-weight", near_weight, "--near-m", str(near_m), "--precision", "fp32",
               "--val-images", "4")  # fmt: skip
        model, card = load_cmwae(out)
        assert card["meta"]["train"]["near_weight"] == float(near_weight) and card["meta"]["train"]["near_m"] == near_m
        gray, depth = (torch.stack(t) for t in zip(*[GrayDepthDataset(dataset, "train")[i] for i in range(24)]))
        with torch.no_grad():
            squared = (model(gray, depth)[1] - depth) ** 2
        near = near_surface_mask(depth, near_m)
        assert near.any() and not near.all()
        errors[near_weight] = (float(squared[near].mean()), float(squared[~near].mean()))
    # the same batches and start: the weighted run traded far error for near error
    (plain_near, plain_far), (weighted_near, weighted_far) = errors["0"], errors["30"]
    assert weighted_near < 0.8 * plain_near and weighted_far > plain_far, errors


def test_a_missing_extra_dataset_is_named(dataset, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "cmnav", *TRAIN, "--data", str(dataset), str(tmp_path / "nowhere"),
                           "--out", str(tmp_path / "x"), "--steps", "1"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode != 0 and f"dataset folder {tmp_path / 'nowhere'} not found" in proc.stderr
    with pytest.raises(ValueError, match="consistency_weight and anchor_from"):
        CmwaeTrainConfig(data_dir="d", out_dir="o", steps=1, anchor_from="a", consistency_weight=1.0).validate()


def test_latent_anchoring_refuses_a_wrong_anchor(dataset, tmp_path):
    base_dir = tmp_path / "tiny"
    _cmnav(*TRAIN, "--data", str(dataset), "--out", str(base_dir), "--steps", "1")
    wrong = subprocess.run([sys.executable, "-m", "cmnav", *TRAIN, "--data", str(dataset), "--out", str(tmp_path / "x"),
                            "--steps", "1", "--anchor", str(base_dir), "--modalities", "depth"],
                           capture_output=True, text=True, timeout=120)  # fmt: skip
    assert wrong.returncode != 0 and "is not the one --size tiny --modalities depth builds" in wrong.stderr
    both = subprocess.run([sys.executable, "-m", "cmnav", *TRAIN, "--data", str(dataset), "--out", str(tmp_path / "y"),
                           "--steps", "1", "--anchor", str(base_dir), "--init-from", str(base_dir)],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert both.returncode == 2 and "not allowed with argument" in both.stderr
    with pytest.raises(ValueError, match="anchor_from starts from the anchor's weights"):
        CmwaeTrainConfig(data_dir="d", out_dir="o", steps=1, anchor_from="a", init_from="b").validate()
    with pytest.raises(ValueError, match="anchor_weight"):
        CmwaeTrainConfig(data_dir="d", out_dir="o", steps=1, anchor_weight=0.0).validate()


def test_fp16_shards_roundtrip(tmp_path):
    from training.checkpoint import load_weights, save_weights

    model = Cmwae(make_config("small"))
    save_weights(tmp_path, model, "cmwae", {}, 0)
    assert len(list(tmp_path.glob("weights-*.pt"))) >= 1
    copy = Cmwae(make_config("small"))
    load_weights(tmp_path, copy)
    for (name, a), b in zip(model.state_dict().items(), copy.state_dict().values()):
        torch.testing.assert_close(a.half().float(), b, msg=name)


def test_multi_process_torchrun_on_cpu(dataset, tmp_path):
    out = tmp_path / "ddp"
    digests = torchrun_digests(*TRAIN, "--data", str(dataset), "--out", str(out), "--steps", "2")
    assert digests[0] == digests[1]
    assert read_card(out, "cmwae")["meta"]["world_size"] == 2
