"""The `cmnav` command: argument parsing only; each subcommand imports its package when it runs,
so `cmnav --help` and the runtime's commands never pay for torch."""

from __future__ import annotations

import argparse
import logging
import sys


def _cmd_sitl(args: argparse.Namespace) -> int:
    from sim.sitl_session import run_sitl_cli

    return run_sitl_cli(args)


def _cmd_export(args: argparse.Namespace) -> int:
    from export.goal_seeker import export_goal_seeker

    export_goal_seeker(args.output)
    print(f"wrote goal-seeker model to {args.output}")
    return 0


def _cmd_dataset(args: argparse.Namespace) -> int:
    from training.data.generate import DatasetSpec, generate_dataset

    spec = DatasetSpec(count=args.count, seed=args.seed, levels=tuple(args.levels), frames_per_room=args.frames_per_room)
    manifest = generate_dataset(args.out, spec)
    print(f"wrote {manifest['frames']} gray/depth pairs from {manifest['rooms']} rooms to {args.out} (TartanAir V1 layout)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cmnav",
        description="Cross-modal navigation for a quadrotor with degraded depth: flight runtime, "
        "software-in-the-loop sim, training and export.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    sitl = sub.add_parser(
        "sitl",
        help="fly one episode: SITL vehicle + the real runtime as separate processes",
        description="Start the SITL vehicle and the runtime, arm, take off, fly the model in "
        "offboard until success (within 1 m of the goal), crash or timeout, then hover, land and "
        "stop both processes.  Writes the MCAP flight log and a top-view trajectory plot.",
    )
    sitl.add_argument("--model", required=True, help="ONNX model with the runtime's contract")
    sitl.add_argument("--level", type=int, default=0, help="curriculum level = number of obstacles (default 0)")
    sitl.add_argument("--seed", type=int, default=0, help="world seed (room, obstacles, start, goal)")
    sitl.add_argument("--timeout", type=float, default=60.0, help="flight time limit in offboard, seconds (default 60)")
    sitl.add_argument("--out", default="runs/sitl", help="directory for the log, plot and summaries (default runs/sitl)")
    sitl.add_argument("--json", action="store_true", help="print the summary as one JSON object on the last line")
    sitl.set_defaults(func=_cmd_sitl)

    dataset = sub.add_parser(
        "dataset",
        help="render gray/depth pairs from the simulated world (TartanAir V1 layout)",
        description="Render gray/depth pairs from random collision-free poses in random rooms across "
        "curriculum levels; one room is one trajectory (ENV/Easy/P000), so splits are by room.",
    )
    dataset.add_argument("--out", required=True, help="output directory")
    dataset.add_argument("--count", type=int, required=True, help="number of pairs")
    dataset.add_argument("--seed", type=int, default=0, help="seed of rooms, poses and camera jitter")
    dataset.add_argument("--levels", type=int, nargs="+", default=[0, 2, 5, 10, 15, 20],
                         help="curriculum levels (obstacle counts), cycled over rooms")  # fmt: skip
    dataset.add_argument("--frames-per-room", type=int, default=16, help="views per room (default 16)")
    dataset.set_defaults(func=_cmd_dataset)

    export = sub.add_parser("export", help="write an ONNX model for the runtime")
    export_sub = export.add_subparsers(dest="what", required=True, metavar="WHAT")
    goal_seeker = export_sub.add_parser(
        "goal-seeker",
        help="a plumbing-check model that ignores the images and steers toward the goal",
    )
    goal_seeker.add_argument("-o", "--output", required=True, help="path of the ONNX file to write")
    goal_seeker.set_defaults(func=_cmd_export)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    return int(args.func(args) or 0)
