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

``--recipe`` runs a recipe instead (:func:`load_recipe`, ``cmnav/recipes/*.toml``): stages of
`cmnav` commands run as processes by the same :class:`StageRunner`; ``recipes/default.toml`` is the
chain of commands behind the shipped models.
"""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

log = logging.getLogger(__name__)

# Shares of the budget for the stages that stop on the clock.
BUDGET_SHARES = {"encoder": 0.35, "teacher": 0.30, "policy": 0.25}
# Time kept back at the end of a call for the checkpoint a training stage writes when it stops:
# this much, or a tenth of a short call.
CALL_RESERVE_S = 30.0


class StageRunner:
    """Runs a pipeline's named stages once each, across as many calls as it takes.

    ``OUT/pipeline_state.json`` records the finished stages, the wall-clock each has spent and what
    each returned.  A stage with a time budget gets what is left of it; a resumable one is also cut
    to what is left of this call (``call_minutes``) and continues (``resume=True``) in the next.
    A run held under other settings continues only where ``adopt(held_settings)`` says it may.
    """

    def __init__(self, out: Path, settings: dict, call_minutes: float | None, adopt: Callable[[dict], bool] | None = None):
        out.mkdir(parents=True, exist_ok=True)
        self.path = out / "pipeline_state.json"
        self.state = json.loads(self.path.read_text()) if self.path.is_file() else {"done": [], "spent_s": {}, "results": {}}
        held = self.state.setdefault("config", settings)
        if held != settings and not (adopt is not None and adopt(held)):
            differ = sorted(k for k in held.keys() | settings.keys() if held.get(k) != settings.get(k))
            raise ValueError(f"{out} holds a pipeline run with other settings (differing: {', '.join(differ)}): use a new --out")
        self.state["config"] = settings
        self.save()
        self.call_end = time.monotonic() + (call_minutes * 60.0 if call_minutes else float("inf"))
        self.reserve_s = min(CALL_RESERVE_S, 6.0 * call_minutes) if call_minutes else CALL_RESERVE_S

    def run(self, name: str, work, budget_s: float | None = None, resumable: bool | None = None) -> bool:
        """Run stage ``name`` unless done: ``work(limit_s, resume)`` with ``limit_s`` what is left
        of ``budget_s`` cut, when ``resumable`` (default: when it has a budget), to what is left of
        this call (None: no limit).  Returns False when this call must stop before it is finished."""
        if name in self.state["done"]:
            return True
        resumable = budget_s is not None if resumable is None else resumable
        spent = self.state["spent_s"].get(name, 0.0)
        stage_left = None if budget_s is None else budget_s - spent
        call_left = self.call_end - time.monotonic() - self.reserve_s if resumable and self.call_end < float("inf") else None
        limit_s = min((x for x in (stage_left, call_left) if x is not None), default=None)
        if limit_s is not None and limit_s <= 0:
            log.info("pipeline: this call's time is up before %s; run the same command again to continue", name)
            return False
        log.info("pipeline stage %s (time limit %s)", name, "none" if limit_s is None else f"{limit_s:.0f} s")
        t0 = time.monotonic()
        try:
            result = work(limit_s, resume=resumable and name in self.state["spent_s"])  # it ran before
        finally:  # failed or stopped too: the time counts, and a resumable stage continues what it wrote
            elapsed = time.monotonic() - t0
            self.state["spent_s"][name] = round(spent + elapsed, 1)
            self.save()
        if result is not None:
            self.state["results"][name] = result
        # Finished unless the call's limit stopped it: it had no limit, it ended on its own before
        # the limit, or its own budget is spent.
        finished = (limit_s is None or elapsed < limit_s - self.reserve_s
                    or (budget_s is not None and spent + elapsed >= budget_s - self.reserve_s))  # fmt: skip
        if finished:
            self.state["done"].append(name)
        self.save()
        if not finished:
            log.info("pipeline: this call's time is up during %s; run the same command again to continue", name)
        return finished

    def save(self) -> None:
        self.path.write_text(json.dumps(self.state, indent=2, default=str))


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
    settings = json.loads(json.dumps({k: v for k, v in asdict(config).items() if k != "call_minutes"}))
    stages_run = StageRunner(out, settings, config.call_minutes)
    budget_s = config.minutes * 60.0
    data_dir = Path(config.dataset) if config.dataset else out / "data"
    encoder_dir, teacher_dir, policy_dir = out / "encoder", out / "teacher", out / "policy"

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
        if not stages_run.run(name, work, None if share is None else share * budget_s):
            return {"done": False, "spent_s": stages_run.state["spent_s"], "out_dir": str(out)}
    results = stages_run.state["results"]
    summary = {"done": True, "config": asdict(config), "command": "cmnav " + shlex.join(argv or []),
               "hardware": _hardware(config.device), "timings_s": stages_run.state["spent_s"], "table1": results["table1"],
               "teacher_table2": results["teacher_table2"], "table2": results["table2"], "export": results["export"],
               "out_dir": str(out)}  # fmt: skip
    (out / "pipeline.json").write_text(json.dumps(summary, indent=2, default=str))
    (out / "MODEL_CARD.md").write_text(model_card(summary, format_table2(results["table2"]), format_table2(results["teacher_table2"])))
    log.info("pipeline done: %s", out)
    return summary


def _hardware(device: str) -> str:
    from bench.train import cpu_name
    from training.fastpath import read_cpu_flags

    fast = sorted(read_cpu_flags() & {"amx_bf16", "avx512_bf16", "avx512_vnni", "avx2"})
    cpu = f"{cpu_name()} ({', '.join(fast) or 'no AVX2'}), {torch.get_num_threads()} torch threads"
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


# --- recipes: a pipeline of `cmnav` commands ------------------------------------------------------

RECIPES_DIR = Path(__file__).parent / "recipes"
RECIPE_KEYS = {"description", "stage"}
STAGE_KEYS = {"name", "command", "minutes", "continues", "report"}


@dataclass(frozen=True)
class RecipeStage:
    name: str
    argv: tuple[str, ...]  # a `cmnav` command line, ``{out}`` already replaced by the run's directory
    minutes: float | None = None  # a training stage's budget: it gets --minutes (what is left of it)
    resumable: bool = False  # its command takes --resume: a call's limit may stop it, the next continues it
    continues: str | None = None  # the earlier stage whose run (the same --out) it continues: always --resume
    report: str | None = None  # a markdown file it writes that the model card includes


@dataclass(frozen=True)
class Recipe:
    name: str
    description: str
    text: str  # the recipe file as read: a run continues only under the same recipe
    stages: tuple[RecipeStage, ...]


def recipe_names() -> list[str]:
    return sorted(p.stem for p in RECIPES_DIR.glob("*.toml"))


def load_recipe(recipe: str, out_dir: str | Path, parser: argparse.ArgumentParser) -> Recipe:
    """A recipe by name (``cmnav/recipes/NAME.toml``) or path: stages of `cmnav` commands, each
    checked against ``parser`` (cmnav's, :func:`cmnav.cli.build_parser`) before anything runs."""
    import tomllib

    path = Path(recipe) if recipe.endswith(".toml") else RECIPES_DIR / f"{recipe}.toml"
    if not path.is_file():
        raise ValueError(f"no recipe {recipe!r} ({path}): give a .toml file or one of {recipe_names()}")
    text = path.read_text()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"recipe {path} is not valid TOML: {err}") from err
    if unknown := sorted(set(data) - RECIPE_KEYS):
        raise ValueError(f"recipe {path}: unknown keys {unknown} (known: {sorted(RECIPE_KEYS)})")
    if not data.get("stage"):
        raise ValueError(f"recipe {path} has no [[stage]]: add the commands it runs")
    stages: list[RecipeStage] = []
    for i, raw in enumerate(data["stage"]):
        where = f"recipe {path}, stage {i + 1} ({raw.get('name', 'unnamed')})"
        if unknown := sorted(set(raw) - STAGE_KEYS):
            raise ValueError(f"{where}: unknown keys {unknown} (known: {sorted(STAGE_KEYS)})")
        if not isinstance(raw.get("name"), str) or not isinstance(raw.get("command"), str):
            raise ValueError(f"{where}: needs a name and a command (strings)")
        try:
            argv = tuple(part.format(out=out_dir) for part in shlex.split(raw["command"]))
            report = None if raw.get("report") is None else raw["report"].format(out=out_dir)
        except (KeyError, IndexError, ValueError) as err:
            raise ValueError(f"{where}: only {{out}} (the run's directory) may be filled in: {err!r}") from err
        minutes = raw.get("minutes")
        if minutes is not None and (not isinstance(minutes, (int, float)) or minutes <= 0):
            raise ValueError(f"{where}: minutes {minutes!r} must be a number > 0")
        if set(argv) & {"--minutes", "--resume"}:
            raise ValueError(f"{where}: the pipeline gives --minutes and --resume itself: use the stage's minutes and continues")
        if raw["name"] in {s.name for s in stages}:
            raise ValueError(f"{where}: the name {raw['name']!r} is used twice")
        try:  # argparse exits on a bad command line: a typo must not wait hours for its stage
            parsed = parser.parse_args(list(argv))
        except SystemExit:
            raise ValueError(f"{where}: `cmnav {shlex.join(argv)}` is not a valid cmnav command (see the message above)") from None
        resumable = hasattr(parsed, "resume")
        if (minutes is not None or raw.get("continues")) and not (resumable and hasattr(parsed, "minutes")):
            raise ValueError(f"{where}: minutes and continues are for training commands (they take --minutes and --resume)")
        if (continues := raw.get("continues")) is not None:
            earlier = {s.name: s for s in stages}.get(continues)
            if earlier is None or _out_of(earlier.argv) != _out_of(argv):
                raise ValueError(f"{where}: continues {continues!r}, which must be an earlier stage with the same --out")
        stages.append(RecipeStage(raw["name"], argv, None if minutes is None else float(minutes), resumable, continues, report))
    return Recipe(path.stem, str(data.get("description", "")).strip(), text, tuple(stages))


def _out_of(argv: tuple[str, ...]) -> str | None:
    return next((argv[i + 1] for i in range(len(argv) - 1) if argv[i] in ("--out", "-o")), None)


def _grown_from(held: dict, recipe: Recipe, out: Path) -> bool:
    """Whether the run in ``out``, held under ``held`` settings, is one of an earlier version of
    ``recipe`` whose stages are this one's first, unchanged (stages added at the end, comments and
    description free): then it goes on, its finished stages standing.  Another recipe: False (the
    runner refuses it); a stage of this one changed or gone: refused here, naming the stage."""
    import tomllib

    if held.get("recipe") != recipe.name:
        return False
    before, now = tomllib.loads(held["recipe_text"])["stage"], tomllib.loads(recipe.text)["stage"]
    if now[: len(before)] != before:
        changed = next((b.get("name") for b, n in zip(before, now) if b != n), None) or before[len(now)].get("name")
        raise ValueError(f"{out} holds a run of another version of recipe {recipe.name!r}, whose stage {changed!r} is changed or gone: "
                         "a run goes on only under stages added at the end; use a new --out")  # fmt: skip
    log.info("pipeline: recipe %s has %d stage(s) more than when this run began; its finished stages stand", recipe.name, len(now) - len(before))
    return True


def _reads(stage: RecipeStage, out: Path) -> list[Path]:
    """The paths under the run's directory ``out`` that ``stage`` reads: its arguments there other
    than its own --out, and the training state there when it continues an earlier stage's run."""
    from training.checkpoint import TRAIN_STATE

    own = _out_of(stage.argv)
    paths = [Path(a) for a in stage.argv if a != own and Path(a) != out and Path(a).is_relative_to(out)]
    return paths + ([Path(own) / TRAIN_STATE] if stage.continues is not None else [])


def _redo_lost_outputs(recipe: Recipe, out: Path, runner: StageRunner) -> None:
    """Mark not done every finished stage whose output a stage still to run reads but is not there
    (the run's directory carried to another machine without its datasets, say), and the stages
    that wrote to the same --out before it: the run makes them again, in the recipe's order."""
    done = runner.state["done"]
    while True:
        todo = [s for s in recipe.stages if s.name not in done]
        lost = {p for s in todo for p in _reads(s, out) if not p.exists()}
        redo = [s for s in recipe.stages if s.name in done and (o := _out_of(s.argv)) is not None
                and any(p == Path(o) or p.is_relative_to(o) for p in lost)]  # fmt: skip
        if not redo:
            break
        for stage in redo:
            log.warning("pipeline: %s, which %s wrote, is gone: running %s again", _out_of(stage.argv), stage.name, stage.name)
            done.remove(stage.name)
    runner.save()


def _stage_argv(stage: RecipeStage, limit_s: float | None, resume: bool) -> list[str]:
    return [*stage.argv, *(["--minutes", f"{limit_s / 60.0:.3f}"] if limit_s is not None else []), *(["--resume"] if resume else [])]


def run_recipe(recipe: Recipe, out_dir: str | Path, call_minutes: float | None = None, argv: list[str] | None = None) -> dict:
    """Run (or continue) ``recipe`` in ``out_dir``, each stage a `cmnav` process whose output goes
    to ``OUT/logs/STAGE.log``.  Returns the summary; ``done`` is False when ``call_minutes`` stopped
    it first (the same command continues, also under the recipe grown by stages at the end).  A stage
    that fails stops the run: what it wrote stays, and the same command retries it."""
    out = Path(out_dir)
    runner = StageRunner(out, {"recipe": recipe.name, "recipe_text": recipe.text}, call_minutes,
                         adopt=lambda held: _grown_from(held, recipe, out))
    (out / "logs").mkdir(exist_ok=True)
    _redo_lost_outputs(recipe, out, runner)

    def command(stage: RecipeStage):
        def work(limit_s, resume):
            stage_argv = _stage_argv(stage, limit_s, resume or stage.continues is not None)
            log_path = out / "logs" / f"{stage.name}.log"
            with log_path.open("a") as log_file:
                log_file.write(f"$ cmnav {shlex.join(stage_argv)}\n")
                log_file.flush()
                proc = subprocess.Popen([sys.executable, "-m", "cmnav", *stage_argv], stdout=log_file, stderr=subprocess.STDOUT)
                try:
                    rc = proc.wait()
                except BaseException:  # the pipeline stopped (SIGTERM, Ctrl-C): its stage stops with it
                    proc.terminate()
                    proc.wait()
                    raise
            if rc != 0:
                tail = "".join(log_path.read_text().splitlines(keepends=True)[-5:])
                raise ValueError(f"stage {stage.name} failed (exit {rc}); its log {log_path} ends:\n{tail}"
                                 "fix the cause and run the same command again: it retries this stage")  # fmt: skip

        return work

    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm)  # a stopped pipeline stops its stage's process
    try:
        for stage in recipe.stages:
            budget_s = None if stage.minutes is None else stage.minutes * 60.0
            if not runner.run(stage.name, command(stage), budget_s, stage.resumable):
                return {"done": False, "spent_s": runner.state["spent_s"], "out_dir": str(out)}
    finally:
        signal.signal(signal.SIGTERM, previous)
    summary = {"done": True, "recipe": recipe.name, "command": "cmnav " + shlex.join(argv or []),
               "hardware": _hardware("cuda" if torch.cuda.is_available() else "cpu"), "timings_s": runner.state["spent_s"],
               "out_dir": str(out),
               "stages": [{"name": s.name, "command": "cmnav " + shlex.join(s.argv), "minutes": s.minutes,
                           "wall_s": runner.state["spent_s"][s.name]} for s in recipe.stages]}  # fmt: skip
    (out / "pipeline.json").write_text(json.dumps(summary, indent=2, default=str))
    (out / "MODEL_CARD.md").write_text(recipe_card(recipe, summary))
    log.info("pipeline done: %s", out)
    return summary


def _exit_on_sigterm(signum, frame):
    raise SystemExit(128 + signum)


def recipe_card(recipe: Recipe, summary: dict) -> str:
    rows = "\n".join(f"| {s['name']} | `{s['command']}` | {'' if s['minutes'] is None else format(s['minutes'], 'g')} | "
                     f"{s['wall_s'] / 60.0:.1f} |" for s in summary["stages"])  # fmt: skip
    total_min = sum(s["wall_s"] for s in summary["stages"]) / 60.0
    reports = "".join(f"\n## {s.name}\n\n{Path(s.report).read_text().strip()}\n" for s in recipe.stages
                      if s.report is not None and Path(s.report).is_file())  # fmt: skip
    return f"""# cmnav models from `cmnav pipeline --recipe {recipe.name}`

{recipe.description}

Made by `{summary['command']}` on {summary['hardware']} (Python {sys.version.split()[0]}), all
stages in {total_min:.0f} min of wall-clock (summed over the calls it took).

## Stages

| stage | command | budget (min) | wall-clock (min) |
|---|---|---|---|
{rows}
{reports}"""
