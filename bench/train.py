"""`cmnav bench train`: env-steps/s of policy training for N envs on one device, and the share
of each stage: rendering, preprocessing + corruption, the frozen encoder, physics, the policy's
action sampling, and the PPO update (timed on the rollout just collected).

Each N runs a short rollout in :class:`training.policy.env.NavEnv` (the training configuration:
a random half of the envs corrupted each step, kicks, jitter) at curriculum level
``level`` with the paper-size policy, after warm-up steps that load kernels and fill caches.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace

import torch

from training.cmwae.model import Cmwae, make_config
from training.cmwae.train import load_cmwae
from training.policy.env import CurriculumConfig, NavEnv, NavEnvConfig
from training.policy.network import POLICY_SIZES, ActorCritic
from training.policy.ppo import PpoConfig, ReturnNormalizer, ppo_update
from training.policy.train import collect_rollout

from .device import device_name, synchronize

STAGES = ("render", "preprocess", "encode", "physics", "policy", "ppo_update")


@dataclass(frozen=True)
class TrainBenchConfig:
    env_counts: tuple[int, ...] = (16, 64)
    device: str = "cpu"
    encoder_dir: str | None = None  # default: a freshly initialised encoder of encoder_size
    encoder_size: str = "paper"
    policy_size: str = "paper"
    rollout_steps: int = 16
    warmup_steps: int = 2
    level: int = 10
    seed: int = 0


def quick(config: TrainBenchConfig) -> TrainBenchConfig:
    """A seconds-long smoke run of the whole path, not a measurement."""
    return replace(config, env_counts=(2,), encoder_size="tiny", policy_size="tiny", rollout_steps=4, warmup_steps=1, level=2)


def run_train_bench(config: TrainBenchConfig) -> dict:
    device = torch.device(config.device)
    torch.manual_seed(config.seed)
    if config.encoder_dir is not None:
        encoder = load_cmwae(config.encoder_dir, device)[0].encoder
        encoder_name = config.encoder_dir
    else:
        encoder = Cmwae(make_config(config.encoder_size)).encoder
        encoder_name = f"untrained {config.encoder_size}-size CMWAE encoder"
    rows = []
    for n in config.env_counts:
        env_config = NavEnvConfig(num_envs=n, curriculum=CurriculumConfig(start_level=config.level, min_level=config.level,
                                                                             max_level=config.level))  # fmt: skip
        env = NavEnv(env_config, encoder, device, seed=config.seed)
        policy = ActorCritic(POLICY_SIZES[config.policy_size]).to(device)
        ppo = PpoConfig(rollout_steps=config.rollout_steps, minibatches=min(4, n))
        normalizer = ReturnNormalizer(n, ppo.gamma, device)
        optimizer = torch.optim.Adam(policy.parameters(), lr=ppo.lr)
        obs = env.reset()
        hidden = policy.initial_hidden(n, device)
        starts = torch.ones(n, dtype=torch.bool, device=device)
        warm = replace(ppo, rollout_steps=config.warmup_steps)
        _, hidden, starts, obs, _ = collect_rollout(policy, env, obs, hidden, starts, normalizer, warm)
        env.stage_seconds = dict.fromkeys(env.stage_seconds, 0.0)
        t0 = time.perf_counter()
        rollout, hidden, starts, obs, _ = collect_rollout(policy, env, obs, hidden, starts, normalizer, ppo)
        synchronize(device)
        t_collect = time.perf_counter() - t0
        policy.train()
        t1 = time.perf_counter()
        ppo_update(policy, optimizer, rollout, ppo, torch.Generator().manual_seed(0))
        synchronize(device)
        t_update = time.perf_counter() - t1
        seconds = dict(env.stage_seconds)
        seconds["policy"] = max(t_collect - sum(seconds.values()), 0.0)  # sampling, buffers, bookkeeping
        seconds["ppo_update"] = t_update
        total = t_collect + t_update
        steps = n * config.rollout_steps
        rows.append({
            "envs": n, "env_steps": steps, "env_steps_per_s": steps / total, "collect_env_steps_per_s": steps / t_collect,
            "share": {k: seconds[k] / total for k in STAGES}, "ms_per_step": {k: 1e3 * seconds[k] / config.rollout_steps for k in STAGES},
        })  # fmt: skip
    return {"device": device_name(device), "encoder": encoder_name, "threads": torch.get_num_threads(),
            "config": asdict(config), "rows": rows}  # fmt: skip


def format_train_bench(result: dict) -> str:
    lines = [
        f"bench train on {result['device']} ({result['threads']} torch threads), encoder: {result['encoder']}, "
        f"level {result['config']['level']}, rollout {result['config']['rollout_steps']} steps",
        "",
        "| envs | env-steps/s (with PPO update) | env-steps/s (collect only) | " + " | ".join(f"{s} %" for s in STAGES) + " |",
        "|---|---|---|" + "---|" * len(STAGES),
    ]
    for row in result["rows"]:
        shares = " | ".join(f"{100 * row['share'][s]:.1f}" for s in STAGES)
        lines.append(f"| {row['envs']} | {row['env_steps_per_s']:.1f} | {row['collect_env_steps_per_s']:.1f} | {shares} |")
    return "\n".join(lines)
