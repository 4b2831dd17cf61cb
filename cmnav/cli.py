"""The `cmnav` command: argument parsing only; each subcommand imports its package when it runs,
so `cmnav --help` and the runtime's commands never pay for torch."""

from __future__ import annotations

import argparse
import logging
import sys

log = logging.getLogger("cmnav")


def _cmd_sitl(args: argparse.Namespace) -> int:
    from sim.sitl_session import run_sitl_cli

    return run_sitl_cli(args)


def _cmd_export(args: argparse.Namespace) -> int:
    from runtime.service.paths import output_file_problem

    if (problem := output_file_problem(args.output)) is not None:
        print(f"cmnav export goal-seeker: -o {args.output}: {problem}", file=sys.stderr)
        return 2
    from export.goal_seeker import export_goal_seeker

    export_goal_seeker(args.output)
    print(f"wrote goal-seeker model to {args.output}")
    return 0


def _cmd_export_policy(args: argparse.Namespace) -> int:
    import json

    missing = [flag for flag, value in (("--encoder", args.encoder), ("--policy", args.policy), ("-o", args.model_out)) if not value]
    if missing:
        print(f"cmnav export: {', '.join(missing)} required (or `cmnav export goal-seeker -o PATH`)", file=sys.stderr)
        return 2
    from runtime.service.paths import output_file_problem

    if (problem := output_file_problem(args.model_out)) is not None:
        print(f"cmnav export: -o {args.model_out}: {problem}", file=sys.stderr)
        return 2
    from export.policy_onnx import ExportError, VariantRefusedError, export_policy
    from runtime.contract import ContractMismatchError
    from runtime.log.reader import ReplayError
    from runtime.model import ModelLoadError

    variants = tuple(v for v in args.variants.split(",") if v) if args.variants else ()
    try:
        report = export_policy(args.encoder, args.policy, args.model_out, recorded=args.recorded, variants=variants)
    except VariantRefusedError as err:  # the fp32 model (and any other variant) was written
        print(err.report.format())
        if args.json:
            print(json.dumps(err.report.to_json()))
        print(f"cmnav export: {err}", file=sys.stderr)
        return 2
    except (ExportError, ReplayError, ModelLoadError, ContractMismatchError) as err:
        print(f"cmnav export: {err}", file=sys.stderr)
        return 2
    print(report.format())
    if args.json:
        print(json.dumps(report.to_json()))
    return 0


def _cmd_dataset(args: argparse.Namespace) -> int:
    from training.data.generate import DatasetSpec, generate_dataset

    spec = DatasetSpec(count=args.count, seed=args.seed, levels=tuple(args.levels), frames_per_room=args.frames_per_room)
    manifest = generate_dataset(args.out, spec)
    print(f"wrote {manifest['frames']} gray/depth pairs from {manifest['rooms']} rooms to {args.out} (TartanAir V1 layout)")
    return 0


def _given(args: argparse.Namespace, *names: str) -> dict:
    """The options among ``names`` given on the command line (they default to None, so that the
    config dataclass keeps the one default)."""
    return {name: getattr(args, name) for name in names if getattr(args, name) is not None}


def _cmd_train_cmwae(args: argparse.Namespace) -> int:
    from training.cmwae.train import CmwaeTrainConfig, train_cmwae

    config = CmwaeTrainConfig(
        data_dir=args.data, out_dir=args.out, scheme=args.scheme, modalities=tuple(args.modalities.split(",")),
        size=args.size, steps=args.steps, epochs=args.epochs if args.steps is None else None,
        batch_size=args.batch_size, lr=args.lr, lr_final=args.lr_final, mmd_weight=args.mmd_weight, seed=args.seed,
        device=args.device, workers=args.workers, checkpoint_every=args.checkpoint_every, resume=args.resume,
        max_wall_s=None if args.minutes is None else args.minutes * 60.0, init_from=args.init_from,
        **_given(args, "precision", "corrupted_loss_weight"),
    )  # fmt: skip
    out = train_cmwae(config)
    print(f"checkpoint in {out}")
    return 0


def _policy_train_config(args: argparse.Namespace, encoder_dir: str | None, corruption: str):
    from training.policy.env import CurriculumConfig
    from training.policy.network import POLICY_SIZES
    from training.policy.ppo import PpoConfig
    from training.policy.train import PolicyTrainConfig

    return PolicyTrainConfig(
        encoder_dir=encoder_dir, out_dir=args.out, env_steps=args.steps, num_envs=args.envs, device=args.device,
        seed=args.seed, corruption=corruption, policy=POLICY_SIZES[args.size],
        ppo=PpoConfig(rollout_steps=args.rollout, minibatches=args.minibatches, lr=args.lr),
        curriculum=CurriculumConfig(start_level=args.start_level, max_level=args.max_level,
                                    window_episodes=args.curriculum_window),
        checkpoint_every=args.checkpoint_every, resume=args.resume, init_from=args.init_from,
        max_wall_s=None if args.minutes is None else args.minutes * 60.0, **_given(args, "precision"),
    )  # fmt: skip


def _cmd_train_policy(args: argparse.Namespace) -> int:
    if args.teacher is not None:
        return _train_student(args)
    from training.policy.train import train_policy

    out = train_policy(_policy_train_config(args, args.encoder, args.corruption))
    print(f"checkpoint in {out}")
    return 0


def _train_student(args: argparse.Namespace) -> int:
    from training.policy.dagger import DaggerConfig, train_dagger
    from training.policy.network import POLICY_SIZES

    if args.init_from is not None:
        print("cmnav train policy: --init-from is for PPO fine-tuning, not with --teacher", file=sys.stderr)
        return 2
    config = DaggerConfig(
        teacher_dir=args.teacher, encoder_dir=args.encoder, out_dir=args.out, env_steps=args.steps, num_envs=args.envs,
        device=args.device, seed=args.seed, corruption=args.corruption, policy=POLICY_SIZES[args.size],
        rollout_steps=args.rollout, minibatches=args.minibatches, max_level=args.max_level,
        checkpoint_every=args.checkpoint_every, resume=args.resume,
        max_wall_s=None if args.minutes is None else args.minutes * 60.0,
        **_given(args, "precision", "beta_decay_env_steps", "projector_off_episode_fraction"),
    )  # fmt: skip
    out = train_dagger(config)
    print(f"student checkpoint in {out}")
    return 0


def _cmd_train_teacher(args: argparse.Namespace) -> int:
    from training.policy.train import train_policy

    out = train_policy(_policy_train_config(args, None, "none"))
    print(f"teacher checkpoint in {out}")
    return 0


def _cmd_eval_cmwae(args: argparse.Namespace) -> int:
    import json

    from training.cmwae.evaluate import CmwaeEvalConfig, evaluate_cmwae

    result = evaluate_cmwae(
        CmwaeEvalConfig(checkpoint=args.checkpoint, data_dir=args.data, split=args.split, out_dir=args.out,
                        device=args.device, max_images=args.max_images, seed=args.seed,
                        **_given(args, "precision"),
                        **({} if args.patch_sides is None else {"patch_sides_px": args.patch_sides}))  # fmt: skip
    )
    print(result["table"])
    low, high = result["patch_sides_px"]
    print(f"patches of side {low}-{high} px; MSE at 50% / 0%: {result['mse_ratio_50_over_0']}; "
          f"table1.json and plots in {result['out_dir']}")  # fmt: skip
    if args.json:
        print(json.dumps(result))
    return 0


def _cmd_eval_policy(args: argparse.Namespace) -> int:
    import json

    from training.policy.evaluate import PolicyEvalConfig, evaluate_policy, format_table2

    config = PolicyEvalConfig(
        policy_dir=args.policy, encoder_dir=args.encoder, levels=tuple(args.levels), conditions=tuple(args.conditions),
        episodes=args.episodes, batch_envs=args.batch_envs, device=args.device, seed=args.seed, out_dir=args.out,
        **_given(args, "precision"),
    )  # fmt: skip
    result = evaluate_policy(config)
    print(format_table2(result))
    print(f"table2.json, table2.md and trajectory plots in {result['out_dir']}")
    if args.json:
        print(json.dumps(result))
    return 0


def _cmd_pipeline(args: argparse.Namespace) -> int:
    from cmnav.pipeline import PipelineConfig, run_pipeline

    config = PipelineConfig(
        out_dir=args.out, minutes=args.minutes, device=args.device, seed=args.seed, dataset_count=args.dataset_count,
        dataset=args.dataset, encoder_size=args.encoder_size, encoder_batch_size=args.encoder_batch_size,
        policy_size=args.policy_size, envs=args.envs, teacher_envs=args.teacher_envs, eval_episodes=args.eval_episodes, eval_levels=tuple(args.eval_levels),
        call_minutes=args.call_minutes,
    )  # fmt: skip
    summary = run_pipeline(config, sys.argv[1:])
    if not summary["done"]:
        print(f"pipeline paused after this call's {args.call_minutes} min (spent so far: {summary['spent_s']}); "
              "run the same command again to continue")  # fmt: skip
        return 3
    print(f"pipeline done in {sum(summary['timings_s'].values()):.0f} s; model card: {args.out}/MODEL_CARD.md")
    return 0


def _cmd_bench_sim(args: argparse.Namespace) -> int:
    import json

    from bench.sim import QUICK, SimBenchConfig, format_sim_bench, run_sim_bench

    result = run_sim_bench(QUICK if args.quick else SimBenchConfig())
    print(json.dumps(result) if args.json else format_sim_bench(result))
    return 0


def _cmd_bench_train(args: argparse.Namespace) -> int:
    import json

    from bench.train import TrainBenchConfig, format_train_bench, quick, run_train_bench

    config = TrainBenchConfig(env_counts=tuple(args.envs), device=args.device, encoder_dir=args.encoder,
                              rollout_steps=args.steps, level=args.level, recorded=tuple(args.recorded or ()),
                              policy_dir=args.policy)  # fmt: skip
    result = run_train_bench(quick(config) if args.quick else config)
    print(json.dumps(result) if args.json else format_train_bench(result))
    return 0


def _cmd_bench_runtime(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from bench.runtime import RuntimeBenchConfig, format_runtime_bench, quick, run_runtime_bench
    from export.policy_onnx import ExportError
    from runtime.contract import ContractMismatchError
    from runtime.model import ModelLoadError

    config = RuntimeBenchConfig(
        model=Path(args.model), encoder=args.encoder and Path(args.encoder), policy=args.policy and Path(args.policy),
        sitl=not args.no_sitl, sitl_level=args.level, sitl_seed=args.seed, sitl_timeout_s=args.sitl_timeout,
        out_dir=Path(args.out), variants=not args.no_variants, pin=not args.no_pin,
    )  # fmt: skip
    try:
        result = run_runtime_bench(quick(config) if args.quick else config)
    except (ModelLoadError, ContractMismatchError, ExportError) as err:
        print(f"cmnav bench runtime: {err}", file=sys.stderr)
        return 2
    print(json.dumps(result) if args.json else format_runtime_bench(result))
    return 0


def _cmd_fly(args: argparse.Namespace) -> int:
    from runtime.programs.fly import run_fly

    return run_fly(args.config, print_json=args.json, check_only=args.check)


def _cmd_replay(args: argparse.Namespace) -> int:
    import json

    from runtime.programs.replay import ReplayError, replay_log

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
        "stop both processes.  Writes the MCAP flight log and a top-view trajectory plot.  With --autopilot "
        "it flies an external autopilot (PX4 SITL) instead of our vehicle: the camera world follows its pose "
        "(docs/px4-sitl.md).",
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
        "geofence, runtime-kill, vehicle-stuck; the summary then lists each fault's trip, detection time and stop time",
    )  # fmt: skip
    sitl.add_argument("--autopilot", metavar="URL",
                      help="fly an external autopilot (PX4 SITL) instead of our vehicle: the camera world follows its "
                      "pose from this MAVLink address, udp://127.0.0.1:14550 for PX4's GCS link (docs/px4-sitl.md)")  # fmt: skip
    sitl.add_argument("--offboard-port", type=int,
                      help="with --autopilot: UDP port on 127.0.0.1 of the autopilot's offboard link the runtime flies "
                      "on (default 14540, PX4 SITL's)")  # fmt: skip
    sitl.add_argument("--allow-remote", action="store_true",
                      help="with --autopilot: accept a host other than 127.0.0.1 (a bench setup; default: refused)")
    sitl.set_defaults(func=_cmd_sitl)

    fly = sub.add_parser(
        "fly",
        help="the field program: fly the policy on the vehicle (what systemd runs)",
        description="Validate the TOML config (nothing talks to the vehicle before it and the model pass), "
        "connect, wait for the pilot to arm, take off and switch to offboard (or, with "
        "mission.allow_arm_takeoff = true, do that itself), fly to the goal, Hold, repeat.  "
        "SIGTERM/SIGINT in any phase: the runtime commands the safe state (in offboard hover, then Hold) and exits.  "
        "Exit 0 done or stopped, 1 a failure a restart may cure, 2 a bad config or model (or an unwritable log with "
        "recorder.required).  "
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

    def add_precision(command: argparse.ArgumentParser) -> None:
        command.add_argument("--precision", choices=["auto", "fp32", "bf16"],
                             help="torch compute precision on the CPU (default auto: bf16 + channels_last where the CPU has "
                             "AMX/AVX512-BF16, fp32 channels_last on AVX2, else fp32; the choice is logged)")  # fmt: skip

    train = sub.add_parser("train", help="train the CMWAE encoder or the navigation policy")
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
    cmwae.add_argument("--modalities", default="gray,depth", choices=["gray,depth", "depth"], metavar="{gray,depth | depth}",
                       help="encoder inputs; 'depth' = the depth-only baseline (DCE-RL stand-in)")  # fmt: skip
    cmwae.add_argument("--size", default="paper", choices=["paper", "small", "tiny"], help="network width (paper = AlexNet)")
    length = cmwae.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, help="optimizer steps")
    length.add_argument("--epochs", type=int, default=10, help="epochs over the train split (default 10)")
    cmwae.add_argument("--batch-size", type=int, default=64)
    cmwae.add_argument("--lr", type=float, default=1e-4, help="Adam learning rate (also applied on --resume)")
    cmwae.add_argument("--lr-final", type=float,
                       help="cosine-decay the learning rate from --lr at step 0 to this at the last step (default: constant)")  # fmt: skip
    cmwae.add_argument("--mmd-weight", type=float, default=10.0, help="lambda of the MMD term")
    cmwae.add_argument("--seed", type=int, default=0)
    cmwae.add_argument("--device", default="cpu", help="cpu or cuda")
    cmwae.add_argument("--workers", type=int, default=2, help="data-loading processes")
    cmwae.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints")
    cmwae.add_argument("--resume", action="store_true", help="continue from the train state in --out")
    cmwae.add_argument("--minutes", type=float, help="stop (with a checkpoint) after this wall-clock time")
    cmwae.add_argument("--corrupted-loss-weight", type=float,
                       help="weight of a corrupted image's reconstruction error against a pristine one's (default 1: the paper's mean)")  # fmt: skip
    cmwae.add_argument("--init-from", metavar="CMWAE_DIR", help="start from this encoder checkpoint's weights (not its optimizer or step)")
    add_precision(cmwae)
    cmwae.set_defaults(func=_cmd_train_cmwae)

    def add_ppo_options(command: argparse.ArgumentParser, envs: int) -> None:
        command.add_argument("--out", required=True, help="checkpoint directory (model.json + fp16 shards + train state)")
        command.add_argument("--steps", type=int, default=1_000_000, help="env steps in total (default 1e6)")
        command.add_argument("--minutes", type=float, help="stop (with a checkpoint) after this wall-clock time")
        command.add_argument("--envs", type=int, default=envs, help=f"envs per process (default {envs})")
        command.add_argument("--device", default="cpu", help="cpu or cuda")
        command.add_argument("--seed", type=int, default=0)
        command.add_argument("--size", choices=["paper", "tiny"], default="paper", help="policy width (paper: FC 256-128-64, GRU 64)")
        command.add_argument("--rollout", type=int, default=32, help="steps per PPO rollout (default 32)")
        command.add_argument("--minibatches", type=int, default=4, help="PPO minibatches per epoch, split over envs")
        command.add_argument("--lr", type=float, default=3e-4)
        command.add_argument("--start-level", type=int, default=0, help="curriculum start level (obstacles)")
        command.add_argument("--max-level", type=int, default=20, help="curriculum cap")
        command.add_argument("--curriculum-window", type=int, default=256, help="episodes per curriculum decision")
        command.add_argument("--checkpoint-every", type=int, default=20, help="PPO iterations between checkpoints")
        command.add_argument("--resume", action="store_true", help="continue from the train state in --out")

    policy = train_sub.add_parser(
        "policy",
        help="train the navigation policy (recurrent PPO) on the batched sim with a frozen encoder",
        description="Recurrent PPO (FC 256-128-64 ELU -> GRU -> FC) on N simulated envs at 15 Hz, with the "
        "frozen encoder, the runtime's observation/action contract, depth corruption on a random half of "
        "the envs each step, kicks, camera jitter and the obstacle curriculum.  Multi-GPU: "
        "`torchrun --nproc_per_node=N -m cmnav train policy ... --device cuda`.",
    )
    policy.add_argument("--encoder", required=True, help="encoder checkpoint directory (cmnav train cmwae)")
    add_ppo_options(policy, envs=64)
    policy.add_argument("--corruption", choices=["train", "none"], default="train",
                        help="depth corruption during training (none: the depth-only baseline policy)")  # fmt: skip
    policy.add_argument("--init-from", metavar="POLICY_DIR",
                        help="start from this policy checkpoint (fine-tuning); when it was trained on another encoder, "
                        "its latent normalisation is re-estimated on --encoder")  # fmt: skip
    policy.add_argument("--teacher", metavar="TEACHER_DIR",
                        help="distil this privileged teacher (cmnav train teacher) by DAgger instead of PPO: the student "
                        "flies a teacher/student mixture, the teacher labels every state it visits; the student's depth is "
                        "corrupted (--corruption), the teacher's is clean")  # fmt: skip
    policy.add_argument("--beta-decay-env-steps", type=int,
                        help="DAgger: env steps over which the teacher's share of the actions falls from 1 to 0 (default 3e5)")
    policy.add_argument("--projector-off-episode-fraction", type=float,
                        help="DAgger: share of episodes whose depth is lost like a D455 without its projector (default 0.15)")
    add_precision(policy)
    policy.set_defaults(func=_cmd_train_policy)

    teacher = train_sub.add_parser(
        "teacher",
        help="train the privileged teacher (recurrent PPO on state + low-resolution clean depth, no encoder)",
        description="The teacher of the distilled policy (DESIGN §5): the same recurrent PPO, reward, curriculum "
        "(to level 20), kicks, camera jitter and action contract as `train policy`, but it observes the 15 state "
        "values and clean depth of the camera's field of view ray cast at 64x36 and min-pooled to 32x18, so no "
        "224 image is rendered and no encoder runs.  It never flies: `cmnav train policy --teacher DIR` distils it.",
    )
    add_ppo_options(teacher, envs=1024)
    teacher.add_argument("--init-from", metavar="TEACHER_DIR", help="start from this teacher checkpoint")
    teacher.set_defaults(func=_cmd_train_teacher, precision=None)

    evaluate = sub.add_parser("eval", help="evaluate a trained encoder (Table I) or policy (Table II)")
    eval_sub = evaluate.add_subparsers(dest="what", required=True, metavar="WHAT")

    def side_range(text: str) -> tuple[int, int]:
        low, _, high = text.partition("-")
        try:
            return int(low), int(high or low)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected MIN-MAX in px, e.g. 1-50 or 100-100") from None

    eval_cmwae = eval_sub.add_parser("cmwae", help="Table I: MSE/SSIM at 0-50%% evaluation corruption on the held-out split")
    eval_cmwae.add_argument("--checkpoint", required=True, help="checkpoint directory")
    eval_cmwae.add_argument("--data", required=True, help="dataset directory")
    eval_cmwae.add_argument("--split", default="test", choices=["train", "val", "test"])
    eval_cmwae.add_argument("--out", help="directory for plots and table1.json (default CHECKPOINT/eval)")
    eval_cmwae.add_argument("--device", default="cpu")
    eval_cmwae.add_argument("--max-images", type=int, help="evaluate at most this many images")
    eval_cmwae.add_argument("--seed", type=int, default=0, help="seed of the evaluation patches")
    eval_cmwae.add_argument("--patch-sides", type=side_range, metavar="MIN-MAX",
                            help="side range of the square patches in px at 224x224 (default 1-50, Table I's; "
                            "100-100: S2's training squares; 1-30: the policy's training patches)")  # fmt: skip
    eval_cmwae.add_argument("--json", action="store_true", help="print the result as JSON on the last line")
    add_precision(eval_cmwae)
    eval_cmwae.set_defaults(func=_cmd_eval_cmwae)

    def int_list(text: str) -> list[int]:
        return [int(x) for x in text.split(",") if x]

    def name_list(text: str) -> list[str]:
        return [x for x in text.split(",") if x]

    eval_policy = eval_sub.add_parser(
        "policy",
        help="Table II: success/timeout/crash %% per level and depth condition, with trajectory plots",
        description="Fly N seeded episodes per (condition, level) in the batched sim with the policy's mean "
        "action and no kicks; the same rooms for every condition and policy.  Conditions: clean, corrupted "
        "(the training patches fixed for the whole episode), projector-off (depth lost like a D455 without "
        "its projector).",
    )
    eval_policy.add_argument("--policy", required=True, help="policy checkpoint directory (cmnav train policy)")
    eval_policy.add_argument("--encoder", help="the encoder checkpoint the policy was trained with (none for a teacher)")
    eval_policy.add_argument("--levels", type=int_list, default=[0, 5, 10, 15, 20], help="comma-separated (default 0,5,10,15,20)")
    eval_policy.add_argument("--conditions", type=name_list, default=["clean", "corrupted", "projector-off"],
                             help="comma-separated subset of clean,corrupted,projector-off (default all)")  # fmt: skip
    eval_policy.add_argument("--episodes", type=int, default=100, help="episodes per cell (default 100)")
    eval_policy.add_argument("--batch-envs", type=int, default=64, help="episodes flown at once")
    eval_policy.add_argument("--device", default="cpu")
    eval_policy.add_argument("--seed", type=int, default=0, help="seed of the rooms")
    eval_policy.add_argument("--out", help="directory for table2.json/.md and plots (default POLICY/eval)")
    eval_policy.add_argument("--json", action="store_true", help="print the result as JSON on the last line")
    add_precision(eval_policy)
    eval_policy.set_defaults(func=_cmd_eval_policy)

    pipeline = sub.add_parser(
        "pipeline",
        help="dataset -> encoder (S2) -> Table I -> policy -> Table II -> export, within a time budget",
        description="The one-command training run for a GPU machine with only torch, onnx, onnxruntime and numpy: "
        "renders a dataset, trains the CMWAE (S2) and the policy on shares of the --minutes budget "
        "(35%% and 50%%), evaluates Table I and II, exports model.onnx, and writes MODEL_CARD.md and "
        "pipeline.json in --out.  Checkpoints are fp16 shards <= 15 MiB.",
    )
    pipeline.add_argument("--out", required=True, help="output directory")
    pipeline.add_argument("--minutes", type=float, required=True, help="wall-clock budget")
    pipeline.add_argument("--device", default="cuda", help="cuda (default) or cpu")
    pipeline.add_argument("--seed", type=int, default=0)
    pipeline.add_argument("--dataset-count", type=int, default=8000, help="gray/depth pairs to render (default 8000)")
    pipeline.add_argument("--dataset", help="use this existing dataset directory instead of rendering one")
    pipeline.add_argument("--encoder-size", choices=["paper", "small", "tiny"], default="paper")
    pipeline.add_argument("--encoder-batch-size", type=int, default=64)
    pipeline.add_argument("--policy-size", choices=["paper", "tiny"], default="paper")
    pipeline.add_argument("--envs", type=int, default=512, help="the student's (DAgger) envs (default 512)")
    pipeline.add_argument("--teacher-envs", type=int, default=1024, help="the teacher's (PPO) envs (default 1024)")
    pipeline.add_argument("--eval-episodes", type=int, default=100, help="Table II episodes per cell (default 100)")
    pipeline.add_argument("--eval-levels", type=int_list, default=[0, 5, 10, 15, 20], help="Table II levels")
    pipeline.add_argument("--call-minutes", type=float,
                          help="stop this call after this long (exit 3); the same command continues the run")  # fmt: skip
    pipeline.set_defaults(func=_cmd_pipeline)

    export = sub.add_parser(
        "export",
        help="write an ONNX model for the runtime: trained encoder + policy, or the goal-seeker",
        usage="cmnav export --encoder CKPT --policy CKPT -o MODEL.onnx [--recorded LOG.mcap ...] [--variants fp16,int8] [--json]\n"
        "       cmnav export goal-seeker -o MODEL.onnx",
        description="Build one ONNX graph for the runtime's control step from a CMWAE encoder checkpoint (its encoder "
        "only) and a policy checkpoint: (gray, depth, state, GRU hidden) -> (action, next hidden, latent), batch 1, "
        "opset 17, with the contract, normalisation, action scaling and provenance (git commit, checkpoint "
        "fingerprints, data, seed, eval tables) in its metadata.  Refuses a policy trained on another encoder.  "
        "Checks ONNX Runtime against torch on random inputs (and on a flight log's frames with --recorded), "
        "max abs error <= 1e-4, then loads the file with the runtime's own loader.  --variants also writes "
        "MODEL.fp16.onnx / MODEL.int8.onnx with their parity cost against the fp32 graph: int8 quantises the "
        "convolutions only (the policy head stays fp32), calibrated on the first half of the --recorded flights, and is "
        "written only if its max action error over >= 300 steps of the other half (GRU state carried) is <= 0.02, else "
        "refused with the numbers (exit 2, the fp32 model is kept).  `cmnav bench runtime` times the variants.",
    )
    export.add_argument("--encoder", metavar="CKPT", help="CMWAE checkpoint directory (cmnav train cmwae), e.g. models/cmwae-s2")
    export.add_argument("--policy", metavar="CKPT", help="policy checkpoint directory (cmnav train policy)")
    export.add_argument("-o", "--output", dest="model_out", metavar="MODEL.onnx", help="path of the ONNX file to write")
    export.add_argument("--recorded", metavar="LOG.mcap", nargs="+", action="extend",
                        help="flight logs (MCAP, cmnav fly/sitl): the first one's frames and states join the parity check; "
                        "the first half of them calibrate int8, the rest judge the variants")  # fmt: skip
    export.add_argument("--variants", default="", metavar="fp16,int8", help="comma-separated: fp16 (for GPU providers), int8 (static QDQ)")
    export.add_argument("--json", action="store_true", help="also print the export report as one JSON line")
    export.set_defaults(func=_cmd_export_policy)
    export_sub = export.add_subparsers(dest="what", required=False, metavar="{goal-seeker}")
    goal_seeker = export_sub.add_parser(
        "goal-seeker",
        prog="cmnav export goal-seeker",
        help="a plumbing-check model that ignores the images and steers toward the goal",
    )
    goal_seeker.add_argument("-o", "--output", required=True, help="path of the ONNX file to write")
    goal_seeker.set_defaults(func=_cmd_export)

    bench = sub.add_parser("bench", help="measure speed as ratios within one run: renderer, runtime step, policy training")
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
    bench_runtime = bench_sub.add_parser(
        "runtime",
        help="the control step: preprocessing, ONNX step (1/2 threads, CUDA/TensorRT when present), torch eager, "
        "SITL grab->command; ratios against the targets",
        description="In one run: p50/p99 of preprocessing, the ONNX step with 1 and 2 intra-op threads (and its "
        "fp16/int8 variants found next to the model), the same networks in torch eager (with --encoder/--policy), "
        "and grab->command in one short SITL flight per CPU model (fp32 and int8), the runtime pinned to a core of its "
        "own with 1 intra-op thread and the SITL vehicle on the other cores, with the overhead split by stage; the model's FLOPs, this CPU's theoretical FP32 peak and its "
        "achieved GEMM rate; and the ratios against the targets (ONNX <= 0.65x eager, <= 1.3x ideal, overhead "
        "<= 3 ms p99, end to end <= 25 ms p99) with PASS/MISS.",
    )
    bench_runtime.add_argument("--model", required=True, help="ONNX model with the runtime's contract (cmnav export)")
    bench_runtime.add_argument("--encoder", help="the CMWAE checkpoint the model was exported from (for the torch eager rows)")
    bench_runtime.add_argument("--policy", help="the policy checkpoint the model was exported from (for the torch eager rows)")
    bench_runtime.add_argument("--no-sitl", action="store_true", help="skip the SITL flights (no end-to-end rows)")
    bench_runtime.add_argument("--no-pin", action="store_true", help="SITL: do not pin the runtime to a core of its own "
                               "(default: runtime on the last CPU with 1 intra-op thread, the SITL vehicle on the others)")  # fmt: skip
    bench_runtime.add_argument("--no-variants", action="store_true", help="do not time MODEL.fp16.onnx / MODEL.int8.onnx")
    bench_runtime.add_argument("--level", type=int, default=0, help="SITL curriculum level (default 0)")
    bench_runtime.add_argument("--seed", type=int, default=0, help="SITL world seed (default 0)")
    bench_runtime.add_argument("--sitl-timeout", type=float, default=20.0, help="SITL offboard time limit, s (default 20)")
    bench_runtime.add_argument("--out", default="runs/bench-runtime", help="directory for the SITL run (default runs/bench-runtime)")
    bench_runtime.add_argument("--json", action="store_true", help="print the result as one JSON object instead")
    bench_runtime.add_argument("--quick", action="store_true", help="a smoke run of every path (a few calls each, 3 s SITL flight)")
    bench_runtime.set_defaults(func=_cmd_bench_runtime)
    bench_train = bench_sub.add_parser(
        "train",
        help="training speed: the encoder per precision, policy env-steps/s (fp32 and the fast path) with each "
        "stage's share, the teacher's env-steps/s, CMWAE train steps/s",
        description="In one run on one device: the frozen encoder's frames/s in fp32, fp32 channels_last and bf16 "
        "channels_last with bf16's latent error; one PPO rollout + update in the batched navigation env for each N "
        "with the encoder in fp32 and on the path --precision auto picks (env-steps/s, each stage's share); the "
        "privileged teacher's env; CMWAE optimizer steps/s per precision.  Ratios are within this run.",
    )
    bench_train.add_argument("--envs", type=lambda t: [int(x) for x in t.split(",") if x], default=[16, 64],
                             help="comma-separated env counts (default 16,64)")  # fmt: skip
    bench_train.add_argument("--device", default="cpu", help="cpu or cuda")
    bench_train.add_argument("--encoder", help="encoder checkpoint (default: an untrained paper-size encoder)")
    bench_train.add_argument("--steps", type=int, default=16, help="rollout steps timed per N (default 16)")
    bench_train.add_argument("--level", type=int, default=10, help="obstacles per room (default 10)")
    bench_train.add_argument("--recorded", nargs="+", metavar="LOG", help="flight logs: bf16's latent (and action) parity on their frames")
    bench_train.add_argument("--policy", help="policy checkpoint for the action parity on --recorded frames")
    bench_train.add_argument("--json", action="store_true", help="print the result as one JSON object instead")
    bench_train.add_argument("--quick", action="store_true", help="a seconds-long smoke run (2 envs, tiny networks)")
    bench_train.set_defaults(func=_cmd_bench_train)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args.func(args) or 0)
    except ValueError as err:  # bad input (config, checkpoint, data): the message names it and the fix
        log.debug("traceback", exc_info=True)
        print(f"cmnav {' '.join(filter(None, (args.command, getattr(args, 'what', None))))}: {err}", file=sys.stderr)
        return 2
