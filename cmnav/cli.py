"""The `cmnav` command: argument parsing only; each subcommand imports its package when it runs,
so `cmnav --help` and the runtime's commands never pay for torch."""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import logging
import sys

log = logging.getLogger("cmnav")
# sim.sitl.camera_feed.DEPTH_MODES, spelled here so that building the parser imports no torch
# (tests/cmnav/test_cli_args.py holds them equal).
SITL_DEPTH_MODES = ("none", "projector-off", "stereo", "stereo-projector-off")
VEHICLE_CHOICES = ("ideal", "px4", "field")  # training.policy.field.VEHICLES, likewise
SITL_ESTIMATES = ("exact", "px4")  # sim.sitl.estimate.ESTIMATES, likewise
VELOCITY_BIAS_MODES = ("correct", "off")  # runtime.tracking.VELOCITY_BIAS_MODES, likewise
APPROACH_CAP_MODES = ("on", "off")  # runtime.programs.sitl.APPROACH_CAP_MODES, likewise
SQUARES_TEACHER_VIEWS = ("clean", "reconstructed")  # training.policy.env.SQUARES_PRIVILEGED, likewise


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
    if (args.policy is None) != (args.encoder is None):
        print("cmnav dataset: --policy and --encoder go together (the policy flies on the encoder it was trained with)",
              file=sys.stderr)  # fmt: skip
        return 2
    if args.policy is not None:
        if args.depth is not None:
            print("cmnav dataset: --depth applies to random poses, not to --policy flights", file=sys.stderr)
            return 2
        return _flight_frames(args)
    if args.every_steps is not None or args.envs is not None:
        print("cmnav dataset: --every-steps and --envs apply to flights (--policy)", file=sys.stderr)
        return 2
    if args.stereo_projector_off_fraction is not None and args.depth != "stereo":
        print("cmnav dataset: --stereo-projector-off-fraction applies to --depth stereo", file=sys.stderr)
        return 2
    from training.data.generate import DatasetSpec, generate_dataset

    levels = {} if args.levels is None else {"levels": tuple(args.levels)}
    spec = DatasetSpec(count=args.count, seed=args.seed, **levels,
                       **_given(args, "frames_per_room", "depth", "stereo_projector_off_fraction"))  # fmt: skip
    manifest = generate_dataset(args.out, spec)
    print(f"wrote {manifest['frames']} gray/depth pairs from {manifest['rooms']} rooms to {args.out} (TartanAir V1 layout)")
    if "stereo" in manifest:
        print(f"with the simulated D455's stereo depth of each frame ({manifest['stereo']['invalid_depth_frac_mean']:.1%} "
              f"invalid on average) in depth_stereo/")  # fmt: skip
    return 0


def _flight_frames(args: argparse.Namespace) -> int:
    from training.policy.flight_frames import FlightFramesSpec, record_flight_frames

    if args.frames_per_room is not None:
        print("cmnav dataset: --frames-per-room is for random poses; a flight keeps frames by --every-steps", file=sys.stderr)
        return 2
    levels = {} if args.levels is None else {"min_level": min(args.levels), "max_level": max(args.levels)}
    spec = FlightFramesSpec(policy_dir=args.policy, encoder_dir=args.encoder, count=args.count, seed=args.seed, **levels,
                            **_given(args, "every_steps", num_envs="envs"))  # fmt: skip
    manifest = record_flight_frames(args.out, spec)
    print(f"wrote {manifest['frames']} gray/depth pairs from {manifest['flights_with_frames']} flights of {args.policy} "
          f"to {args.out} (TartanAir V1 layout); finished flights: {manifest['flight_outcomes']}")  # fmt: skip
    return 0


def _given(args: argparse.Namespace, *names: str, **renamed: str) -> dict:
    """The options among ``names`` (and ``field=option`` in ``renamed``) given on the command line,
    keyed by the config field: they default to None, so that the config dataclass keeps the one
    default (see :func:`_config_option`)."""
    pairs = [(name, name) for name in names] + list(renamed.items())
    return {field: getattr(args, option) for field, option in pairs if getattr(args, option) is not None}


def _field_default(field: str) -> object:
    """The default of a config dataclass field named ``module:Class.field``."""
    where, _, name = field.rpartition(".")
    module, _, cls = where.partition(":")
    config = getattr(importlib.import_module(module), cls)
    found = next(f for f in dataclasses.fields(config) if f.name == name)
    return found.default_factory() if found.default is dataclasses.MISSING else found.default


def _shown(value: object) -> str:
    """A default as the option takes it on the command line (a tuple as a comma-separated list)."""
    return ",".join(str(v) for v in value) if isinstance(value, (tuple, list)) else str(value)


def _config_option(command: argparse.ArgumentParser, flag: str, *fields: str, help: str, **kwargs) -> None:
    """An option whose default lives in the config dataclass field(s) it sets (``module:Class.field``):
    it defaults to None (the command passes it on only when given, :func:`_given`), and ``--help``
    shows the field's default (:class:`_ConfigDefaultsFormatter`), read when the help is printed,
    so that building the parser imports no training module (``cmnav fly`` never loads torch)."""
    action = command.add_argument(flag, default=None, help=help, **kwargs)
    action.config_fields = fields


class _ConfigDefaultsFormatter(argparse.HelpFormatter):
    """Appends ``(default X)`` from the config dataclasses to each :func:`_config_option`'s help."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = super()._get_help_string(action)
        fields = getattr(action, "config_fields", ())
        if not fields:
            return text
        shown = list(dict.fromkeys(_shown(_field_default(field)) for field in fields))
        if len(shown) == 1:
            default = f"default {shown[0]}"
        else:
            default = "defaults " + ", ".join(f"{field.rpartition('.')[0].partition(':')[2]} {_shown(_field_default(field))}"
                                              for field in fields)  # fmt: skip
        return f"{text} ({default.replace('%', '%%')})"  # the help is a %-format string (argparse's %(default)s)


def _name_tuple(text: str) -> tuple[str, ...]:
    return tuple(x for x in text.split(",") if x)


def _use_formatter(parser: argparse.ArgumentParser, formatter: type[argparse.HelpFormatter]) -> None:
    """``formatter`` for ``parser`` and every subcommand's parser under it."""
    parser.formatter_class = formatter
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for subparser in action.choices.values():
                _use_formatter(subparser, formatter)


def _cmd_train_cmwae(args: argparse.Namespace) -> int:
    from training.cmwae.train import CmwaeTrainConfig, train_cmwae

    config = CmwaeTrainConfig(
        data_dir=args.data[0], extra_data_dirs=tuple(args.data[1:]), out_dir=args.out, steps=args.steps, epochs=args.epochs if args.steps is None else None,
        lr_final=args.lr_final, resume=args.resume, max_wall_s=None if args.minutes is None else args.minutes * 60.0,
        init_from=args.init_from, anchor_from=args.anchor,
        **_given(args, "scheme", "modalities", "size", "batch_size", "lr", "mmd_weight", "seed", "device", "workers",
                 "checkpoint_every", "precision", "corrupted_loss_weight", "anchor_weight", "consistency_weight", "near_weight",
                 "near_m", "pooled_weight", "hidden_far_weight", "val_images", "squares_share"),
    )  # fmt: skip
    out = train_cmwae(config)
    print(f"checkpoint in {out}")
    return 0


def _policy_train_config(args: argparse.Namespace, encoder_dir: str | None, corruption: str | None):
    from training.policy.env import CurriculumConfig
    from training.policy.network import POLICY_SIZES
    from training.policy.ppo import PpoConfig
    from training.policy.train import PolicyTrainConfig

    return PolicyTrainConfig(
        encoder_dir=encoder_dir, out_dir=args.out, policy=POLICY_SIZES[args.size],
        **({} if corruption is None else {"corruption": corruption}),
        ppo=PpoConfig(**_given(args, "minibatches", "lr", "target_kl", rollout_steps="rollout")),
        curriculum=CurriculumConfig(**_given(args, "start_level", "max_level", window_episodes="curriculum_window")),
        resume=args.resume, keep_checkpoints=args.keep_checkpoints, init_from=args.init_from,
        max_wall_s=None if args.minutes is None else args.minutes * 60.0,
        env_overrides=_given(args, "squares_episode_fraction"),
        **_given(args, "device", "seed", "checkpoint_every", "precision", "vehicle", "end_at_goal", "init_log_std",
                 "critic_warmup_iterations", "freeze_obs_norm", num_envs="envs", env_steps="steps"),
    )  # fmt: skip


def _cmd_train_policy(args: argparse.Namespace) -> int:
    if args.teacher is not None:
        return _train_student(args)
    dagger_only = _given_flags(args, "field", "projector_off_episode_fraction", "squares_teacher_view", "beta_start", "beta_decay_env_steps",
                               "near_weight")  # fmt: skip
    if dagger_only:
        print(f"cmnav train policy: {', '.join(dagger_only)} train a student by DAgger: give --teacher TEACHER_DIR", file=sys.stderr)
        return 2
    from training.policy.train import train_policy

    out = train_policy(_policy_train_config(args, args.encoder, args.corruption))
    print(f"checkpoint in {out}")
    return 0


def _given_flags(args: argparse.Namespace, *names: str) -> list[str]:
    """The options among ``names`` given on the command line (:func:`_given`), as their flags."""
    return [f"--{name.replace('_', '-')}" for name in _given(args, *names)]


def _train_student(args: argparse.Namespace) -> int:
    if ppo_only := _given_flags(args, "init_log_std", "critic_warmup_iterations", "freeze_obs_norm", "target_kl"):
        print(f"cmnav train policy: {', '.join(ppo_only)} fine-tune by PPO, which --teacher (DAgger) is not: drop --teacher",
              file=sys.stderr)  # fmt: skip
        return 2
    from training.policy.dagger import DaggerConfig, train_dagger
    from training.policy.network import POLICY_SIZES

    config = DaggerConfig(
        teacher_dir=args.teacher, encoder_dir=args.encoder, out_dir=args.out,
        policy=POLICY_SIZES[args.size], resume=args.resume, keep_checkpoints=args.keep_checkpoints, init_from=args.init_from,
        max_wall_s=None if args.minutes is None else args.minutes * 60.0,
        **_given(args, "device", "seed", "corruption", "minibatches", "min_level", "max_level", "checkpoint_every", "precision",
                 "lr", "beta_start", "beta_decay_env_steps", "projector_off_episode_fraction", "squares_episode_fraction", "squares_teacher_view", "near_weight", "near_m",
                 "vehicle", "end_at_goal", "field_depth", "field_env_fraction", num_envs="envs", outside_teacher_dir="outside_teacher", rollout_steps="rollout", env_steps="steps", field_conditions="field"),
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
        CmwaeEvalConfig(checkpoint=args.checkpoint, data_dir=args.data, out_dir=args.out, max_images=args.max_images,
                        **_given(args, "split", "device", "seed", "precision", "near_m"),
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
        policy_dir=args.policy, encoder_dir=args.encoder, out_dir=args.out, teacher_dir=args.teacher,
        **_given(args, "levels", "conditions", "episodes", "batch_envs", "device", "seed", "rooms", "precision"),
    )  # fmt: skip
    result = evaluate_policy(config)
    print(format_table2(result))
    print(f"table2.json, table2.md and trajectory plots in {result['out_dir']}")
    if args.json:
        print(json.dumps(result))
    return 0


def _cmd_pipeline(args: argparse.Namespace) -> int:
    from cmnav.pipeline import PipelineConfig, load_recipe, run_pipeline, run_recipe

    paper_options = _given(args, "device", "seed", "dataset_count", "encoder_size", "encoder_batch_size", "policy_size",
                           "envs", "teacher_envs", "eval_episodes", "eval_levels")  # fmt: skip
    if args.recipe is not None:
        if given := [name for name, value in (("--minutes", args.minutes), ("--dataset", args.dataset)) if value is not None] + [
            "--" + k.replace("_", "-") for k in paper_options
        ]:  # fmt: skip
            raise ValueError(f"{', '.join(given)} set the paper's recipe; with --recipe the recipe's stages say everything: drop them")
        summary = run_recipe(load_recipe(args.recipe, args.out, build_parser()), args.out, args.call_minutes, sys.argv[1:])
    else:
        if args.minutes is None:
            raise ValueError("the paper's recipe needs --minutes (its wall-clock budget), or give --recipe")
        summary = run_pipeline(PipelineConfig(
            out_dir=args.out, minutes=args.minutes, dataset=args.dataset, call_minutes=args.call_minutes, **paper_options,
        ), sys.argv[1:])  # fmt: skip
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

    return run_fly(args.config, print_json=args.json, check_only=args.check, camera_bag=args.camera_bag)


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


def _cmd_report(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from runtime.log.reader import ReplayError
    from runtime.report import ReportUnavailableError, find_companions, write_report

    summary, room = find_companions(args.log)
    try:
        if args.summary is not None:
            summary = json.loads(Path(args.summary).read_text())
        html_path, png_path = write_report(args.log, args.output, summary, room)
    except (ReplayError, ReportUnavailableError) as err:
        print(f"cmnav report: {err}", file=sys.stderr)
        return 2
    except (OSError, json.JSONDecodeError) as err:
        print(f"cmnav report: {err}: check the paths given exist and the output directory is writable", file=sys.stderr)
        return 2
    print(f"report {html_path}\nplots {png_path}")
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
    sitl.add_argument("--degrade", default="none", choices=SITL_DEPTH_MODES,
                      help="depth of the SITL camera: rendered (none), with a D455's losses without its IR projector "
                      "(projector-off, about a quarter lost), or the simulated D455's stereo depth matched from rendered "
                      "IR images, projector on or off (stereo, stereo-projector-off; ~40 ms a frame of one core)")  # fmt: skip
    sitl.add_argument("--estimate", default="exact", choices=SITL_ESTIMATES,
                      help="what our SITL vehicle's autopilot knows of its state: exact (the truth) or px4 (PX4 SIH's "
                      "EKF2 as measured, biased and drifting, reported to the runtime and flown: the vehicle slides by "
                      "its velocity error as PX4 SIH's did; the camera sees the truth) (default exact)")  # fmt: skip
    sitl.add_argument("--velocity-bias", default="correct", choices=VELOCITY_BIAS_MODES,
                      help="the runtime's vehicle.velocity_bias_correction: correct (the autopilot's velocity estimate "
                      "less its error against the rate of its own position, and every setpoint corrected by it, so the "
                      "vehicle flies the command; runtime/tracking.py) or off (the estimate as reported) "
                      "(default correct)")  # fmt: skip
    sitl.add_argument("--approach-cap", default="on", choices=APPROACH_CAP_MODES,
                      help="the runtime's mission.approach_cap: within 3 m of the goal the command is slowed so that the "
                      "brake after it stops 0.5 m short of the surfaces seen ahead (on), or flown as the policy gives "
                      "it (off) (default on)")  # fmt: skip
    sitl.add_argument(
        "--inject", action="append", default=[], metavar="KIND@SECONDS",
        help="inject a fault SECONDS after offboard start (repeatable): camera-stall, camera-garbage, "
        "camera-blackout, telemetry-loss, pilot-takeover, offboard-refused@0, inference-overrun, nan-action, "
        "geofence, runtime-kill (SIGKILL of the runtime: the autopilot's failsafe decides), runtime-stop (SIGTERM "
        "to the runtime, as systemd sends: it brakes to a hover, then commands Hold), vehicle-stuck; the summary "
        "then lists each fault's trip, detection time and stop time.  With --autopilot the world follower injects "
        "the camera faults on the frames it serves; telemetry-loss, pilot-takeover, offboard-refused and "
        "vehicle-stuck need our SITL vehicle",
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
    fly.add_argument("--camera-bag", metavar="FILE",
                     help="fly on a RealSense recording (.bag / .db3 from realsense-viewer or rs.recorder) played in real "
                     "time instead of the configured camera: camera.source = \"bag\", camera.bag.path = FILE; its end "
                     "is a lost camera (a bench dry run; needs pyrealsense2)")  # fmt: skip
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

    report = sub.add_parser(
        "report",
        help="draw a flight log as one HTML page and a PNG",
        description="One self-contained HTML page (images inline) and a PNG of its plots from a flight log: "
        "top view (with the room of a SITL flight), commanded vs achieved velocity per axis, step latency "
        "histogram with p50/p99, invalid depth over time, watchdog events and verdicts, camera frames at the "
        "start, each trip and the end.  The summary.json and episode.json that cmnav sitl writes beside its log "
        "are read when present.  Needs the extra `report` (matplotlib).",
    )
    report.add_argument("log", help="MCAP flight log (cmnav fly / cmnav sitl)")
    report.add_argument("-o", "--output", help="the HTML page to write (default: the log's name with .html); the PNG goes beside it")
    report.add_argument("--summary", help="a JSON summary to show beside the log's figures (default: summary.json beside the log)")
    report.set_defaults(func=_cmd_report)

    dataset = sub.add_parser(
        "dataset",
        help="render gray/depth pairs from the simulated world (TartanAir V1 layout)",
        description="Render gray/depth pairs from random collision-free poses in random rooms across "
        "curriculum levels; one room is one trajectory (ENV/Easy/P000), so splits are by room.  With --policy and "
        "--encoder, record them along that policy's own flights instead (levels drawn uniformly between the smallest "
        "and the largest --levels, kicks, the training corruption on what it sees; clean frames kept): one frame in "
        "--every-steps of each flight and every frame of the last second before each crash, views random poses "
        "rarely give; one flight is one trajectory.",
    )
    dataset.add_argument("--out", required=True, help="output directory")
    dataset.add_argument("--count", type=int, required=True, help="number of pairs")
    dataset.add_argument("--seed", type=int, default=0, help="seed of rooms, poses and camera jitter")
    _config_option(dataset, "--levels", "training.data.generate:DatasetSpec.levels", type=int, nargs="+",
                   help="curriculum levels (obstacle counts), cycled over rooms (with --policy: drawn uniformly between the "
                   "smallest and the largest)")  # fmt: skip
    _config_option(dataset, "--frames-per-room", "training.data.generate:DatasetSpec.frames_per_room", type=int, help="views per room")
    _config_option(dataset, "--depth", "training.data.generate:DatasetSpec.depth", choices=["rendered", "stereo"],
                   help="stereo: also store the simulated D455's stereo depth of each frame (depth_stereo/), the degraded "
                   "input of `cmnav train cmwae --scheme stereo`")  # fmt: skip
    _config_option(dataset, "--stereo-projector-off-fraction", "training.data.generate:DatasetSpec.stereo_projector_off_fraction",
                   type=float, help="with --depth stereo: share of frames matched with the IR projector off")  # fmt: skip
    dataset.add_argument("--policy", metavar="POLICY_DIR", help="record along this policy's flights (needs --encoder)")
    dataset.add_argument("--encoder", metavar="CMWAE_DIR", help="the encoder the --policy was trained with")
    _config_option(dataset, "--every-steps", "training.policy.flight_frames:FlightFramesSpec.every_steps", type=int,
                   help="with --policy: keep one frame in this many along each flight")  # fmt: skip
    _config_option(dataset, "--envs", "training.policy.flight_frames:FlightFramesSpec.num_envs", type=int,
                   help="with --policy: flights flown at once")  # fmt: skip
    dataset.set_defaults(func=_cmd_dataset)

    def add_near_options(command: argparse.ArgumentParser, config: str, weighted: str, prefix: str = "") -> None:
        """--near-weight / --near-m of ``config`` ("module:Class"): the extra weight of ``weighted``."""
        _config_option(command, "--near-weight", f"{config}.near_weight", type=float, help=f"{prefix}extra weight of {weighted}")
        _config_option(command, "--near-m", f"{config}.near_m", type=float, help=f"{prefix}distance (m) under which --near-weight applies")

    def add_precision(command: argparse.ArgumentParser) -> None:
        command.add_argument("--precision", choices=["auto", "fp32", "bf16"],
                             help="torch compute precision on the CPU (default auto: bf16 + channels_last where the CPU has "
                             "AMX/AVX512-BF16, fp32 channels_last on AVX2, else fp32; the choice is logged)")  # fmt: skip

    train = sub.add_parser("train", help="train the CMWAE encoder, the privileged teacher, or the navigation policy (PPO or DAgger)")
    train_sub = train.add_subparsers(dest="what", required=True, metavar="WHAT")
    cmwae = train_sub.add_parser(
        "cmwae",
        help="train the cross-modal encoder (WAE-MMD) with depth corruption on the fly",
        description="Train the CMWAE on gray/depth pairs (TartanAir V1/V2 layout, e.g. from `cmnav dataset`). "
        "Multi-GPU: `torchrun --nproc_per_node=N -m cmnav train cmwae ... --device cuda`.",
    )
    cmwae.add_argument("--data", required=True, nargs="+", metavar="DIR",
                       help="dataset directories; the train splits of all are trained on, the validation curve stays on "
                       "the first one's val split (e.g. --data runs/data/sim12k runs/data/flights)")  # fmt: skip
    _config_option(cmwae, "--scheme", "training.cmwae.train:CmwaeTrainConfig.scheme",
                   choices=["s1", "s2", "policy", "none", "stereo", "stereo-mix"],
                   help="training corruption (none: the clean-depth baseline; policy: the policy's 1-30 px patches at "
                        "S2's coverages, for fine-tuning an encoder to what the student flies with; stereo: the "
                        "simulated D455's depth a `cmnav dataset --depth stereo` dataset stores, clean depth the target; "
                        "stereo-mix: half the images that stereo depth, half clean, with S2's squares on a quarter and "
                        "the policy's patches on another quarter of them)")  # fmt: skip
    _config_option(cmwae, "--squares-share", "training.cmwae.train:CmwaeTrainConfig.squares_share", type=float,
                   help="--scheme stereo-mix: share of the images that get S2's 100 px squares rather than the policy's "
                        "patches (S2 leaves half of them pristine)")  # fmt: skip
    cmwae.add_argument("--out", required=True, help="checkpoint directory (model.json + fp16 shards + train state)")
    _config_option(cmwae, "--modalities", "training.cmwae.train:CmwaeTrainConfig.modalities", type=_name_tuple,
                   choices=[("gray", "depth"), ("depth",)], metavar="{gray,depth | depth}",
                   help="encoder inputs; 'depth' = the depth-only baseline (DCE-RL stand-in)")  # fmt: skip
    _config_option(cmwae, "--size", "training.cmwae.train:CmwaeTrainConfig.size", choices=["paper", "small", "tiny"], help="network width (paper = AlexNet)")
    length = cmwae.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, help="optimizer steps")
    length.add_argument("--epochs", type=int, default=10, help="epochs over the train split (default 10)")
    _config_option(cmwae, "--batch-size", "training.cmwae.train:CmwaeTrainConfig.batch_size", type=int, help="pairs per optimizer step")
    _config_option(cmwae, "--lr", "training.cmwae.train:CmwaeTrainConfig.lr", type=float, help="Adam learning rate (also applied on --resume)")
    cmwae.add_argument("--lr-final", type=float,
                       help="cosine-decay the learning rate from --lr at step 0 to this at the last step (default: constant)")  # fmt: skip
    _config_option(cmwae, "--mmd-weight", "training.cmwae.train:CmwaeTrainConfig.mmd_weight", type=float, help="lambda of the MMD term")
    _config_option(cmwae, "--seed", "training.cmwae.train:CmwaeTrainConfig.seed", type=int, help="random seed")
    _config_option(cmwae, "--device", "training.cmwae.train:CmwaeTrainConfig.device", help="cpu or cuda")
    _config_option(cmwae, "--workers", "training.cmwae.train:CmwaeTrainConfig.workers", type=int, help="data-loading processes")
    _config_option(cmwae, "--checkpoint-every", "training.cmwae.train:CmwaeTrainConfig.checkpoint_every", type=int, help="steps between checkpoints")
    cmwae.add_argument("--resume", action="store_true", help="continue from the train state in --out")
    cmwae.add_argument("--minutes", type=float, help="stop (with a checkpoint) after this wall-clock time")
    _config_option(cmwae, "--corrupted-loss-weight", "training.cmwae.train:CmwaeTrainConfig.corrupted_loss_weight", type=float,
                   help="weight of a corrupted image's reconstruction error against a pristine one's (1: the paper's mean)")  # fmt: skip
    start = cmwae.add_mutually_exclusive_group()
    start.add_argument("--init-from", metavar="CMWAE_DIR", help="start from this encoder checkpoint's weights (not its optimizer or step)")
    start.add_argument("--anchor", metavar="CMWAE_DIR",
                       help="latent anchoring: start from this checkpoint, freeze its decoder, and pull the latent of "
                            "corrupted depth toward its latent of the clean pair (keeps the clean reconstruction)")  # fmt: skip
    _config_option(cmwae, "--val-images", "training.cmwae.train:CmwaeTrainConfig.val_images", type=int,
                   help="validation images scored at each checkpoint (MSE at 0 and 50 %% corruption)")
    _config_option(cmwae, "--anchor-weight", "training.cmwae.train:CmwaeTrainConfig.anchor_weight", type=float,
                   help="weight of the latent-anchoring term (with --anchor)")
    _config_option(cmwae, "--consistency-weight", "training.cmwae.train:CmwaeTrainConfig.consistency_weight", type=float,
                   help="fine-tuning encoder and decoder (--init-from, no --anchor): weight of the pull of each corrupted "
                   "image's latent toward this encoder's own latent of the same pair with clean depth")  # fmt: skip
    add_near_options(cmwae, "training.cmwae.train:CmwaeTrainConfig",
                     "the pixels whose true surface is nearer than --near-m in each image's reconstruction error "
                     "(0: the paper's plain mean)")  # fmt: skip
    _config_option(cmwae, "--pooled-weight", "training.cmwae.train:CmwaeTrainConfig.pooled_weight", type=float,
                   help="weight of the teacher's-view term: the error of the nearest surface per cell of the teacher's "
                   "18 x 32 depth grid, near cells weighted by --near-weight (0: off)")  # fmt: skip
    _config_option(cmwae, "--hidden-far-weight", "training.cmwae.train:CmwaeTrainConfig.hidden_far_weight", type=float,
                   help="pessimism under hidden depth: extra weight of the pixels the degraded input lost (and of the "
                   "teacher's-view cells holding one) where the reconstruction reads farther than the truth (0: off)")  # fmt: skip
    add_precision(cmwae)
    cmwae.set_defaults(func=_cmd_train_cmwae)

    def add_vehicle_option(command: argparse.ArgumentParser, *fields: str) -> None:
        _config_option(command, "--vehicle", *fields, choices=VEHICLE_CHOICES,
                       help="the vehicle flown: ideal (commands followed at once), px4 (PX4 v1.16's identified response "
                       "with its delays, image-to-command latency and EKF2-like estimates, randomized per episode: Table "
                       "II's `px4`) or field (px4 under examples/cmnav.toml's speed caps, episodes lengthened as the "
                       "top speed is cut: Table II's `field` less its camera; a teacher still observes the true state)")  # fmt: skip

    def add_end_at_goal_option(command: argparse.ArgumentParser, *fields: str) -> None:
        _config_option(command, "--end-at-goal", *fields, action="store_true",
                       help="end each episode in success at its first step within 1 m of the goal, as `cmnav fly` does, "
                       "paid the reward of hovering on the goal for the steps left (default: the paper's 10 s episodes, "
                       "success if within 1 m at the end); Table II keeps the paper's rule and counts `reached` beside it")  # fmt: skip

    def add_ppo_options(command: argparse.ArgumentParser, student: bool, envs: int | None = None) -> None:
        """The options of `train policy` (PPO, or DAgger with --teacher: ``student``) and `train teacher`;
        ``envs``: the command's own default number of envs (None: the config's)."""
        dagger = ("training.policy.dagger:DaggerConfig",) if student else ()
        command.add_argument("--out", required=True, help="checkpoint directory (model.json + fp16 shards + train state)")
        _config_option(command, "--steps", "training.policy.train:PolicyTrainConfig.env_steps", *[f"{c}.env_steps" for c in dagger],
                       type=int, help="env steps in total")  # fmt: skip
        command.add_argument("--minutes", type=float, help="stop (with a checkpoint) after this wall-clock time")
        if envs is None:
            _config_option(command, "--envs", "training.policy.train:PolicyTrainConfig.num_envs", *[f"{c}.num_envs" for c in dagger], type=int,
                           help="envs per process")  # fmt: skip
        else:
            command.add_argument("--envs", type=int, default=envs, help=f"envs per process (default {envs})")
        _config_option(command, "--device", "training.policy.train:PolicyTrainConfig.device", *[f"{c}.device" for c in dagger], help="cpu or cuda")
        _config_option(command, "--seed", "training.policy.train:PolicyTrainConfig.seed", *[f"{c}.seed" for c in dagger], type=int, help="random seed")
        command.add_argument("--size", choices=["paper", "tiny"], default="paper", help="policy width (paper: FC 256-128-64, GRU 64)")
        _config_option(command, "--rollout", "training.policy.ppo:PpoConfig.rollout_steps", *[f"{c}.rollout_steps" for c in dagger], type=int,
                       help="steps per rollout")  # fmt: skip
        _config_option(command, "--minibatches", "training.policy.ppo:PpoConfig.minibatches", *[f"{c}.minibatches" for c in dagger], type=int,
                       help="PPO minibatches per epoch, split over envs")  # fmt: skip
        _config_option(command, "--lr", "training.policy.ppo:PpoConfig.lr", *[f"{c}.lr" for c in dagger], type=float,
                       help="learning rate, of PPO (of the student's imitation loss with --teacher); also applied on --resume")  # fmt: skip
        _config_option(command, "--target-kl", "training.policy.ppo:PpoConfig.target_kl", type=float,
                       help="PPO: end an update's epochs at the first minibatch whose approximate KL from the rollout's policy "
                       "passes 1.5x this (none: all epochs run); small steps for a policy with little action noise")  # fmt: skip
        _config_option(command, "--start-level", "training.policy.env:CurriculumConfig.start_level", type=int, help="curriculum start level (obstacles)")
        _config_option(command, "--max-level", "training.policy.env:CurriculumConfig.max_level", *[f"{c}.max_level" for c in dagger], type=int,
                       help="curriculum cap")  # fmt: skip
        _config_option(command, "--curriculum-window", "training.policy.env:CurriculumConfig.window_episodes", type=int,
                       help="episodes per curriculum decision")  # fmt: skip
        _config_option(command, "--checkpoint-every", "training.policy.train:PolicyTrainConfig.checkpoint_every", *[f"{c}.checkpoint_every" for c in dagger],
                       type=int, help="iterations between checkpoints")  # fmt: skip
        command.add_argument("--keep-checkpoints", action="store_true",
                             help="also keep every checkpoint's weights in OUT/checkpoints/step-N (a policy directory each): "
                             "the one an evaluation chose is never overwritten")  # fmt: skip
        command.add_argument("--resume", action="store_true", help="continue from the train state in --out")

    policy = train_sub.add_parser(
        "policy",
        help="train the navigation policy on the batched sim with a frozen encoder: recurrent PPO, or DAgger "
        "from a teacher (--teacher)",
        description="The deployed network (FC 256-128-64 ELU -> GRU -> FC) on N simulated envs at 15 Hz, with the "
        "frozen encoder, the runtime's observation/action contract, depth corruption on a random half of "
        "the envs each step, kicks, camera jitter and the obstacle curriculum.  By recurrent PPO, or with "
        "--teacher by DAgger: the privileged teacher labels every state a teacher/student mixture visits.  "
        "Multi-GPU (PPO): `torchrun --nproc_per_node=N -m cmnav train policy ... --device cuda`.",
    )
    policy.add_argument("--encoder", required=True, help="encoder checkpoint directory (cmnav train cmwae)")
    add_ppo_options(policy, student=True)
    _config_option(policy, "--corruption", "training.policy.train:PolicyTrainConfig.corruption",
                   "training.policy.dagger:DaggerConfig.corruption", choices=["train", "none"],
                   help="depth corruption during training (none: the depth-only baseline policy)")  # fmt: skip
    policy.add_argument("--init-from", metavar="POLICY_DIR",
                        help="start from this policy checkpoint (PPO fine-tuning, or with --teacher a student distilled "
                        "before); when it was trained on another encoder, its latent normalisation is re-estimated on "
                        "--encoder")  # fmt: skip
    policy.add_argument("--teacher", metavar="TEACHER_DIR",
                        help="distil this privileged teacher (cmnav train teacher) by DAgger instead of PPO: the student "
                        "flies a teacher/student mixture, the teacher labels every state it visits; the student's depth is "
                        "corrupted (--corruption), the teacher's is clean")  # fmt: skip
    _config_option(policy, "--beta-decay-env-steps", "training.policy.dagger:DaggerConfig.beta_decay_env_steps", type=int,
                   help="DAgger: env steps over which the teacher's share of the actions falls from --beta-start to 0")
    _config_option(policy, "--beta-start", "training.policy.dagger:DaggerConfig.beta_start", type=float,
                   help="DAgger: the teacher's share of the executed actions at the start (0: the student flies from the "
                   "first step, e.g. with --init-from a distilled student)")  # fmt: skip
    _config_option(policy, "--projector-off-episode-fraction", "training.policy.dagger:DaggerConfig.projector_off_episode_fraction", type=float,
                   help="DAgger: share of episodes whose depth is lost like a D455 without its projector")
    _config_option(policy, "--squares-episode-fraction", "training.policy.dagger:DaggerConfig.squares_episode_fraction",
                   "training.policy.env:NavEnvConfig.squares_episode_fraction", type=float,
                   help="share of the episodes (with --teacher, of those outside the field; with --corruption train) that "
                   "keep one mask of 50-100 px squares to 20-50 %% for the whole episode instead of the per-step 1-30 px "
                   "patches (the kind of loss of Table II's patches-100px)")  # fmt: skip
    _config_option(policy, "--init-log-std", "training.policy.train:PolicyTrainConfig.init_log_std", type=float,
                   help="PPO with --init-from: set the policy's log std of the action noise to this (a DAgger student "
                   "keeps its untrained -0.5; the PPO teacher ends near -2.4), the noise PPO explores with")  # fmt: skip
    _config_option(policy, "--critic-warmup-iterations", "training.policy.train:PolicyTrainConfig.critic_warmup_iterations", type=int,
                   help="PPO: iterations at the start in which only the value head learns (the policy flies unchanged), so "
                   "that a distilled student's untrained critic gives advantages before the policy moves")  # fmt: skip
    _config_option(policy, "--freeze-obs-norm", "training.policy.train:PolicyTrainConfig.freeze_obs_norm", action="store_true",
                   help="PPO: keep the observation normaliser's statistics as loaded (a fine-tune's new episodes do not "
                   "shift the inputs under the policy)")  # fmt: skip
    _config_option(policy, "--squares-teacher-view", "training.policy.dagger:DaggerConfig.squares_teacher_view", choices=SQUARES_TEACHER_VIEWS,
                   help="DAgger: what the teacher sees under the squares of --squares-episode-fraction: the clean depth, or "
                   "the encoder's reconstruction from the student's gray + masked depth (what the student can know there)")  # fmt: skip
    _config_option(policy, "--field", "training.policy.dagger:DaggerConfig.field_conditions", action="store_true",
                   help="DAgger: train in the field, Table II's `field` condition (stereo depth in place of --corruption, the "
                   "gray camera's exposure and noise, image-to-command latency, PX4's randomized response, EKF2-like "
                   "state estimates, examples/cmnav.toml's speed caps)")  # fmt: skip
    _config_option(policy, "--field-depth", "training.policy.dagger:DaggerConfig.field_depth", choices=("stereo", "approx"),
                   help="DAgger --field: the depth trained on: the simulated D455's stereo matching, or its parametric "
                   "stand-in (sim.sensor.approx, its error against stereo in docs/sensor.md; 3x the env-steps/s)")  # fmt: skip
    _config_option(policy, "--field-env-fraction", "training.policy.dagger:DaggerConfig.field_env_fraction", type=float,
                   help="DAgger --field: the share of the envs that fly the field; the others train as without --field "
                   "(--corruption on --vehicle, the paper's 10 s episodes even with --end-at-goal), labelled by --outside-teacher, "
                   "so the student keeps Table II's clean rows")  # fmt: skip
    _config_option(policy, "--outside-teacher", "training.policy.dagger:DaggerConfig.outside_teacher_dir", metavar="TEACHER_DIR",
                   help="DAgger --field with --field-env-fraction below 1: the teacher of the envs outside the field "
                   "(default: --teacher)")  # fmt: skip
    add_vehicle_option(policy, "training.policy.dagger:DaggerConfig.vehicle", "training.policy.train:PolicyTrainConfig.vehicle")
    add_end_at_goal_option(policy, "training.policy.dagger:DaggerConfig.end_at_goal", "training.policy.train:PolicyTrainConfig.end_at_goal")
    _config_option(policy, "--min-level", "training.policy.dagger:DaggerConfig.min_level", type=int,
                   help="DAgger: the lowest obstacle level; each episode's level is drawn uniformly from "
                   "[--min-level, --max-level]")  # fmt: skip
    add_near_options(policy, "training.policy.dagger:DaggerConfig",
                     "the steps whose teacher sees a surface nearer than --near-m, in the imitation loss (0: every "
                     "step alike)", prefix="DAgger: ")  # fmt: skip
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
    add_ppo_options(teacher, student=False, envs=1024)
    teacher.add_argument("--init-from", metavar="TEACHER_DIR", help="start from this teacher checkpoint")
    add_vehicle_option(teacher, "training.policy.train:PolicyTrainConfig.vehicle")
    add_end_at_goal_option(teacher, "training.policy.train:PolicyTrainConfig.end_at_goal")
    teacher.set_defaults(func=_cmd_train_teacher, precision=None, squares_episode_fraction=None, init_log_std=None,
                         critic_warmup_iterations=None, freeze_obs_norm=None)  # `train policy`'s PPO fine-tune options

    evaluate = sub.add_parser("eval", help="evaluate a trained encoder (Table I) or policy (Table II)")
    eval_sub = evaluate.add_subparsers(dest="what", required=True, metavar="WHAT")

    def side_range(text: str) -> tuple[int, int]:
        low, _, high = text.partition("-")
        try:
            return int(low), int(high or low)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected MIN-MAX in px, e.g. 1-50 or 100-100") from None

    eval_cmwae = eval_sub.add_parser("cmwae", help="Table I: MSE/SSIM at 0-50%% evaluation corruption on the held-out split",
                                     description="Table I: MSE/SSIM at 0-50% evaluation corruption on the held-out split; on a "
                                     "`cmnav dataset --depth stereo` dataset also with its stereo depth as the input, "
                                     "projector on and off apart.")  # fmt: skip
    eval_cmwae.add_argument("--checkpoint", required=True, help="checkpoint directory")
    eval_cmwae.add_argument("--data", required=True, help="dataset directory")
    _config_option(eval_cmwae, "--split", "training.cmwae.evaluate:CmwaeEvalConfig.split", choices=["train", "val", "test"], help="dataset split")
    eval_cmwae.add_argument("--out", help="directory for plots and table1.json (default CHECKPOINT/eval)")
    _config_option(eval_cmwae, "--device", "training.cmwae.evaluate:CmwaeEvalConfig.device", help="cpu or cuda")
    eval_cmwae.add_argument("--max-images", type=int, help="evaluate at most this many images")
    _config_option(eval_cmwae, "--seed", "training.cmwae.evaluate:CmwaeEvalConfig.seed", type=int, help="seed of the evaluation patches")
    eval_cmwae.add_argument("--patch-sides", type=side_range, metavar="MIN-MAX",
                            help="side range of the square patches in px at 224x224 (default 1-50, Table I's; "
                            "100-100: S2's training squares; 1-30: the policy's training patches)")  # fmt: skip
    _config_option(eval_cmwae, "--near-m", "training.cmwae.evaluate:CmwaeEvalConfig.near_m", type=float,
                   help="the near-surface MSE column: pixels whose true depth is below this (m)")  # fmt: skip
    eval_cmwae.add_argument("--json", action="store_true", help="print the result as JSON on the last line")
    add_precision(eval_cmwae)
    eval_cmwae.set_defaults(func=_cmd_eval_cmwae)

    def int_list(text: str) -> tuple[int, ...]:
        return tuple(int(x) for x in text.split(",") if x)

    eval_policy = eval_sub.add_parser(
        "policy",
        help="Table II: success/timeout/crash %% per level and depth condition, with trajectory plots",
        description="Fly N seeded episodes per (condition, level) in the batched sim with the policy's mean "
        "action and no kicks; the same rooms for every condition and policy.  Conditions: clean, corrupted "
        "(the training patches fixed for the whole episode), projector-off (depth lost like a D455 without "
        "its projector), stereo and stereo-projector-off (the simulated D455: depth matched from rendered IR "
        "images, projector on / off), patches-1-50px and patches-100px (Table I's 1-50 px and S2's 100 px "
        "squares to 50 %, fixed for the episode), field (stereo depth and the sensor and vehicle as in the field) "
        "and px4 (clean depth, PX4 v1.16's identified response with its delays and estimates).  Each cell gives "
        "success / timeout / crash % and the success rate's Wilson 95 % interval; with --teacher, also the "
        "student's imitation gap to that teacher.",
    )
    eval_policy.add_argument("--policy", required=True, help="policy checkpoint directory (cmnav train policy)")
    eval_policy.add_argument("--encoder", help="the encoder checkpoint the policy was trained with (none for a teacher)")
    _config_option(eval_policy, "--levels", "training.policy.evaluate:PolicyEvalConfig.levels", type=int_list, help="comma-separated")
    _config_option(eval_policy, "--conditions", "training.policy.evaluate:PolicyEvalConfig.conditions", type=_name_tuple,
                   help="comma-separated subset of clean,corrupted,projector-off,stereo,stereo-projector-off,"
                   "patches-1-50px,patches-100px,field,px4 (clean depth on PX4's response)")  # fmt: skip
    _config_option(eval_policy, "--episodes", "training.policy.evaluate:PolicyEvalConfig.episodes", type=int, help="episodes per cell")
    _config_option(eval_policy, "--batch-envs", "training.policy.evaluate:PolicyEvalConfig.batch_envs", type=int, help="episodes flown at once")
    _config_option(eval_policy, "--device", "training.policy.evaluate:PolicyEvalConfig.device", help="cpu or cuda")
    _config_option(eval_policy, "--seed", "training.policy.evaluate:PolicyEvalConfig.seed", type=int, help="seed of the rooms")
    eval_policy.add_argument("--rooms", choices=["validation", "test"],
                             help="room set: validation (seed 0) to choose models on, test (seed 1) for published tables")  # fmt: skip
    eval_policy.add_argument("--out", help="directory for table2.json/.md and plots (default POLICY/eval)")
    eval_policy.add_argument("--teacher", metavar="TEACHER_DIR",
                             help="a privileged teacher that labels every step of the policy's own flights: each cell "
                                  "adds the imitation gap (the squared distance of the policy's action from the "
                                  "teacher's, as DAgger regresses it) over all steps and in the last second before "
                                  "crashes")  # fmt: skip
    eval_policy.add_argument("--json", action="store_true", help="print the result as JSON on the last line")
    add_precision(eval_policy)
    eval_policy.set_defaults(func=_cmd_eval_policy)

    pipeline = sub.add_parser(
        "pipeline",
        help="a training recipe run stage by stage, resumable: the paper's (within --minutes) or --recipe's",
        description="Without --recipe, the paper's recipe for a GPU machine with only torch, onnx, onnxruntime and "
        "numpy: renders a dataset, trains the CMWAE (S2), the privileged teacher (PPO) and the student (DAgger) "
        "on shares of the --minutes budget (35%, 30% and 25%), evaluates Table I, the teacher's and the "
        "student's Table II, exports model.onnx, and writes MODEL_CARD.md and pipeline.json in --out.  "
        "Checkpoints are fp16 shards <= 15 MiB.  With --recipe, the stages of a recipe file (cmnav commands, "
        "each training stage with its minutes), each a process logging to OUT/logs/STAGE.log; MODEL_CARD.md "
        "lists the stages and their wall-clock.  Either continues where a stopped call left off.",
    )
    pipeline.add_argument("--out", required=True, help="output directory")
    pipeline.add_argument("--recipe", help="a recipe: a name (cmnav/recipes/NAME.toml: default makes the "
                          "shipped models from nothing) or a .toml file")  # fmt: skip
    pipeline.add_argument("--minutes", type=float, help="the paper's recipe: its wall-clock budget")
    _config_option(pipeline, "--device", "cmnav.pipeline:PipelineConfig.device", help="cuda or cpu")
    _config_option(pipeline, "--seed", "cmnav.pipeline:PipelineConfig.seed", type=int, help="random seed")
    _config_option(pipeline, "--dataset-count", "cmnav.pipeline:PipelineConfig.dataset_count", type=int, help="gray/depth pairs to render")
    pipeline.add_argument("--dataset", help="use this existing dataset directory instead of rendering one")
    _config_option(pipeline, "--encoder-size", "cmnav.pipeline:PipelineConfig.encoder_size", choices=["paper", "small", "tiny"], help="encoder width")
    _config_option(pipeline, "--encoder-batch-size", "cmnav.pipeline:PipelineConfig.encoder_batch_size", type=int, help="encoder training batch")
    _config_option(pipeline, "--policy-size", "cmnav.pipeline:PipelineConfig.policy_size", choices=["paper", "tiny"], help="policy width")
    _config_option(pipeline, "--envs", "cmnav.pipeline:PipelineConfig.envs", type=int, help="the student's (DAgger) envs")
    _config_option(pipeline, "--teacher-envs", "cmnav.pipeline:PipelineConfig.teacher_envs", type=int, help="the teacher's (PPO) envs")
    _config_option(pipeline, "--eval-episodes", "cmnav.pipeline:PipelineConfig.eval_episodes", type=int, help="Table II episodes per cell")
    _config_option(pipeline, "--eval-levels", "cmnav.pipeline:PipelineConfig.eval_levels", type=int_list, help="Table II levels")
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
    export.add_argument("--encoder", metavar="CKPT", help="CMWAE checkpoint directory (cmnav train cmwae), e.g. models/cmwae-stereo")
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
        "SITL end to end and grab->command; ratios against the targets",
        description="In one run: p50/p99 of preprocessing, the ONNX step with 1 and 2 intra-op threads (and its "
        "fp16/int8 variants found next to the model), the same networks in torch eager (with --encoder/--policy), "
        "and, in one short SITL flight per CPU model (fp32 and int8) with the runtime pinned to a core of its "
        "own with 1 intra-op thread and the SITL vehicle on the other cores: end to end (the frame's capture -> "
        "command), grab->command (the runtime's receipt of the frame -> command) with its overhead around the step "
        "split by stage, and the frame's age when the step began; the model's FLOPs, this CPU's theoretical FP32 "
        "peak and its achieved GEMM rate; and the ratios against the targets (ONNX <= 0.65x eager, <= 1.3x ideal, "
        "grab->command minus the step <= 3 ms p99, end to end <= 25 ms p99) with PASS/MISS.",
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
    _use_formatter(parser, _ConfigDefaultsFormatter)
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
