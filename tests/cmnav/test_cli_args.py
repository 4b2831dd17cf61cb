"""Bad arguments are refused by `cmnav` itself, before any process starts or any work is done:
exit code 2 and one line naming the option, never a traceback from a child process."""

import subprocess
import sys
from pathlib import Path

import pytest

from tests.runtime.onnx_models import save, step_model

ROOT = Path(__file__).resolve().parents[2]


def _cmnav(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cmnav", *args], capture_output=True, text=True, timeout=120, cwd=ROOT)


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return save(step_model(), tmp_path_factory.mktemp("models") / "good.onnx")


@pytest.mark.parametrize("args, message", [
    (["--seed", "-5"], "--seed -5 must be an integer in [0, 2**64 - 1]"),
    (["--seed", str(2**64)], f"--seed {2**64} must be an integer in [0, 2**64 - 1]"),
    (["--level", "-1"], "--level -1 must be an integer >= 0 (the number of obstacles)"),
    (["--timeout", "0"], "--timeout 0.0 must be a positive number of seconds"),
    (["--timeout", "nan"], "--timeout nan must be a positive number of seconds"),
])  # fmt: skip
def test_sitl_ranges_are_checked_before_any_process_starts(model, tmp_path, args, message):
    out = tmp_path / "runs"
    proc = _cmnav("sitl", "--model", str(model), "--out", str(out), *args)
    assert proc.returncode == 2 and proc.stderr.strip() == f"cmnav sitl: {message}", proc.stderr
    assert not out.exists()


def test_sitl_estimate_is_our_vehicles_not_an_external_autopilots(model, tmp_path):
    out = tmp_path / "runs"
    proc = _cmnav("sitl", "--model", str(model), "--out", str(out), "--estimate", "px4", "--autopilot", "udp://127.0.0.1:14550")
    assert proc.returncode == 2 and "--estimate is our SITL vehicle's" in proc.stderr, proc.stderr
    assert not out.exists()


def test_sitl_out_that_is_a_file_is_refused(model, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    proc = _cmnav("sitl", "--model", str(model), "--out", str(blocker))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == f"cmnav sitl: --out {blocker}: {blocker} is a file, not a directory: pass a writable directory"


def test_export_output_that_is_a_directory_is_refused(tmp_path):
    proc = _cmnav("export", "goal-seeker", "-o", str(tmp_path))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert f"-o {tmp_path}: {tmp_path} is a directory: give a file name" in proc.stderr


def test_export_output_under_a_file_is_refused(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    proc = _cmnav("export", "goal-seeker", "-o", str(blocker / "sub" / "m.onnx"))
    assert proc.returncode == 2 and f"{blocker} is a file, not a directory" in proc.stderr and "Traceback" not in proc.stderr
    proc = _cmnav("export", "--encoder", "e", "--policy", "p", "-o", str(tmp_path))
    assert proc.returncode == 2 and "is a directory" in proc.stderr and "Traceback" not in proc.stderr


def test_the_sitl_depth_modes_are_the_camera_feeds():
    from cmnav.cli import SITL_DEPTH_MODES
    from sim.sitl.camera_feed import DEPTH_MODES

    assert SITL_DEPTH_MODES == DEPTH_MODES


def test_the_sitl_estimates_are_the_vehicles():
    from cmnav.cli import SITL_ESTIMATES
    from sim.sitl.estimate import ESTIMATES

    assert SITL_ESTIMATES == ESTIMATES


def test_the_velocity_bias_modes_are_the_runtimes():
    from cmnav.cli import VELOCITY_BIAS_MODES
    from runtime.tracking import VELOCITY_BIAS_MODES as RUNTIME_MODES

    assert VELOCITY_BIAS_MODES == RUNTIME_MODES


def test_the_approach_cap_modes_are_the_sitl_runtimes():
    from cmnav.cli import APPROACH_CAP_MODES
    from runtime.programs.sitl import APPROACH_CAP_MODES as RUNTIME_MODES

    assert APPROACH_CAP_MODES == RUNTIME_MODES


def test_the_vehicle_choices_are_trainings():
    from cmnav.cli import VEHICLE_CHOICES
    from training.policy.field import VEHICLES

    assert VEHICLE_CHOICES == VEHICLES


def test_the_squares_teacher_views_are_the_envs():
    from cmnav.cli import SQUARES_TEACHER_VIEWS
    from training.policy.env import SQUARES_PRIVILEGED

    assert SQUARES_TEACHER_VIEWS == SQUARES_PRIVILEGED


def test_dagger_options_without_a_teacher_are_refused_not_ignored(tmp_path):
    out = tmp_path / "policy"
    proc = _cmnav("train", "policy", "--encoder", "e", "--out", str(out), "--projector-off-episode-fraction", "0.3", "--beta-start", "0")
    assert proc.returncode == 2 and proc.stderr.strip() == (
        "cmnav train policy: --projector-off-episode-fraction, --beta-start train a student by DAgger: give --teacher TEACHER_DIR"), proc.stderr
    assert not out.exists()


def test_the_cmwae_schemes_are_trainings():
    import argparse

    from cmnav.cli import build_parser
    from training.cmwae.train import CORRUPTION_SCHEMES

    def sub(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
        return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]

    cmwae = sub(sub(build_parser(), "train"), "cmwae")
    scheme = next(a for a in cmwae._actions if "--scheme" in a.option_strings)
    assert tuple(scheme.choices) == CORRUPTION_SCHEMES
