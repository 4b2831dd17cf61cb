"""``python -m sim.sitl`` argument handling (the process itself is exercised end to end elsewhere)."""

from pathlib import Path

import pytest

from sim.sitl.__main__ import parse_args

BASE = ["--mavlink-port", "14540", "--camera-port", "5600", "--level", "2", "--seed", "7",
        "--episode-json", "ep.json", "--trace", "trace.json"]  # fmt: skip


def test_defaults():
    config = parse_args(BASE)
    assert (config.mavlink_port, config.camera_port, config.level, config.seed) == (14540, 5600, 2, 7)
    assert (config.episode_json, config.trace_json) == (Path("ep.json"), Path("trace.json"))
    assert (config.physics_hz, config.camera_hz) == (100.0, 15.0)


@pytest.mark.parametrize(
    "extra, named",
    [(["--physics-hz", "5"], "--physics-hz"), (["--camera-hz", "0"], "--camera-hz"), (["--level", "-1"], "--level"),
     (["--mavlink-port", "70000"], "--mavlink-port")],
)  # fmt: skip
def test_bad_values_are_named(extra, named, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_args(BASE + extra)
    assert exit_info.value.code == 2 and named in capsys.readouterr().err


def test_missing_option(capsys):
    with pytest.raises(SystemExit):
        parse_args(BASE[:-2])
    assert "--trace" in capsys.readouterr().err


def test_faults_and_status_file():
    config = parse_args(BASE + ["--inject", "camera-stall@2", "--inject", "offboard-refused@0", "--status-json", "s.json"])
    assert [str(i) for i in config.injections] == ["camera-stall@2", "offboard-refused@0"]
    assert config.status_json == Path("s.json")
    assert parse_args(BASE).injections == () and parse_args(BASE).status_json is None


def test_runtime_faults_are_refused_here(capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_args(BASE + ["--inject", "nan-action@2"])
    assert exit_info.value.code == 2 and "unknown fault kind 'nan-action' here" in capsys.readouterr().err


def test_stand_in_needs_no_camera_port_and_takes_a_pose_link():
    base = [a for a in BASE if a not in ("--camera-port", "5600")]
    config = parse_args(base + ["--stand-in", "--pose-port", "14550", "--heading-deg", "90"])
    assert config.stand_in and config.camera_port is None and config.pose_port == 14550 and config.heading_deg == 90.0
    assert parse_args(BASE).pose_port is None and not parse_args(BASE).stand_in


@pytest.mark.parametrize(
    "argv, named",
    [([a for a in BASE if a not in ("--camera-port", "5600")], "--camera-port"),
     (BASE + ["--pose-port", "0"], "--pose-port"), (BASE + ["--heading-deg", "400"], "--heading-deg")],
)  # fmt: skip
def test_stand_in_options_are_checked(argv, named, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_args(argv)
    assert exit_info.value.code == 2 and named in capsys.readouterr().err
