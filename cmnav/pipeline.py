"""`cmnav pipeline`: dataset -> encoder (S2) -> Table I -> teacher -> student -> Table II -> export,
within a wall-clock budget on one device (DESIGN §5's recipe: a privileged teacher trained by PPO
on state + low-resolution clean depth, distilled by DAgger into the deployed policy, whose depth is
corrupted as the paper trains), leaving everything a commit needs in one directory:

  OUT/data/               the rendered dataset (not committed)
  OUT/encoder/            CMWAE S2 checkpoint: model.json + fp16 shards <= 15 MiB (+ train_state.pt)
  OUT/encoder/eval/       table1.json (+ plots when OpenCV is installed)
  OUT/teacher/            the privileged teacher (+ eval/: its clean Table II, the student's upper bound)
  OUT/policy/             the distilled student: model.json + fp16 shard (+ train_state.pt)
  OUT/policy/eval/        table2.json, table2.md (+ trajectory plots when OpenCV is installed)
  OUT/model.onnx          the runtime's model, parity-checked
  OUT/MODEL_CARD.md       how it was made, both tables, stage timings
  OUT/pipeline.json       the same as data

It needs only torch, onnx, onnxruntime and numpy (the offline GPU machine's set): the dataset is
written without OpenCV, SSIM comes from the vendored pytorch-msssim wheel.  The budget is split
over the stages by ``BUDGET_SHARES``; the two training stages stop on their share of the clock
and the rest take what they take (small next to training at the default sizes).

A machine that limits one command's run time (the lent GPU machine: 10 min) runs it in several
calls: ``call_minutes`` stops a call cleanly, ``OUT/pipeline_state.json`` records the finished
stages and the time spent, and the same command continues where the last call stopped.
"""

from __future__ import annotations

import json
import logging
import platform
import shlex
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

log = logging.getLogger(__name__)

# Shares of the budget for the stages that stop on the clock.
BUDGET_SHARES = {"encoder": 0.35, "teacher": 0.30, "policy": 0.25}
# Time kept back at the end of a call for the checkpoint a training stage writes when it stops:
# this much, or a tenth of a short call.
CALL_RESERVE_S = 30.0


@dataclass(frozen=True)
class PipelineConfig:
    out_dir: str
    minutes: float
    device: str = "cuda"
    seed: int = 0
    dataset_count: int = 8000
    dataset: str | None = None  # an existing dataset directory: skip rendering one
    encoder_size: str = "paper"
    encoder_batch_size: int = 64
    policy_size: str = "paper"
    envs: int = 512  # the student's (DAgger) envs
    teacher_envs: int = 1024
    eval_episodes: int = 100
    eval_levels: tuple[int, ...] = (0, 5, 10, 15, 20)
    table1_max_images: int | None = None
    # This call stops (checkpointed) after this long; the same command continues (for machines that
    # limit one command's run time).  None: run to the end.
    call_minutes: float | None = None

    def validate(self) -> None:
        if self.minutes <= 0:
            raise ValueError(f"--minutes {self.minutes} must be > 0")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise ValueError("--device cuda but torch sees no CUDA device: use --device cpu (slow) or check the driver")


def run_pipeline(config: PipelineConfig, argv: list[str] | None = None) -> dict:
    """Run (or continue) the pipeline in ``config.out_dir``.  Returns the summary; its ``done``
    is False when the call's own limit (``call_minutes``) stopped it first: run the same command
    again to continue (finished stages are skipped, training stages resume from their state)."""
    from export.policy_onnx import export_policy

    from training.cmwae.evaluate import CmwaeEvalConfig, evaluate_cmwae
    from training.cmwae.train import CmwaeTrainConfig, train_cmwae
    from training.data.generate import DatasetSpec, generate_dataset
    from training.policy.evaluate import PolicyEvalConfig, evaluate_policy, format_table2
    from training.policy.dagger import DaggerConfig, train_dagger
    from training.policy.network import POLICY_SIZES
    from training.policy.train import PolicyTrainConfig, train_policy

    config.validate()
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    state_path = out / "pipeline_state.json"
    state = json.loads(state_path.read_text()) if state_path.is_file() else {"done": [], "spent_s": {}, "results": {}}
    settings = json.loads(json.dumps({k: v for k, v in asdict(config).items() if k != "call_minutes"}))
    if state.setdefault("config", settings) != settings:
        raise ValueError(f"{out} holds a pipeline run with other settings ({state['config']}): use a new --out")
    budget_s = config.minutes * 60.0
    call_end = time.monotonic() + (config.call_minutes * 60.0 if config.call_minutes else float("inf"))
    reserve_s = min(CALL_RESERVE_S, 6.0 * config.call_minutes) if config.call_minutes else CALL_RESERVE_S
    data_dir = Path(config.dataset) if config.dataset else out / "data"
    encoder_dir, teacher_dir, policy_dir = out / "encoder", out / "teacher", out / "policy"

    def run(name: str, work, budget_share: float | None = None) -> bool:
        """Run stage ``name`` unless done; a training stage gets what is left of its share of the
        budget, cut to what is left of this call.  Returns False when the call must stop."""
        if name in state["done"]:
            return True
        spent = state["spent_s"].get(name, 0.0)
        limit_s = None
        if budget_share is not None:
            limit_s = min(budget_share * budget_s - spent, call_end - time.monotonic() - reserve_s)
            if limit_s <= 0:
                return False
        log.info("pipeline stage %s (time limit %s)", name, "none" if limit_s is None else f"{limit_s:.0f} s")
        t0 = time.monotonic()
        result = work(limit_s, resume=spent > 0)
        state["spent_s"][name] = round(spent + time.monotonic() - t0, 1)
        if result is not None:
            state["results"][name] = result
        finished = budget_share is None or state["spent_s"][name] >= budget_share * budget_s - reserve_s
        if finished:
            state["done"].append(name)
        state_path.write_text(json.dumps(state, indent=2, default=str))
        return finished

    def dataset(limit_s, resume):
        return generate_dataset(data_dir, DatasetSpec(count=config.dataset_count, seed=config.seed))

    def encoder(limit_s, resume):
        train_cmwae(CmwaeTrainConfig(
            data_dir=str(data_dir), out_dir=str(encoder_dir), scheme="s2", size=config.encoder_size, steps=10**9,
            batch_size=config.encoder_batch_size, seed=config.seed, device=config.device, workers=2,
            checkpoint_every=1000, max_wall_s=limit_s, resume=resume,
        ))  # fmt: skip

    def table1(limit_s, resume):
        return evaluate_cmwae(CmwaeEvalConfig(checkpoint=str(encoder_dir), data_dir=str(data_dir), device=config.device,
                                              max_images=config.table1_max_images, seed=config.seed))  # fmt: skip

    def teacher(limit_s, resume):
        train_policy(PolicyTrainConfig(
            encoder_dir=None, out_dir=str(teacher_dir), env_steps=10**12, num_envs=config.teacher_envs, corruption="none",
            device=config.device, seed=config.seed, policy=POLICY_SIZES[config.policy_size], max_wall_s=limit_s,
            resume=resume,
        ))  # fmt: skip

    def teacher_table2(limit_s, resume):
        return evaluate_policy(PolicyEvalConfig(
            policy_dir=str(teacher_dir), encoder_dir=None, levels=config.eval_levels, conditions=("clean",),
            episodes=config.eval_episodes, batch_envs=min(config.eval_episodes, 256), device=config.device, seed=config.seed,
        ))  # fmt: skip

    def policy(limit_s, resume):
        train_dagger(DaggerConfig(
            teacher_dir=str(teacher_dir), encoder_dir=str(encoder_dir), out_dir=str(policy_dir), env_steps=10**12,
            num_envs=config.envs, device=config.device, seed=config.seed, policy=POLICY_SIZES[config.policy_size],
            max_wall_s=limit_s, resume=resume,
        ))  # fmt: skip

    def table2(limit_s, resume):
        return evaluate_policy(PolicyEvalConfig(
            policy_dir=str(policy_dir), encoder_dir=str(encoder_dir), levels=config.eval_levels,
            episodes=config.eval_episodes, batch_envs=min(config.eval_episodes, 256), device=config.device, seed=config.seed,
        ))  # fmt: skip

    def export(limit_s, resume):
        return export_policy(encoder_dir, policy_dir, out / "model.onnx").to_json()

    stages = [("dataset", dataset, None), ("encoder", encoder, BUDGET_SHARES["encoder"]), ("table1", table1, None),
              ("teacher", teacher, BUDGET_SHARES["teacher"]), ("teacher_table2", teacher_table2, None),
              ("policy", policy, BUDGET_SHARES["policy"]), ("table2", table2, None), ("export", export, None)]  # fmt: skip
    if config.dataset is not None:
        stages = stages[1:]
    for name, work, share in stages:
        if not run(name, work, share):
            log.info("pipeline: this call's time is up during %s; run the same command again to continue", name)
            return {"done": False, "spent_s": state["spent_s"], "out_dir": str(out)}
    results = state["results"]
    summary = {"done": True, "config": asdict(config), "command": "cmnav " + shlex.join(argv or []),
               "hardware": _hardware(config.device), "timings_s": state["spent_s"], "table1": results["table1"],
               "teacher_table2": results["teacher_table2"], "table2": results["table2"], "export": results["export"],
               "out_dir": str(out)}  # fmt: skip
    (out / "pipeline.json").write_text(json.dumps(summary, indent=2, default=str))
    (out / "MODEL_CARD.md").write_text(model_card(summary, format_table2(results["table2"]), format_table2(results["teacher_table2"])))
    log.info("pipeline done: %s", out)
    return summary


def _hardware(device: str) -> str:
    cpu = f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} torch threads"
    if device.startswith("cuda") and torch.cuda.is_available():
        return f"{torch.cuda.get_device_name(0)} x{torch.cuda.device_count()}; CPU {cpu}; torch {torch.__version__}"
    return f"CPU only ({cpu}); torch {torch.__version__}"


def model_card(summary: dict, table2_md: str, teacher_table2_md: str) -> str:
    c, t1 = summary["config"], summary["table1"]
    timings = ", ".join(f"{k} {v:.0f} s" for k, v in summary["timings_s"].items())
    export = summary["export"]
    return f"""# cmnav model from `cmnav pipeline`

Made by one run of `{summary['command']}` on {summary['hardware']}
(Python {sys.version.split()[0]}). Budget {c['minutes']} min; stages: {timings}.

- Data: {'`' + c['dataset'] + '`' if c['dataset'] else f"{c['dataset_count']} rendered gray/depth pairs (`cmnav dataset`, seed {c['seed']})"}.
- Encoder: CMWAE, scheme S2, {c['encoder_size']} size, batch {c['encoder_batch_size']}, {t1['step']} steps.
- Teacher: recurrent PPO on state + 32x18 clean depth (no encoder), {c['policy_size']} size, {c['teacher_envs']} envs,
  seed {c['seed']}; `teacher/model.json` has its env steps and curriculum level.  It never flies.
- Policy: the deployed network distilled from the teacher by DAgger, {c['envs']} envs, its depth corrupted as the
  paper trains (1-30 px patches, projector-off episodes); `policy/model.json` has its env steps.
- Export: `model.onnx`, parity (max abs error, ONNX Runtime vs torch): {json.dumps(export.get('parity'))}.

## Table I (held-out split, MSE x10^-3 / SSIM x10^-2)

{t1['table']}

MSE at 50 % over 0 %: {t1['mse_ratio_50_over_0']}x (the paper's: 1.35x).

## Table II ({c['eval_episodes']} episodes per cell; success / timeout / crash %)

The distilled policy:

{table2_md}

The teacher (clean depth only: its upper bound):

{teacher_table2_md}
"""
