"""`cmnav fly --config` against the SITL vehicle, real processes over loopback.

- Dry run (``allow_arm_takeoff = true``): the runtime arms, takes off, flies to the goal and lands
  (and lands without flying when the autopilot refuses offboard);
  systemd's READY / WATCHDOG / STATUS arrive on a NOTIFY_SOCKET set here; the episode's log
  replays to the recorded actions.
- Pilot mode (the default): the runtime only flies.  A pilot — pymavlink here, behind a small UDP
  router like mavlink-router on a real vehicle — arms, takes off and switches to offboard; the
  runtime then flies to the goal and commands Hold.
"""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from runtime.programs.replay import replay_log
from sim.sitl_session import free_port
from tests.e2e.fly_helpers import READY_TIMEOUT_S, NotifyListener, Sitl, finish_fly, fly_config, pilot_rig, start_fly

pytestmark = pytest.mark.timeout(180)


def _near_goal(sitl: Sitl) -> list[float]:
    """Half way to the world's goal, at its height: inside the room, a short flight."""
    gx, gy, gz = sitl.episode["goal_rel_home_enu_m"]
    return [gx / 2.0, gy / 2.0, gz]


def _fly_dry_run(goal_seeker: Path, tmp_path: Path, inject: tuple[str, ...] = ()) -> tuple[int, dict, str, Sitl, list[str]]:
    """`cmnav fly` with ``allow_arm_takeoff = true`` against a SITL vehicle (with its ``inject``ed
    faults): exit code, summary, runtime log, the (stopped) vehicle and the sd_notify messages."""
    runtime_port = free_port(socket.SOCK_DGRAM)
    sitl = Sitl(tmp_path, runtime_port, inject=inject)
    notify = NotifyListener(tmp_path / "notify")
    try:
        mission = f"allow_arm_takeoff = true\ntakeoff_alt_m = {sitl.episode['takeoff_alt_m']:.3f}\nmax_episodes = 1"
        config = fly_config(goal_seeker, runtime_port, sitl.camera_port, _near_goal(sitl), tmp_path / "logs", mission)
        code, summary = finish_fly(start_fly(tmp_path, config, notify), tmp_path)
    finally:
        sitl.stop()
        notify.close()
    return code, summary, (tmp_path / "fly.log").read_text(), sitl, notify.messages


def test_dry_run_flies_to_the_goal_notifies_systemd_and_replays(goal_seeker, tmp_path):
    code, summary, log_text, _, messages = _fly_dry_run(goal_seeker, tmp_path)
    assert code == 0, f"exit {code}: {summary}\n{log_text[-4000:]}"
    (episode,) = summary["episodes"]
    assert episode["outcome"] == "success" and episode["watchdog_trips"] == [] and episode["frames"] > 10
    assert "landed and disarmed" in log_text

    assert next(m for m in messages if m.startswith("STATUS=")).startswith("STATUS=connecting to the autopilot")
    ready = next(i for i, m in enumerate(messages) if m.startswith("READY=1"))
    assert any(m.startswith("STATUS=episode 1: flying to the goal") for m in messages[ready:])
    assert "WATCHDOG=1" in messages[ready:]  # the flight loop fed systemd's watchdog
    assert messages[-1] == "STOPPING=1"

    report = replay_log(episode["log"])
    assert report.same_model and report.steps == episode["frames"]
    assert report.max_abs_diff <= 1e-5


def test_dry_run_lands_when_the_autopilot_refuses_offboard(goal_seeker, tmp_path):
    """The episode script (``runtime.programs.episode``) that ``cmnav sitl`` flies too: the refusal
    is the episode's trip, Hold, then the landing; the policy never flies."""
    code, summary, log_text, sitl, _ = _fly_dry_run(goal_seeker, tmp_path, inject=("offboard-refused@0",))
    assert code == 1, f"exit {code}: {summary}\n{log_text[-4000:]}"
    (episode,) = summary["episodes"]
    assert (episode["outcome"], episode["abort_reason"], episode["frames"]) == ("aborted", "offboard_refused", 0)
    assert [t["cause"] for t in episode["watchdog_trips"]] == ["offboard_refused"]
    assert episode["log"] is not None and Path(episode["log"]).exists()
    assert "landed and disarmed" in log_text and "Traceback" not in log_text
    assert sitl.modes()[-1] == "LAND", sitl.modes()


def test_pilot_mode_waits_for_the_pilot_then_flies(goal_seeker, tmp_path):
    with pilot_rig(tmp_path) as rig:
        runtime_port, sitl, notify, pilot = rig.runtime_port, rig.sitl, rig.notify, rig.pilot
        config = fly_config(goal_seeker, runtime_port, sitl.camera_port, _near_goal(sitl), tmp_path / "logs", "max_episodes = 1")
        rig.proc = proc = start_fly(tmp_path, config, notify)
        assert notify.ready.wait(READY_TIMEOUT_S), f"no READY:\n{(tmp_path / 'fly.log').read_text()[-3000:]}"
        pilot.wait(lambda: pilot.heartbeat is not None, 10.0, "vehicle heartbeat")
        assert not pilot.heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED  # the runtime did not arm
        pilot.arm_and_take_off(sitl.episode["takeoff_alt_m"])
        assert proc.poll() is None
        assert any("waiting for the pilot" in m for m in notify.messages)
        # Accepted only because the runtime streams setpoints while it waits (PX4's rule).
        pilot.switch_to_offboard()
        code, summary = finish_fly(proc, tmp_path)
        pilot.wait(pilot.in_hold, 10.0, "Hold after the episode")
    assert code == 0, f"exit {code}: {summary}\n{(tmp_path / 'fly.log').read_text()[-4000:]}"
    (episode,) = summary["episodes"]
    assert episode["outcome"] == "success" and episode["watchdog_trips"] == []
    assert "WATCHDOG=1" in notify.messages
