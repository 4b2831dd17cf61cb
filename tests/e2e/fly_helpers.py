"""Running `cmnav fly` and the SITL vehicle as real processes over loopback, for the end-to-end
tests of this folder: the SITL vehicle, a systemd notify listener, a MAVLink router (pilot and
runtime on one vehicle), the runtime's config and process.  Every process is stopped by its PID."""

from __future__ import annotations

import contextlib
import json
import os
import resource
import select
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from sim.sitl.ground_station import GroundStation
from sim.sitl_session import free_port, stop_process

ROOT = Path(__file__).resolve().parents[2]
LOOPBACK = "127.0.0.1"
READY_TIMEOUT_S = 60.0
FLY_TIMEOUT_S = 120.0


class NotifyListener:
    """Collects sd_notify datagrams on a unix socket, as systemd would receive them."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(self.path)
        self._sock.settimeout(0.1)
        self.messages: list[str] = []
        self.ready = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                message = self._sock.recv(4096).decode()
            except socket.timeout:
                continue
            self.messages.append(message)
            if message.startswith("READY=1"):
                self.ready.set()

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._sock.close()


class MavlinkRouter:
    """vehicle <-> runtime and pilot, like mavlink-router: every datagram from the vehicle goes to
    both; what either sends goes to the vehicle."""

    def __init__(self, runtime_port: int, pilot_port: int) -> None:
        def bound() -> socket.socket:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind((LOOPBACK, 0))
            return sock

        self._vehicle_side, self._runtime_side, self._pilot_side = bound(), bound(), bound()
        self.port = self._vehicle_side.getsockname()[1]  # the SITL vehicle's --mavlink-port
        self._outputs = [(self._runtime_side, (LOOPBACK, runtime_port)), (self._pilot_side, (LOOPBACK, pilot_port))]
        self._vehicle_addr: tuple | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        sockets = [self._vehicle_side, self._runtime_side, self._pilot_side]
        while not self._stop.is_set():
            readable, _, _ = select.select(sockets, [], [], 0.05)
            for sock in readable:
                try:
                    data, addr = sock.recvfrom(65535)
                except ConnectionRefusedError:
                    continue  # ICMP from a send to a port nobody listens on yet
                try:
                    if sock is self._vehicle_side:
                        self._vehicle_addr = addr
                        for out, dest in self._outputs:
                            out.sendto(data, dest)
                    elif self._vehicle_addr is not None:
                        self._vehicle_side.sendto(data, self._vehicle_addr)
                except OSError:
                    pass  # a listener not up yet: MAVLink over UDP loses such datagrams too

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        for sock in (self._vehicle_side, self._runtime_side, self._pilot_side):
            sock.close()


class Sitl:
    """``python -m sim.sitl`` on free ports, stopped by PID."""

    def __init__(self, tmp: Path, mavlink_port: int, level: int = 0, seed: int = 2, inject: tuple[str, ...] = ()) -> None:
        """``inject``: the vehicle's faults (``KIND@SECONDS``, ``python -m sim.sitl --inject``)."""
        self.camera_port = free_port(socket.SOCK_STREAM)
        self.log_path = tmp / "sitl.log"
        self.status_path = tmp / "vehicle_status.json"
        self.trace_path = tmp / "trace.json"
        episode_path = tmp / "episode.json"
        with open(self.log_path, "w") as log_file:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "sim.sitl", "--mavlink-port", str(mavlink_port), "--camera-port", str(self.camera_port),
                 "--level", str(level), "--seed", str(seed), "--episode-json", str(episode_path),
                 "--trace", str(self.trace_path), "--status-json", str(self.status_path),
                 *[arg for text in inject for arg in ("--inject", text)]],
                stdout=log_file, stderr=subprocess.STDOUT, cwd=ROOT,
            )  # fmt: skip
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not episode_path.exists():
            assert self.proc.poll() is None, f"SITL vehicle exited:\n{self.log_path.read_text()[-3000:]}"
            assert time.monotonic() < deadline, "SITL vehicle not ready"
            time.sleep(0.05)
        self.episode = json.loads(episode_path.read_text())

    def modes(self) -> list[str]:
        """The vehicle's mode log so far (its live status file)."""
        try:
            return [mode for _, mode in json.loads(self.status_path.read_text())["mode_log"]]
        except (OSError, json.JSONDecodeError, KeyError):
            return []

    def stop(self) -> None:
        stop_process(self.proc, "SITL vehicle", 10.0)

    def trace(self) -> dict:
        """Ground truth, written when the vehicle stops."""
        return json.loads(self.trace_path.read_text())


def fly_config(model: Path, runtime_port: int, camera_port: int, goal: list[float], log_dir: Path, mission: str) -> str:
    return f"""
[vehicle]
url = "udpin://127.0.0.1:{runtime_port}"
[camera]
source = "sim"
[camera.sim]
port = {camera_port}
[policy]
model_path = "{model}"
providers = ["CPUExecutionProvider"]
[mission]
goal_rel_home_enu_m = [{goal[0]:.3f}, {goal[1]:.3f}, {goal[2]:.3f}]
episode_timeout_s = 30.0
{mission}
[recorder]
log_dir = "{log_dir}"
"""


def start_fly(tmp_path: Path, config: str, notify: NotifyListener, file_size_limit_bytes: int | None = None) -> subprocess.Popen:
    """``cmnav fly --config --json`` with its log in ``tmp_path / "fly.log"``.  ``file_size_limit_bytes``
    (RLIMIT_FSIZE) makes every write of the process past that size in a regular file fail (EFBIG), as a
    full disk does (ENOSPC), for any user; its stderr then goes through a pipe (see finish_fly)."""
    path = tmp_path / "cmnav.toml"
    path.write_text(config)
    env = dict(os.environ, NOTIFY_SOCKET=notify.path, WATCHDOG_USEC="2000000", PYTHONUNBUFFERED="1")
    command = [sys.executable, "-m", "cmnav", "fly", "--config", str(path), "--json"]
    if file_size_limit_bytes is not None:
        def limit() -> None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (file_size_limit_bytes, file_size_limit_bytes))

        return subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                preexec_fn=limit)  # fmt: skip
    with open(tmp_path / "fly.log", "w") as log_file:
        return subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=log_file, text=True)


def finish_fly(proc: subprocess.Popen, tmp_path: Path) -> tuple[int, dict]:
    try:
        stdout, stderr = proc.communicate(timeout=FLY_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        stdout, stderr = proc.communicate()
    if stderr is not None:
        (tmp_path / "fly.log").write_text(stderr)
    lines = stdout.strip().splitlines()
    summary = json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}
    assert summary, f"no summary; runtime log:\n{(tmp_path / 'fly.log').read_text()[-4000:]}"
    return proc.returncode, summary


class Pilot(GroundStation):
    """A ground station / RC pilot over pymavlink: arms, takes off, selects offboard (``sim.sitl.ground_station``)."""


@dataclass
class PilotRig:
    """Pilot mode's pieces: the SITL vehicle, the MAVLink router between it, the runtime's port and
    the pilot's, the sd_notify listener, and the `cmnav fly` process once started."""

    runtime_port: int
    router: MavlinkRouter
    sitl: Sitl
    notify: NotifyListener
    pilot: Pilot
    proc: subprocess.Popen | None = None


@contextlib.contextmanager
def pilot_rig(tmp: Path):
    """A :class:`PilotRig`; everything it started is stopped on the way out."""
    runtime_port, pilot_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    router = MavlinkRouter(runtime_port, pilot_port)
    rig = PilotRig(runtime_port, router, Sitl(tmp, router.port), NotifyListener(tmp / "notify"), Pilot(pilot_port))
    try:
        yield rig
    finally:
        if rig.proc is not None and rig.proc.poll() is None:
            rig.proc.kill()
            rig.proc.wait()
        rig.pilot.close()
        rig.sitl.stop()
        rig.router.close()
        rig.notify.close()
