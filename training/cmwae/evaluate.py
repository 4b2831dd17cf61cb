"""`cmnav eval cmwae`: Table I — mean depth-reconstruction MSE and SSIM on the held-out split at
0/20/30/40/50 % evaluation corruption (square patches of side 1..50 px, or other sides to see how the
encoder copes with S2's 100 px squares or the policy's 1..30 px patches), as a markdown table like
the paper's, plus MSE/SSIM box plots and a grid of example inputs and reconstructions.  A column the
paper has not: the MSE over the surfaces nearer than ``near_m`` (per image that has any, then
averaged), the obstacles a policy is about to hit, which the whole-frame mean dilutes; the
teacher's-view MSE, the error of the nearest surface per cell of the teacher's 18 x 32 depth grid
(what the privileged teacher flies on, so what the student's latent has to carry); and the
latent shift, what the policy sees of the corruption: the mean squared distance per dimension of
the latent of corrupted depth from the latent of the same pair with clean depth, over the clean
latents' variance per dimension (0: corruption leaves the latent where it was).  On a dataset with
the simulated D455's depth (`cmnav dataset --depth stereo`), a second table has it as the input,
a row per projector state, scored the same way against the clean depth.

The table needs only torch: SSIM comes from pytorch-msssim, or from its wheel in vendor/ where it
is not installed (training.vendored).  The plots are drawn with OpenCV and skipped, with one
warning, where it is missing (the offline GPU machine); ``plots`` then lists only those drawn."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from sim.degradation import EVALUATION_COVERAGES, EVALUATION_PATCH_SIDES_PX, corrupt_depth, evaluation_scheme, patch_masks
from sim.plot import opencv_for_drawing

from ..data.tartanair import DatasetError, GrayDepthDataset, GrayDepthStereoDataset, stereo_projector_on
from ..fastpath import choose_fast_path
from ..vendored import import_vendored
from .loss import NEAR_SURFACE_M, near_surface_mask, pooled_nearest_error
from .train import load_cmwae

ssim = import_vendored("pytorch_msssim").ssim
RERUN = "cmnav eval cmwae"


@dataclass(frozen=True)
class CmwaeEvalConfig:
    checkpoint: str
    data_dir: str
    split: str = "test"
    out_dir: str | None = None  # plots; default <checkpoint>/eval
    device: str = "cpu"
    batch_size: int = 32
    max_images: int | None = None
    seed: int = 0
    coverages: tuple[float, ...] = EVALUATION_COVERAGES
    patch_sides_px: tuple[int, int] = EVALUATION_PATCH_SIDES_PX  # Table I's; e.g. (100, 100): S2's own squares
    precision: str = "auto"  # training.fastpath: the encoder under bf16 autocast where the CPU has it (decoder fp32)
    near_m: float = NEAR_SURFACE_M  # the near-surface column: true depth below this (m), invalid pixels excluded


@torch.no_grad()
def evaluate_cmwae(config: CmwaeEvalConfig) -> dict:
    schemes = {c: evaluation_scheme(c, config.patch_sides_px) for c in config.coverages}  # bad sides fail here, first
    model, card = load_cmwae(config.checkpoint, config.device)
    path = choose_fast_path(config.precision, config.device)
    model = path.prepare_trained(model)
    dataset = GrayDepthDataset(config.data_dir, config.split)
    loader = DataLoader(dataset, batch_size=config.batch_size, num_workers=0)
    scorer = _Scorer(model, path, config)
    per_coverage: dict[float, _Scores] = {}
    examples: dict[float, tuple] = {}
    for coverage in config.coverages:
        generator = torch.Generator().manual_seed(config.seed)  # same patches for every model
        scores = _Scores()
        for batch, (gray, depth) in enumerate(_limited(loader, config.max_images)):
            masks = patch_masks(torch.full((depth.shape[0],), coverage), schemes[coverage], generator)
            corrupted = corrupt_depth(depth, masks)
            recon = scorer.score(scores, batch, gray, depth, corrupted)
            scores.coverage += masks.float().mean(dim=(1, 2)).tolist()
            if coverage not in examples:
                examples[coverage] = (gray[:4], corrupted[:4], recon[:4], depth[:4])
        per_coverage[coverage] = scores
    latent_var = scorer.latent_var()
    rows = [{"corruption_pct": int(round(c * 100)), "actual_coverage_pct": round(100 * float(np.mean(v.coverage)), 2),
             **v.summary(latent_var)} for c, v in per_coverage.items()]  # fmt: skip
    stereo_rows = _stereo_rows(scorer, config, latent_var)
    out = Path(config.out_dir) if config.out_dir else Path(config.checkpoint) / "eval"
    out.mkdir(parents=True, exist_ok=True)
    labels = [f"{r['corruption_pct']}%" for r in rows]
    plots = {
        "mse": box_plot(out / "mse_boxplot.png", labels, [1e3 * np.asarray(v.mse) for v in per_coverage.values()], "MSE x1e-3"),
        "ssim": box_plot(out / "ssim_boxplot.png", labels, [1e2 * np.asarray(v.ssim) for v in per_coverage.values()], "SSIM x1e-2"),
        "examples": example_grid(out / "examples.png", examples),
    }  # fmt: skip
    result = {
        "checkpoint": str(config.checkpoint),
        "scheme": card["meta"].get("train", {}).get("scheme"),
        "modalities": card["config"]["modalities"],
        "step": card["step"],
        "split": config.split,
        "patch_sides_px": list(config.patch_sides_px),
        "fast_path": path.name,
        "rows": rows,
        "near_m": config.near_m,
        "latent_var": float(f"{latent_var:.4g}"),
        "table": markdown_table(rows, config.near_m) + (f"\n\n{stereo_table(stereo_rows, config.near_m)}" if stereo_rows else ""),
        "stereo_rows": stereo_rows,
        "mse_ratio_50_over_0": _ratio(rows),
        "out_dir": str(out),
        "plots": {name: str(path) for name, path in plots.items() if path is not None},
    }
    (out / "table1.json").write_text(json.dumps(result, indent=2))
    return result


@dataclass
class _Scores:
    """Per-image scores of one input kind (a coverage, or the stereo depth)."""

    mse: list[float] = field(default_factory=list)
    ssim: list[float] = field(default_factory=list)
    coverage: list[float] = field(default_factory=list)
    near_mse: list[float | None] = field(default_factory=list)  # None: an image without near pixels
    near_share: list[float] = field(default_factory=list)
    pooled_mse: list[float] = field(default_factory=list)
    latent_shift: list[float] = field(default_factory=list)

    def summary(self, latent_var: float) -> dict:
        near_mse = [v for v in self.near_mse if v is not None]
        return {
            "mse_e3": round(1e3 * float(np.mean(self.mse)), 3),
            "ssim_e2": round(1e2 * float(np.mean(self.ssim)), 2),
            "near_mse_e3": round(1e3 * float(np.mean(near_mse)), 3) if near_mse else None,
            "near_images": len(near_mse),
            "near_pixels_pct": round(100 * float(np.mean(self.near_share)), 2),
            "teacher_view_mse_e3": round(1e3 * float(np.mean(self.pooled_mse)), 3),
            "latent_shift_over_var": float(f"{float(np.mean(self.latent_shift)) / max(latent_var, 1e-12):.4g}"),
            "images": len(self.mse),
        }


class _Scorer:
    """Reconstructs batches and scores them against the clean depth; the clean latents of the
    first pass over the loader (batch by batch) are the reference of every latent shift."""

    def __init__(self, model, path, config: CmwaeEvalConfig) -> None:
        self.model, self.path, self.config = model, path, config
        self.clean_latents: list[torch.Tensor] = []

    def score(self, scores: _Scores, batch: int, gray: torch.Tensor, depth: torch.Tensor, corrupted: torch.Tensor) -> torch.Tensor:
        """Adds the batch's scores to ``scores``; returns the reconstruction."""
        device, path = self.config.device, self.path
        gray_in = path.image(gray.to(device))
        with path.autocast(device):
            z, recon = self.model(gray_in, path.image(corrupted.to(device)))
            if batch == len(self.clean_latents):
                self.clean_latents.append(self.model.encoder(gray_in, path.image(depth.to(device))).float().cpu())
        scores.latent_shift += ((z.float().cpu() - self.clean_latents[batch]) ** 2).mean(dim=1).tolist()
        recon = recon.float().cpu()
        squared = (recon - depth) ** 2
        scores.mse += squared.mean(dim=(1, 2, 3)).tolist()
        near = near_surface_mask(depth, self.config.near_m)
        near_count = near.sum(dim=(1, 2, 3))
        scores.near_share += (near_count / near[0].numel()).tolist()
        scores.near_mse += [v if k > 0 else None for v, k in
                            zip(((squared * near).sum(dim=(1, 2, 3)) / near_count.clamp(min=1)).tolist(), near_count.tolist())]  # fmt: skip
        scores.pooled_mse += pooled_nearest_error(recon, depth).tolist()
        scores.ssim += ssim(recon, depth, data_range=1.0, size_average=False).tolist()
        return recon

    def latent_var(self) -> float:
        return float(torch.cat(self.clean_latents).var(dim=0).mean())


def _limited(loader: DataLoader, max_images: int | None):
    """The loader's batches, cut to ``max_images`` images in all."""
    seen = 0
    for batch in loader:
        if max_images is not None:
            if seen >= max_images:
                return
            batch = [t[: max_images - seen] for t in batch]
        seen += batch[0].shape[0]
        yield batch


def _stereo_rows(scorer: _Scorer, config: CmwaeEvalConfig, latent_var: float) -> list[dict]:
    """Where the dataset stores the simulated D455's depth (`cmnav dataset --depth stereo`): the
    same images with it as the input, projector on and off apart (rows), against the clean depth."""
    try:
        dataset = GrayDepthStereoDataset(config.data_dir, config.split)
    except DatasetError:
        return []  # no stereo depth: Table I's rows only
    on = stereo_projector_on(config.data_dir, dataset.samples)
    by_projector = {True: _Scores(), False: _Scores()}
    loader = DataLoader(dataset, batch_size=config.batch_size, num_workers=0)
    first = 0
    for batch, (gray, depth, stereo) in enumerate(_limited(loader, config.max_images)):
        both = _Scores()
        scorer.score(both, batch, gray, depth, stereo)
        for k, projector_on in enumerate(on[first : first + depth.shape[0]]):
            for name, values in vars(both).items():
                if values:  # all but coverage
                    getattr(by_projector[projector_on], name).append(values[k])
        first += depth.shape[0]
    return [{"input": f"stereo, projector {'on' if key else 'off'}", **scores.summary(latent_var)}
            for key, scores in by_projector.items() if scores.mse]  # fmt: skip


def _ratio(rows: list[dict]) -> float | None:
    by = {r["corruption_pct"]: r["mse_e3"] for r in rows}
    return round(by[50] / by[0], 3) if 0 in by and 50 in by and by[0] > 0 else None


def markdown_table(rows: list[dict], near_m: float) -> str:
    """Table I: a row per coverage."""
    return _table("corruption", [f"{r['corruption_pct']}%" for r in rows], rows, near_m)


def stereo_table(rows: list[dict], near_m: float) -> str:
    """The stereo depth as the input: a row per projector state."""
    return _table("input", [r["input"] for r in rows], rows, near_m)


def _table(what: str, labels: list[str], rows: list[dict], near_m: float) -> str:
    lines = [f"| {what} | MSE (x10^-3) | SSIM (x10^-2) | MSE < {near_m:g} m (x10^-3) | teacher's view MSE (x10^-3) | "
             "latent shift / var | images (with near pixels) |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    lines += [f"| {label} | {r['mse_e3']:.2f} | {r['ssim_e2']:.2f} | "
              f"{'-' if r['near_mse_e3'] is None else format(r['near_mse_e3'], '.2f')} | {r['teacher_view_mse_e3']:.2f} | "
              f"{r['latent_shift_over_var']:.3f} | "
              f"{r['images']} ({r['near_images']}) |" for label, r in zip(labels, rows)]  # fmt: skip
    return "\n".join(lines)


def box_plot(path: Path, labels: list[str], series: list[np.ndarray], ylabel: str) -> Path | None:
    """Box plots (median, quartiles, whiskers at 1.5 IQR) drawn with OpenCV; None without it."""
    cv2 = opencv_for_drawing(RERUN)
    if cv2 is None:
        return None
    width, height, margin = 120 * len(series) + 100, 420, 60
    image = np.full((height, width, 3), 255, np.uint8)
    lo = min(float(np.min(s)) for s in series if len(s))
    hi = max(float(np.max(s)) for s in series if len(s))
    span = hi - lo if hi > lo else 1.0

    def y(v: float) -> int:
        return int(height - margin - (v - lo) / span * (height - 2 * margin))

    for i, (label, values) in enumerate(zip(labels, series)):
        x = 100 + i * 120
        if len(values):
            q1, med, q3 = np.percentile(values, [25, 50, 75])
            iqr = q3 - q1
            low = float(np.min(values[values >= q1 - 1.5 * iqr]))
            high = float(np.max(values[values <= q3 + 1.5 * iqr]))
            cv2.line(image, (x, y(low)), (x, y(high)), (0, 0, 0), 1)
            cv2.rectangle(image, (x - 30, y(q3)), (x + 30, y(q1)), (230, 200, 160), -1)
            cv2.rectangle(image, (x - 30, y(q3)), (x + 30, y(q1)), (0, 0, 0), 1)
            cv2.line(image, (x - 30, y(med)), (x + 30, y(med)), (0, 0, 200), 2)
            for outlier in values[(values < low) | (values > high)][:200]:
                cv2.circle(image, (x, y(float(outlier))), 2, (80, 80, 80), -1)
        cv2.putText(image, label, (x - 18, height - 25), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    for v in np.linspace(lo, hi, 5):
        cv2.putText(image, f"{v:.3g}", (5, y(float(v)) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.putText(image, f"{ylabel} by corruption", (margin, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1)
    cv2.imwrite(str(path), image)
    return path


def example_grid(path: Path, examples: dict[float, tuple]) -> Path | None:
    """Rows: coverage x example; columns: gray, corrupted depth input, reconstruction, target.
    Drawn with OpenCV; None without it."""
    cv2 = opencv_for_drawing(RERUN)
    if cv2 is None:
        return None
    rows = []
    for coverage, (gray, corrupted, recon, depth) in examples.items():
        for k in range(gray.shape[0]):
            tiles = [(t[k, 0].numpy() * 255).clip(0, 255).astype(np.uint8) for t in (gray, corrupted, recon, depth)]
            row = np.hstack([cv2.resize(t, (112, 112), interpolation=cv2.INTER_AREA) for t in tiles])
            cv2.putText(row, f"{int(coverage * 100)}%", (3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, 255, 1)
            rows.append(row)
    header = np.full((18, 448), 255, np.uint8)
    for i, name in enumerate(("gray", "depth in", "recon", "target")):
        cv2.putText(header, name, (i * 112 + 4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, 0, 1)
    cv2.imwrite(str(path), np.vstack([header, *rows]))
    return path
