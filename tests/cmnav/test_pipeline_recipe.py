"""`cmnav pipeline --recipe`: a recipe's `cmnav` commands run stage by stage, across calls cut short
by --call-minutes, the training stages continued with --resume; bad recipes refused before any
stage runs."""

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cmnav.cli import build_parser
from cmnav.pipeline import StageRunner, _redo_lost_outputs, load_recipe, recipe_names
from tests.e2e.test_sitl_stop import _children

REPO = Path(__file__).resolve().parents[2]

# Tiny networks, a handful of steps: the whole chain of the shipped recipe in miniature (dataset,
# encoder, teacher, student, Table II, export), two training stages on the clock.
TINY_RECIPE = """
description = "a tiny chain for the test"

[[stage]]
name = "dataset"
command = "dataset --out {out}/data --count 80 --seed 0"

[[stage]]
name = "encoder"
command = "train cmwae --data {out}/data --out {out}/encoder --size tiny --steps 2 --batch-size 4 --workers 0 --device cpu"

[[stage]]
name = "teacher"
command = "train teacher --out {out}/teacher --size tiny --envs 8 --rollout 8 --steps 128 --checkpoint-every 1 --device cpu"

[[stage]]
name = "teacher-slower"
command = "train teacher --out {out}/teacher --size tiny --envs 8 --rollout 8 --lr 1e-4 --steps 1000000000 --checkpoint-every 1 --device cpu"
minutes = 0.3
continues = "teacher"

[[stage]]
name = "student"
command = "train policy --teacher {out}/teacher --encoder {out}/encoder --out {out}/student --size tiny --envs 4 --rollout 8 --steps 64 --checkpoint-every 1 --device cpu"

[[stage]]
name = "table2"
command = "eval policy --policy {out}/student --encoder {out}/encoder --levels 0 --conditions clean --episodes 1 --batch-envs 1 --device cpu --out {out}/student/eval"
report = "{out}/student/eval/table2.md"

[[stage]]
name = "export"
command = "export --encoder {out}/encoder --policy {out}/student -o {out}/model.onnx"
"""


def _pipeline(recipe: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "cmnav", "pipeline", "--recipe", str(recipe), "--out", str(out), *extra]
    return subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=280)


def test_a_recipe_runs_to_the_end_over_several_calls(tmp_path):
    recipe = tmp_path / "tiny.toml"
    recipe.write_text(TINY_RECIPE)
    out = tmp_path / "run"
    codes = []
    for _ in range(6):
        proc = _pipeline(recipe, out, "--call-minutes", "0.25")
        codes.append(proc.returncode)
        assert proc.returncode in (0, 3), proc.stderr[-3000:]
        if proc.returncode == 0:
            break
    assert codes[0] == 3 and codes[-1] == 0, codes  # the teacher's 0.3 more min do not fit in one 0.25 min call
    state = json.loads((out / "pipeline_state.json").read_text())
    assert state["done"] == ["dataset", "encoder", "teacher", "teacher-slower", "student", "table2", "export"]
    assert state["spent_s"]["teacher-slower"] >= 0.3 * 60 - 3  # its whole budget, over two calls
    commands = [line for line in (out / "logs" / "teacher-slower.log").read_text().splitlines() if line.startswith("$ ")]
    assert len(commands) >= 2 and all(c.endswith("--resume") for c in commands)  # it continues the teacher's run
    # which started it (on a loaded machine the 0.25 min call can cut the teacher too: then it resumes, as it should)
    teacher = [line for line in (out / "logs" / "teacher.log").read_text().splitlines() if line.startswith("$ ")]
    assert not teacher[0].endswith("--resume") and all(c.endswith("--resume") for c in teacher[1:]), teacher
    assert "--resume" not in (out / "logs" / "dataset.log").read_text()  # stages without minutes run once, as written
    card = (out / "MODEL_CARD.md").read_text()
    assert "| teacher-slower | `cmnav train teacher --out " in card and "| 0.3 |" in card
    assert "| clean | 0 | 1 |" in card  # the report the Table II stage wrote
    summary = json.loads((out / "pipeline.json").read_text())
    assert [s["name"] for s in summary["stages"]] == state["done"]

    from runtime.model import PolicyModel

    PolicyModel(out / "model.onnx")  # what the recipe exported loads in the runtime


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (("--steps 2 --batch-size 4", "--stpes 2 --batch-size 4"), "is not a valid cmnav command"),
        (('minutes = 0.3', 'minutes = 0.3\nminuts = 2'), "unknown keys ['minuts']"),
        (("{out}/data --count", "{data}/data --count"), "only {out}"),
        (('minutes = 0.3', 'minutes = -1'), "must be a number > 0"),
        (('name = "student"', 'name = "teacher"'), "used twice"),
        (('description = "a tiny', 'descripton = "a tiny'), "unknown keys ['descripton']"),
        (("--checkpoint-every 1 --device cpu\"\nminutes", "--checkpoint-every 1 --minutes 3 --device cpu\"\nminutes"), "gives --minutes"),
        (('name = "export"', 'name = "export"\nminutes = 1'), "for training commands"),
        (('name = "student"', 'name = "student"\ncontinues = "encoder"'), "same --out"),
    ],
)
def test_a_bad_recipe_is_refused_before_any_stage_runs(tmp_path, change, message):
    recipe = tmp_path / "bad.toml"
    recipe.write_text(TINY_RECIPE.replace(*change, 1))
    proc = _pipeline(recipe, tmp_path / "run")
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr
    assert not (tmp_path / "run" / "pipeline_state.json").exists()  # nothing ran


def test_a_finished_stage_whose_output_is_gone_runs_again_when_a_later_stage_reads_it(tmp_path):
    # The run's directory carried to a new machine without its datasets (models/pipeline-default:
    # the datasets are not committed), in the middle of the run: the stages still to run get them back.
    recipe = tmp_path / "lost.toml"
    recipe.write_text(TINY_RECIPE.split("[[stage]]\nname = \"teacher\"")[0] + (
        '[[stage]]\nname = "table1"\ncommand = "eval cmwae --checkpoint {out}/encoder --data {out}/data --max-images 4 '
        '--out {out}/encoder/eval"\n'))  # fmt: skip
    out = tmp_path / "run"
    assert _pipeline(recipe, out).returncode == 0
    state_path = out / "pipeline_state.json"
    state = json.loads(state_path.read_text())
    assert state["done"] == ["dataset", "encoder", "table1"]
    state["done"].remove("table1")  # as if the call had stopped before it
    state_path.write_text(json.dumps(state))
    shutil.rmtree(out / "data")
    proc = _pipeline(recipe, out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"{out / 'data'}, which dataset wrote, is gone: running dataset again" in proc.stderr
    runs = {name: (out / "logs" / f"{name}.log").read_text().count("\n$ cmnav") + 1 for name in ("dataset", "encoder", "table1")}
    assert runs == {"dataset": 2, "encoder": 1, "table1": 2}, runs  # the encoder's output is there: not made again
    assert sorted(json.loads(state_path.read_text())["done"]) == ["dataset", "encoder", "table1"]
    assert (out / "encoder" / "eval" / "table1.json").is_file()


def test_a_run_goes_on_under_its_recipe_grown_by_stages_at_the_end_and_under_no_other_change(tmp_path):
    stages = TINY_RECIPE.split("[[stage]]\n")
    recipe, out = tmp_path / "grows.toml", tmp_path / "run"
    recipe.write_text("[[stage]]\n".join(stages[:2]))  # the dataset alone
    assert _pipeline(recipe, out).returncode == 0
    recipe.write_text("# a comment added\n" + "[[stage]]\n".join(stages[:3]))  # and the encoder after it
    proc = _pipeline(recipe, out)
    assert proc.returncode == 0 and "1 stage(s) more than when this run began" in proc.stderr, proc.stderr[-3000:]
    assert json.loads((out / "pipeline_state.json").read_text())["done"] == ["dataset", "encoder"]
    assert (out / "logs" / "dataset.log").read_text().count("$ cmnav") == 1  # not run again
    for change in (("--count 80", "--count 81"), ('name = "encoder"', 'name = "encoder"\nminutes = 1')):
        recipe.write_text("[[stage]]\n".join(stages[:3]).replace(*change))
        proc = _pipeline(recipe, out)
        changed = "dataset" if "count" in change[0] else "encoder"
        assert proc.returncode == 2 and f"stage {changed!r} is changed or gone" in proc.stderr and "new --out" in proc.stderr, proc.stderr
    recipe.write_text("[[stage]]\n".join(stages[:2]))  # a stage taken away
    proc = _pipeline(recipe, out)
    assert proc.returncode == 2 and "stage 'encoder' is changed or gone" in proc.stderr, proc.stderr
    other = tmp_path / "other.toml"  # another recipe altogether
    other.write_text("[[stage]]\n".join(stages[:3]))
    proc = _pipeline(other, out)
    assert proc.returncode == 2 and "other settings (differing: recipe, " in proc.stderr and "new --out" in proc.stderr, proc.stderr


def test_a_continued_run_whose_training_state_is_gone_is_made_again_from_its_first_stage(tmp_path):
    out = tmp_path / "run"
    (tmp_path / "tiny.toml").write_text(TINY_RECIPE)
    recipe = load_recipe(str(tmp_path / "tiny.toml"), out, build_parser())
    runner = StageRunner(out, {"recipe": recipe.name}, None)
    runner.state["done"] = ["dataset", "encoder", "teacher"]
    for made in ("data", "encoder", "teacher"):
        (out / made).mkdir()
    _redo_lost_outputs(recipe, out, runner)  # teacher-slower continues the teacher's run: it needs its state
    assert runner.state["done"] == ["dataset", "encoder"]
    runner.state["done"].append("teacher")
    (out / "teacher" / "train_state.pt").write_bytes(b"")
    _redo_lost_outputs(recipe, out, runner)
    assert runner.state["done"] == ["dataset", "encoder", "teacher"]


def test_a_failing_stage_stops_the_run_and_names_its_log(tmp_path):
    recipe = tmp_path / "fail.toml"
    recipe.write_text('[[stage]]\nname = "encoder"\ncommand = "train cmwae --data {out}/missing --out {out}/encoder --size tiny --steps 1"\n')
    proc = _pipeline(recipe, tmp_path / "run")
    assert proc.returncode == 2 and "stage encoder failed" in proc.stderr and "logs/encoder.log" in proc.stderr, proc.stderr
    assert "missing" in proc.stderr  # the log's tail: the training command's own message
    state = json.loads((tmp_path / "run" / "pipeline_state.json").read_text())
    assert state["done"] == [] and "encoder" in state["spent_s"]


def test_the_shipped_recipes_are_valid(tmp_path):
    assert recipe_names(), "cmnav/recipes holds no recipe"
    for name in recipe_names():
        recipe = load_recipe(name, tmp_path, build_parser())  # every command parses; placeholders are known
        assert recipe.description and recipe.stages
        assert all(str(tmp_path) in " ".join(s.argv) for s in recipe.stages if "--out" in s.argv or "-o" in s.argv)


def test_a_stopped_pipeline_stops_its_stage(tmp_path):
    recipe = tmp_path / "long.toml"
    recipe.write_text('[[stage]]\nname = "teacher"\nminutes = 10\ncommand = "train teacher --out {out}/teacher '
                      '--size tiny --envs 8 --rollout 8 --steps 1000000000 --device cpu"\n')  # fmt: skip
    out = tmp_path / "run"
    pipeline = subprocess.Popen([sys.executable, "-m", "cmnav", "pipeline", "--recipe", str(recipe), "--out", str(out)], cwd=REPO,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not _children(pipeline.pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        stage_pids = _children(pipeline.pid)
        assert stage_pids, "the teacher stage never started"
        pipeline.terminate()
        assert pipeline.wait(timeout=60) == 143
        deadline = time.monotonic() + 30
        while any(Path(f"/proc/{pid}").exists() for pid in stage_pids) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not any(Path(f"/proc/{pid}").exists() for pid in stage_pids), "the stage outlived its pipeline"
        state = json.loads((out / "pipeline_state.json").read_text())
        assert state["done"] == [] and "teacher" in state["spent_s"]  # it ran: the next call resumes it (--resume)
    finally:
        if pipeline.poll() is None:
            pipeline.kill()
