"""Recurrent PPO with GAE for :class:`~training.policy.network.ActorCritic` on :class:`NavEnv`.

Written here rather than taken from rsl-rl-lib or skrl (DESIGN §5 asks for a maintained library
unless it cannot express the architecture):
- rsl-rl-lib (5.5) builds its recurrent model as observation -> RNN -> MLP; the paper's policy is
  FC 256-128-64 -> GRU -> FC, which its RNNModel cannot express without replacing the model class
  and its rollout storage.  It also requires tensordict (a compiled extension pinned to torch
  releases), GitPython and onnxscript, none of which the offline GPU machine has, and the
  one-command pipeline must run with torch, onnx, onnxruntime and numpy alone.
- skrl needs gymnasium and its wrappers for the same offline machine, and its RNN examples also put
  the RNN first.
The algorithm is Sample Factory's as PAPER.md lists it: rollouts of 32 steps, 4 epochs, clip 0.2,
GAE (gamma 0.98, lambda 0.95), value loss coefficient 2.0, reward scale 0.1, normalised inputs
(inside the network) and returns; the GRU is trained by truncated back-propagation through each
32-step rollout, its state reset where episodes begin.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from .network import ActorCritic


@dataclass(frozen=True)
class PpoConfig:
    rollout_steps: int = 32
    epochs: int = 4
    minibatches: int = 4  # split over envs (whole sequences stay together)
    lr: float = 3e-4  # the paper's 1e-4 is for 1e8 steps; short runs learn faster at 3e-4
    gamma: float = 0.98
    gae_lambda: float = 0.95
    clip: float = 0.2
    value_coef: float = 2.0
    entropy_coef: float = 0.001
    reward_scale: float = 0.1
    normalize_returns: bool = True
    max_grad_norm: float = 1.0
    # Stop an update's epochs early once a minibatch's approximate KL from the rollout's policy passes
    # 1.5x this (Stable-Baselines3's target_kl), before that minibatch steps; None: every epoch runs.
    # With a small action noise (a fine-tuned student's std 0.1), a small move of the mean is a large KL.
    target_kl: float | None = None

    def validate(self, num_envs: int) -> None:
        if self.rollout_steps < 1 or self.epochs < 1 or self.minibatches < 1:
            raise ValueError("rollout_steps, epochs and minibatches must be >= 1")
        if self.target_kl is not None and not self.target_kl > 0:
            raise ValueError(f"target_kl={self.target_kl} must be > 0 (or None: no early stop)")
        if self.minibatches > num_envs:
            raise ValueError(f"minibatches={self.minibatches} cannot exceed the number of envs ({num_envs})")

    def to_json(self) -> dict:
        return asdict(self)


class ReturnNormalizer:
    """Scales rewards by the running standard deviation of the discounted return (as Sample
    Factory's normalised returns and gym's VecNormalize do), so value targets stay O(1)."""

    def __init__(self, num_envs: int, gamma: float, device: torch.device) -> None:
        self.gamma = gamma
        self.ret = torch.zeros(num_envs, device=device)
        self.mean, self.var, self.count = 0.0, 1.0, 1e-4

    def __call__(self, reward: Tensor, done: Tensor) -> Tensor:
        self.ret = self.ret * self.gamma + reward
        batch_mean, batch_var, n = float(self.ret.mean()), float(self.ret.var(unbiased=False)), self.ret.numel()
        delta, total = batch_mean - self.mean, self.count + n
        self.mean += delta * n / total
        self.var = (self.var * self.count + batch_var * n + delta**2 * self.count * n / total) / total
        self.count = total
        self.ret = torch.where(done, torch.zeros_like(self.ret), self.ret)
        return reward / (self.var**0.5 + 1e-8)

    def state_dict(self) -> dict:
        return {"mean": self.mean, "var": self.var, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.mean, self.var, self.count = state["mean"], state["var"], state["count"]


@dataclass
class Rollout:
    """One rollout of T steps x N envs.  starts[t]: obs[t] begins an episode (hidden zeroed)."""

    obs: Tensor  # [T, N, 79]
    starts: Tensor  # [T, N] bool
    actions: Tensor  # [T, N, 3] raw samples
    log_probs: Tensor  # [T, N]
    values: Tensor  # [T, N]
    rewards: Tensor  # [T, N] scaled / normalised
    dones: Tensor  # [T, N] bool
    hidden0: Tensor  # [N, H]
    last_value: Tensor  # [N]


def gae(rollout: Rollout, gamma: float, lam: float) -> tuple[Tensor, Tensor]:
    """(advantages, returns) [T, N]; an ended episode does not bootstrap (success, crash and
    timeout all end it, as in Aerial Gym)."""
    steps = rollout.rewards.shape[0]
    advantages = torch.zeros_like(rollout.rewards)
    next_adv = torch.zeros_like(rollout.last_value)
    next_value = rollout.last_value
    for t in reversed(range(steps)):
        not_done = (~rollout.dones[t]).float()
        delta = rollout.rewards[t] + gamma * next_value * not_done - rollout.values[t]
        next_adv = delta + gamma * lam * not_done * next_adv
        advantages[t] = next_adv
        next_value = rollout.values[t]
    return advantages, advantages + rollout.values


def ppo_update(
    model: ActorCritic,
    optimizer: torch.optim.Optimizer,
    rollout: Rollout,
    config: PpoConfig,
    generator: torch.Generator,
    reduce_grads=None,
    critic_only: bool = False,
    reduce_mean=None,
) -> dict[str, float]:
    """Epochs x minibatches of clipped PPO on one rollout; returns mean losses.  ``reduce_grads``
    (multi-GPU) averages gradients across processes before each optimizer step, ``reduce_mean`` a
    tensor (so that every process stops at the same minibatch).  ``critic_only``:
    the loss is the value loss alone (a fine-tune's critic warm-up: ``optimizer`` then holds the
    value head only, so the policy does not move while its critic learns its returns).  With
    ``config.target_kl`` the epochs end at the first minibatch whose KL passes 1.5x it (that
    minibatch does not step); ``updates`` in the result counts the optimizer steps taken."""
    advantages, returns = gae(rollout, config.gamma, config.gae_lambda)
    advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    num_envs = rollout.obs.shape[1]
    stats = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "approx_kl": 0.0, "clip_fraction": 0.0}
    evaluated, updates = 0, 0
    trained = [p for group in optimizer.param_groups for p in group["params"]]  # the norm clipped is of what steps
    kl_limit = None if config.target_kl is None or critic_only else 1.5 * config.target_kl
    for _ in range(config.epochs):
        if evaluated > updates:  # the KL limit was passed
            break
        order = torch.randperm(num_envs, generator=generator).to(rollout.obs.device)
        for idx in order.chunk(config.minibatches):
            mean, value = model.unroll(rollout.obs[:, idx], rollout.hidden0[idx], rollout.starts[:, idx])
            dist = torch.distributions.Normal(mean, model.log_std.exp())
            log_prob = dist.log_prob(rollout.actions[:, idx]).sum(-1)
            ratio = torch.exp(log_prob - rollout.log_probs[:, idx])
            adv = advantages[:, idx]
            policy_loss = -torch.min(ratio * adv, ratio.clamp(1 - config.clip, 1 + config.clip) * adv).mean()
            old_value = rollout.values[:, idx]
            value_clipped = old_value + (value - old_value).clamp(-config.clip, config.clip)
            ret = returns[:, idx]
            value_loss = torch.max((value - ret).square(), (value_clipped - ret).square()).mean()
            entropy = dist.entropy().sum(-1).mean()
            with torch.no_grad():  # of the policy before this minibatch's step
                log_ratio = log_prob - rollout.log_probs[:, idx]
                approx_kl = ((ratio - 1) - log_ratio).mean()
                stats["approx_kl"] += float(approx_kl)
                stats["clip_fraction"] += float(((ratio - 1).abs() > config.clip).float().mean())
            stats["policy_loss"] += float(policy_loss.detach())
            stats["value_loss"] += float(value_loss.detach())
            stats["entropy"] += float(entropy.detach())
            evaluated += 1
            if reduce_mean is not None and kl_limit is not None:
                approx_kl = reduce_mean(approx_kl)
            if kl_limit is not None and float(approx_kl) > kl_limit:
                break
            loss = config.value_coef * value_loss
            if not critic_only:
                loss = loss + policy_loss - config.entropy_coef * entropy
            model.zero_grad(set_to_none=True)
            loss.backward()
            if reduce_grads is not None:
                reduce_grads()
            torch.nn.utils.clip_grad_norm_(trained, config.max_grad_norm)
            optimizer.step()
            updates += 1
    return {k: v / evaluated for k, v in stats.items()} | {"updates": float(updates)}
