"""A stop signal to `cmnav fly` (what `systemctl stop` sends) in each phase, against the SITL
vehicle, real processes over loopback: the runtime commands the safe state itself (in offboard a
hover setpoint, then Hold; taking off, Hold; landing goes on, under the autopilot's Land) and
records the stop, and the
vehicle's offboard-loss failsafe never fires.  The SITL vehicle's failsafe is PX4's default
(COM_OBL_RC_ACT = 0: Position mode, which lands a vehicle without RC), so a runtime that left the
vehicle to it would show a "Failsafe" event and a landing here.

After the runtime exits, the test listens on the runtime's MAVLink port for longer than PX4's
COM_OF_LOSS_T (1 s): the vehicle must stay in the commanded state (or finish its landing).
"""

from __future__ import annotations

import json
import signal
import socket
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from pymavlink import mavutil

from sim.sitl.px4 import Px4Mode
from sim.sitl_session import free_port
from tests.e2e.fly_helpers import LOOPBACK, READY_TIMEOUT_S, NotifyListener, Sitl, finish_fly, fly_config, start_fly

pytestmark = pytest.mark.timeout(180)

PHASE_TIMEOUT_S = 60.0
OBSERVE_AFTER_EXIT_S = 2.5  # > COM_OF_LOSS_T (1 s) + one heartbeat period
LANDED_TIMEOUT_S = 20.0


def _wait(predicate, what: str, proc, tmp_path: Path) -> None:
    deadline = time.monotonic() + PHASE_TIMEOUT_S
    while not predicate():
        assert proc.poll() is None, f"cmnav fly exited ({proc.returncode}) before {what}:\n{_fly_log(tmp_path)}"
        assert time.monotonic() < deadline, f"{what} not reached:\n{_fly_log(tmp_path)}"
        time.sleep(0.02)


def _fly_log(tmp_path: Path) -> str:
    return (tmp_path / "fly.log").read_text(errors="replace")[-4000:]


def _heartbeats(port: int, duration_s: float, until=None) -> list[tuple[str, bool]]:
    """(mode, armed) of the vehicle's HEARTBEATs on ``port`` for ``duration_s`` (or until ``until``
    holds for one): the runtime has exited, so its port is free to listen on."""
    link = mavutil.mavlink_connection(f"udpin:{LOOPBACK}:{port}", source_system=255, source_component=190)
    seen: list[tuple[str, bool]] = []
    try:
        deadline = time.monotonic() + duration_s
        while time.monotonic() < deadline:
            msg = link.recv_match(type="HEARTBEAT", blocking=True, timeout=0.2)
            if msg is None or msg.get_srcComponent() != 1:
                continue
            seen.append((Px4Mode.from_custom_mode(msg.custom_mode).name, bool(msg.base_mode & 128)))
            if until is not None and until(seen[-1]):
                break
    finally:
        link.close()
    return seen


def _no_failsafe(sitl: Sitl) -> list[str]:
    events = [text for _, text in sitl.trace()["events"]]
    assert not any("ailsafe" in text for text in events), events
    return events


@pytest.mark.parametrize("phase", ["taking_off", "episode", "landing"])
def test_stop_signal_in_a_dry_run_ends_in_the_runtimes_safe_state(goal_seeker, tmp_path, phase):
    runtime_port = free_port(socket.SOCK_DGRAM)
    sitl = Sitl(tmp_path, runtime_port)
    notify = NotifyListener(tmp_path / "notify")
    proc = None
    try:
        goal = list(sitl.episode["goal_rel_home_enu_m"])
        if phase == "landing":  # a short flight that reaches its goal
            goal = [goal[0] / 2.0, goal[1] / 2.0, goal[2]]
        mission = f"allow_arm_takeoff = true\ntakeoff_alt_m = {sitl.episode['takeoff_alt_m']:.3f}\nmax_episodes = 1"
        proc = start_fly(tmp_path, fly_config(goal_seeker, runtime_port, sitl.camera_port, goal, tmp_path / "logs", mission), notify)
        if phase == "taking_off":
            _wait(lambda: sitl.modes()[-1:] == ["TAKEOFF"], "take-off", proc, tmp_path)
        elif phase == "episode":
            _wait(lambda: any(m.startswith("STATUS=episode 1: flying") for m in notify.messages), "the episode", proc, tmp_path)
            time.sleep(1.0)  # flying the policy
        else:  # the dry run's own landing in offboard (mission.land_in_offboard): the autopilot's Land finishes it
            _wait(lambda: any(m == "STATUS=dry run: landing in offboard" for m in notify.messages), "landing", proc, tmp_path)
            time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        if phase == "episode":
            time.sleep(0.05)
            proc.send_signal(signal.SIGINT)  # a second signal is harmless (in the loop: tests/runtime/test_signals.py)
        code, summary = finish_fly(proc, tmp_path)
        after = _heartbeats(runtime_port, OBSERVE_AFTER_EXIT_S if phase != "landing" else LANDED_TIMEOUT_S,
                            until=(lambda hb: not hb[1]) if phase == "landing" else None)  # fmt: skip
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        sitl.stop()
        notify.close()
    log_text = _fly_log(tmp_path)
    assert code == 0, f"exit {code}: {summary}\n{log_text}"
    stop = summary["stop"]
    assert stop["cause"] == "SIGTERM" and stop["phase"] == phase and stop["t_s"] > 0.0, stop
    assert f"stopped on SIGTERM while {phase}" in log_text
    assert "Traceback" not in log_text and "un-acquired" not in log_text
    modes = sitl.modes()
    events = _no_failsafe(sitl)
    assert after, "no heartbeat after the runtime exited"
    if phase == "landing":
        assert stop["action"] == "landing_continues"
        assert after[-1] == ("LAND", False) and "Disarmed by landing" in events, (after, events)
        return
    assert all(mode == "HOLD" for mode, _ in after), after  # still in Hold after COM_OF_LOSS_T: no failsafe
    if phase == "taking_off":
        assert stop["action"] == "hold" and modes[-2:] == ["TAKEOFF", "HOLD"], modes
        assert "OFFBOARD" not in modes
    else:
        assert stop["action"] == "hover_then_hold" and modes[-2:] == ["OFFBOARD", "HOLD"], modes
        assert "stopping on SIGTERM while episode: hover, then Hold" in log_text
        (episode,) = summary["episodes"]
        assert episode["outcome"] == "aborted" and episode["abort_reason"] == "stopped by SIGTERM"
        assert episode["frames"] > 0 and episode["time_s"] > 0.0
        assert {"event": "stop", "cause": "SIGTERM", "response": "hover_then_hold"}.items() <= _stop_event(episode["log"]).items()


def _stop_event(log_path: str) -> dict:
    """The episode's flight log records the stop on its /watchdog channel."""
    with open(log_path, "rb") as f:
        for _, _channel, message in make_reader(f).iter_messages(topics=["/watchdog"]):
            event = json.loads(message.data)
            if event["event"] == "stop":
                return event
    raise AssertionError(f"no stop event in {log_path}")


def test_stop_signal_while_waiting_for_the_pilot_leaves_the_vehicle_alone(goal_seeker, tmp_path):
    runtime_port = free_port(socket.SOCK_DGRAM)
    sitl = Sitl(tmp_path, runtime_port)
    notify = NotifyListener(tmp_path / "notify")
    proc = None
    try:
        config = fly_config(goal_seeker, runtime_port, sitl.camera_port, sitl.episode["goal_rel_home_enu_m"], tmp_path / "logs", "")
        proc = start_fly(tmp_path, config, notify)
        assert notify.ready.wait(READY_TIMEOUT_S), _fly_log(tmp_path)
        _wait(lambda: any("waiting for the pilot" in m for m in notify.messages), "waiting for the pilot", proc, tmp_path)
        proc.send_signal(signal.SIGTERM)
        code, summary = finish_fly(proc, tmp_path)
        after = _heartbeats(runtime_port, OBSERVE_AFTER_EXIT_S)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        sitl.stop()
        notify.close()
    assert code == 0, _fly_log(tmp_path)
    assert summary["stop"]["phase"] == "waiting_for_pilot" and summary["stop"]["action"] == "none", summary["stop"]
    assert summary["episodes"] == [] and summary["error"] == "stopped by SIGTERM"
    assert after and all(hb == ("HOLD", False) for hb in after), after  # never armed, never commanded
    assert sitl.modes() == ["HOLD"]
    _no_failsafe(sitl)


def test_stop_signal_while_connecting_is_recorded(goal_seeker, tmp_path):
    """No autopilot answers: the stop comes while MAVSDK waits for a heartbeat."""
    notify = NotifyListener(tmp_path / "notify")
    proc = None
    try:
        config = fly_config(goal_seeker, free_port(socket.SOCK_DGRAM), 9, [1.0, 0.0, 1.0], tmp_path / "logs", "")
        proc = start_fly(tmp_path, config.replace("[vehicle]\n", "[vehicle]\nconnect_timeout_s = 60.0\n"), notify)
        _wait(lambda: any(m.startswith("STATUS=connecting") for m in notify.messages), "connecting", proc, tmp_path)
        proc.send_signal(signal.SIGTERM)
        code, summary = finish_fly(proc, tmp_path)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        notify.close()
    assert code == 0, _fly_log(tmp_path)
    assert summary["stop"]["phase"] == "connecting" and summary["stop"]["action"] == "none"
    assert "STOPPING=1" in notify.messages
