"""`cmnav fly` (dry run, SITL vehicle, real processes) with a log disk that is full before
offboard or fills during it.  The recorder is an observer: a full disk before offboard refuses
offboard with a clear reason and lands (``recorder.required = true``, the default) or flies
unrecorded (``false``); a disk that fills in flight costs the log, never the flight.

The full disk is the process's file-size limit (RLIMIT_FSIZE): every write past it fails with
EFBIG where a full disk fails with ENOSPC — the same I/O error through foxglove's writer, for any
user and without mounting anything (tests/runtime/test_recorder.py also fills a real tmpfs where
it may mount one).
"""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from sim.sitl_session import free_port
from tests.e2e.fly_helpers import (
    READY_TIMEOUT_S, NotifyListener, Sitl, finish_fly, fly_config, pilot_rig, start_fly,
)  # fmt: skip

pytestmark = pytest.mark.timeout(180)

NOTHING_FITS = 0
ABOUT_A_SECOND_OF_LOG = 300_000  # bytes: the metadata fits, the camera frames soon do not


def _dry_run(goal_seeker: Path, tmp_path: Path, limit_bytes: int, recorder: str = "") -> tuple[int, dict, str, dict]:
    runtime_port = free_port(socket.SOCK_DGRAM)
    sitl = Sitl(tmp_path, runtime_port)
    notify = NotifyListener(tmp_path / "notify")
    try:
        gx, gy, gz = sitl.episode["goal_rel_home_enu_m"]
        mission = f"allow_arm_takeoff = true\ntakeoff_alt_m = {sitl.episode['takeoff_alt_m']:.3f}\nmax_episodes = 1"
        config = fly_config(goal_seeker, runtime_port, sitl.camera_port, [gx / 2.0, gy / 2.0, gz], tmp_path / "logs", mission)
        code, summary = finish_fly(start_fly(tmp_path, config + recorder, notify, file_size_limit_bytes=limit_bytes), tmp_path)
    finally:
        sitl.stop()
        notify.close()
    return code, summary, (tmp_path / "fly.log").read_text(errors="replace"), sitl.trace()


def _landed_without_failsafe(trace: dict) -> list[str]:
    events = [text for _, text in trace["events"]]
    assert "Disarmed by landing" in events and not any("ailsafe" in text for text in events), events
    return [mode for _, mode in trace["mode_log"]]


def test_full_disk_before_offboard_refuses_offboard_and_lands(goal_seeker, tmp_path):
    code, summary, log_text, trace = _dry_run(goal_seeker, tmp_path, NOTHING_FITS)
    assert code == 2, f"{summary}\n{log_text[-3000:]}"
    assert summary["error"].startswith("offboard refused: the flight log cannot be written"), summary["error"]
    assert "recorder.required = true" in summary["error"] and summary["log_error"]
    assert summary["episodes"] == [] and "Traceback" not in log_text
    modes = _landed_without_failsafe(trace)
    assert "OFFBOARD" not in modes and modes[-1] == "LAND", modes


def test_full_disk_before_offboard_flies_unrecorded_when_not_required(goal_seeker, tmp_path):
    code, summary, log_text, trace = _dry_run(goal_seeker, tmp_path, NOTHING_FITS, "required = false\n")
    assert code == 0, f"{summary}\n{log_text[-3000:]}"
    (episode,) = summary["episodes"]
    assert episode["outcome"] == "success" and episode["log"] is None and summary["log_error"]
    assert "is not recorded (recorder.required = false)" in log_text
    assert "OFFBOARD" in _landed_without_failsafe(trace)


def test_disk_full_in_offboard_costs_the_log_not_the_flight(goal_seeker, tmp_path):
    code, summary, log_text, trace = _dry_run(goal_seeker, tmp_path, ABOUT_A_SECOND_OF_LOG)
    assert code == 0, f"{summary}\n{log_text[-3000:]}"
    (episode,) = summary["episodes"]
    assert episode["outcome"] == "success" and episode["watchdog_trips"] == []
    assert episode["log_error"] and episode["log_records_dropped"] > 0 and summary["log_error"] == episode["log_error"]
    assert log_text.count("flight log: writing") == 1  # logged once
    assert "Traceback" not in log_text and "landed and disarmed" in log_text
    assert "OFFBOARD" in _landed_without_failsafe(trace)


def test_full_disk_answers_the_pilots_switch_to_offboard_with_hold(goal_seeker, tmp_path):
    """Pilot mode: the pilot's switch into offboard cannot be prevented, only answered — the runtime
    hovers and commands Hold at once, records the refusal, and never flies the policy."""
    with pilot_rig(tmp_path) as rig:
        runtime_port, sitl, notify, pilot = rig.runtime_port, rig.sitl, rig.notify, rig.pilot
        config = fly_config(goal_seeker, runtime_port, sitl.camera_port, sitl.episode["goal_rel_home_enu_m"], tmp_path / "logs",
                            "max_episodes = 1")  # fmt: skip
        rig.proc = proc = start_fly(tmp_path, config, notify, file_size_limit_bytes=NOTHING_FITS)
        assert notify.ready.wait(READY_TIMEOUT_S), "no READY"
        pilot.wait(lambda: pilot.heartbeat is not None, 10.0, "vehicle heartbeat")
        pilot.arm_and_take_off(sitl.episode["takeoff_alt_m"])
        pilot.switch_to_offboard()
        code, summary = finish_fly(proc, tmp_path)
        pilot.wait(pilot.in_hold, 10.0, "Hold commanded by the runtime")
    log_text = (tmp_path / "fly.log").read_text(errors="replace")
    assert code == 0, f"{summary}\n{log_text[-3000:]}"
    (episode,) = summary["episodes"]
    assert episode["outcome"] == "refused" and "the flight log cannot be written" in episode["abort_reason"]
    assert "episode 1 refused, hover then Hold" in log_text and "Traceback" not in log_text
    trace = sitl.trace()
    modes = [mode for _, mode in trace["mode_log"]]
    assert modes[-2:] == ["OFFBOARD", "HOLD"], modes
    assert not any("ailsafe" in text for _, text in trace["events"])
