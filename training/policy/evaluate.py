"""Table II: success / timeout / crash % of a trained policy per curriculum level and depth
condition, flown in the batched sim exactly as in training (same world, contract, 15 Hz) but with
the mean action, no kicks, and the same seeded rooms for every condition and policy.

Conditions: ``clean`` (full depth), ``corrupted`` (the training patches, 1-30 px to 50 %, fixed
for the whole episode, as in the paper), ``projector-off`` (``sim.degradation.ProjectorOffModel``
on every frame: depth lost on low-texture, dark, oblique or far surfaces), ``stereo`` and
``stereo-projector-off`` (the simulated D455 of ``sim.sensor``: depth matched from rendered IR
images, its projector on / off), and the out-of-distribution patches, fixed for the episode:
``patches-1-50px`` (Table I's 1-50 px squares to 50 %) and ``patches-100px`` (S2's 100 px
squares, to 50 %); ``field``: stereo depth (projector on) and everything else the field does,
together (``training.policy.field``: gray-camera exposure, gain, blur and noise, image-to-command
latency, PX4's randomized response and command delays, EKF2-like state estimates, the shipped field
config's speed caps with the episode lengthened to match).

Rooms: ``validation`` (seed 0) for choosing models, ``test`` (seed 1) for the tables we publish;
table2.json names which, with the fingerprints of the policy and the encoder measured and the
encoder's precision path.

With a privileged teacher (``teacher_dir``, `cmnav eval policy --teacher`), every step of the
policy's own flights is also labelled with the teacher's action, and each cell gives the imitation
gap: how far the policy is from what DAgger taught it, over all steps and in the last second
before each crash (where it parts from a teacher that sees what it cannot).
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from runtime.contract.constants import CAMERA_RATE_HZ, GOAL_REACHED_RADIUS_M, STATE_DIM
from sim.degradation import evaluation_scheme
from sim.plot import plot_top_view

from ..checkpoint import checkpoint_fingerprint
from ..cmwae.train import load_cmwae
from ..fastpath import FrozenEncoder, check_action_parity
from ..progress import Progress
from ..stats import wilson_interval
from .env import (CRASH, OUTCOMES, STEREO_MODES, SUCCESS, TIMEOUT, CurriculumConfig, NavEnv, NavEnvConfig, env_encoder,
                  parity_frames)  # fmt: skip
from .dagger import check_teacher_fits, load_teacher
from .field import field_description, field_env_overrides, px4_vehicle_env_overrides
from .network import TEACHER, check_trained_on, load_policy

log = logging.getLogger(__name__)
# Table II's conditions: the NavEnvConfig fields each sets (everything else as in training).
CONDITIONS: dict[str, dict] = {
    "clean": {"corruption": "none"},
    "corrupted": {"corruption": "episode"},
    "projector-off": {"corruption": "projector-off"},
    "stereo": {"corruption": "stereo"},
    "stereo-projector-off": {"corruption": "stereo-projector-off"},
    "patches-1-50px": {"corruption": "episode", "corruption_scheme": evaluation_scheme(0.5)},
    "patches-100px": {"corruption": "episode", "corruption_scheme": evaluation_scheme(0.5, (100, 100))},
    "field": {"corruption": "stereo"},  # and the rest of the field: condition_env_overrides
    "px4": {"corruption": "none"},  # and PX4's response (training.policy.field.px4_vehicle_env_overrides)
}
# The conditions that fly in the field (training.policy.field) besides their depth; on PX4's response alone.
FIELD_CONDITIONS = ("field",)
PX4_VEHICLE_CONDITIONS = ("px4",)
# Room sets: models are chosen on validation rooms; published tables use test rooms no choice saw.
ROOMS = {"validation": 0, "test": 1}


@dataclass(frozen=True)
class PolicyEvalConfig:
    policy_dir: str
    encoder_dir: str | None  # None for a privileged teacher (it has no encoder)
    levels: tuple[int, ...] = (0, 5, 10, 15, 20)
    conditions: tuple[str, ...] = ("clean", "corrupted", "projector-off")
    episodes: int = 100
    batch_envs: int = 64  # episodes flown at once
    device: str = "cpu"
    seed: int = 0  # seed of the rooms; ``rooms`` names a set instead
    rooms: str | None = None  # "validation" (seed 0) or "test" (seed 1)
    out_dir: str | None = None  # plots and table2.json (default POLICY/eval)
    plots_per_cell: int = 2
    # A privileged teacher whose action labels every step of the policy's own flights (what DAgger
    # regresses): each cell then gives the imitation gap (``imitation_gap``).
    teacher_dir: str | None = None
    precision: str = "auto"  # the frozen encoder's fast path (training.fastpath)
    # Smoke runs only: end every episode after this many seconds (its condition's length
    # otherwise); table2.json records it, a published table leaves it None.
    episode_duration_s: float | None = None

    @property
    def room_seed(self) -> int:
        return self.seed if self.rooms is None else ROOMS[self.rooms]

    @property
    def room_set(self) -> str:
        """What table2.json says about the rooms: the named set, or the bare seed."""
        named = {seed: name for name, seed in ROOMS.items()}
        return self.rooms or f"seed {self.seed}" + (f" (the {named[self.seed]} rooms)" if self.seed in named else "")

    def validate(self) -> None:
        unknown = [c for c in self.conditions if c not in CONDITIONS]
        if unknown:
            raise ValueError(f"unknown conditions {unknown}: choose from {sorted(CONDITIONS)}")
        if self.rooms is not None and self.rooms not in ROOMS:
            raise ValueError(f"rooms={self.rooms!r} must be one of {sorted(ROOMS)} (validation: seed 0, for choosing; "
                             f"test: seed 1, for reporting)")  # fmt: skip
        if self.rooms is not None and self.seed not in (0, ROOMS[self.rooms]):
            raise ValueError(f"rooms={self.rooms!r} is seed {ROOMS[self.rooms]}, but seed={self.seed} was given: give one of them")
        if self.episodes < 1 or self.batch_envs < 1:
            raise ValueError("episodes and batch_envs must be >= 1")
        if self.episode_duration_s is not None and self.episode_duration_s <= 0.0:
            raise ValueError(f"episode_duration_s={self.episode_duration_s} must be > 0 (or None: the condition's own)")
        if not self.levels or min(self.levels) < 0:
            raise ValueError(f"levels={self.levels} must be non-negative obstacle counts")


def condition_env_overrides(condition: str) -> dict:
    """The NavEnvConfig fields ``condition`` sets (the field's read from the shipped field config)."""
    overrides = dict(CONDITIONS[condition])
    if condition in FIELD_CONDITIONS:
        overrides |= field_env_overrides()
    if condition in PX4_VEHICLE_CONDITIONS:
        overrides |= px4_vehicle_env_overrides()
    return overrides


def table2_env(encoder, level: int, condition: str, num_envs: int, device, seed: int, first_episode: int = 0,
               teacher_obs: bool = False, episode_duration_s: float | None = None, decoder=None) -> NavEnv:  # fmt: skip
    """The env of Table II's episodes ``first_episode`` .. ``first_episode + num_envs - 1`` at
    ``level`` under ``condition``: no kicks, no reset after an episode ends.  Its rooms depend on
    (seed, level, episode number), not on the condition or policy.  With the encoder's ``decoder``
    the teacher's privileged depth under the episode's masks is its reconstruction
    (NavEnvConfig.squares_privileged)."""
    overrides = condition_env_overrides(condition) | ({} if episode_duration_s is None else {"episode_duration_s": episode_duration_s})
    overrides |= {} if decoder is None else {"squares_privileged": "reconstructed"}
    config = NavEnvConfig(num_envs=num_envs, kick_probability=0.0, **overrides,
                          curriculum=CurriculumConfig(start_level=level, min_level=level, max_level=level))  # fmt: skip
    return NavEnv(config, encoder, device, seed=seed * 100_003 + level * 1009 + first_episode, fixed_level=level,
                  auto_reset=False, teacher_obs=teacher_obs, decoder=decoder)  # fmt: skip


@torch.no_grad()
def fly_episodes(policy, encoder, level: int, condition: str, episodes: int, batch_envs: int, device, seed: int,
                 episode_duration_s: float | None = None, teacher=None):  # fmt: skip
    """Fly ``episodes`` episodes at ``level`` under ``condition``; yields per episode
    (outcome code, trajectory [T, 3], world description, gap).  With a ``teacher`` (its privileged
    observation: the true state and clean depth), gap [T] is the squared distance of the policy's
    action from the teacher's label at every step flown (what DAgger regresses); None without."""
    done_count = 0
    while done_count < episodes:
        n = min(batch_envs, episodes - done_count)
        env = table2_env(encoder, level, condition, n, device, seed, first_episode=done_count,
                         teacher_obs=teacher is not None, episode_duration_s=episode_duration_s)  # fmt: skip
        obs = env.reset()
        teacher_obs = None if teacher is None else env.teacher_observation()
        teacher_hidden = None if teacher is None else teacher.initial_hidden(n, device)
        worlds = [env.world.describe(i) for i in range(n)]
        hidden = policy.initial_hidden(n, device)
        outcome = torch.zeros(n, dtype=torch.long)
        trajectory = [env.trajectory_point()]
        gaps = []
        while bool(env.active.any()):
            mean, _, hidden = policy.step(obs, hidden)
            if teacher is not None:
                label, _, teacher_hidden = teacher.step(teacher_obs, teacher_hidden)
                gaps.append(((mean - label.clamp(-1.0, 1.0)) ** 2).sum(-1).cpu())
            result = env.step(mean)
            outcome[result.done.cpu()] = result.outcome[result.done].cpu()
            trajectory.append(env.trajectory_point())
            obs, teacher_obs = result.obs, result.teacher_obs
        path = torch.stack(trajectory, dim=1).numpy()  # [n, T, 3]; frozen after the end
        gap = torch.stack(gaps, dim=1).numpy() if gaps else None  # [n, T]
        for i in range(n):
            steps = int(env.step_count[i])
            yield int(outcome[i]), path[i, : steps + 1], worlds[i], None if gap is None else gap[i, :steps]
        done_count += n


def imitation_gap(gaps: list[np.ndarray], outcomes: list[int]) -> dict:
    """A cell's imitation gap from its episodes' per-step gaps (:func:`fly_episodes`): the mean
    over every step flown, and over the last second before each crash (where the policy and its
    teacher part when the policy cannot tell what the teacher sees)."""
    tail = round(CAMERA_RATE_HZ)
    before_crash = [g[-tail:].mean() for g, code in zip(gaps, outcomes) if code == CRASH and len(g)]
    return {"imitation_gap": float(np.concatenate(gaps).mean()),
            "imitation_gap_before_crash": float(np.mean(before_crash)) if before_crash else None}  # fmt: skip


@torch.no_grad()
def check_policy_parity(policy, reference: nn.Module, fast: nn.Module, device, seed: int) -> float | None:
    """On a bf16 encoder: the largest change of the policy's first action its latent causes on
    rendered frames (heading for a goal 6 m ahead, at rest), refused beyond the bound; None in fp32."""
    if not (isinstance(fast, FrozenEncoder) and fast.path.bf16):
        return None
    gray, depth = parity_frames(reference, device, seed=seed + 1)
    state = torch.zeros(gray.shape[0], STATE_DIM, device=device)
    state[:, 0], state[:, 3] = 1.0, 0.5
    hidden = policy.initial_hidden(gray.shape[0], device)
    actions = [policy.step(torch.cat([state, enc(gray, depth).float()], dim=1), hidden)[0] for enc in (reference, fast)]
    error = check_action_parity(*actions)
    log.info("bf16 encoder: the policy's action moves by at most %.4f on %d rendered frames", error, gray.shape[0])
    return error


def evaluate_policy(config: PolicyEvalConfig) -> dict:
    """Run every (condition, level) cell; write table2.json, table2.md and trajectory plots."""
    config.validate()
    device = torch.device(config.device)
    policy, card = load_policy(config.policy_dir, device)
    conditions = config.conditions
    if card.get("meta", {}).get("role") == TEACHER:
        if config.teacher_dir is not None:
            raise ValueError(f"{config.policy_dir} is a privileged teacher itself: --teacher measures a student's "
                             f"imitation gap to the teacher it learns from; leave it out")  # fmt: skip
        if config.encoder_dir is not None:
            raise ValueError(f"{config.policy_dir} is a privileged teacher (state + clean low-resolution depth, no "
                             f"encoder): evaluate it without --encoder")  # fmt: skip
        # It sees clean depth and the true state whatever the camera and the estimate do: only the
        # rows with clean depth (clean, the vehicle-only px4) and the field (its vehicle, latency
        # and speed caps; the bound of what a student distilled from it can reach) describe it.
        conditions = tuple(c for c in conditions if c == "clean" or c in PX4_VEHICLE_CONDITIONS + FIELD_CONDITIONS) or ("clean",)
        fingerprint, encoder, action_parity = None, None, None
    elif config.encoder_dir is None:
        raise ValueError(f"{config.policy_dir} flies on an encoder's latent: pass --encoder (the checkpoint it was trained with)")
    else:
        fingerprint = check_trained_on(card, config.policy_dir, config.encoder_dir)
        cmwae, _ = load_cmwae(config.encoder_dir, device)
        encoder = env_encoder(cmwae.encoder, config.precision, device, seed=config.seed)
        action_parity = check_policy_parity(policy, cmwae.encoder, encoder, device, config.seed)
    teacher = None if config.teacher_dir is None else load_teacher(config.teacher_dir, device)[0]
    if teacher is not None:
        check_teacher_fits(teacher, NavEnvConfig(), config.teacher_dir)
    out = Path(config.out_dir or Path(config.policy_dir) / "eval")
    out.mkdir(parents=True, exist_ok=True)
    cells: list[dict] = []
    stereo = {c: asdict(NavEnvConfig().stereo) | {"projector_on": CONDITIONS[c]["corruption"] == "stereo"}
              for c in conditions if CONDITIONS[c]["corruption"] in STEREO_MODES}  # fmt: skip
    result = {
        "policy": str(config.policy_dir), "role": card.get("meta", {}).get("role", "policy"),
        "policy_fingerprint": checkpoint_fingerprint(config.policy_dir),
        "encoder": config.encoder_dir, "encoder_fingerprint": fingerprint,
        "teacher": config.teacher_dir, "teacher_fingerprint": None if teacher is None else checkpoint_fingerprint(config.teacher_dir),
        "rooms": config.room_set, "room_seed": config.room_seed,
        "fast_path": {"encoder": getattr(getattr(encoder, "path", None), "name", "fp32"), "bf16_action_error": action_parity,
                      "precision_requested": config.precision},
        "stereo_sensor": stereo,
        "field": {c: field_description(condition_env_overrides(c)) for c in conditions if c in FIELD_CONDITIONS + PX4_VEHICLE_CONDITIONS},
        "policy_env_steps": card.get("step"), "config": asdict(replace(config, out_dir=str(out))), "cells": cells,
        "complete": False,  # until the last cell: the tables are written after every cell, so a run stopped early keeps its cells
    }  # fmt: skip
    n_cells = len(conditions) * len(config.levels)
    progress = Progress(n_cells * config.episodes, "eval policy", unit="episodes")
    for condition in conditions:
        for level in config.levels:
            counts = {SUCCESS: 0, TIMEOUT: 0, CRASH: 0}
            reached = 0
            gaps, codes = [], []
            for k, (code, path, world, gap) in enumerate(
                fly_episodes(policy, encoder, level, condition, config.episodes, config.batch_envs, device, config.room_seed,
                             config.episode_duration_s, teacher)
            ):
                counts[code] += 1
                if gap is not None:
                    gaps.append(gap)
                    codes.append(code)
                reached += reached_goal(path, world["goal_m"])
                if k < config.plots_per_cell:
                    plot_top_view(out / f"{condition}_level{level:02d}_ep{k}_{OUTCOMES[code]}.png", world["room_size_m"],
                                  world["boxes"], world["start_m"], world["goal_m"], path,
                                  title=f"{condition}, level {level}, episode {k}: {OUTCOMES[code]}")  # fmt: skip
                progress.update(1)
            total = sum(counts.values())
            low, high = wilson_interval(counts[SUCCESS], total)
            cells.append({
                "condition": condition, "level": level, "episodes": total,
                "success_pct": 100.0 * counts[SUCCESS] / total, "timeout_pct": 100.0 * counts[TIMEOUT] / total,
                "crash_pct": 100.0 * counts[CRASH] / total, "success_ci95_pct": [100.0 * low, 100.0 * high],
                "reached_pct": 100.0 * reached / total,
            } | (imitation_gap(gaps, codes) if teacher is not None else {}))  # fmt: skip
            log.info("cell %d of %d: %s", len(cells), n_cells, format_table2({"cells": cells[-1:]}).splitlines()[-1])
            result["complete"] = len(cells) == n_cells
            _write_tables(out, result)
    progress.close()
    result["out_dir"] = str(out)
    return result


def _write_tables(out: Path, result: dict) -> None:
    (out / "table2.json").write_text(json.dumps(result, indent=2))
    stopped = "" if result["complete"] else "\n\nIncomplete: the run stopped (or is still running) before its last cell.\n"
    (out / "table2.md").write_text(format_table2(result) + "\n" + stopped)


def reached_goal(path_m: np.ndarray, goal_m) -> bool:
    """The runtime's success: the vehicle came within GOAL_REACHED_RADIUS_M of the goal before any
    crash (``path_m`` [T, 3] per control step, ending at a crash's contact).  Table II's own success
    (the paper's, Aerial Gym's) asks it to be there when the episode ends at 10 s; on a vehicle
    that slides (PX4 flies its estimate) the two part, and a campaign on PX4 counts this one."""
    distance_m = np.linalg.norm(np.asarray(path_m, dtype=np.float64) - np.asarray(goal_m, dtype=np.float64), axis=-1)
    return bool((distance_m < GOAL_REACHED_RADIUS_M).any())


def format_table2(result: dict) -> str:
    """The paper's layout: condition, level, success / timeout / crash %, and the success rate's
    Wilson 95 % interval; then the runtime's "reached" (:func:`reached_goal`), and with a teacher
    the imitation gap (:func:`imitation_gap`) over all steps and in the last second before crashes."""
    with_gap = any("imitation_gap" in c for c in result["cells"])
    gap_header = " imitation gap | gap, last 1 s before crashes |" if with_gap else ""
    lines = ["| condition | level | episodes | success % | 95 % interval | timeout % | crash % | reached % |" + gap_header,
             "|---|---|---|---|---|---|---|---|" + "---|---|" * with_gap]  # fmt: skip
    for c in result["cells"]:
        low, high = c["success_ci95_pct"]
        reached = f"{c['reached_pct']:.1f}" if "reached_pct" in c else "–"
        gap = ""
        if with_gap:
            before_crash = c.get("imitation_gap_before_crash")
            gap = f" {c['imitation_gap']:.4f} | {'–' if before_crash is None else format(before_crash, '.4f')} |"
        lines.append(f"| {c['condition']} | {c['level']} | {c['episodes']} | {c['success_pct']:.1f} | {low:.0f}–{high:.0f} | "
                     f"{c['timeout_pct']:.1f} | {c['crash_pct']:.1f} | {reached} |" + gap)  # fmt: skip
    return "\n".join(lines)

