"""Where a distilled student loses to its teacher, measured on the student's own flights:
    .venv/bin/python scripts/student-gap.py --student models/student-pooled --encoder models/cmwae-pooled \
        --teacher models/teacher --levels 5,15,20 --episodes 20

The student flies Table II's seeded rooms with clean depth (the rooms of `cmnav eval policy`, mean
action, no kicks); along each trajectory the teacher labels every state from its privileged observation (its
own GRU state carried), and the encoder's decoder reconstructs the depth the student's latent
holds.  Per level it prints, for the steps of successful episodes and for the last second (15
steps) before each crash: the student's squared action error against the teacher, the
reconstruction's MSE against the clean depth over the whole frame and over the pixels nearer than
--near-m (the surfaces a crash is made of) and in the teacher's view (the nearest surface per cell
of its 18 x 32 grid), and the share of near pixels.  A high action error
with a good reconstruction points at the imitation; reconstruction errors that grow near
obstacles point at the encoder.
"""

from __future__ import annotations

import argparse
import json

import torch
from torch import nn

from runtime.contract.constants import CONTROL_PERIOD_S, STATE_DIM
from training.cmwae.loss import NEAR_SURFACE_M, near_surface_mask, pooled_nearest_error
from training.cmwae.train import load_cmwae
from training.policy.env import CRASH, SUCCESS
from training.policy.evaluate import table2_env
from training.policy.network import load_policy

METRICS = ("action_mse", "recon_mse", "recon_mse_near", "recon_mse_teacher_view", "near_share")
PHASES = {SUCCESS: "successful episodes", CRASH: "last 1 s before a crash"}


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
    window = round(1.0 / CONTROL_PERIOD_S)  # the last second before a crash
    result = {}
    for level in args.levels:
        n = args.episodes
        env = table2_env(tap, level, "clean", n, "cpu", args.seed, teacher_obs=True)  # `cmnav eval policy`'s rooms
        obs, teacher_obs = env.reset(), env.teacher_observation()
        h_student, h_teacher = student.initial_hidden(n, "cpu"), teacher.initial_hidden(n, "cpu")
        active, metrics = [], []  # per step: [n] bool, [n, len(METRICS)]
        outcome = torch.zeros(n, dtype=torch.long)
        while bool(env.active.any()):
            recon = cmwae.decoder(obs[:, STATE_DIM:])
            depth = torch.zeros_like(recon)  # ended episodes are not encoded (NavEnv.live_envs): no target there
            depth[env.live_envs()] = tap.depth
            squared = (recon - depth) ** 2
            close = near_surface_mask(depth, args.near_m)
            action, _, h_student = student.step(obs, h_student)
            label, _, h_teacher = teacher.step(teacher_obs, h_teacher)
            active.append(env.active.clone())
            metrics.append(torch.stack([
                ((action.clamp(-1, 1) - label.clamp(-1, 1)) ** 2).mean(-1),
                squared.mean(dim=(1, 2, 3)),
                (squared * close).sum(dim=(1, 2, 3)) / close.sum(dim=(1, 2, 3)).clamp(min=1),
                pooled_nearest_error(recon, depth),
                close.float().mean(dim=(1, 2, 3)),
            ], dim=-1))  # fmt: skip
            step = env.step(action)
            outcome[step.done] = step.outcome[step.done]
            obs, teacher_obs = step.obs, step.teacher_obs
        active_tn, metrics_tnm = torch.stack(active), torch.stack(metrics)
        chosen = {PHASES[SUCCESS]: [], PHASES[CRASH]: []}
        for i in range(n):
            steps = metrics_tnm[active_tn[:, i], i]  # [steps of episode i, len(METRICS)]
            if int(outcome[i]) == SUCCESS:
                chosen[PHASES[SUCCESS]].append(steps)
            elif int(outcome[i]) == CRASH:
                chosen[PHASES[CRASH]].append(steps[-window:])
        result[level] = {"episodes": n, "crashes": int((outcome == CRASH).sum()), "successes": int((outcome == SUCCESS).sum())}
        for phase, parts in chosen.items():
            if parts:
                rows = torch.cat(parts)
                result[level][phase] = {"steps": len(rows), **dict(zip(METRICS, rows.mean(dim=0).tolist()))}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--student", required=True)
    parser.add_argument("--encoder", required=True)
    parser.add_argument("--teacher", required=True)
    parser.add_argument("--levels", default="5,15,20", type=lambda s: [int(x) for x in s.split(",")])
    parser.add_argument("--episodes", default=20, type=int)
    parser.add_argument("--near-m", default=NEAR_SURFACE_M, type=float, help=f"'near' pixels: true depth below this (default {NEAR_SURFACE_M} m)")
    parser.add_argument("--seed", default=0, type=int)
    args = parser.parse_args()
    result = measure(args)
    print("| level | phase | steps | action MSE vs teacher | recon MSE x1e-3 | recon MSE near x1e-3 | "
          "recon MSE teacher's view x1e-3 | near pixels % |")
    print("|---|---|---|---|---|---|---|---|")
    for level, r in result.items():
        for phase in PHASES.values():
            if phase in r:
                p = r[phase]
                print(f"| {level} | {phase} | {p['steps']} | {p['action_mse']:.4f} | {1e3 * p['recon_mse']:.2f} | "
                      f"{1e3 * p['recon_mse_near']:.2f} | {1e3 * p['recon_mse_teacher_view']:.2f} | {100 * p['near_share']:.1f} |")  # fmt: skip
    print(json.dumps(result))


if __name__ == "__main__":
    main()
