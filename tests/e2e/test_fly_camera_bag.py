"""`cmnav fly --camera-bag FILE` against the SITL vehicle: a RealSense recording written by
librealsense's recorder from sim-rendered frames flies through the live camera's code path
(playback in real time); its end is a lost camera (the watchdog's stale_frame trip: hover, Hold,
land); the episode's log holds the recorded frames and replays to the recorded actions exactly."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import numpy as np
import pytest

from export.goal_seeker import export_goal_seeker
from runtime.log.reader import FlightLogReader, LoggedFrame
from runtime.log.topics import TOPIC_DEPTH, TOPIC_GRAY
from runtime.programs.replay import replay_log
from sim.sitl_session import free_port
from tests.e2e.fly_helpers import ROOT, NotifyListener, Sitl, finish_fly, fly_config
from tests.runtime.camera.realsense_recording import recording_suffix, render_walk, write_recording

rs = pytest.importorskip(
    "pyrealsense2",
    reason="pyrealsense2 cannot be imported here: it needs `pip install 'cmnav[realsense]'` and the libusb-1.0 system "
    "library (apt-get install libusb-1.0-0)",
    exc_type=ImportError,  # not installed, or installed without the libusb-1.0 it loads at import
)

pytestmark = pytest.mark.timeout(240)

# 20 s at 15 Hz: start-up (model, connect, health, take-off) takes 6 s of it here, more than 10 s
# on a loaded CI machine, and the rest ends before the goal-seeker, capped at SPEED_CAP_M_S by the
# config's [policy.limits], covers the >= 7 m to the world's goal at level 0.
RECORDING_FRAMES = 300
SPEED_CAP_M_S = 0.4


def test_a_recording_flies_through_cmnav_fly_and_its_log_replays_exactly(tmp_path):
    model = tmp_path / "goal-seeker.onnx"
    export_goal_seeker(str(model))
    frames = render_walk(RECORDING_FRAMES, level=3, seed=5)
    recording = write_recording(tmp_path / f"field{recording_suffix(rs)}", frames)

    runtime_port = free_port(socket.SOCK_DGRAM)
    sitl = Sitl(tmp_path, runtime_port, level=0)
    notify = NotifyListener(tmp_path / "notify")
    try:
        mission = (f"allow_arm_takeoff = true\ntakeoff_alt_m = {sitl.episode['takeoff_alt_m']:.3f}\nmax_episodes = 1\n"
                   f"[policy.limits]\nmax_speed_m_s = {SPEED_CAP_M_S}")  # fmt: skip
        config = fly_config(model, runtime_port, sitl.camera_port, sitl.episode["goal_rel_home_enu_m"], tmp_path / "logs", mission)
        (tmp_path / "cmnav.toml").write_text(config)  # camera.source = "sim": --camera-bag replaces it
        env = dict(os.environ, NOTIFY_SOCKET=notify.path, WATCHDOG_USEC="2000000", PYTHONUNBUFFERED="1")
        with open(tmp_path / "fly.log", "w") as log_file:
            proc = subprocess.Popen(
                [sys.executable, "-m", "cmnav", "fly", "--config", str(tmp_path / "cmnav.toml"), "--json",
                 "--camera-bag", str(recording)],
                cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=log_file, text=True,
            )  # fmt: skip
        code, summary = finish_fly(proc, tmp_path)
    finally:
        sitl.stop()
        notify.close()
    log_text = (tmp_path / "fly.log").read_text()
    (episode,) = summary["episodes"]
    # The recording ended in flight: camera lost, the stale-frame trip, hover, Hold, landing.
    assert code == 1, f"exit {code}: {summary}\n{log_text[-4000:]}"
    assert (episode["outcome"], episode["abort_reason"]) == ("aborted", "stale_frame"), episode
    assert episode["frames"] > 10, episode
    assert "end of the RealSense recording" in log_text and "landed and disarmed" in log_text

    # What was flown on is the recording: every logged gray image is one of the recorded frames, in order.
    reader = FlightLogReader(episode["log"])
    logged = [r for r in reader.records((TOPIC_DEPTH, TOPIC_GRAY)) if isinstance(r, LoggedFrame)]
    assert len(logged) >= episode["frames"]
    flat = frames.gray_u8.reshape(len(frames), -1)
    indices = []
    for frame in logged:
        (match,) = np.flatnonzero((flat == frame.gray_u8.reshape(1, -1)).all(axis=1))[:1]
        indices.append(int(match))
    assert indices == sorted(indices) and indices[-1] == RECORDING_FRAMES - 1, indices

    report = replay_log(episode["log"])
    assert report.same_model and report.steps == episode["frames"] and report.steps_without_frame == 0
    assert report.max_abs_diff == 0.0
