"""How far the parametric D455 (:mod:`sim.sensor.approx`) is from the stereo path it stands in
for, on the views of a `cmnav dataset --depth stereo` folder, and the fit of its loss model.

    python -m bench.stereo_approx DATASET [--frames 600] [--fit]

Frames are split by trajectory (``training.data.tartanair.assign_splits``): the loss model is
fitted on the train split (``--fit`` prints the weights for ``StereoApproxConfig``), the table is
measured on the test split.  The stereo depth (424 x 240) is brought to the clean depth's grid by
the decimation filter's median, as the SITL camera serves it.  Per projector state: the invalid
share (mean, per-frame correlation and mean absolute difference), pixel agreement and IoU of the
invalid masks, how far lost regions reach (P(lost at +k px | lost)), and the relative range error
of what both keep (robust sigma = 1.4826 MAD, 95th percentile of |error|) by range.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from sim.camera import CameraModel
from sim.sensor import decimate_depth
from sim.sensor.approx import CUES, StereoApproxConfig, approx_stereo_depth, loss_cues
from training.data.tartanair import assign_splits, find_samples, read_depth_m, read_gray_u8, stereo_depth_path, stereo_projector_on

RANGE_BINS_M = ((0.53, 2.0), (2.0, 4.0), (4.0, 10.0))
LAGS_PX = (2, 4, 8)


def load_views(dataset: Path, frames: int, seed: int = 0) -> dict[str, list[dict]]:
    """Up to ``frames`` views (clean depth, gray, decimated stereo depth, projector state) drawn
    at random from the dataset, by split ("train", "test")."""
    manifest = json.loads((dataset / "manifest.json").read_text())
    if not manifest.get("stereo", {}).get("projector_on"):
        raise SystemExit(f"{dataset} has no stereo depth: make one with `cmnav dataset --depth stereo --out {dataset}`")
    samples = find_samples(dataset)
    random.Random(seed).shuffle(samples)
    splits = assign_splits(sorted({s.trajectory for s in samples}), val_fraction=0.0, test_fraction=0.33)
    views: dict[str, list[dict]] = {"train": [], "test": []}
    chosen = samples[:frames]
    for sample, projector_on in zip(chosen, stereo_projector_on(dataset, chosen)):
        clean = read_depth_m(sample.depth_path, sample.layout)
        stereo = np.load(stereo_depth_path(sample))
        factor = stereo.shape[1] // clean.shape[1]
        decimated = decimate_depth(torch.from_numpy(stereo)[None], factor)[0].numpy()
        views[splits[sample.trajectory]].append({"depth": clean, "gray": read_gray_u8(sample.image_path),
                                                 "stereo": decimated, "projector_on": bool(projector_on)})  # fmt: skip
    return views


def fit_loss_weights(views: list[dict], fx_px: float, config: StereoApproxConfig) -> np.ndarray:
    """Logistic regression of "the stereo path lost this pixel" on the model's cues (L-BFGS, a
    light L2 on all but the bias)."""
    x = torch.cat([_cues(v, fx_px, config) for v in views]).double()
    y = torch.cat([torch.from_numpy(v["stereo"] <= 0.0).flatten() for v in views]).double()
    w = torch.zeros(x.shape[1], dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([w], max_iter=200, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = torch.nn.functional.binary_cross_entropy_with_logits(x @ w, y) + 1e-4 * (w[1:] ** 2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return w.detach().numpy()


def _cues(view: dict, fx_px: float, config: StereoApproxConfig) -> torch.Tensor:
    depth = torch.from_numpy(view["depth"]).float()[None]
    gray = torch.from_numpy(view["gray"])[None]
    return loss_cues(depth, gray, fx_px, config)[0].flatten(1).T


def compare(views: list[dict], fx_px: float, config: StereoApproxConfig, seed: int = 0) -> dict:
    """The table's row for one projector state (see the module doc)."""
    generator = torch.Generator().manual_seed(seed)
    share_a, share_s, agree, inter, union = [], [], [], 0, 0
    reach = {k: ([], []) for k in LAGS_PX}
    errors = {b: ([], []) for b in RANGE_BINS_M}
    for v in views:
        depth = torch.from_numpy(v["depth"]).float()[None]
        approx = approx_stereo_depth(depth, torch.from_numpy(v["gray"])[None], fx_px, config, generator)[0].numpy()
        lost_a, lost_s = approx <= 0.0, v["stereo"] <= 0.0
        share_a.append(lost_a.mean())
        share_s.append(lost_s.mean())
        agree.append((lost_a == lost_s).mean())
        inter += int((lost_a & lost_s).sum())
        union += int((lost_a | lost_s).sum())
        for k, (a, s) in reach.items():
            for lost, out in ((lost_a, a), (lost_s, s)):
                if lost[:, :-k].any():
                    out.append(lost[:, k:][lost[:, :-k]].mean())
        for (lo, hi), (a, s) in errors.items():
            inside = (v["depth"] >= lo) & (v["depth"] < hi)
            for measured, lost, out in ((approx, lost_a, a), (v["stereo"], lost_s, s)):
                keep = inside & ~lost
                out.append((measured[keep] - v["depth"][keep]) / v["depth"][keep])
    share_a, share_s = np.array(share_a), np.array(share_s)

    def robust_sigma(x: np.ndarray) -> float:
        return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else math.nan

    row = {
        "frames": len(views),
        "lost_share": {"approx": round(float(share_a.mean()), 3), "stereo": round(float(share_s.mean()), 3)},
        "per_frame_lost": {"correlation": round(float(np.corrcoef(share_a, share_s)[0, 1]), 3),
                           "mean_abs_diff": round(float(np.abs(share_a - share_s).mean()), 3)},  # fmt: skip
        "pixels_agree": round(float(np.mean(agree)), 3),
        "lost_iou": round(inter / max(union, 1), 3),
        "lost_reach": {f"{k}px": {"approx": round(float(np.mean(a)), 3), "stereo": round(float(np.mean(s)), 3)} for k, (a, s) in reach.items()},
        "range_error": {},
    }
    for (lo, hi), (a, s) in errors.items():
        a, s = np.concatenate(a), np.concatenate(s)
        row["range_error"][f"{lo:g}-{hi:g} m"] = {
            "robust_sigma": {"approx": round(robust_sigma(a), 4), "stereo": round(robust_sigma(s), 4)},
            "p95_abs": {"approx": round(float(np.percentile(np.abs(a), 95)), 3), "stereo": round(float(np.percentile(np.abs(s), 95)), 3)},
        }  # fmt: skip
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.stereo_approx", description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="a `cmnav dataset --depth stereo` folder")
    parser.add_argument("--frames", type=int, default=600, help="views drawn from it (default 600)")
    parser.add_argument("--fit", action="store_true", help="fit the loss model on the train split and use it")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    views = load_views(args.dataset, args.frames, args.seed)
    height, width = views["test"][0]["depth"].shape
    fx_px = CameraModel(width_px=width, height_px=height).fx_px
    result = {}
    for on in (True, False):
        config = StereoApproxConfig(projector_on=on)
        if args.fit:
            weights = tuple(round(float(w), 3) for w in fit_loss_weights([v for v in views["train"] if v["projector_on"] == on], fx_px, config))
            print(f"loss weights, projector {'on' if on else 'off'} ({', '.join(CUES)}): {weights}", file=sys.stderr)
            config = replace(config, **{f"loss_weights_projector_{'on' if on else 'off'}": weights})
        result["projector_on" if on else "projector_off"] = compare([v for v in views["test"] if v["projector_on"] == on], fx_px, config, args.seed)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
