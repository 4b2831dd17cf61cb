"""`cmnav train cmwae`: WAE-MMD training of the CMWAE (or the depth-only baseline encoder) with
depth corruption applied on the fly; progress, TensorBoard scalars, periodic checkpoints,
resume, and multi-GPU through torchrun (DistributedDataParallel)."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import ConcatDataset, DataLoader
from torch.utils.data.distributed import DistributedSampler

from sim.degradation import SCHEMES, corrupt_depth, corrupt_with_scheme, evaluation_scheme, patch_masks

from ..checkpoint import load_train_state, load_weights, read_card, save_train_state, save_weights
from ..data.tartanair import GrayDepthDataset, GrayDepthStereoDataset
from ..distributed import DistInfo, all_reduce_mean, log_weights_digest, run_distributed, wall_budget_spent
from ..fastpath import PRECISIONS, FastPath, FrozenEncoder, choose_fast_path
from ..progress import Progress
from ..tensorboard import ScalarWriter
from .curve import record_val_point
from .loss import (NEAR_SURFACE_M, check_near_weighting, cmwae_loss, hidden_pixels, hidden_too_far, near_surface_mask,
                   pooled_nearest_error)
from .model import MODALITIES, Cmwae, CmwaeConfig, make_config

log = logging.getLogger(__name__)
CHECKPOINT_KIND = "cmwae"
# stereo: the corrupted input is the simulated D455's depth the dataset stores for each frame
# (`cmnav dataset --depth stereo`), the target its clean rendered depth.  stereo-mix: what a
# deployed encoder meets, mixed per image: the stored stereo depth on STEREO_MIX_STEREO_FRACTION of
# the images (the clean depth on the rest), then, on top, one of two patch schemes drawn per image
# with its own pristine share: S2's 100 px squares on the images CmwaeTrainConfig.squares_share
# draws (a quarter of all at its default: S2 leaves half of its images pristine), the policy's 1-30 px
# patches on the others' half; the target is the clean depth.
STEREO_SCHEMES = ("stereo", "stereo-mix")
CORRUPTION_SCHEMES = ("s1", "s2", "policy", "none", *STEREO_SCHEMES)
STEREO_MIX_STEREO_FRACTION = 0.5
STEREO_MIX_SQUARES_SHARE = 0.5


@dataclass(frozen=True)
class CmwaeTrainConfig:
    data_dir: str
    out_dir: str
    # More datasets whose train splits join data_dir's (e.g. frames along a policy's flights, `cmnav
    # dataset --policy`); the validation curve stays on data_dir's val split, Table I's images.
    extra_data_dirs: tuple[str, ...] = ()
    scheme: str = "s2"
    # stereo-mix: the share of the images whose overlay is S2's 100 px squares (the rest: the policy's
    # patches); S2 leaves half of them pristine, so 0.5 puts squares on a quarter of all images.
    squares_share: float = STEREO_MIX_SQUARES_SHARE
    modalities: tuple[str, ...] = MODALITIES
    size: str = "paper"
    steps: int | None = None
    epochs: int | None = None
    batch_size: int = 64
    lr: float = 1e-4
    lr_final: float | None = None  # cosine decay from lr at step 0 to lr_final at the last step; None: constant
    mmd_weight: float = 10.0
    # Weight of a corrupted image's reconstruction error against a pristine one's (1: the paper's
    # plain mean).  S2 corrupts half the images; above 1 the gradient leans on depth-from-gray.
    corrupted_loss_weight: float = 1.0
    precision: str = "auto"  # training.fastpath: bf16 autocast (fp32 master weights and loss) where the CPU has it
    init_from: str | None = None  # start from this checkpoint's weights (not its optimizer or step)
    # Latent anchoring: fine-tune only the encoder of this CMWAE checkpoint (its decoder frozen) so
    # that the latent of corrupted depth comes close to the anchor's latent of the same pair with
    # clean depth: loss += anchor_weight * mean (z - z_anchor(gray, clean depth))^2.  The decoder
    # and the clean latents stay where they were, so the clean reconstruction stays, and what is
    # learnt is depth-from-gray where depth is missing.  Starts from the anchor's weights.
    anchor_from: str | None = None
    anchor_weight: float = 1.0
    # Cross-modal consistency, for fine-tuning encoder and decoder together (no anchor): loss +=
    # consistency_weight * mean over the corrupted images of (z - sg[z(gray, clean depth)])^2, the
    # latent of corrupted depth pulled toward this encoder's own latent of the same pair with clean
    # depth.  Anchoring keeps the anchor's clean latents; this lets them improve (new views) while
    # the corrupted latents follow them.
    consistency_weight: float = 0.0
    # Near-surface weighting: each image's reconstruction error is a weighted mean over its pixels,
    # weight 1 + near_weight where the true surface is nearer than near_m (m).  A small near object
    # (a panel's edge) is what the vehicle hits, and the plain mean gives it almost no weight.
    near_weight: float = 0.0
    near_m: float = NEAR_SURFACE_M
    # The teacher's view: loss += pooled_weight * the error of the nearest surface per cell of the
    # teacher's 18 x 32 grid (loss.TEACHER_GRID, near cells weighted as above).  A pole a few pixels
    # wide is a few pixels of the full-frame mean but a whole cell of what the teacher flies on.
    pooled_weight: float = 0.0
    # Pessimism under hidden depth: the pixels the degraded input lost (and, in the teacher's-view
    # term, the cells holding one) whose reconstruction reads farther than the truth weigh
    # hidden_far_weight more.  Under a 100 px square the mean-square optimum blends near and far
    # guesses, and a surface read too far is what the policy flies into; this tilts the guess near.
    hidden_far_weight: float = 0.0
    seed: int = 0
    device: str = "cpu"
    workers: int = 2
    checkpoint_every: int = 500
    log_every: int = 10
    val_images: int = 256
    resume: bool = False
    max_wall_s: float | None = None  # stop (with a checkpoint) after this long

    def validate(self) -> None:
        if self.scheme not in CORRUPTION_SCHEMES:
            raise ValueError(f"scheme={self.scheme!r} must be one of {CORRUPTION_SCHEMES}")
        if not 0.0 <= self.squares_share <= 1.0:
            raise ValueError(f"squares_share={self.squares_share} must lie in [0, 1]")
        if self.squares_share != STEREO_MIX_SQUARES_SHARE and self.scheme != "stereo-mix":
            raise ValueError(f"squares_share applies to scheme 'stereo-mix', not {self.scheme!r}")
        if (self.steps is None) == (self.epochs is None):
            raise ValueError("give exactly one of steps or epochs")
        for key in ("batch_size", "checkpoint_every", "log_every"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key}={getattr(self, key)} must be >= 1")
        if (self.steps or 1) < 1 or (self.epochs or 1) < 1:
            raise ValueError("steps and epochs must be >= 1")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision={self.precision!r} must be one of {PRECISIONS}")
        if not 0.0 < self.corrupted_loss_weight <= 100.0:
            raise ValueError(f"corrupted_loss_weight={self.corrupted_loss_weight} must lie in (0, 100]")
        if not 0.0 < self.anchor_weight <= 1000.0:
            raise ValueError(f"anchor_weight={self.anchor_weight} must lie in (0, 1000]")
        if not 0.0 <= self.consistency_weight <= 1000.0:
            raise ValueError(f"consistency_weight={self.consistency_weight} must lie in [0, 1000]")
        check_near_weighting(self.near_weight, self.near_m)
        if not 0.0 <= self.pooled_weight <= 1000.0:
            raise ValueError(f"pooled_weight={self.pooled_weight} must lie in [0, 1000]")
        if not 0.0 <= self.hidden_far_weight <= 1000.0:
            raise ValueError(f"hidden_far_weight={self.hidden_far_weight} must lie in [0, 1000]")
        if self.consistency_weight > 0.0 and self.anchor_from is not None:
            raise ValueError("consistency_weight and anchor_from both pull the corrupted latent: anchoring toward the "
                             "anchor's clean latent, consistency toward this encoder's own; give one")  # fmt: skip
        if self.anchor_from is not None and self.init_from is not None:
            raise ValueError("anchor_from starts from the anchor's weights: give it or init_from, not both")
        if self.lr <= 0 or (self.lr_final is not None and not 0 <= self.lr_final <= self.lr):
            raise ValueError(f"lr={self.lr}, lr_final={self.lr_final}: need lr > 0 and 0 <= lr_final <= lr")


def learning_rate(config: CmwaeTrainConfig, step: int, total_steps: int) -> float:
    """The learning rate for optimizer step `step` (0-based) of `total_steps`: constant, or a cosine from
    lr to lr_final. It depends on the step alone, so a resumed run follows the same schedule."""
    if config.lr_final is None:
        return config.lr
    progress = min(step / max(total_steps - 1, 1), 1.0)
    return config.lr_final + 0.5 * (config.lr - config.lr_final) * (1.0 + math.cos(math.pi * progress))


def _pixel_weights(config: CmwaeTrainConfig, recon: torch.Tensor, depth: torch.Tensor, hidden: torch.Tensor) -> torch.Tensor | None:
    """Each pixel's weight in its image's reconstruction error (None: the plain mean): near
    surfaces weigh near_weight more, hidden pixels read too far hidden_far_weight more."""
    if not config.near_weight and not config.hidden_far_weight:
        return None
    weights = 1.0 + config.near_weight * near_surface_mask(depth, config.near_m)
    return weights + config.hidden_far_weight * hidden_too_far(recon, depth, hidden)


def _corrupt(depth: torch.Tensor, scheme: str, generator: torch.Generator, stereo: torch.Tensor | None = None,
             squares_share: float = STEREO_MIX_SQUARES_SHARE) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """(corrupted depth, [B] bool: which images were degraded); ``stereo``: the stored stereo depth
    of the batch (the stereo schemes); ``squares_share``: stereo-mix's share of S2's squares."""
    if scheme in STEREO_SCHEMES and stereo is None:
        raise ValueError(f"scheme {scheme!r} needs the stereo depth of each frame: a `cmnav dataset --depth stereo` dataset")
    if scheme == "stereo":
        return stereo, torch.ones(depth.shape[0], dtype=torch.bool)
    if scheme == "stereo-mix":
        return _stereo_mix(depth, stereo, generator, squares_share)
    if scheme == "none":
        return depth, torch.zeros(depth.shape[0], dtype=torch.bool)
    corrupted, masks = corrupt_with_scheme(depth, SCHEMES[scheme], generator)
    return corrupted, masks.flatten(1).any(dim=1)


def _stereo_mix(depth: torch.Tensor, stereo: torch.Tensor, generator: torch.Generator,
                squares_share: float) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Scheme "stereo-mix" (see STEREO_MIX_STEREO_FRACTION): each image's base is its stereo or its
    clean depth; on top of it S2's squares with probability ``squares_share``, else the policy's
    patches."""
    batch = depth.shape[0]
    use_stereo = torch.rand(batch, generator=generator) < STEREO_MIX_STEREO_FRACTION
    corrupted = torch.where(use_stereo[:, None, None, None], stereo, depth)
    squares = torch.rand(batch, generator=generator) < squares_share
    masked = torch.zeros(batch, dtype=torch.bool)
    for name, chosen in (("s2", squares), ("policy", ~squares)):
        patched, masks = corrupt_with_scheme(corrupted, SCHEMES[name], generator)
        hit = chosen & masks.flatten(1).any(dim=1)
        corrupted = torch.where(hit[:, None, None, None], patched, corrupted)
        masked |= hit
    return corrupted, use_stereo | masked


@torch.no_grad()
def validation_mse(model: Cmwae, loader: DataLoader, device: torch.device, coverage: float, max_images: int, seed: int,
                   path: FastPath) -> float:  # fmt: skip
    """Mean reconstruction MSE on up to max_images with Table I's evaluation corruption."""
    model.eval()
    generator = torch.Generator().manual_seed(seed)
    total, count = 0.0, 0
    for gray, depth, *_ in loader:
        if count >= max_images:
            break
        masks = patch_masks(torch.full((depth.shape[0],), coverage), evaluation_scheme(coverage), generator)
        corrupted = corrupt_depth(depth, masks)
        with path.autocast(device):
            _, recon = model(path.image(gray.to(device)), path.image(corrupted.to(device)))
        total += float(((recon.float().cpu() - depth) ** 2).mean(dim=(1, 2, 3)).sum())
        count += depth.shape[0]
    model.train()
    return total / max(count, 1)


@torch.no_grad()
def validation_stereo_mse(model: Cmwae, loader: DataLoader, device: torch.device, max_images: int, path: FastPath) -> float:
    """Mean reconstruction MSE on up to max_images with their stored stereo depth as the input."""
    model.eval()
    total, count = 0.0, 0
    for gray, depth, stereo in loader:
        if count >= max_images:
            break
        with path.autocast(device):
            _, recon = model(path.image(gray.to(device)), path.image(stereo.to(device)))
        total += float(((recon.float().cpu() - depth) ** 2).mean(dim=(1, 2, 3)).sum())
        count += depth.shape[0]
    model.train()
    return total / max(count, 1)


def train_cmwae(config: CmwaeTrainConfig) -> Path:
    """Train; returns the checkpoint directory."""
    config.validate()
    return run_distributed(config.device, lambda info, device: _train(config, info, device))


def _train(config: CmwaeTrainConfig, info: DistInfo, device: torch.device) -> Path:
    out = Path(config.out_dir)
    torch.manual_seed(config.seed)
    dataset = GrayDepthStereoDataset if config.scheme in STEREO_SCHEMES else GrayDepthDataset
    train_set = ConcatDataset([dataset(d, "train") for d in (config.data_dir, *config.extra_data_dirs)])
    val_set = dataset(config.data_dir, "val")
    sampler = DistributedSampler(train_set, seed=config.seed) if info.enabled else None
    loader_generator = torch.Generator().manual_seed(config.seed)
    loader = DataLoader(train_set, batch_size=config.batch_size, shuffle=sampler is None, sampler=sampler,
                        num_workers=config.workers, drop_last=len(train_set) >= config.batch_size,
                        generator=loader_generator, persistent_workers=config.workers > 0)  # fmt: skip
    val_loader = DataLoader(val_set, batch_size=config.batch_size, num_workers=0)
    total_steps = config.steps if config.steps is not None else config.epochs * len(loader)

    model_config = make_config(config.size, config.modalities)
    path = choose_fast_path(config.precision, device)
    model = path.prepare_trained(Cmwae(model_config).to(device))
    anchor_net, anchor_card = _read_anchor(config, model_config)
    if anchor_net is not None:
        model.decoder.requires_grad_(False)
    optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=config.lr)
    corruption_generator = torch.Generator().manual_seed(config.seed * 1000 + info.rank)
    loss_generator = torch.Generator(device=device).manual_seed(config.seed * 1000 + info.rank + 1)
    step, epoch = 0, 0
    state = load_train_state(out) if config.resume else None
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        step, epoch = state["step"], state["epoch"]
        corruption_generator.set_state(state["corruption_rng"])
        log.info("resumed %s at step %d", out, step)
    elif config.init_from is not None:
        init_card = _read_matching_card(config.init_from, model_config, config)
        load_weights(config.init_from, model)
        log.info("initialised from %s (step %s)", config.init_from, init_card.get("step"))
    elif anchor_net is not None:
        model.load_state_dict(anchor_net.state_dict())
        log.info("initialised from the anchor %s (step %s)", config.anchor_from, anchor_card.get("step"))
    anchor = None if anchor_net is None else FrozenEncoder(anchor_net.encoder.to(device), path)
    if config.resume and state is None:
        log.warning("--resume: no training state in %s, starting %s", out,
                    "from scratch" if config.init_from is None else f"from {config.init_from}")  # fmt: skip
    ddp_model = DistributedDataParallel(model) if info.enabled else model
    writer = ScalarWriter(out / "tensorboard") if info.is_main else None
    desc = f"train cmwae ({config.scheme}, {'+'.join(config.modalities)})"
    progress = Progress(total_steps, desc, unit="steps", initial=step) if info.is_main else None
    meta = {"train": asdict(config), "world_size": info.world_size, "dataset": str(config.data_dir),
            "extra_datasets": list(config.extra_data_dirs),
            "fast_path": {"name": path.name, "reason": path.reason}}  # fmt: skip

    def checkpoint() -> None:
        val = {f"val/mse_{int(c * 100)}pct": validation_mse(model, val_loader, device, c, config.val_images, config.seed, path)
               for c in (0.0, 0.5)}  # fmt: skip
        val["val/mse_ratio_50_over_0"] = val["val/mse_50pct"] / max(val["val/mse_0pct"], 1e-12)
        if config.scheme in STEREO_SCHEMES:
            val["val/mse_stereo"] = validation_stereo_mse(model, val_loader, device, config.val_images, path)
        if writer is not None:
            writer.add_scalars(step, val)
            record_val_point(out, step, val)
            save_weights(out, model, CHECKPOINT_KIND, asdict(model_config), step, {**meta, **val})
            save_train_state(out, {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
                                   "epoch": epoch, "corruption_rng": corruption_generator.get_state()})  # fmt: skip

    t_last, images = time.monotonic(), 0
    t_start = t_last
    model.train()
    while step < total_steps:
        if sampler is not None:
            sampler.set_epoch(epoch)
        for gray, depth, *stereo in loader:
            if step >= total_steps:
                break
            corrupted, was_corrupted = _corrupt(depth, config.scheme, corruption_generator, *stereo, squares_share=config.squares_share)
            hidden = hidden_pixels(corrupted, depth).to(device)
            gray, depth, corrupted = path.image(gray.to(device)), depth.to(device), path.image(corrupted.to(device))
            with path.autocast(device):
                z, recon = ddp_model(gray, corrupted)
            weights = torch.where(was_corrupted, config.corrupted_loss_weight, 1.0).to(device)
            pixel_weights = _pixel_weights(config, recon.float(), depth, hidden)
            losses = cmwae_loss(recon.float(), depth, z.float(), config.mmd_weight, loss_generator, weights, pixel_weights)
            if config.pooled_weight > 0.0:
                losses["pooled"] = pooled_nearest_error(recon.float(), depth, config.near_weight, config.near_m,
                                                        hidden=hidden, hidden_far_weight=config.hidden_far_weight).mean()  # fmt: skip
                losses["loss"] = losses["loss"] + config.pooled_weight * losses["pooled"]
            if anchor is not None:
                with torch.no_grad():
                    z_anchor = anchor(gray, path.image(depth))
                losses["anchor"] = ((z.float() - z_anchor) ** 2).mean()
                losses["loss"] = losses["loss"] + config.anchor_weight * losses["anchor"]
            if config.consistency_weight > 0.0:
                hit = was_corrupted.nonzero().squeeze(1).to(device)  # a clean image's clean latent is z itself
                with torch.no_grad(), path.autocast(device):
                    z_clean = model.encoder(path.image(gray[hit]), path.image(depth[hit])).float()
                losses["consistency"] = ((z.float()[hit] - z_clean) ** 2).mean(dim=1).sum() / max(len(hit), 1)
                losses["loss"] = losses["loss"] + config.consistency_weight * losses["consistency"]
            lr = learning_rate(config, step, total_steps)
            for group in optimizer.param_groups:
                group["lr"] = lr  # also overrides the rate a resumed optimizer state carries
            optimizer.zero_grad(set_to_none=True)
            losses["loss"].backward()
            optimizer.step()
            step += 1
            images += gray.shape[0] * info.world_size
            if step % config.log_every == 0 or step == total_steps:
                values = {k: float(all_reduce_mean(v.detach(), info)) for k, v in losses.items()}
                now = time.monotonic()
                if writer is not None:
                    writer.add_scalars(step, {f"train/{k}": v for k, v in values.items()}
                                       | {"train/images_per_s": images / (now - t_last), "train/lr": lr})  # fmt: skip
                t_last, images = now, 0
                if progress is not None:
                    progress.update(0, loss=values["loss"], mse=values["recon_mse"], mmd=values["mmd"],
                                    **{k: values[k] for k in ("pooled", "anchor", "consistency") if k in values})
            if progress is not None:
                progress.update(1)
            if step % config.checkpoint_every == 0 and step < total_steps:
                checkpoint()
            if wall_budget_spent(config.max_wall_s, t_start, info, device):
                log.info("wall-clock budget of %.0f s reached at step %d", config.max_wall_s, step)
                total_steps = step
                break
        epoch += 1
    checkpoint()
    log_weights_digest(model, info)
    if progress is not None:
        progress.close()
    if writer is not None:
        writer.close()
    return out


def _read_matching_card(ckpt_dir: str, model_config: CmwaeConfig, config: CmwaeTrainConfig) -> dict:
    """The card of a checkpoint to start from, refused unless its network is the one being trained."""
    card = read_card(ckpt_dir, CHECKPOINT_KIND)
    if _config_from_card(card) != model_config:
        raise ValueError(f"{ckpt_dir}: its network ({card['config']}) is not the one "
                         f"--size {config.size} --modalities {','.join(config.modalities)} builds")  # fmt: skip
    return card


def _read_anchor(config: CmwaeTrainConfig, model_config: CmwaeConfig) -> tuple[Cmwae | None, dict]:
    """The --anchor checkpoint (read once: the trained model starts from its weights, its encoder
    becomes the frozen anchor) and its card; (None, {}) without --anchor."""
    if config.anchor_from is None:
        return None, {}
    card = _read_matching_card(config.anchor_from, model_config, config)
    anchor = Cmwae(model_config)
    load_weights(config.anchor_from, anchor)
    return anchor, card


def _config_from_card(card: dict) -> CmwaeConfig:
    return CmwaeConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in card["config"].items()})


def load_cmwae(ckpt_dir: str | Path, device: str | torch.device = "cpu") -> tuple[Cmwae, dict]:
    """The trained network (eval mode) and its card."""
    card = read_card(ckpt_dir, CHECKPOINT_KIND)
    model = Cmwae(_config_from_card(card))
    load_weights(ckpt_dir, model)
    return model.to(device).eval(), card
