"""``python -m sim.follower`` options, and a follower whose autopilot never shows up."""

import threading
from pathlib import Path

import pytest

from sim.follower.follower import FollowerConfig, FollowerNotReadyError, WorldFollower
from sim.follower.__main__ import parse_args

BASE = ["--autopilot", "udp://127.0.0.1:14550", "--camera-port", "5600", "--level", "1", "--seed", "3",
        "--episode-json", "ep.json", "--trace", "trace.json"]  # fmt: skip


def test_defaults():
    config = parse_args(BASE)
    assert (config.listen_host, config.listen_port, config.camera_port) == ("127.0.0.1", 14550, 5600)
    assert (config.level, config.seed, config.episode_json, config.trace_json) == (1, 3, Path("ep.json"), Path("trace.json"))


def test_remote_autopilot_needs_allow_remote(capsys):
    argv = ["--autopilot", "udp://192.168.1.7:14550"] + BASE[2:]
    with pytest.raises(SystemExit) as exit_info:
        parse_args(argv)
    assert exit_info.value.code == 2 and "--allow-remote" in capsys.readouterr().err
    assert parse_args(argv + ["--allow-remote"]).listen_host == "192.168.1.7"


@pytest.mark.parametrize("extra, named", [(["--level", "-1"], "--level"), (["--camera-hz", "0"], "--camera-hz"),
                                          (["--timeout-s", "0"], "--timeout-s")])  # fmt: skip
def test_bad_values_are_named(extra, named, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_args(BASE + extra)
    assert exit_info.value.code == 2 and named in capsys.readouterr().err


def test_camera_faults_are_parsed_and_the_others_refused(capsys):
    config = parse_args(BASE + ["--inject", "camera-stall@3", "--inject", "camera-blackout@1.5"])
    assert [str(i) for i in config.injections] == ["camera-stall@3", "camera-blackout@1.5"]
    for inject, named in (("vehicle-stuck@2", "not with an external autopilot"), ("nan-action@2", "unknown fault kind"),
                          ("camera-stall", "expected KIND@SECONDS")):  # fmt: skip
        with pytest.raises(SystemExit) as exit_info:
            parse_args(BASE + ["--inject", inject])
        assert exit_info.value.code == 2 and named in capsys.readouterr().err


def test_an_absent_autopilot_is_named_and_the_trace_still_written(tmp_path):
    config = FollowerConfig("127.0.0.1", 0, 0, 0, 1, tmp_path / "ep.json", tmp_path / "trace.json", ready_timeout_s=0.3)
    follower = WorldFollower(config)
    with pytest.raises(FollowerNotReadyError, match="no HEARTBEAT yet.*Is it running and sending MAVLink to udp 127.0.0.1:"):
        follower.run(threading.Event())
    assert not config.episode_json.exists() and config.trace_json.exists()
