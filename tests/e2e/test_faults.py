"""Fault injection end to end: per fault kind, one short `cmnav sitl` flight at level 0 with the
goal-seeker and the fault about 2 s after offboard, the real processes over loopback.

Each flight is checked against the runtime's own record (trip cause, detect_ms, response) and the
SITL vehicle's ground truth (``faults`` in the summary: the vehicle slower than 0.2 m/s within 1 s
of the trip; runtime-kill: the vehicle's own failsafe within 1.5 s of the kill — with PX4's default
COM_OBL_RC_ACT, Position mode, which without RC descends and lands, as real PX4 does).  The bounds are the
system's specification (DESIGN §3 and the watchdog's configured limits), not this machine's speed.
"""

import json
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.reader import NonSeekingReader

from runtime.config import WatchdogConfig

pytestmark = pytest.mark.timeout(150)

WATCHDOG = WatchdogConfig()
HEARTBEAT_PERIOD_MS = 1000.0  # the runtime learns the flight mode from PX4's 1 Hz HEARTBEAT
STOP_AFTER_TRIP_S = 1.0
KILL_TO_FAILSAFE_S = 1.5  # PX4's COM_OF_LOSS_T = 1 s after the last setpoint, plus margin
DETECT_MS = 1000.0  # condition true -> trip, for every trip the runtime records
FLIGHT_TIMEOUT_S = "12"

# inject, trip cause, response, how long after the injection the trip may come by design (ms),
# the vehicle's last mode: LAND (sitl_flight lands after any abort), POSCTL (the pilot has it:
# nothing more is sent), HOLD (telemetry lost: the Hold arrives, the runtime learns nothing more
# and MAVSDK stops sending to a peer silent for 10 s, so the land command never leaves)
CASES = [
    ("camera-stall@2", "stale_frame", "hover_then_hold", WATCHDOG.frame_stale_ms, "LAND"),
    ("camera-garbage@2", "bad_frames", "hover_then_hold", WATCHDOG.frame_stale_ms, "LAND"),
    ("camera-blackout@2", "depth_invalid", "hover_then_hold", 1000.0 * WATCHDOG.depth_invalid_max_s, "LAND"),
    ("telemetry-loss@2", "stale_telemetry", "hover_then_hold", WATCHDOG.telemetry_stale_ms, "HOLD"),
    ("pilot-takeover@2", "pilot_left_offboard", "stop_commanding", HEARTBEAT_PERIOD_MS, "POSCTL"),
    ("offboard-refused@0", "offboard_refused", "hold", 0.0, "LAND"),
    ("inference-overrun@2", "step_deadline", "hover_then_hold", WATCHDOG.step_trip_ms, "LAND"),
    ("nan-action@2", "bad_action", "hover_then_hold", 0.0, "LAND"),
    ("geofence@2", "geofence", "hover_then_hold", 0.0, "LAND"),
    ("geofence@0", "geofence", "hover_then_hold", 0.0, "LAND"),
    # The vehicle brakes to a stop; the error passes the bound within a few tenths of a second.
    ("vehicle-stuck@2", "tracking", "hover_then_hold", 1000.0 * WATCHDOG.tracking_window_s, "LAND"),
]


def _fly(model: Path, out: Path, inject: str) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "cmnav", "sitl", "--model", str(model), "--out", str(out), "--json", "--level", "0",
         "--seed", "1", "--timeout", FLIGHT_TIMEOUT_S, "--inject", inject],
        capture_output=True, text=True, timeout=140,
    )  # fmt: skip
    lines = proc.stdout.strip().splitlines()
    assert proc.returncode == 1 and lines and lines[-1].startswith("{"), f"exit {proc.returncode}:\n{proc.stderr[-3000:]}"
    return json.loads(lines[-1])


def _count_messages(log: str) -> int:
    """Messages in an MCAP log, complete or cut short by a kill."""
    count = 0
    with open(log, "rb") as f:
        try:
            for _ in NonSeekingReader(f).iter_messages(log_time_order=False):
                count += 1
        except (EndOfFile, RecordLengthLimitExceeded, struct.error):
            pass  # the cut of a killed runtime's log
    return count


@pytest.mark.parametrize("inject, cause, response, trip_within_ms, end_mode", CASES, ids=[c[0] for c in CASES])
def test_fault_trips_and_stops_the_vehicle(goal_seeker, tmp_path, inject, cause, response, trip_within_ms, end_mode):
    summary = _fly(goal_seeker, tmp_path, inject)
    (fault,) = summary["faults"]
    assert fault["injected"], fault
    assert summary["outcome"] == "aborted" and summary["abort_reason"] == cause
    trip = summary["watchdog_trips"][0]
    assert (trip["cause"], trip["response"]) == (cause, response)
    assert (fault["cause"], fault["response"], fault["detect_ms"]) == (cause, response, trip["detect_ms"])
    assert 0.0 <= fault["detect_ms"] < DETECT_MS
    assert fault["trip_after_inject_ms"] < trip_within_ms + DETECT_MS, fault
    assert fault["stopped_after_trip_s"] is not None and fault["stopped_after_trip_s"] <= STOP_AFTER_TRIP_S, fault
    modes = [mode for _, mode in json.loads((Path(summary["run_dir"]) / "trace.json").read_text())["mode_log"]]
    assert modes[-1] == end_mode, modes
    if response == "stop_commanding":
        assert fault["hold_entered_s"] is None and modes.count("POSCTL") == 1  # no Hold, nothing after the pilot's switch
    else:
        assert fault["hold_entered_s"] is not None, fault  # Hold, on the vehicle's side whatever the runtime saw
    assert _count_messages(summary["log"]) > 10


def test_runtime_kill_ends_in_the_vehicles_failsafe_landing(goal_seeker, tmp_path):
    """A killed runtime cannot command Hold: PX4's failsafe (default COM_OBL_RC_ACT = 0, Position
    mode) takes over, and without RC input it descends where the vehicle is."""
    summary = _fly(goal_seeker, tmp_path, "runtime-kill@2")
    (fault,) = summary["faults"]
    assert summary["outcome"] == "aborted" and summary["abort_reason"] == "runtime_killed"
    assert (fault["cause"], fault["response"]) == ("offboard_loss_failsafe", "vehicle_failsafe")
    trip = summary["watchdog_trips"][-1]
    assert trip["cause"] == "offboard_loss_failsafe" and trip["mode"] == "POSCTL"
    assert 0.0 < trip["t_s"] <= KILL_TO_FAILSAFE_S and fault["detect_ms"] == pytest.approx(1000.0 * trip["t_s"], abs=1.0)
    trace = json.loads((Path(summary["run_dir"]) / "trace.json").read_text())
    assert any("Failsafe activated" in text and "no RC: landing" in text for _, text in trace["events"])
    heights = [p[2] for t, p in zip(trace["t_s"], trace["pos_enu_m"]) if t >= trace["mode_log"][-1][0]]
    assert heights and heights[-1] < heights[0] - 0.3, heights[:3] + heights[-3:]  # descending, not holding
    assert _count_messages(summary["log"]) > 10  # cut short, still readable


def test_runtime_stop_ends_in_the_runtimes_own_hover_and_hold(goal_seeker, tmp_path):
    """SIGTERM (what systemd sends) mid-episode: the runtime brakes, commands Hold itself and
    records the stop; the vehicle's offboard-loss failsafe never fires."""
    summary = _fly(goal_seeker, tmp_path, "runtime-stop@2")
    assert summary["outcome"] == "aborted" and summary["abort_reason"] == "runtime_stopped"
    stop = summary["stop"]
    assert (stop["cause"], stop["phase"], stop["action"]) == ("SIGTERM", "episode", "hover_then_hold"), stop
    (fault,) = summary["faults"]
    assert fault["injected"] and fault["stop"] == stop
    assert (fault["cause"], fault["response"]) == ("stop_signal", "hover_then_hold")
    assert fault["detect_ms"] >= 0.0 and fault["trip_after_inject_ms"] == fault["detect_ms"], fault  # signal -> handler
    assert fault["stopped_after_trip_s"] is not None and fault["hold_entered_s"] is not None, fault
    trace = json.loads((Path(summary["run_dir"]) / "trace.json").read_text())
    modes = [mode for _, mode in trace["mode_log"]]
    assert modes[modes.index("OFFBOARD") :] == ["OFFBOARD", "HOLD"], modes
    assert not any("ailsafe" in text for _, text in trace["events"])
    assert _count_messages(summary["log"]) > 10
