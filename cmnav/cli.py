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


def _cmd_train_cmwae(args: argparse.Namespace) -> int:
    from training.cmwae.train import CmwaeTrainConfig, train_cmwae

    config = CmwaeTrainConfig(
        data_dir=args.data, out_dir=args.out, scheme=args.scheme, modalities=tuple(args.modalities.split(",")),
        size=args.size, steps=args.steps, epochs=args.epochs if args.steps is None else None,
        batch_size=args.batch_size, lr=args.lr, mmd_weight=args.mmd_weight, seed=args.seed, device=args.device,
        workers=args.workers, checkpoint_every=args.checkpoint_every, resume=args.resume,
    )  # fmt: skip
    out = train_cmwae(config)
    print(f"checkpoint in {out}")
    return 0


def _cmd_eval_cmwae(args: argparse.Namespace) -> int:
    import json

    from training.cmwae.evaluate import CmwaeEvalConfig, evaluate_cmwae

    result = evaluate_cmwae(
        CmwaeEvalConfig(checkpoint=args.checkpoint, data_dir=args.data, split=args.split, out_dir=args.out,
                        device=args.device, max_images=args.max_images, seed=args.seed)  # fmt: skip
    )
    print(result["table"])
    print(f"MSE at 50% / 0%: {result['mse_ratio_50_over_0']}; plots in {result['plots']['mse'].rsplit('/', 1)[0]}")
    if args.json:
        print(json.dumps(result))
    return 0


def _cmd_bench_sim(args: argparse.Namespace) -> int:
    import json

    from bench.sim import QUICK, SimBenchConfig, format_sim_bench, run_sim_bench

    result = run_sim_bench(QUICK if args.quick else SimBenchConfig())
    print(json.dumps(result) if args.json else format_sim_bench(result))
    return 0


def _cmd_fly(args: argparse.Namespace) -> int:
    from runtime.fly import run_fly

    return run_fly(args.config, print_json=args.json, check_only=args.check)


def _cmd_replay(args: argparse.Namespace) -> int:
    import json

    from runtime.replay import ReplayError, replay_log

    try:
        report = replay_log(args.log, args.model)
    except ReplayError as err:
        print(f"cmnav replay: {err}", file=sys.stderr)
        return 2
    print(report.format())
    if args.json:
        print(json.dumps(report.to_json()))
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
    sitl.add_argument("--degrade", default="none", choices=["none", "projector-off"],
                      help="depth degradation of the SITL camera (projector-off: a D455 without its IR projector, "
                      "about a quarter of the depth lost)")  # fmt: skip
    sitl.add_argument(
        "--inject", action="append", default=[], metavar="KIND@SECONDS",
        help="inject a fault SECONDS after offboard start (repeatable): camera-stall, camera-garbage, "
        "camera-blackout, telemetry-loss, pilot-takeover, offboard-refused@0, inference-overrun, nan-action, "
        "geofence, runtime-kill; the summary then lists each fault's trip, detection time and stop time",
    )  # fmt: skip
    sitl.set_defaults(func=_cmd_sitl)

    fly = sub.add_parser(
        "fly",
        help="the field program: fly the policy on the vehicle (what systemd runs)",
        description="Validate the TOML config (nothing talks to the vehicle before it and the model pass), "
        "connect, wait for the pilot to arm, take off and switch to offboard (or, with "
        "mission.allow_arm_takeoff = true, do that itself), fly to the goal, Hold, repeat.  "
        "Exit 0 done or stopped, 1 a failure a restart may cure, 2 a bad config or model.  "
        "Every key: examples/cmnav.toml.",
    )
    fly.add_argument("--config", required=True, help="TOML config, e.g. /etc/cmnav/cmnav.toml")
    fly.add_argument("--json", action="store_true", help="print a JSON summary (episodes, logs, error) on the last line at exit")
    fly.add_argument("--check", action="store_true", help="only validate the config and load the model, then exit 0 (or 2)")
    fly.set_defaults(func=_cmd_fly)

    replay = sub.add_parser(
        "replay",
        help="feed a flight log back through the policy and report action differences",
        description="Recompute every recorded policy step from the log's camera frames, telemetry and goal "
        "(same preprocessing, ONNX step and GRU resets as in flight) and compare the actions with the "
        "recorded ones: about 0 with the model that flew, the would-be actions of another model with --model.  "
        "A log cut short by a killed process replays up to its last complete chunk.",
    )
    replay.add_argument("log", help="MCAP flight log (cmnav fly / cmnav sitl)")
    replay.add_argument("--model", help="ONNX model to replay with (default: the one recorded in the log)")
    replay.add_argument("--json", action="store_true", help="also print the report, with per-step differences, as one JSON line")
    replay.set_defaults(func=_cmd_replay)

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

    train = sub.add_parser("train", help="train the CMWAE encoder (the policy comes with issue 5)")
    train_sub = train.add_subparsers(dest="what", required=True, metavar="WHAT")
    cmwae = train_sub.add_parser(
        "cmwae",
        help="train the cross-modal encoder (WAE-MMD) with depth corruption on the fly",
        description="Train the CMWAE on gray/depth pairs (TartanAir V1/V2 layout, e.g. from `cmnav dataset`). "
        "Multi-GPU: `torchrun --nproc_per_node=N -m cmnav train cmwae ... --device cuda`.",
    )
    cmwae.add_argument("--data", required=True, help="dataset directory")
    cmwae.add_argument("--scheme", choices=["s1", "s2", "none"], default="s2", help="training corruption (none: the clean-depth baseline)")
    cmwae.add_argument("--out", required=True, help="checkpoint directory (model.json + fp16 shards + train state)")
    cmwae.add_argument("--modalities", default="gray,depth", choices=["gray,depth", "depth"],
                       help="encoder inputs; 'depth' = the depth-only baseline (DCE-RL stand-in)")  # fmt: skip
    cmwae.add_argument("--size", default="paper", choices=["paper", "small", "tiny"], help="network width (paper = AlexNet)")
    length = cmwae.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, help="optimizer steps")
    length.add_argument("--epochs", type=int, default=10, help="epochs over the train split (default 10)")
    cmwae.add_argument("--batch-size", type=int, default=64)
    cmwae.add_argument("--lr", type=float, default=1e-4)
    cmwae.add_argument("--mmd-weight", type=float, default=10.0, help="lambda of the MMD term")
    cmwae.add_argument("--seed", type=int, default=0)
    cmwae.add_argument("--device", default="cpu", help="cpu or cuda")
    cmwae.add_argument("--workers", type=int, default=2, help="data-loading processes")
    cmwae.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints")
    cmwae.add_argument("--resume", action="store_true", help="continue from the train state in --out")
    cmwae.set_defaults(func=_cmd_train_cmwae)

    evaluate = sub.add_parser("eval", help="evaluate a trained encoder (Table I)")
    eval_sub = evaluate.add_subparsers(dest="what", required=True, metavar="WHAT")
    eval_cmwae = eval_sub.add_parser("cmwae", help="Table I: MSE/SSIM at 0-50%% evaluation corruption on the held-out split")
    eval_cmwae.add_argument("--checkpoint", required=True, help="checkpoint directory")
    eval_cmwae.add_argument("--data", required=True, help="dataset directory")
    eval_cmwae.add_argument("--split", default="test", choices=["train", "val", "test"])
    eval_cmwae.add_argument("--out", help="directory for plots and table1.json (default CHECKPOINT/eval)")
    eval_cmwae.add_argument("--device", default="cpu")
    eval_cmwae.add_argument("--max-images", type=int, help="evaluate at most this many images")
    eval_cmwae.add_argument("--seed", type=int, default=0, help="seed of the evaluation patches")
    eval_cmwae.add_argument("--json", action="store_true", help="print the result as JSON on the last line")
    eval_cmwae.set_defaults(func=_cmd_eval_cmwae)

    export = sub.add_parser("export", help="write an ONNX model for the runtime")
    export_sub = export.add_subparsers(dest="what", required=True, metavar="WHAT")
    goal_seeker = export_sub.add_parser(
        "goal-seeker",
        help="a plumbing-check model that ignores the images and steers toward the goal",
    )
    goal_seeker.add_argument("-o", "--output", required=True, help="path of the ONNX file to write")
    goal_seeker.set_defaults(func=_cmd_export)

    bench = sub.add_parser("bench", help="measure speed as ratios within one run (today: the renderer, bench sim)")
    bench_sub = bench.add_subparsers(dest="what", required=True, metavar="WHAT")
    bench_sim = bench_sub.add_parser(
        "sim",
        help="renderer frames/s: fast path vs the plain reference, CPU and CUDA",
        description="Time the fast renderer and the plain reference at the raw camera size for "
        "N in {1, 16, 64} envs and 0/10/26 obstacles (and on CUDA when present), in one run "
        "(about a minute on 2 idle cores); print frames/s, their ratio and the fast path's mismatch "
        "against the reference as a markdown table.",
    )
    bench_sim.add_argument("--json", action="store_true", help="print the result as one JSON object instead")
    bench_sim.add_argument("--quick", action="store_true", help="a few seconds' smoke run (N in {1, 2}, 0/3 obstacles, one timed call)")  # fmt: skip
    bench_sim.set_defaults(func=_cmd_bench_sim)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    return int(args.func(args) or 0)
