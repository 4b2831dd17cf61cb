"""`cmnav sitl --autopilot`: what is refused before anything starts (loopback only unless
--allow-remote; faults only our vehicle can inject), and the follower's summary fields."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from runtime.faults.catalogue import FaultSite, parse_injection
from sim.sitl_session import SitlRequest, autopilot_request, merge_summary, run_sitl_cli

from tests.sim.test_sitl_session import EPISODE, FLIGHT, _trace


def _args(tmp_path, url, **extra):
    base = dict(model="m.onnx", level=0, seed=0, timeout=10.0, out=str(tmp_path), json=False, inject=[],
                degrade="none", autopilot=url, offboard_port=None, allow_remote=False)  # fmt: skip
    return argparse.Namespace(**{**base, **extra})


@pytest.mark.parametrize("url", ["udp://10.0.0.2:14550", "udp://0.0.0.0:14550"])
def test_another_host_is_refused_before_anything_starts(tmp_path, capsys, url):
    assert run_sitl_cli(_args(tmp_path, url)) == 2
    err = capsys.readouterr().err
    assert "is not 127.0.0.1" in err and "--allow-remote" in err
    assert not any(tmp_path.iterdir())  # nothing ran, nothing written


def test_the_cli_refuses_a_remote_autopilot_with_a_clear_line(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "cmnav", "sitl", "--model", "m.onnx", "--autopilot", "udp://192.168.1.7:14550", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith("cmnav sitl: --autopilot 'udp://192.168.1.7:14550': host 192.168.1.7")


def test_allow_remote_accepts_another_host_and_defaults_fill_in():
    base = SitlRequest(Path("m.onnx"), 0, 0, 10.0, Path("out"))
    request = autopilot_request(base, "udp://192.168.1.7:14550", None, allow_remote=True)
    assert (request.autopilot_url, request.offboard_port, request.allow_remote) == ("udp://192.168.1.7:14550", 14540, True)


@pytest.mark.parametrize("port", [0, 70000])
def test_bad_offboard_port_is_named(port):
    with pytest.raises(ValueError, match="--offboard-port"):
        autopilot_request(SitlRequest(Path("m.onnx"), 0, 0, 10.0, Path("out")), "udp://127.0.0.1:14550", port, False)


def test_camera_runtime_and_signal_faults_fly_with_an_external_autopilot():
    injections = tuple(parse_injection(t) for t in ("camera-stall@2", "camera-garbage@3", "camera-blackout@4",
                                                       "nan-action@1", "runtime-stop@5"))  # fmt: skip
    request = autopilot_request(SitlRequest(Path("m.onnx"), 0, 0, 10.0, Path("out"), injections), "udp://127.0.0.1:14550", None, False)
    # The camera faults go to the follower (the vehicle's site), the others where they happen.
    assert request.injections_at(FaultSite.VEHICLE) == ["--inject", "camera-stall@2", "--inject", "camera-garbage@3",
                                                        "--inject", "camera-blackout@4"]  # fmt: skip
    assert request.injections_at(FaultSite.RUNTIME) == ["--inject", "nan-action@1"]


@pytest.mark.parametrize("inject, reason", [
    ("telemetry-loss@2", "that link is PX4's own"), ("pilot-takeover@2", "RC mode switch"),
    ("offboard-refused@0", "PX4 itself decides"), ("vehicle-stuck@2", "PX4's dynamics (SIH)"),
])  # fmt: skip
def test_faults_the_follower_cannot_do_are_refused_with_one_line(tmp_path, capsys, inject, reason):
    assert run_sitl_cli(_args(tmp_path, "udp://127.0.0.1:14550", inject=["camera-stall@1", inject])) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"cmnav sitl: --inject {inject}: not with an external autopilot: ") and reason in line
    assert "cmnav sitl without --autopilot" in line
    assert not any(tmp_path.iterdir())  # nothing ran, nothing written


def test_summary_of_a_followed_flight_has_ground_truth_and_autopilot(tmp_path):
    request = SitlRequest(Path("m.onnx"), 1, 7, 30.0, tmp_path, autopilot_url="udp://127.0.0.1:14550")
    trace = dict(_trace(), verdict={"contact": None, "geofence": None, "goal_reached_t_s": 14.0, "timeout_t_s": None,
                                    "offboard_t_s": 5.0})  # fmt: skip
    summary = merge_summary(request, EPISODE, FLIGHT, trace, tmp_path, 30.0)
    assert summary["autopilot"] == "udp://127.0.0.1:14550" and summary["ground_truth"]["goal_reached_t_s"] == 14.0
    assert summary["tracking_error_m_s"] is None  # FLIGHT names no log file that exists
