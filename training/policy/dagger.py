"""`cmnav train policy --teacher DIR`: the deployed policy distilled from the privileged teacher by
DAgger (DESIGN §5; Loquercio et al. 2021, Xing et al. 2024).

Every control step the executing policy is a mixture: in each env, with probability beta the
teacher's action, else the student's (beta falls linearly from ``beta_start`` to ``beta_end``
over ``beta_decay_env_steps``), so that the student soon visits its own states.  At every state
visited the teacher labels the action it would take from its privileged observation (the 15 state
values + clean low-resolution depth, its own GRU state carried along the same trajectory), while
the student sees what the camera gives: gray + depth corrupted as the paper trains (1-30 px
patches to 50 % in a random share of the envs each step, and projector-off episodes), through the
frozen encoder.  Only the student learns: truncated back-propagation through time over each
rollout's sequences, a mean-squared error to the teacher's clipped action, on the latest rollouts
kept in a small aggregate buffer.  With ``near_weight`` K the steps whose privileged depth holds a
surface nearer than ``near_m`` weigh 1 + K in that error: the second before a crash is a few per
cent of the states visited, and it is where a student's actions part from its teacher's.

The student is exactly the network that ships (ActorCritic, 79 inputs, FC 256-128-64 ELU -> GRU
64 -> FC 3, the normaliser inside); `cmnav export` exports it as any policy.  Its value head is
not trained here (a PPO fine-tune would warm it up first).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from runtime.contract.constants import STATE_DIM

from ..checkpoint import checkpoint_fingerprint, keep_checkpoint, load_train_state, save_train_state, save_weights
from ..cmwae.loss import NEAR_SURFACE_M, check_near_weighting, near_surface_mask
from ..cmwae.train import load_cmwae
from ..distributed import DistInfo, log_weights_digest, wall_budget_spent
from ..progress import Progress
from ..tensorboard import ScalarWriter
from .env import CRASH, SUCCESS, TIMEOUT, CurriculumConfig, NavEnv, NavEnvConfig, env_encoder
from .field import FIELD_DEPTHS, check_vehicle, field_env_overrides, vehicle_env_overrides
from .network import CHECKPOINT_KIND, STUDENT, TEACHER, ActorCritic, PolicyConfig, load_policy
from .train import check_resumed_task, init_from_policy

log = logging.getLogger(__name__)
_SINGLE = DistInfo()  # one process: the teacher labels every step of its own envs


@dataclass(frozen=True)
class DaggerConfig:
    teacher_dir: str
    encoder_dir: str
    out_dir: str
    env_steps: int = 2_000_000
    num_envs: int = 64
    rollout_steps: int = 32  # the truncated-BPTT sequence length
    beta_start: float = 1.0
    beta_end: float = 0.0
    beta_decay_env_steps: int = 300_000
    buffer_rollouts: int = 16  # the aggregate: the latest rollouts trained on each iteration
    epochs: int = 2  # passes over the buffer per iteration
    minibatches: int = 4  # per pass, split over (rollout, env) sequences
    lr: float = 5e-4
    max_grad_norm: float = 1.0
    # The student's depth: "train" = the paper's training patches on a random share of envs each
    # step; "none" = clean (the depth-only baseline).  The teacher always sees clean depth.
    corruption: str = "train"
    corrupted_env_fraction: float = 0.5
    projector_off_episode_fraction: float = 0.15
    # Of the other episodes outside the field, this share keeps one mask of large squares for the
    # whole episode (NavEnvConfig.squares_episode_fraction) instead of the per-step patches.
    squares_episode_fraction: float = 0.0
    # What the teacher sees under those squares (NavEnvConfig.squares_privileged): "clean" depth,
    # or "reconstructed": the encoder's reconstruction from the student's gray + masked depth.
    squares_teacher_view: str = "clean"
    # Train in the field (training.policy.field, Table II's ``field``): the student sees the
    # simulated D455's stereo depth (in place of ``corruption``) and the gray camera, latency,
    # PX4's randomized response, EKF2-like estimates and the field config's speed caps act.
    field_conditions: bool = False
    # The field's depth while training: "stereo" (the simulated D455, as Table II's ``field``
    # measures) or "approx" (its parametric stand-in, sim.sensor.approx: 3x the env-steps/s in cmnav bench train).
    field_depth: str = "stereo"
    # With the field: the share of the envs that fly it; the others train as without it (the
    # ``corruption`` patches on ``vehicle``), labelled by ``outside_teacher_dir`` (default: the
    # teacher), so that the student keeps what it flies outside the field (Table II's clean rows).
    field_env_fraction: float = 1.0
    outside_teacher_dir: str | None = None
    # The vehicle the student flies: "ideal" (the batched sim's: commands followed at once) or
    # "px4" (PX4 v1.16's identified response, latency and EKF2-like estimates alone, Table II's
    # ``px4``: what `cmnav sitl --autopilot` flies); the field includes the latter.
    vehicle: str = "ideal"
    # Episodes end in success at the goal, as the runtime's do (NavEnvConfig.end_at_goal); with the
    # envs split (field_env_fraction), in the field's envs only: the others keep the paper's 10 s,
    # the rule of Table II's rows outside the field.
    end_at_goal: bool = False
    min_level: int = 0
    max_level: int = 20
    # Extra weight of the steps whose teacher sees a surface nearer than near_m (m) in the
    # imitation loss (0: every step alike).
    near_weight: float = 0.0
    near_m: float = NEAR_SURFACE_M
    device: str = "cpu"
    seed: int = 0
    precision: str = "auto"
    checkpoint_every: int = 20  # iterations
    keep_checkpoints: bool = False  # every checkpoint's weights also kept in OUT/checkpoints/step-N (training.checkpoint.keep_checkpoint)
    resume: bool = False
    # Start the student from this policy (weights and normaliser; the latent statistics re-estimated
    # when it flew another encoder), e.g. a student distilled on the previous encoder.
    init_from: str | None = None
    max_wall_s: float | None = None
    policy: PolicyConfig = PolicyConfig()
    env_overrides: dict = field(default_factory=dict)

    def env_parts(self) -> list[tuple[bool, int]]:
        """The envs each rollout flies as (in the field, how many): the field's first."""
        in_field = round(self.num_envs * self.field_env_fraction) if self.field_conditions else 0
        return [(field, n) for field, n in ((True, in_field), (False, self.num_envs - in_field)) if n > 0]

    def env_config(self, in_field: bool | None = None, num_envs: int | None = None) -> NavEnvConfig:
        """The config of the envs in the field (``in_field``; default: with ``field_conditions``)
        or outside it, ``num_envs`` of them (default: all)."""
        in_field = self.field_conditions if in_field is None else in_field
        curriculum = CurriculumConfig(start_level=self.min_level, min_level=self.min_level, max_level=self.max_level)
        field_options = {"corruption": FIELD_DEPTHS[self.field_depth], **field_env_overrides()} if in_field else vehicle_env_overrides(self.vehicle)
        return replace(NavEnvConfig(num_envs=num_envs or self.num_envs, corruption=self.corruption, curriculum=curriculum,
                                    corrupted_env_fraction=self.corrupted_env_fraction, level_sampling="uniform",
                                    projector_off_episode_fraction=self.projector_off_episode_fraction,
                                    squares_episode_fraction=0.0 if in_field else self.squares_episode_fraction,
                                    squares_privileged="clean" if in_field else self.squares_teacher_view,
                                    end_at_goal=self.end_at_goal and (in_field or not self.field_conditions)),
                       **(field_options | self.env_overrides))  # fmt: skip

    def validate(self) -> None:
        if self.corruption not in ("train", "none"):
            raise ValueError(f"corruption={self.corruption!r} must be 'train' or 'none' (the depth-only baseline)")
        if self.field_depth not in FIELD_DEPTHS:
            raise ValueError(f"field_depth={self.field_depth!r} must be one of {', '.join(FIELD_DEPTHS)}")
        check_vehicle(self.vehicle)
        if self.vehicle != "ideal" and self.field_conditions and self.field_env_fraction == 1.0:
            raise ValueError(f"vehicle={self.vehicle!r} with the field in every env: the field flies its own vehicle already; "
                             f"give one of them (or a field_env_fraction below 1 for the envs outside the field)")  # fmt: skip
        if not 0.0 < self.field_env_fraction <= 1.0:
            raise ValueError(f"field_env_fraction={self.field_env_fraction} must be in (0, 1]")
        if (self.field_env_fraction < 1.0 or self.outside_teacher_dir is not None) and not self.field_conditions:
            raise ValueError("field_env_fraction and outside_teacher_dir split the envs between the field and outside it: "
                             "they need field_conditions")  # fmt: skip
        if self.squares_episode_fraction > 0.0 and all(in_field for in_field, _ in self.env_parts()):
            raise ValueError(f"squares_episode_fraction={self.squares_episode_fraction} applies to the envs outside the field, "
                             f"and field_env_fraction=1.0 puts every env in it: give a field_env_fraction below 1")  # fmt: skip
        if self.squares_teacher_view != "clean" and self.squares_episode_fraction == 0.0:
            raise ValueError(f"squares_teacher_view={self.squares_teacher_view!r} is the teacher's view under the squares "
                             f"episodes' squares: give a squares_episode_fraction above 0")  # fmt: skip
        if not 0.0 <= self.beta_end <= self.beta_start <= 1.0:
            raise ValueError(f"need 0 <= beta_end ({self.beta_end}) <= beta_start ({self.beta_start}) <= 1")
        for key in ("env_steps", "num_envs", "rollout_steps", "buffer_rollouts", "epochs", "minibatches", "checkpoint_every"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key}={getattr(self, key)} must be >= 1")
        check_near_weighting(self.near_weight, self.near_m)
        if self.minibatches > self.num_envs * self.buffer_rollouts:
            raise ValueError(f"minibatches={self.minibatches} exceeds the buffer's {self.num_envs * self.buffer_rollouts} sequences")
        if self.policy.obs_dim != PolicyConfig().obs_dim:
            raise ValueError("the student is the deployed network: its observation is the contract's 79 values")
        for in_field, n in self.env_parts():
            self.env_config(in_field, n).validate()

    def beta(self, env_steps: int) -> float:
        """The teacher's share of the executed actions after ``env_steps`` env steps."""
        progress = min(env_steps / max(self.beta_decay_env_steps, 1), 1.0)
        return self.beta_start + (self.beta_end - self.beta_start) * progress


@dataclass
class Sequences:
    """One rollout of T steps x N envs as the student saw it, labelled by the teacher."""

    obs: Tensor  # [T, N, 79] the student's observations
    starts: Tensor  # [T, N] bool: an episode begins at this step
    labels: Tensor  # [T, N, 3] the teacher's action, clipped to [-1, 1]
    hidden0: Tensor  # [N, H] the student's GRU state before step 0
    weights: Tensor  # [T, N] each step's weight in the imitation loss


def near_surface_states(teacher_obs: Tensor, near_m: float) -> Tensor:
    """[N] bool: the teacher's clean depth (of [N, 15 + W*H], normalised by DEPTH_MAX_M) holds a
    surface nearer than ``near_m`` metres (`near_surface_mask`, the encoder's rule)."""
    return near_surface_mask(teacher_obs[:, STATE_DIM:], near_m).any(dim=-1)


@torch.no_grad()
def collect(student: ActorCritic, teacher: ActorCritic, env: NavEnv, carry: dict, steps: int, beta: float,
            generator: torch.Generator, near_weight: float = 0.0, near_m: float = NEAR_SURFACE_M) -> tuple[Sequences, dict]:  # fmt: skip
    """Fly ``steps`` steps with the beta-mixture of teacher and student; label every visited state
    with the teacher's action, weighted 1 + ``near_weight`` at `near_surface_states`.  ``carry``
    holds what continues between calls: obs, teacher_obs, both GRU states, starts.  Returns the
    labelled sequences and episode counts."""
    student.eval()
    obs, teacher_obs = carry["obs"], carry["teacher_obs"]
    h_student, h_teacher, starts = carry["h_student"], carry["h_teacher"], carry["starts"]
    n = env.num_envs
    buf_obs = torch.zeros(steps, n, obs.shape[-1], device=obs.device)
    buf_starts = torch.zeros(steps, n, dtype=torch.bool, device=obs.device)
    buf_labels = torch.zeros(steps, n, 3, device=obs.device)
    buf_near = torch.zeros(steps, n, dtype=torch.bool, device=obs.device)
    hidden0 = torch.where(starts.unsqueeze(-1), torch.zeros_like(h_student), h_student)
    outcomes = {SUCCESS: 0, CRASH: 0, TIMEOUT: 0}
    teacher_steps = 0
    for t in range(steps):
        student.obs_norm.update(obs)
        h_student = torch.where(starts.unsqueeze(-1), torch.zeros_like(h_student), h_student)
        h_teacher = torch.where(starts.unsqueeze(-1), torch.zeros_like(h_teacher), h_teacher)
        student_action, _, h_student = student.step(obs, h_student)
        teacher_action, _, h_teacher = teacher.step(teacher_obs, h_teacher)
        label = teacher_action.clamp(-1.0, 1.0)
        by_teacher = torch.rand(n, generator=generator).to(obs.device) < beta
        teacher_steps += int(by_teacher.sum())
        result = env.step(torch.where(by_teacher.unsqueeze(-1), label, student_action))
        buf_obs[t], buf_starts[t], buf_labels[t] = obs, starts, label
        buf_near[t] = near_surface_states(teacher_obs, near_m)
        for code in outcomes:
            outcomes[code] += int((result.outcome[result.done] == code).sum())
        obs, teacher_obs, starts = result.obs, result.teacher_obs, result.done
    carry.update(obs=obs, teacher_obs=teacher_obs, h_student=h_student, h_teacher=h_teacher, starts=starts)
    finished = sum(outcomes.values())
    stats = {"finished": float(finished), "teacher_share": teacher_steps / (steps * n)}
    if finished:
        stats |= {"success_rate": outcomes[SUCCESS] / finished, "crash_rate": outcomes[CRASH] / finished}
    stats["near_share"] = float(buf_near.float().mean())
    return Sequences(buf_obs, buf_starts, buf_labels, hidden0, 1.0 + near_weight * buf_near.float()), stats


def distill(student: ActorCritic, optimizer: torch.optim.Optimizer, buffer: list[Sequences], epochs: int,
            minibatches: int, max_grad_norm: float, generator: torch.Generator) -> float:  # fmt: skip
    """Fit the student to the teacher's labels on every sequence in ``buffer`` (truncated BPTT
    over each rollout), each step's squared error weighted by the sequences' weights; returns the
    mean loss of the last pass."""
    student.train()
    obs = torch.cat([b.obs for b in buffer], dim=1)
    starts = torch.cat([b.starts for b in buffer], dim=1)
    labels = torch.cat([b.labels for b in buffer], dim=1)
    hidden0 = torch.cat([b.hidden0 for b in buffer], dim=0)
    weights = torch.cat([b.weights for b in buffer], dim=1)
    sequences = obs.shape[1]
    losses: list[float] = []
    for _ in range(epochs):
        losses = []
        order = torch.randperm(sequences, generator=generator).to(obs.device)
        for chunk in order.chunk(minibatches):
            mean, _ = student.unroll(obs[:, chunk], hidden0[chunk], starts[:, chunk])
            w = weights[:, chunk]
            loss = ((mean - labels[:, chunk]).pow(2).mean(dim=-1) * w).sum() / w.sum()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(student.parameters(), max_grad_norm)
            optimizer.step()
            losses.append(float(loss.detach()))
    return sum(losses) / len(losses)


def load_teacher(teacher_dir: str | Path, device: torch.device) -> tuple[ActorCritic, dict]:
    teacher, card = load_policy(teacher_dir, device)
    if card.get("meta", {}).get("role") != TEACHER:
        raise ValueError(f"--teacher {teacher_dir} is not a privileged teacher (meta.role is "
                         f"{card.get('meta', {}).get('role')!r}): train one with cmnav train teacher")  # fmt: skip
    for p in teacher.parameters():
        p.requires_grad_(False)
    return teacher, card


def check_teacher_fits(teacher: ActorCritic, env_config: NavEnvConfig, teacher_dir: str | Path) -> None:
    """Refuse a teacher whose observation is not ``env_config``'s privileged one (another depth size)."""
    if teacher.config.obs_dim != env_config.privileged_obs_dim:
        raise ValueError(f"the teacher {teacher_dir} observes {teacher.config.obs_dim} values, this env's privileged "
                         f"observation has {env_config.privileged_obs_dim}: give a teacher trained on that privileged depth size")  # fmt: skip


def train_dagger(config: DaggerConfig) -> Path:
    """Distil the teacher into the deployed student; returns the checkpoint directory."""
    config.validate()
    device = torch.device(config.device)
    out = Path(config.out_dir)
    torch.manual_seed(config.seed)
    teacher, teacher_card = load_teacher(config.teacher_dir, device)
    outside_teacher = teacher if config.outside_teacher_dir is None else load_teacher(config.outside_teacher_dir, device)[0]
    cmwae, encoder_card = load_cmwae(config.encoder_dir, device)
    encoder_fingerprint = checkpoint_fingerprint(config.encoder_dir)
    encoder = env_encoder(cmwae.encoder, config.precision, device, seed=config.seed)
    parts = []  # (name, env, its teacher, its carry): the field's envs first
    for k, (in_field, n) in enumerate(config.env_parts()):
        env_config = config.env_config(in_field, n)
        part_teacher = teacher if in_field else outside_teacher  # the same one unless the envs are split
        check_teacher_fits(part_teacher, env_config, config.teacher_dir if in_field else config.outside_teacher_dir or config.teacher_dir)
        env = NavEnv(env_config, encoder, device, seed=config.seed * 1000 + 7 + k, teacher_obs=True, decoder=cmwae.decoder)
        parts.append(("field" if in_field else "outside", env, part_teacher, {}))
    student = ActorCritic(config.policy).to(device)
    optimizer = torch.optim.Adam(student.parameters(), lr=config.lr)
    generator = torch.Generator().manual_seed(config.seed * 1000 + 11)
    iteration, env_steps = 0, 0
    state = load_train_state(out) if config.resume else None
    if state is not None:
        check_resumed_task(state, out, config.encoder_dir, encoder_fingerprint, config.vehicle, config.end_at_goal)
        student.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        for group in optimizer.param_groups:
            group["lr"] = config.lr  # the configured rate, not the one the optimizer state carries
        rngs = state.get("env_rngs") or [state["env_rng"]]  # env_rng: a state written before the envs could be split
        if len(rngs) != len(parts):
            raise ValueError(f"--resume: {out} trained {len(rngs)} group(s) of envs (in the field / outside it), this "
                             f"config gives {len(parts)}: resume with the same --field and --field-env-fraction")  # fmt: skip
        for (_, part_env, _, _), rng in zip(parts, rngs):
            part_env.generator.set_state(rng)
        generator.set_state(state["rng"])
        iteration, env_steps = state["iteration"], state["env_steps"]
        init_meta = state.get("init_from")
        log.info("resumed %s at iteration %d (%d env steps)", out, iteration, env_steps)
        if config.init_from is not None:
            log.info("--init-from %s ignored: resuming %s, which already started from it", config.init_from, out)
    else:
        if config.resume:
            log.warning("--resume: no training state in %s, starting %s", out,
                        "from scratch" if config.init_from is None else f"from {config.init_from}")  # fmt: skip
        init_meta = None if config.init_from is None else init_from_policy(student, config.init_from, encoder_fingerprint, parts[0][1])
    steps_per_iteration = config.rollout_steps * config.num_envs
    total_iterations = -(-config.env_steps // steps_per_iteration)
    writer = ScalarWriter(out / "tensorboard")
    progress = Progress(total_iterations * steps_per_iteration, "distil policy (DAgger)", unit="env-steps", initial=env_steps)
    meta = {
        "role": STUDENT, "algorithm": "dagger",
        "train": {k: v for k, v in asdict(config).items() if k != "policy"},
        "teacher": str(config.teacher_dir), "teacher_fingerprint": checkpoint_fingerprint(config.teacher_dir),
        "teacher_env_steps": teacher_card.get("step"),
        **({} if config.outside_teacher_dir is None else {"outside_teacher_fingerprint": checkpoint_fingerprint(config.outside_teacher_dir)}),
        "encoder": str(config.encoder_dir), "encoder_fingerprint": encoder_fingerprint,
        "encoder_step": encoder_card.get("step"),
        "encoder_scheme": encoder_card.get("meta", {}).get("train", {}).get("scheme"),
        "encoder_modalities": encoder_card["config"]["modalities"], "world_size": 1, "seed": config.seed,
    }  # fmt: skip
    if init_meta is not None:
        meta["init_from"] = init_meta

    def checkpoint() -> None:
        save_weights(out, student, CHECKPOINT_KIND, config.policy.to_json(), env_steps,
                     {**meta, "env_steps": env_steps, "iteration": iteration})  # fmt: skip
        if config.keep_checkpoints:
            keep_checkpoint(out)
        save_train_state(out, {"model": student.state_dict(), "optimizer": optimizer.state_dict(), "iteration": iteration,
                               "env_steps": env_steps, "env_rngs": [part[1].generator.get_state() for part in parts], "rng": generator.get_state(),
                               "encoder_fingerprint": encoder_fingerprint, "init_from": init_meta, "vehicle": config.vehicle,
                               "end_at_goal": config.end_at_goal})  # fmt: skip

    for _, part_env, part_teacher, carry in parts:
        n = part_env.num_envs
        carry.update(obs=part_env.reset(), teacher_obs=part_env.teacher_observation(), starts=torch.ones(n, dtype=torch.bool, device=device),
                     h_student=student.initial_hidden(n, device), h_teacher=part_teacher.initial_hidden(n, device))  # fmt: skip
    buffer: deque[Sequences] = deque(maxlen=config.buffer_rollouts * len(parts))
    t_start = time.monotonic()
    while iteration < total_iterations:
        t_iter = time.monotonic()
        beta = config.beta(env_steps)
        stats = {}
        for name, part_env, part_teacher, carry in parts:
            sequences, part_stats = collect(student, part_teacher, part_env, carry, config.rollout_steps, beta, generator,
                                            config.near_weight, config.near_m)  # fmt: skip
            buffer.append(sequences)
            stats |= {(k if len(parts) == 1 else f"{name}/{k}"): v for k, v in part_stats.items()}
        loss = distill(student, optimizer, list(buffer), config.epochs, config.minibatches, config.max_grad_norm, generator)
        iteration += 1
        env_steps += steps_per_iteration
        writer.add_scalars(env_steps, {"dagger/loss": loss, "dagger/beta": beta, "perf/env_steps_per_s": steps_per_iteration / (time.monotonic() - t_iter)}
                           | {f"episodes/{k}": v for k, v in stats.items()})  # fmt: skip
        success = {"success": stats.get("success_rate", float("nan"))} if len(parts) == 1 else {
            f"success_{name}": stats.get(f"{name}/success_rate", float("nan")) for name, *_ in parts}  # fmt: skip
        progress.update(steps_per_iteration, beta=round(beta, 3), loss=loss, **success)
        if iteration % config.checkpoint_every == 0 and iteration < total_iterations:
            checkpoint()
        if config.max_wall_s is not None and wall_budget_spent(config.max_wall_s, t_start, _SINGLE, device):
            log.info("wall-clock budget of %.0f s reached after %d env steps", config.max_wall_s, env_steps)
            break
    checkpoint()
    log_weights_digest(student, _SINGLE)
    progress.close()
    writer.close()
    return out

