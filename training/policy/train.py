"""`cmnav train policy`: recurrent PPO on the batched navigation environment with the frozen
encoder; progress, TensorBoard scalars, periodic checkpoints, resume, and multi-GPU through
torchrun (each process runs its own envs; gradients are averaged)."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
import torch.distributed as dist

from runtime.contract.constants import OBS_LATENT

from ..checkpoint import checkpoint_fingerprint, keep_checkpoint, load_train_state, save_train_state, save_weights
from ..cmwae.train import load_cmwae
from ..distributed import DistInfo, all_reduce_mean, log_weights_digest, run_distributed, wall_budget_spent
from ..progress import Progress
from ..tensorboard import ScalarWriter
from .env import CRASH, SUCCESS, TIMEOUT, CurriculumConfig, NavEnv, NavEnvConfig, env_encoder
from .field import check_vehicle, vehicle_env_overrides
from .network import CHECKPOINT_KIND, ActorCritic, PolicyConfig, load_policy, policy_role
from .ppo import PpoConfig, ReturnNormalizer, Rollout, ppo_update

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PolicyTrainConfig:
    encoder_dir: str | None  # None: the privileged teacher (state + low-resolution clean depth, no encoder)
    out_dir: str
    env_steps: int = 1_000_000  # total over all processes
    num_envs: int = 64  # per process
    device: str = "cpu"
    seed: int = 0
    corruption: str = "train"  # "none" for the depth-only baseline policy
    policy: PolicyConfig = PolicyConfig()
    ppo: PpoConfig = PpoConfig()
    curriculum: CurriculumConfig = CurriculumConfig()
    checkpoint_every: int = 20  # PPO iterations
    keep_checkpoints: bool = False  # every checkpoint's weights also kept in OUT/checkpoints/step-N (training.checkpoint.keep_checkpoint)
    resume: bool = False
    init_from: str | None = None  # start from this policy checkpoint (fine-tuning, e.g. after retraining the encoder)
    # Fine-tuning a distilled student by PPO (DAgger trains neither its critic nor its action noise):
    # the --init-from policy's log std of the action noise set to this (None: kept), ...
    init_log_std: float | None = None
    # ... its critic warmed up for this many iterations (the value head alone learns; the policy
    # flies unchanged) before PPO moves the policy, ...
    critic_warmup_iterations: int = 0
    # ... and its observation normaliser kept as it is (the new episodes' inputs do not shift it).
    freeze_obs_norm: bool = False
    max_wall_s: float | None = None  # stop (with a checkpoint) after this long
    precision: str = "auto"  # the frozen encoder's fast path (training.fastpath)
    env_overrides: dict = field(default_factory=dict)  # other NavEnvConfig fields
    # The vehicle flown: "ideal" (commands followed at once, true state) or "px4" (PX4 v1.16's
    # identified response, latency and EKF2-like estimates: training.policy.field.px4_vehicle_env_overrides;
    # a teacher still observes the true state).
    vehicle: str = "ideal"
    # Episodes end in success at the goal, as the runtime's do (NavEnvConfig.end_at_goal).
    end_at_goal: bool = False

    def env_config(self) -> NavEnvConfig:
        return replace(NavEnvConfig(num_envs=self.num_envs, corruption=self.corruption, curriculum=self.curriculum,
                                    end_at_goal=self.end_at_goal),
                       **vehicle_env_overrides(self.vehicle), **self.env_overrides)  # fmt: skip

    def validate(self) -> None:
        check_vehicle(self.vehicle)
        if self.env_steps < 1:
            raise ValueError(f"env_steps={self.env_steps} must be >= 1")
        if self.checkpoint_every < 1:
            raise ValueError(f"checkpoint_every={self.checkpoint_every} must be >= 1")
        if self.critic_warmup_iterations < 0:
            raise ValueError(f"critic_warmup_iterations={self.critic_warmup_iterations} must be >= 0")
        if self.init_log_std is not None and self.init_from is None and not self.resume:
            raise ValueError("init_log_std sets the action noise of the --init-from policy: give --init-from POLICY_DIR "
                             "(a run from scratch starts at PolicyConfig.init_log_std)")  # fmt: skip
        self.env_config().validate()
        self.policy.validate()
        self.ppo.validate(self.num_envs)


def train_policy(config: PolicyTrainConfig) -> Path:
    """Train; returns the checkpoint directory."""
    config.validate()
    return run_distributed(config.device, lambda info, device: _train(config, info, device))


def _reduce_grads(model: ActorCritic, info: DistInfo):
    if not info.enabled:
        return None

    def reduce() -> None:
        for p in model.parameters():
            if p.grad is not None:
                p.grad.copy_(all_reduce_mean(p.grad, info))

    return reduce


def _train(config: PolicyTrainConfig, info: DistInfo, device: torch.device) -> Path:
    out = Path(config.out_dir)
    torch.manual_seed(config.seed + info.rank)
    if config.encoder_dir is None:  # the teacher: its observation is privileged, there is no encoder
        encoder, encoder_card, encoder_fingerprint = None, {}, None
        policy_config = replace(config.policy, obs_dim=config.env_config().privileged_obs_dim)
    else:
        cmwae, encoder_card = load_cmwae(config.encoder_dir, device)
        encoder_fingerprint = checkpoint_fingerprint(config.encoder_dir)
        encoder = env_encoder(cmwae.encoder, config.precision, device, seed=config.seed)
        policy_config = config.policy
    role = policy_role(encoder_fingerprint)
    env = NavEnv(config.env_config(), encoder, device, seed=config.seed * 1000 + info.rank)
    model = ActorCritic(policy_config).to(device)
    if config.freeze_obs_norm:
        model.obs_norm.max_count = 0  # RunningNorm.update stops at max_count: the loaded statistics stay
    optimizer = torch.optim.Adam(model.parameters(), lr=config.ppo.lr)
    critic_optimizer = torch.optim.Adam(model.value_head.parameters(), lr=config.ppo.lr)
    normalizer = ReturnNormalizer(config.num_envs, config.ppo.gamma, device)
    update_generator = torch.Generator().manual_seed(config.seed * 1000 + info.rank + 1)
    iteration, env_steps = 0, 0
    state = load_train_state(out) if config.resume else None
    if state is not None:
        check_resumed_task(state, out, config.encoder_dir, encoder_fingerprint, config.vehicle, config.end_at_goal)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        if "critic_optimizer" in state:  # written since the critic warm-up (critic_warmup_iterations)
            critic_optimizer.load_state_dict(state["critic_optimizer"])
        for group in optimizer.param_groups + critic_optimizer.param_groups:
            group["lr"] = config.ppo.lr  # --lr also applies to a resumed run (the optimizer state carries the old one)
        normalizer.load_state_dict(state["return_normalizer"])
        env.curriculum.load_state_dict(state["curriculum"])
        env.generator.set_state(state["env_rng"])
        update_generator.set_state(state["update_rng"])
        iteration, env_steps = state["iteration"], state["env_steps"]
        init_meta = state.get("init_from")  # where this run's weights started, if not from scratch
        log.info("resumed %s at iteration %d (%d env steps, level %d)", out, iteration, env_steps, env.curriculum.level)
        if config.init_from is not None:
            log.info("--init-from %s ignored: resuming %s, which already started from it", config.init_from, out)
    else:
        if config.resume:
            log.warning("--resume: no training state in %s, starting from scratch", out)
        init_meta = None if config.init_from is None else init_from_policy(model, config.init_from, encoder_fingerprint, env)
        if config.init_log_std is not None:
            if init_meta is None:  # --resume found no state to resume, and nothing to start from was given
                raise ValueError(f"--init-log-std: {out} holds no training state to resume; give --init-from POLICY_DIR")
            with torch.no_grad():
                model.log_std.fill_(config.init_log_std)
            init_meta["log_std_set_to"] = config.init_log_std
    if info.enabled:  # every process starts from rank 0's weights
        for tensor in list(model.parameters()) + list(model.buffers()):
            dist.broadcast(tensor.data, src=0)

    steps_per_iteration = config.ppo.rollout_steps * config.num_envs * info.world_size
    total_iterations = -(-config.env_steps // steps_per_iteration)
    writer = ScalarWriter(out / "tensorboard") if info.is_main else None
    progress = Progress(total_iterations * steps_per_iteration, f"train {role}", unit="env-steps",
                        initial=env_steps) if info.is_main else None  # fmt: skip
    meta = {
        "train": {k: v for k, v in asdict(config).items() if k not in ("policy",)},
        "role": role,
        "encoder": None if config.encoder_dir is None else str(config.encoder_dir),
        "encoder_fingerprint": encoder_fingerprint,
        "encoder_step": encoder_card.get("step"),
        "encoder_scheme": encoder_card.get("meta", {}).get("train", {}).get("scheme"),
        "world_size": info.world_size,
        "seed": config.seed,
    }
    if init_meta is not None:
        meta["init_from"] = init_meta

    def checkpoint() -> None:
        if not info.is_main:
            return
        save_weights(out, model, CHECKPOINT_KIND, policy_config.to_json(), env_steps,
                     {**meta, "env_steps": env_steps, "iteration": iteration, "curriculum_level": env.curriculum.level})  # fmt: skip
        if config.keep_checkpoints:
            keep_checkpoint(out)
        save_train_state(out, {
            "model": model.state_dict(), "optimizer": optimizer.state_dict(), "critic_optimizer": critic_optimizer.state_dict(),
            "iteration": iteration,
            "env_steps": env_steps, "return_normalizer": normalizer.state_dict(),
            "curriculum": env.curriculum.state_dict(), "env_rng": env.generator.get_state(),
            "update_rng": update_generator.get_state(), "encoder_fingerprint": encoder_fingerprint,
            "init_from": meta.get("init_from"), "vehicle": config.vehicle, "end_at_goal": config.end_at_goal,
        })  # fmt: skip

    obs = env.reset()
    hidden = model.initial_hidden(config.num_envs, device)
    starts = torch.ones(config.num_envs, dtype=torch.bool, device=device)
    t_start = time.monotonic()
    reduce_grads = _reduce_grads(model, info)
    reduce_mean = (lambda value: all_reduce_mean(value, info)) if info.enabled else None  # --target-kl's stop, decided on all processes
    while iteration < total_iterations:
        t_iter = time.monotonic()
        env.stage_seconds = dict.fromkeys(env.stage_seconds, 0.0)
        rollout, hidden, starts, obs, episode_stats = collect_rollout(model, env, obs, hidden, starts, normalizer, config.ppo)
        t_collect = time.monotonic() - t_iter
        model.train()
        warming_up = iteration < config.critic_warmup_iterations
        losses = ppo_update(model, critic_optimizer if warming_up else optimizer, rollout, config.ppo, update_generator,
                            reduce_grads, critic_only=warming_up, reduce_mean=reduce_mean)  # fmt: skip
        iteration += 1
        env_steps += steps_per_iteration
        elapsed = time.monotonic() - t_iter
        if writer is not None:
            scalars = {f"train/{k}": v for k, v in losses.items()}
            scalars |= {f"reward/{k}": v for k, v in episode_stats.pop("reward_terms").items()}
            scalars |= {f"episodes/{k}": v for k, v in episode_stats.items()}
            scalars |= {"curriculum/level": env.curriculum.level, "curriculum/changes": env.curriculum.changes,
                        "perf/env_steps_per_s": steps_per_iteration / elapsed,
                        "perf/collect_share": t_collect / elapsed, "train/action_std": float(model.log_std.detach().exp().mean())}  # fmt: skip
            scalars |= {f"perf/{k}_s": v for k, v in env.stage_seconds.items()}
            writer.add_scalars(env_steps, scalars)
        if progress is not None:
            progress.update(steps_per_iteration, level=env.curriculum.level, success=episode_stats.get("success_rate", float("nan")),
                            reward=episode_stats["mean_step_reward"])  # fmt: skip
        if iteration % config.checkpoint_every == 0 and iteration < total_iterations:
            checkpoint()
        if wall_budget_spent(config.max_wall_s, t_start, info, device):
            log.info("wall-clock budget of %.0f s reached after %d env steps", config.max_wall_s, env_steps)
            break
    checkpoint()
    log_weights_digest(model, info)
    if progress is not None:
        progress.close()
    if writer is not None:
        writer.close()
    return out


def check_resumed_task(state: dict, out: Path, encoder_dir, encoder_fingerprint: str | None, vehicle: str,
                       end_at_goal: bool) -> None:  # fmt: skip
    """--resume goes on with the task the run started on: the encoder (None: a teacher's privileged
    depth), the vehicle flown and where episodes end (train states written before the last two were
    recorded: the ideal vehicle, the paper's 10 s)."""
    if state.get("encoder_fingerprint") != encoder_fingerprint:
        raise ValueError(f"--resume: {out} was trained on encoder {state.get('encoder_fingerprint')}, but {encoder_dir} is "
                         f"{encoder_fingerprint}; resume with the same --encoder or start a new --out")  # fmt: skip
    if state.get("vehicle", "ideal") != vehicle:
        raise ValueError(f"--resume: {out} was trained on the {state.get('vehicle', 'ideal')} vehicle, but --vehicle "
                         f"{vehicle} was given; resume with the same --vehicle or start a new --out")  # fmt: skip
    if state.get("end_at_goal", False) != end_at_goal:
        given = "given" if end_at_goal else "not given"
        raise ValueError(f"--resume: {out} was trained with episodes ending {'at the goal' if state.get('end_at_goal') else 'at 10 s'}, "
                         f"but --end-at-goal was {given}; resume with the same episodes or start a new --out")  # fmt: skip


LATENT_STATS_RESETS = 8  # env resets whose first observations re-estimate the latent statistics


@torch.no_grad()
def init_from_policy(model: ActorCritic, init_dir: str, encoder_fingerprint: str, env: NavEnv) -> dict:
    """Load another run's policy (weights, log-std, observation normaliser) into ``model`` to fine-tune it.

    When that policy was trained on another encoder, its normaliser's latent statistics describe the
    old encoder's latents; they are re-estimated on this encoder's latents (the first observations
    of ``LATENT_STATS_RESETS`` env resets) so that the network again sees standardised latents.
    Returns what the card records: the source, its fingerprint, steps and encoder."""
    source, card = load_policy(init_dir, next(model.parameters()).device)
    if PolicyConfig.from_json(card["config"]) != model.config:
        raise ValueError(f"--init-from {init_dir}: its network {card['config']} differs from this run's "
                         f"{model.config.to_json()}; pass the --size it was trained with")  # fmt: skip
    model.load_state_dict(source.state_dict())
    source_encoder = card.get("meta", {}).get("encoder_fingerprint")
    restandardised = source_encoder != encoder_fingerprint
    if restandardised:
        latents = torch.cat([env.reset()[:, OBS_LATENT] for _ in range(LATENT_STATS_RESETS)])
        model.obs_norm.mean[OBS_LATENT] = latents.mean(dim=0)
        model.obs_norm.var[OBS_LATENT] = latents.var(dim=0, unbiased=False)
    log.info("starting from %s (%s env steps, encoder %s)%s", init_dir, card.get("step"), source_encoder,
             "; latent statistics re-estimated on this encoder" if restandardised else "")  # fmt: skip
    return {"dir": str(init_dir), "fingerprint": checkpoint_fingerprint(init_dir), "env_steps": card.get("step"),
            "encoder_fingerprint": source_encoder, "latent_stats_reestimated": restandardised}  # fmt: skip


@torch.no_grad()
def collect_rollout(model, env, obs, hidden, starts, normalizer, ppo: PpoConfig):
    model.eval()
    steps, n = ppo.rollout_steps, env.num_envs
    device = obs.device
    buf_obs = torch.zeros(steps, n, obs.shape[-1], device=device)
    buf_starts = torch.zeros(steps, n, dtype=torch.bool, device=device)
    buf_actions = torch.zeros(steps, n, 3, device=device)
    buf_logp = torch.zeros(steps, n, device=device)
    buf_values = torch.zeros(steps, n, device=device)
    buf_rewards = torch.zeros(steps, n, device=device)
    buf_dones = torch.zeros(steps, n, dtype=torch.bool, device=device)
    hidden0 = hidden.clone()
    outcomes = {SUCCESS: 0, CRASH: 0, TIMEOUT: 0}
    terms_sum: dict[str, float] = {}
    raw_reward_sum = 0.0
    for t in range(steps):
        model.obs_norm.update(obs)
        hidden = torch.where(starts.unsqueeze(-1), torch.zeros_like(hidden), hidden)
        mean, value, hidden = model.step(obs, hidden)
        action_dist = torch.distributions.Normal(mean, model.log_std.exp())
        action = action_dist.sample()
        result = env.step(action)
        buf_obs[t], buf_starts[t], buf_actions[t] = obs, starts, action
        buf_logp[t], buf_values[t] = action_dist.log_prob(action).sum(-1), value
        reward = result.reward * ppo.reward_scale
        buf_rewards[t] = normalizer(reward, result.done) if ppo.normalize_returns else reward
        buf_dones[t] = result.done
        raw_reward_sum += float(result.reward.mean())
        for code in outcomes:
            outcomes[code] += int((result.outcome[result.done] == code).sum())
        for k, v in result.reward_terms.items():
            terms_sum[k] = terms_sum.get(k, 0.0) + v
        obs, starts = result.obs, result.done
    next_hidden = torch.where(starts.unsqueeze(-1), torch.zeros_like(hidden), hidden)
    _, last_value, _ = model.step(obs, next_hidden)
    rollout = Rollout(buf_obs, buf_starts, buf_actions, buf_logp, buf_values, buf_rewards, buf_dones, hidden0, last_value)
    finished = sum(outcomes.values())
    stats = {"finished": float(finished), "mean_step_reward": raw_reward_sum / steps,
             "reward_terms": {k: v / steps for k, v in terms_sum.items()}}  # fmt: skip
    if finished:
        stats |= {"success_rate": outcomes[SUCCESS] / finished, "crash_rate": outcomes[CRASH] / finished,
                  "timeout_rate": outcomes[TIMEOUT] / finished}  # fmt: skip
    return rollout, hidden, starts, obs, stats

