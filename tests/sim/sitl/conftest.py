"""Launching the real SITL vehicle process for the end-to-end tests of this folder (shared by
two modules, hence a conftest).  Every process is stopped by its PID in the fixture teardown."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from sim.sitl_session import free_port, stop_process

READY_TIMEOUT_S = 60.0




@dataclass
class SitlProcess:
    proc: subprocess.Popen
    mavlink_port: int
    camera_port: int
    episode: dict
    trace_path: Path
    log_path: Path
    t_launch_s: float
    t_ready_s: float

    def log_tail(self, chars: int = 3000) -> str:
        return self.log_path.read_text(errors="replace")[-chars:]

    def stop(self) -> int:
        """SIGTERM by PID; SIGKILL if it does not exit in time.  Returns the exit code."""
        return stop_process(self.proc, "SITL vehicle")

    def trace(self) -> dict:
        return json.loads(self.trace_path.read_text())


@pytest.fixture
def launch_sitl(tmp_path: Path) -> Iterator[Callable[..., SitlProcess]]:
    """Factory: ``launch_sitl(level=0, seed=1)`` starts ``python -m sim.sitl`` on free ports and
    returns once its episode JSON exists."""
    launched: list[SitlProcess] = []

    def launch(level: int = 0, seed: int = 1, extra: tuple[str, ...] = ()) -> SitlProcess:
        run_dir = tmp_path / f"sitl{len(launched)}"
        run_dir.mkdir()
        episode_path, log_path = run_dir / "episode.json", run_dir / "sitl.log"
        mavlink_port, camera_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
        t_launch_s = time.monotonic()
        with open(log_path, "w") as log_file:
            proc = subprocess.Popen(
                [sys.executable, "-m", "sim.sitl", "--mavlink-port", str(mavlink_port), "--camera-port", str(camera_port),
                 "--level", str(level), "--seed", str(seed), "--episode-json", str(episode_path),
                 "--trace", str(run_dir / "trace.json"), *extra],
                stdout=log_file, stderr=subprocess.STDOUT,
            )  # fmt: skip
        sitl = SitlProcess(proc, mavlink_port, camera_port, {}, run_dir / "trace.json", log_path, t_launch_s, 0.0)
        launched.append(sitl)
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not episode_path.exists():
            assert proc.poll() is None, f"SITL vehicle exited with {proc.returncode}:\n{sitl.log_tail()}"
            assert time.monotonic() < deadline, f"SITL vehicle not ready in {READY_TIMEOUT_S} s:\n{sitl.log_tail()}"
            time.sleep(0.02)
        sitl.t_ready_s = time.monotonic()
        sitl.episode = json.loads(episode_path.read_text())
        return sitl

    try:
        yield launch
    finally:
        for sitl in launched:
            sitl.stop()
