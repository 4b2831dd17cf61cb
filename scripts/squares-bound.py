"""What the teacher flies under Table II's episode-long masks when it is shown, under them, only what
the student can know there (the bound of a student distilled from it, `cmnav train policy
--squares-teacher-view reconstructed`):
    .venv/bin/python scripts/squares-bound.py --teacher models/teacher --encoder models/cmwae-stereo \
        --condition patches-100px --views reconstructed,clean --levels 5,10,15,20 --episodes 100

The teacher flies the rooms of `cmnav eval policy --rooms validation` (mean action, no kicks) under
``--condition``'s masks on its privileged observation (NavEnvConfig.squares_privileged): the clean
depth under the masks too (``clean``, what DAgger's teacher sees by default), or there the depth the
encoder reconstructs from the student's gray + masked depth (``reconstructed``).  Per view and
level it prints the success and crash shares.
"""

from __future__ import annotations

import argparse
import time

import torch

from training.cmwae.train import load_cmwae
from training.policy.env import CRASH, SQUARES_PRIVILEGED, SUCCESS, env_encoder
from training.policy.evaluate import CONDITIONS, ROOMS, table2_env
from training.policy.network import load_policy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--teacher", required=True)
    parser.add_argument("--encoder", required=True)
    parser.add_argument("--condition", default="patches-100px", choices=[c for c, o in CONDITIONS.items() if o.get("corruption") == "episode"])
    parser.add_argument("--views", default=",".join(SQUARES_PRIVILEGED))
    parser.add_argument("--levels", default="5,10,15,20")
    parser.add_argument("--episodes", type=int, default=100)
    args = parser.parse_args()
    views = args.views.split(",")
    if unknown := set(views) - set(SQUARES_PRIVILEGED):
        parser.error(f"--views {sorted(unknown)}: choose from {', '.join(SQUARES_PRIVILEGED)}")
    torch.set_grad_enabled(False)
    teacher, _ = load_policy(args.teacher)
    cmwae, _ = load_cmwae(args.encoder, "cpu")
    encoder = env_encoder(cmwae.encoder, "auto", "cpu")
    for view in views:
        for level in (int(x) for x in args.levels.split(",")):
            t0 = time.time()
            env = table2_env(encoder, level, args.condition, args.episodes, "cpu", ROOMS["validation"], teacher_obs=True,
                             decoder=cmwae.decoder if view == "reconstructed" else None)  # fmt: skip
            env.reset()
            obs, hidden = env.teacher_observation(), teacher.initial_hidden(args.episodes)
            outcome = torch.zeros(args.episodes, dtype=torch.long)
            while bool(env.active.any()):
                action, _, hidden = teacher.step(obs, hidden)
                result = env.step(action)
                obs, outcome[result.done] = result.teacher_obs, result.outcome[result.done]
            print(f"{args.condition} view {view} level {level}: success {float((outcome == SUCCESS).float().mean()):.2f} "
                  f"crash {float((outcome == CRASH).float().mean()):.2f} ({time.time() - t0:.0f} s)", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
