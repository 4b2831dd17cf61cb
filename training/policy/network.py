"""The navigation policy (PAPER.md §Policy): observation -> FC 256-128-64 ELU -> GRU -> FC -> 3,
with a value head on the GRU output, and the observation normaliser inside the network so the
exported graph carries it.

Observation = the runtime's 15-value state then the encoder's 64-d latent (79 values,
``runtime.contract.constants``).  The action head outputs the mean of a Gaussian whose
state-independent log standard deviation is a parameter; the runtime flies the mean.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.distributed as dist
from torch import Tensor, nn

from runtime.contract.constants import ACTION_DIM, OBSERVATION_DIM

log = logging.getLogger(__name__)

CHECKPOINT_KIND = "policy"


@dataclass(frozen=True)
class PolicyConfig:
    mlp_sizes: tuple[int, ...] = (256, 128, 64)
    gru_size: int = 64
    init_log_std: float = -0.5
    # The running observation statistics stop updating after this many samples (a frozen
    # normaliser keeps late training from shifting the inputs under the policy).
    obs_norm_max_count: float = 1e8

    def validate(self) -> None:
        if not self.mlp_sizes or any(s <= 0 for s in self.mlp_sizes):
            raise ValueError(f"PolicyConfig.mlp_sizes={self.mlp_sizes} must be positive widths")
        if self.gru_size <= 0:
            raise ValueError(f"PolicyConfig.gru_size={self.gru_size} must be > 0")

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> PolicyConfig:
        known = {k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items() if k in cls.__dataclass_fields__}
        return cls(**known)


# Paper size, and a tiny one for tests.
POLICY_SIZES: dict[str, PolicyConfig] = {
    "paper": PolicyConfig(),
    "tiny": PolicyConfig(mlp_sizes=(32, 16), gru_size=8),
}


class RunningNorm(nn.Module):
    """Per-feature running mean/variance (parallel Welford), applied as (x - mean) / sqrt(var + eps)
    clipped to +-clip.  The statistics are buffers: they are saved, loaded and exported."""

    def __init__(self, size: int, eps: float = 1e-5, clip: float = 10.0, max_count: float = 1e8) -> None:
        super().__init__()
        self.eps, self.clip, self.max_count = eps, clip, max_count
        self.register_buffer("mean", torch.zeros(size))
        self.register_buffer("var", torch.ones(size))
        # An integer count: checkpoints store float tensors as fp16, which would overflow it.
        self.register_buffer("count", torch.tensor(0, dtype=torch.int64))

    @torch.no_grad()
    def update(self, x: Tensor) -> None:
        x = x.reshape(-1, x.shape[-1]).float()
        if float(self.count) >= self.max_count:
            return
        # Moments summed over every process under torchrun, so that all ranks keep the same
        # statistics (and so the same network): (n, sum x, sum x^2).
        sums = torch.cat([torch.tensor([float(x.shape[0])], device=x.device), x.sum(dim=0), x.square().sum(dim=0)])
        if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
            dist.all_reduce(sums)
        n = float(sums[0])
        if n == 0:
            return
        batch_mean = sums[1 : 1 + x.shape[1]] / n
        batch_var = (sums[1 + x.shape[1] :] / n - batch_mean.square()).clamp_min(0.0)
        count = float(self.count)
        total = count + n
        delta = batch_mean - self.mean
        self.mean += delta * (n / total)
        self.var.copy_((self.var * count + batch_var * n + delta.square() * count * n / total) / total)
        self.count.fill_(int(total))

    def forward(self, x: Tensor) -> Tensor:
        return ((x - self.mean) / torch.sqrt(self.var + self.eps)).clamp(-self.clip, self.clip)


class ActorCritic(nn.Module):
    """obs [..., 79] -> (action mean [..., 3], value [...], hidden).  ``hidden`` is [B, H]."""

    def __init__(self, config: PolicyConfig = PolicyConfig()) -> None:
        super().__init__()
        config.validate()
        self.config = config
        self.obs_norm = RunningNorm(OBSERVATION_DIM, max_count=config.obs_norm_max_count)
        layers: list[nn.Module] = []
        width = OBSERVATION_DIM
        for size in config.mlp_sizes:
            layers += [nn.Linear(width, size), nn.ELU()]
            width = size
        self.mlp = nn.Sequential(*layers)
        self.gru = nn.GRUCell(width, config.gru_size)
        self.action_head = nn.Linear(config.gru_size, ACTION_DIM)
        self.value_head = nn.Linear(config.gru_size, 1)
        self.log_std = nn.Parameter(torch.full((ACTION_DIM,), float(config.init_log_std)))
        nn.init.orthogonal_(self.action_head.weight, gain=0.01)
        nn.init.zeros_(self.action_head.bias)
        nn.init.orthogonal_(self.value_head.weight, gain=1.0)
        nn.init.zeros_(self.value_head.bias)

    @property
    def hidden_size(self) -> int:
        return self.config.gru_size

    def initial_hidden(self, batch: int, device: torch.device | str = "cpu") -> Tensor:
        return torch.zeros(batch, self.config.gru_size, device=device)

    def step(self, obs: Tensor, hidden: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """One control step for a batch: obs [B, 79], hidden [B, H] -> (mean [B, 3], value [B],
        hidden_next [B, H])."""
        h = self.gru(self.mlp(self.obs_norm(obs)), hidden)
        return self.action_head(h), self.value_head(h).squeeze(-1), h

    def unroll(self, obs: Tensor, hidden0: Tensor, starts: Tensor) -> tuple[Tensor, Tensor]:
        """Re-run a rollout: obs [T, B, 79], hidden0 [B, H] (the state before step 0), starts
        [T, B] bool (an episode begins at this step: its hidden state is zeroed first) ->
        (mean [T, B, 3], value [T, B]).  The MLP runs on all T x B at once; only the GRU loops."""
        features = self.mlp(self.obs_norm(obs))
        h = hidden0
        outputs = []
        for t in range(obs.shape[0]):
            h = torch.where(starts[t].unsqueeze(-1), torch.zeros_like(h), h)
            h = self.gru(features[t], h)
            outputs.append(h)
        hs = torch.stack(outputs)
        return self.action_head(hs), self.value_head(hs).squeeze(-1)


class EncoderMismatchError(ValueError):
    """The policy was trained on another encoder than the one given."""


def check_trained_on(policy_card: dict, policy_dir: str | Path, encoder_dir: str | Path) -> str:
    """The fingerprint of ``encoder_dir``, after checking that the policy (its card) was trained on that
    encoder; :class:`EncoderMismatchError` names both fingerprints and the fix.  A card that names no
    encoder is let through with a warning."""
    from training.checkpoint import checkpoint_fingerprint

    fingerprint = checkpoint_fingerprint(encoder_dir)
    meta = policy_card.get("meta", {})
    trained_on = meta.get("encoder_fingerprint")
    if trained_on is None:
        log.warning("%s does not name the encoder it was trained on (meta.encoder_fingerprint); cannot check it", policy_dir)
    elif trained_on != fingerprint:
        raise EncoderMismatchError(
            f"the policy {policy_dir} was trained on encoder {trained_on} ({meta.get('encoder')}), but {encoder_dir} is "
            f"{fingerprint}: pass --encoder the checkpoint the policy was trained with (meta.encoder_fingerprint in the "
            f"policy's model.json), or fine-tune the policy on this encoder: cmnav train policy --encoder {encoder_dir} "
            f"--init-from {policy_dir} --out NEW_DIR"
        )
    return fingerprint


def load_policy(ckpt_dir, device: torch.device | str = "cpu") -> tuple[ActorCritic, dict]:
    """The trained policy (eval mode) from a checkpoint directory, and its card."""
    from training.checkpoint import load_weights, read_card

    card = read_card(ckpt_dir, CHECKPOINT_KIND)
    model = ActorCritic(PolicyConfig.from_json(card["config"]))
    load_weights(ckpt_dir, model)
    return model.to(device).eval(), card
