"""Where a distilled student loses to its teacher, measured on the student's own flights:
    .venv/bin/python scripts/student-gap.py --student models/student-s2 --encoder models/cmwae-s2 \
        --teacher models/teacher --levels 5,15,20 --episodes 20

The student flies Table II's seeded rooms with clean depth (the rooms of `cmnav eval policy`, mean
action, no kicks); along each trajectory the teacher labels every state from its privileged observation (its
own GRU state carried), and the encoder's decoder reconstructs the depth the student's latent
holds.  Per level it prints, for the steps of successful episodes and for the last second (15
steps) before each crash: the student's squared action error against the teacher, the
reconstruction's MSE against the clean depth over the whole frame and over the pixels nearer than
--near-m (the surfaces a crash is made of), and the share of such pixels.  A high action error
with a good reconstruction points at the imitation; reconstruction errors that grow near
obstacles point at the encoder.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict

import torch
from torch import nn

from runtime.contract.constants import CONTROL_PERIOD_S, DEPTH_MAX_M, STATE_DIM
from training.cmwae.train import load_cmwae
from training.policy.env import CRASH, SUCCESS, CurriculumConfig, NavEnv, NavEnvConfig
from training.policy.network import load_policy


class Tap(nn.Module):
    """The encoder, keeping the depth it was last given: clean here, the reconstruction's target."""

    def __init__(self, encoder: nn.Module) -> None:
        super().__init__()
        self.encoder = encoder
        self.depth: torch.Tensor | None = None

    def forward(self, gray: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        self.depth = depth
        return self.encoder(gray, depth)


@torch.no_grad()
def measure(args: argparse.Namespace) -> dict:
    student, _ = load_policy(args.student, "cpu")
    teacher, _ = load_policy(args.teacher, "cpu")
    cmwae, _ = load_cmwae(args.encoder, "cpu")
    tap = Tap(cmwae.encoder)
    near = args.near_m / DEPTH_MAX_M
    window = round(1.0 / CONTROL_PERIOD_S)  # the last second before a crash
    result = {}
    for level in args.levels:
        n = args.episodes
        config = NavEnvConfig(num_envs=n, corruption="none", kick_probability=0.0,
                              curriculum=CurriculumConfig(start_level=level, min_level=level, max_level=level))  # fmt: skip
        # The seeds of `cmnav eval policy`'s first batch at this level (training.policy.evaluate).
        env = NavEnv(config, tap, "cpu", seed=args.seed * 100_003 + level * 1009, fixed_level=level, auto_reset=False,
                     teacher_obs=True)  # fmt: skip
        obs, teacher_obs = env.reset(), env.teacher_observation()
        h_student, h_teacher = student.initial_hidden(n, "cpu"), teacher.initial_hidden(n, "cpu")
        per_step = []  # (active [n], action error [n], recon mse [n], near mse [n], near share [n])
        outcome = torch.zeros(n, dtype=torch.long)
        while bool(env.active.any()):
            active = env.active.clone()
            recon = cmwae.decoder(obs[:, STATE_DIM:])
            target = tap.depth
            close = target < near
            squared = (recon - target) ** 2
            near_count = close.sum(dim=(1, 2, 3)).clamp(min=1)
            action, _, h_student = student.step(obs, h_student)
            label, _, h_teacher = teacher.step(teacher_obs, h_teacher)
            error = ((action.clamp(-1, 1) - label.clamp(-1, 1)) ** 2).mean(-1)
            per_step.append((active, error, squared.mean(dim=(1, 2, 3)), (squared * close).sum(dim=(1, 2, 3)) / near_count,
                             close.float().mean(dim=(1, 2, 3))))  # fmt: skip
            step = env.step(action)
            outcome[step.done] = step.outcome[step.done]
            obs, teacher_obs = step.obs, step.teacher_obs
        sums = defaultdict(lambda: torch.zeros(4))
        counts = defaultdict(int)
        for i in range(n):
            steps = [t for t, s in enumerate(per_step) if s[0][i]]
            if int(outcome[i]) == CRASH:
                phase, chosen = "last 1 s before a crash", steps[-window:]
            elif int(outcome[i]) == SUCCESS:
                phase, chosen = "successful episodes", steps
            else:
                continue
            for t in chosen:
                sums[phase] += torch.stack([per_step[t][k][i] for k in range(1, 5)])
                counts[phase] += 1
        result[level] = {
            "episodes": n, "crashes": int((outcome == CRASH).sum()), "successes": int((outcome == SUCCESS).sum()),
            **{phase: {"steps": counts[phase], **dict(zip(("action_mse", "recon_mse", "recon_mse_near", "near_share"),
                                                          (sums[phase] / counts[phase]).tolist()))}
               for phase in counts},
        }  # fmt: skip
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--student", required=True)
    parser.add_argument("--encoder", required=True)
    parser.add_argument("--teacher", required=True)
    parser.add_argument("--levels", default="5,15,20", type=lambda s: [int(x) for x in s.split(",")])
    parser.add_argument("--episodes", default=20, type=int)
    parser.add_argument("--near-m", default=1.5, type=float, help="'near' pixels: true depth below this (default 1.5 m)")
    parser.add_argument("--seed", default=0, type=int)
    args = parser.parse_args()
    result = measure(args)
    print("| level | phase | steps | action MSE vs teacher | recon MSE x1e-3 | recon MSE near x1e-3 | near pixels % |")
    print("|---|---|---|---|---|---|---|")
    for level, r in result.items():
        for phase in ("successful episodes", "last 1 s before a crash"):
            if phase in r:
                p = r[phase]
                print(f"| {level} | {phase} | {p['steps']} | {p['action_mse']:.4f} | {1e3 * p['recon_mse']:.2f} | "
                      f"{1e3 * p['recon_mse_near']:.2f} | {100 * p['near_share']:.1f} |")  # fmt: skip
    print(json.dumps(result))


if __name__ == "__main__":
    main()
