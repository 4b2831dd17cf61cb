"""`cmnav fly`: a bad config or model stops it with exit code 2 before any MAVLink is sent;
`--check` validates a config and its model without a vehicle.

The configs point the vehicle at ``udpout://127.0.0.1:PORT`` where the test listens: MAVSDK sends
heartbeats there as soon as it connects (the control case shows it), so silence on PORT means
nothing was attempted.
"""

import json
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import onnxruntime as ort
import pytest

from runtime.programs.fly import run_fly
from tests.runtime.onnx_models import save, step_model

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("models")
    return {"good": save(step_model(), tmp / "good.onnx"), "old": save(step_model(metadata={}), tmp / "old.onnx"),
            "nan": save(step_model(action_offset=float("nan")), tmp / "nan.onnx")}


@pytest.fixture
def mavlink_sniffer():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    yield sock
    sock.close()


@pytest.fixture
def notify_socket(tmp_path):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify"))
    sock.setblocking(False)
    yield sock
    sock.close()


def _datagrams(sock: socket.socket) -> list[bytes]:
    out = []
    while True:
        try:
            out.append(sock.recv(65535))
        except BlockingIOError:
            return out


def _config(model: Path, port: int, policy: str = "", extra: str = "", vehicle: str = "") -> str:
    return (
        f'[vehicle]\nurl = "udpout://127.0.0.1:{port}"\n{vehicle}\n'
        f'[policy]\nmodel_path = "{model}"\n{policy}\n'
        '[camera]\nsource = "sim"\n[camera.sim]\nport = 9\n'
        "[mission]\ngoal_rel_home_enu_m = [5.0, 0.0, 1.5]\n"
        f"{extra}\n"
    )


def _fly(tmp_path: Path, text: str, notify: socket.socket) -> subprocess.CompletedProcess:
    path = tmp_path / "cmnav.toml"
    path.write_text(text)
    env = dict(os.environ, NOTIFY_SOCKET=notify.getsockname(), WATCHDOG_USEC="2000000")
    return subprocess.run([sys.executable, "-m", "cmnav", "fly", "--config", str(path), "--json"], capture_output=True,
                          text=True, timeout=60, cwd=ROOT, env=env)  # fmt: skip


# case: (policy-table lines, other tables, model, what stderr must name)
BAD = {
    "unknown key": ("", "[watchdog]\ntelemetry_stale = 1.0", "good", "unknown key watchdog.telemetry_stale"),
    "wrong type": ("", "[recorder]\nmax_logs = 2.5", "good", "recorder.max_logs = 2.5 is a number: must be an integer"),
    "out of range": ("", "[watchdog]\nstep_trip_ms = 10.0", "good", "watchdog.step_trip_ms=10.0 is invalid: must be >= the control period"),
    "looser speed": ("", "[policy.limits]\nmax_speed_m_s = 2.5", "good", "policy.limits.max_speed_m_s=2.5 must be in [0, 2.0]"),
    "bad sha256": ('model_sha256 = "' + "ab" * 32 + '"', "", "good", "policy.model_sha256 = '" + "ab" * 32 + "' but"),
    "missing model": ("", "", "missing", "policy.model_path = "),
    "model without contract": ("", "", "old", "model refused, nothing armed"),
    "model that outputs NaN": ("", "", "nan", "outputs NaN/Inf (action) on all-zero inputs"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(BAD))
def test_bad_config_exits_2_before_any_mavlink(case, models, tmp_path, mavlink_sniffer, notify_socket):
    policy, extra, model, message = BAD[case]
    model_path = models.get(model, tmp_path / "missing.onnx")
    text = _config(model_path, mavlink_sniffer.getsockname()[1], policy=policy, extra=extra)
    proc = _fly(tmp_path, text, notify_socket)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert message in proc.stderr, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1])["episodes"] == []
    assert _datagrams(mavlink_sniffer) == []  # no MAVLink was sent
    assert not any(m.startswith(b"READY=1") for m in _datagrams(notify_socket))


def test_control_a_good_config_does_talk_mavlink(models, tmp_path, mavlink_sniffer, notify_socket):
    """The same setup with a good config sends MAVLink at once (so silence above means something),
    then gives up on the missing autopilot with exit code 1 (systemd retries that one)."""
    text = _config(models["good"], mavlink_sniffer.getsockname()[1], vehicle="connect_timeout_s = 1.0")
    proc = _fly(tmp_path, text, notify_socket)
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert "no autopilot heartbeat" in proc.stderr
    assert len(_datagrams(mavlink_sniffer)) > 0
    messages = _datagrams(notify_socket)
    assert any(m.startswith(b"STATUS=connecting to the autopilot") for m in messages)
    assert not any(m.startswith(b"READY=1") for m in messages) and b"STOPPING=1" in messages


def _check(tmp_path: Path, text: str, capsys) -> tuple[int, str]:
    path = tmp_path / "check.toml"
    path.write_text(text)
    code = run_fly(path, check_only=True)
    return code, capsys.readouterr().out


def test_check_validates_the_field_example_without_a_vehicle(models, tmp_path, capsys):
    example = (ROOT / "examples" / "cmnav.toml").read_text()
    example = re.sub(r'^model_path = ".*"', f'model_path = "{models["good"]}"', example, flags=re.M)
    example = re.sub(r"^providers = .*", 'providers = ["CPUExecutionProvider"]', example, flags=re.M)
    example = re.sub(r'^log_dir = ".*"', f'log_dir = "{tmp_path / "logs"}"', example, flags=re.M)  # /var/log/cmnav is the Jetson's
    code, out = _check(tmp_path, example, capsys)
    assert code == 0 and "config valid" in out and str(models["good"]) in out


@pytest.mark.skipif("TensorrtExecutionProvider" in ort.get_available_providers(), reason="TensorRT is available here")
def test_unavailable_provider_refuses_or_falls_back_per_config(models, tmp_path, capsys, caplog):
    providers = 'providers = ["TensorrtExecutionProvider", "CPUExecutionProvider"]'
    code, _ = _check(tmp_path, _config(models["good"], 9, policy=providers), capsys)
    assert code == 2
    assert "execution provider(s) ['TensorrtExecutionProvider'] not in this ONNX Runtime build" in caplog.text
    code, out = _check(tmp_path, _config(models["good"], 9, policy=providers + "\nprovider_fallback = true"), capsys)
    assert code == 0 and "loads on ['CPUExecutionProvider']" in out
    assert "falling back to ['CPUExecutionProvider']" in caplog.text


def test_check_refuses_a_model_that_outputs_nan(models, tmp_path, capsys, caplog):
    code, out = _check(tmp_path, _config(models["nan"], 9), capsys)
    assert code == 2 and "config valid" not in out
    assert "model refused, nothing armed" in caplog.text and "outputs NaN/Inf (action) on all-zero inputs" in caplog.text


def test_json_error_object_for_a_file_that_is_not_utf8(tmp_path, mavlink_sniffer, notify_socket):
    path = tmp_path / "cmnav.toml"
    path.write_bytes(b"[vehicle]\nurl = \"udpin://caf\xe9:1\"\n")
    env = dict(os.environ, NOTIFY_SOCKET=notify_socket.getsockname())
    proc = subprocess.run([sys.executable, "-m", "cmnav", "fly", "--config", str(path), "--json"], capture_output=True,
                          text=True, timeout=60, cwd=ROOT, env=env)  # fmt: skip
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    error = json.loads(proc.stdout.strip().splitlines()[-1])["error"]
    assert error.startswith(f"config: {path} is not UTF-8 text"), error
