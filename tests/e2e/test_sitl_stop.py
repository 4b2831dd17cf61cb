"""SIGTERM (what `timeout` sends) or a terminal's Ctrl-C to `cmnav sitl` mid-flight: it forwards the stop to its children
and stops them by PID — the runtime first, which commands hover then Hold and records the stop —
leaves no process behind, and still prints its summary; a second signal changes nothing."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from export.goal_seeker import export_goal_seeker

pytestmark = pytest.mark.timeout(180)

ROOT = Path(__file__).resolve().parents[2]
OFFBOARD_TIMEOUT_S = 90.0


def _children(pid: int) -> list[int]:
    """PIDs whose parent is ``pid`` (Linux /proc)."""
    children = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # exited meanwhile
        if int(fields[1]) == pid:
            children.append(int(stat.parent.name))
    return children


def _offboard_entered(out: Path) -> bool:
    for status in out.glob("*/vehicle_status.json"):
        try:
            return any(mode == "OFFBOARD" for _, mode in json.loads(status.read_text())["mode_log"])
        except (OSError, json.JSONDecodeError, KeyError):
            return False
    return False


@pytest.mark.parametrize("how", ["sigterm", "ctrl-c"])
def test_a_stop_signal_to_cmnav_sitl_stops_its_children_and_records_the_stop(tmp_path, how):
    """``sigterm``: to the process, as `timeout` and `kill` send it.  ``ctrl-c``: SIGINT to the
    whole foreground process group, as a terminal sends it."""
    model = tmp_path / "goal-seeker.onnx"
    export_goal_seeker(str(model))
    out = tmp_path / "runs"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cmnav", "sitl", "--model", str(model), "--out", str(out), "--json", "--level", "0",
         "--seed", "1", "--timeout", "30"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,  # its own group
    )  # fmt: skip
    children: list[int] = []
    try:
        deadline = time.monotonic() + OFFBOARD_TIMEOUT_S
        while not _offboard_entered(out):
            assert proc.poll() is None, proc.communicate()[1][-3000:]
            assert time.monotonic() < deadline, "the vehicle never entered OFFBOARD"
            time.sleep(0.05)
        time.sleep(2.5)  # the runtime sees OFFBOARD up to one 1 Hz HEARTBEAT later, then flies the policy
        children = _children(proc.pid)
        assert len(children) == 2, children  # the SITL vehicle and the runtime
        if how == "sigterm":
            proc.send_signal(signal.SIGTERM)
        else:
            os.killpg(proc.pid, signal.SIGINT)  # cmnav sitl and whatever else is in its group
        time.sleep(0.2)
        proc.send_signal(signal.SIGINT)  # a second signal while stopping: ignored
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        for pid in children:  # left behind only if the test failed
            if Path(f"/proc/{pid}").exists():
                subprocess.run(["kill", "-9", str(pid)], check=False)
    assert proc.returncode == 1, stderr[-3000:]  # aborted
    assert "Traceback" not in stderr
    alive = [pid for pid in children if Path(f"/proc/{pid}").exists()]
    assert alive == [], f"processes left behind: {alive}"
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["outcome"] == "aborted" and summary["abort_reason"] == f"stopped by {'SIGTERM' if how == 'sigterm' else 'SIGINT'}"
    stop = summary["stop"]
    assert (stop["cause"], stop["phase"], stop["action"]) == ("SIGTERM", "episode", "hover_then_hold"), stop
    assert summary["time_s"] > 0.0 and summary["frames"] > 0
    run_dir = Path(summary["run_dir"])
    runtime_log = (run_dir / "runtime.log").read_text()
    assert "stopped on SIGTERM while episode: hover_then_hold" in runtime_log and "Traceback" not in runtime_log
    trace = json.loads((run_dir / "trace.json").read_text())
    modes = [mode for _, mode in trace["mode_log"]]
    assert modes[-2:] == ["OFFBOARD", "HOLD"], modes
    assert not any("ailsafe" in text for _, text in trace["events"])
