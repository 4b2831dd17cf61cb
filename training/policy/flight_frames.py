"""`cmnav dataset --policy DIR --encoder DIR`: gray/depth pairs recorded along a policy's own
flights, for fine-tuning the encoder on the views a flying policy meets.

`cmnav dataset` renders random collision-free poses, at least 0.4 m from anything, looking mostly
down the room; a policy sees what its own flight brings, and in its last second before a crash the
near object it is about to hit, which is where the student's latent was measured to lose it
(models/student-s2/MODEL_CARD.md).  Here the policy flies the batched sim (levels drawn uniformly,
kicks, its training corruption on what it sees), and the clean frames along its trajectories are
kept: one in ``every_steps`` of each flight, and every frame of the last ``crash_window_steps``
before each crash.  One flight is one trajectory
(``flight_L05_E003_00012/Easy/P000``), so the splits of training.data.tartanair never put frames of
one flight on both sides.
"""

from __future__ import annotations

import json
import logging
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ..cmwae.train import load_cmwae
from ..data.generate import write_pair
from ..progress import Progress
from .env import CRASH, OUTCOMES, CurriculumConfig, NavEnv, NavEnvConfig, env_encoder
from .network import TEACHER, check_trained_on, load_policy

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FlightFramesSpec:
    policy_dir: str
    encoder_dir: str
    count: int
    seed: int  # of the rooms, levels, kicks and corruption (the CLI's --seed, as for random poses)
    min_level: int = 0
    max_level: int = 20
    num_envs: int = 32
    every_steps: int = 4  # keep one frame in this many along each flight
    crash_window_steps: int = 15  # ... and every frame of the last second (15 control steps) before a crash
    corruption: str = "train"  # what the policy sees while it flies; the frames kept are always clean
    precision: str = "auto"

    def validate(self) -> None:
        for key in ("count", "num_envs", "every_steps", "crash_window_steps"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key}={getattr(self, key)} must be >= 1")
        if not 0 <= self.min_level <= self.max_level:
            raise ValueError(f"levels {self.min_level}..{self.max_level}: need 0 <= min <= max")
        if self.corruption not in ("train", "none"):
            raise ValueError(f"corruption={self.corruption!r} must be 'train' (the paper's training patches) or 'none'")


@torch.no_grad()
def record_flight_frames(out_dir: str | Path, spec: FlightFramesSpec) -> dict:
    """Fly the policy until ``spec.count`` frames are written under ``out_dir`` (TartanAir V1
    layout); returns (and writes) a manifest with the flights' outcomes."""
    spec.validate()
    out = Path(out_dir)
    policy, card = load_policy(spec.policy_dir, "cpu")
    if card.get("meta", {}).get("role") == TEACHER:
        raise ValueError(f"--policy {spec.policy_dir} is a privileged teacher: it flies without the camera; record "
                         "along a deployed policy or student (cmnav train policy)")  # fmt: skip
    check_trained_on(card, spec.policy_dir, spec.encoder_dir)
    cmwae, _ = load_cmwae(spec.encoder_dir, "cpu")
    curriculum = CurriculumConfig(start_level=spec.min_level, min_level=spec.min_level, max_level=spec.max_level)
    config = NavEnvConfig(num_envs=spec.num_envs, corruption=spec.corruption, curriculum=curriculum, level_sampling="uniform",
                          projector_off_episode_fraction=0.15 if spec.corruption == "train" else 0.0)  # fmt: skip
    env = NavEnv(config, env_encoder(cmwae.encoder, spec.precision, "cpu", seed=spec.seed), "cpu", seed=spec.seed)
    out.mkdir(parents=True, exist_ok=True)
    n = spec.num_envs
    obs = env.reset()
    hidden = policy.initial_hidden(n, "cpu")
    starts = torch.ones(n, dtype=torch.bool)
    flights = [0] * n  # per env: the number of its current flight
    steps = torch.zeros(n, dtype=torch.long)  # per env: the step of its current flight
    recent: list[deque] = [deque() for _ in range(n)]  # per env: (flight, step, gray, depth) of the last crash_window_steps
    written: dict[str, int] = {}  # trajectory -> frames written
    invalid_fracs: list[float] = []  # one per frame written
    outcomes = dict.fromkeys(OUTCOMES.values(), 0)  # of the flights finished
    outcome_of: dict[str, str] = {}  # trajectory -> how its flight ended (flights still running are absent)
    from_crash_windows = 0
    progress = Progress(spec.count, f"flight frames {out}", unit="frames")

    def write(name: str, gray: torch.Tensor, depth: torch.Tensor) -> bool:
        if len(invalid_fracs) >= spec.count:
            return False
        invalid_fracs.append(write_pair(out, name, written.get(name, 0), gray, depth))
        written[name] = written.get(name, 0) + 1
        progress.update(1)
        return True

    while len(invalid_fracs) < spec.count:
        frames = env.last_render
        for i in range(n):
            flight = f"flight_L{int(env.episode_level[i]):02d}_E{i:03d}_{flights[i]:05d}"
            recent[i].append((flight, int(steps[i]), frames.gray_u8[i].clone(), frames.depth_m[i].clone()))
            if len(recent[i]) > spec.crash_window_steps:
                flight, step, gray, depth = recent[i].popleft()
                if step % spec.every_steps == 0:
                    write(flight, gray, depth)
        hidden = torch.where(starts.unsqueeze(-1), torch.zeros_like(hidden), hidden)
        action, _, hidden = policy.step(obs, hidden)
        result = env.step(action)
        steps += 1
        for i in result.done.nonzero().squeeze(1).tolist():
            crashed = int(result.outcome[i]) == CRASH
            outcomes[OUTCOMES[int(result.outcome[i])]] += 1
            if recent[i]:
                outcome_of[recent[i][-1][0]] = OUTCOMES[int(result.outcome[i])]
            for flight, step, gray, depth in recent[i]:
                if (crashed or step % spec.every_steps == 0) and write(flight, gray, depth):
                    from_crash_windows += int(crashed and step % spec.every_steps != 0)
            recent[i].clear()
            flights[i] += 1
            steps[i] = 0
        obs, starts = result.obs, result.done
    progress.close()
    manifest = {"source": "policy flights", "spec": asdict(spec), "policy_env_steps": card.get("step"),
                "frames": len(invalid_fracs), "flights_with_frames": len(written), "flight_outcomes": outcomes,
                "frames_added_from_crash_windows": from_crash_windows,
                "outcome_by_trajectory": {name: outcome_of[name] for name in written if name in outcome_of},
                "layout": "tartanair-v1", "invalid_depth_frac_mean": float(np.mean(invalid_fracs))}  # fmt: skip
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    log.info("%d frames from %d flights (finished: %s) in %s", manifest["frames"], len(written), outcomes, out)
    return manifest
