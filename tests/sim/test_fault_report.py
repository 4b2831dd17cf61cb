"""Fault records measured on a synthetic ground-truth trace (sim.fault_report)."""

import numpy as np
import pytest

from runtime.faults.catalogue import FaultKind, Injection
from sim.fault_report import RuntimeSignal, fault_records, vehicle_failsafe_trip

T_OFFBOARD = 100.0


def _trace(speed_of_t, modes, injections=()):
    t = np.round(np.arange(90.0, 110.0, 0.05), 3)
    speed = np.array([speed_of_t(x) for x in t])
    return {
        "t_s": t.tolist(),
        "vel_enu_m_s": np.stack([speed, np.zeros_like(t), np.zeros_like(t)], axis=1).tolist(),
        "mode_log": [[90.0, "HOLD"], [T_OFFBOARD, "OFFBOARD"], *modes],
        "injections": [{"kind": k, "t_s": ts} for k, ts in injections],
    }


def test_camera_stall_record():
    # Stall at 102.0; the runtime's episode began 0.6 s after the vehicle's OFFBOARD entry and
    # tripped 0.25 s after the stall; the vehicle was below 0.2 m/s from 102.7 until landing.
    trace = _trace(lambda t: 1.5 if t < 102.7 else (0.05 if t < 104.0 else 0.7), [[103.25, "HOLD"], [104.0, "LAND"]],
                   [("camera-stall", 102.0)])  # fmt: skip
    flight = {"t_episode_start_s": 100.6, "watchdog_trips": [
        {"cause": "stale_frame", "t_s": 1.65, "detect_ms": 4.0, "response": "hover_then_hold", "hold_t_s": 2.65},
        {"cause": "bad_action", "t_s": 1.7, "detect_ms": 0.0, "response": "already_tripped", "hold_t_s": None}]}  # fmt: skip
    (record,) = fault_records((Injection(FaultKind.CAMERA_STALL, 2.0),), trace, flight, None)
    assert record == {
        "kind": "camera-stall", "at_s": 2.0, "injected": True, "t_inject_s": 2.0, "cause": "stale_frame",
        "detect_ms": 4.0, "response": "hover_then_hold", "trip_after_inject_ms": pytest.approx(250.0),
        "stopped_within_s": pytest.approx(0.7), "stopped_after_trip_s": pytest.approx(0.45), "hold_entered_s": 1.25,
        "hold_commanded_s": pytest.approx(1.25),
    }  # fmt: skip


def test_a_followed_autopilots_coarse_mode_log_takes_the_runtimes_hold():
    # The follower's mode log comes from PX4's 1 Hz HEARTBEAT: the runtime's Hold at 104.1 lasted
    # 20 ms before its landing, which the log shows only at 104.8; the descent (0.7 m/s) follows.
    trace = _trace(lambda t: 1.5 if t < 103.9 else (0.05 if t < 104.12 else 0.7), [[104.8, "LAND"]],
                   [("camera-stall", 102.0)])  # fmt: skip
    trace["mode_log_period_s"] = 1.0
    flight = {"t_episode_start_s": 100.6, "watchdog_trips": [
        {"cause": "stale_frame", "t_s": 1.65, "detect_ms": 4.0, "response": "hover_then_hold", "hold_t_s": 3.5}]}  # fmt: skip
    (record,) = fault_records((Injection(FaultKind.CAMERA_STALL, 2.0),), trace, flight, None)
    assert record["hold_entered_s"] is None and record["hold_commanded_s"] == pytest.approx(2.1)
    assert record["stopped_within_s"] == pytest.approx(1.9)  # stopped before the Hold; the descent is the landing's
    # Read as an exact mode log, the descent before the LAND sighting would count as never stopping.
    del trace["mode_log_period_s"]
    (record,) = fault_records((Injection(FaultKind.CAMERA_STALL, 2.0),), trace, flight, None)
    assert record["stopped_within_s"] is None


def test_a_fault_that_never_came_is_marked():
    trace = _trace(lambda t: 0.0, [[101.0, "HOLD"]])
    (record,) = fault_records((Injection(FaultKind.NAN_ACTION, 5.0),), trace, {"injections": []}, None)
    assert record["injected"] is False and record["cause"] is None and record["stopped_within_s"] is None


def test_runtime_kill_is_the_vehicles_failsafe():
    trace = _trace(lambda t: 1.2 if t < 103.4 else 0.1, [[103.05, "HOLD"]])
    (record,) = fault_records((Injection(FaultKind.RUNTIME_KILL, 2.0),), trace, {}, RuntimeSignal(FaultKind.RUNTIME_KILL, 102.0, 1e9))
    assert record["cause"] == "offboard_loss_failsafe" and record["response"] == "vehicle_failsafe"
    assert record["detect_ms"] == pytest.approx(1050.0) and record["hold_entered_s"] == pytest.approx(1.05)
    assert record["stopped_within_s"] == pytest.approx(1.4) and record["stopped_after_trip_s"] == pytest.approx(0.35)
    trip, t_hold = vehicle_failsafe_trip([(90.0, "HOLD"), (100.0, "OFFBOARD")], 102.0)
    assert trip is None and t_hold is None
    # PX4's default failsafe (COM_OBL_RC_ACT = 0): Position mode, which lands a vehicle without RC.
    trip, t_failsafe = vehicle_failsafe_trip([(100.0, "OFFBOARD"), (103.1, "POSCTL")], 102.0)
    assert trip["mode"] == "POSCTL" and trip["hold_t_s"] is None and t_failsafe == 103.1


def test_runtime_stop_is_the_runtimes_own_stop_and_the_vehicles_hold():
    # SIGTERM at 102.0 (wall clock 5000.0); the runtime's handler ran 30 ms later, braked, Hold at 103.4.
    trace = _trace(lambda t: 1.2 if t < 103.1 else 0.05, [[103.4, "HOLD"]])
    stop = {"cause": "SIGTERM", "phase": "episode", "action": "hover_then_hold", "t_s": 12.3, "time_unix_s": 5000.03}
    flight = {"t_episode_start_s": 100.6, "watchdog_trips": [], "stop": stop}
    signal = RuntimeSignal(FaultKind.RUNTIME_STOP, 102.0, 5000.0)
    (record,) = fault_records((Injection(FaultKind.RUNTIME_STOP, 2.0),), trace, flight, signal)
    assert record["injected"] and record["t_inject_s"] == pytest.approx(2.0) and record["stop"] == stop
    assert (record["cause"], record["response"]) == ("stop_signal", "hover_then_hold")
    assert record["detect_ms"] == pytest.approx(30.0) and record["trip_after_inject_ms"] == pytest.approx(30.0)
    assert record["hold_entered_s"] == pytest.approx(1.4) and record["stopped_within_s"] == pytest.approx(1.1)
    # A runtime that had ended before the signal recorded no stop: no trip, the vehicle's Hold still measured.
    (record,) = fault_records((Injection(FaultKind.RUNTIME_STOP, 2.0),), trace, dict(flight, stop=None), signal)
    assert record["injected"] and record["cause"] is None and record["hold_entered_s"] == pytest.approx(1.4)
    # The signal was never sent (the flight ended first).
    (record,) = fault_records((Injection(FaultKind.RUNTIME_STOP, 2.0),), trace, flight, None)
    assert record["injected"] is False and record["cause"] is None


def test_still_moving_at_the_end_never_stopped():
    trace = _trace(lambda t: 1.0, [], [("pilot-takeover", 102.0)])
    (record,) = fault_records((Injection(FaultKind.PILOT_TAKEOVER, 2.0),), trace, {}, None)
    assert record["stopped_within_s"] is None and record["cause"] is None and record["hold_entered_s"] is None


def test_already_stopped_and_holding_counts_from_the_injection():
    # offboard-refused: hovering in Hold after take-off when the refusal comes, landing 20 ms later.
    trace = _trace(lambda t: 0.01, [[103.02, "LAND"]], [("offboard-refused", 103.0)])
    trace["mode_log"] = [[90.0, "TAKEOFF"], [95.0, "HOLD"], [103.02, "LAND"]]
    flight = {"t_episode_start_s": 102.99, "watchdog_trips": [
        {"cause": "offboard_refused", "t_s": 0.013, "detect_ms": 13.0, "response": "hold", "hold_t_s": None}]}  # fmt: skip
    (record,) = fault_records((Injection(FaultKind.OFFBOARD_REFUSED, 0.0),), trace, flight, None)
    assert record["t_inject_s"] == 0.0 and record["cause"] == "offboard_refused" and record["response"] == "hold"
    assert record["stopped_within_s"] == 0.0 and record["hold_entered_s"] == 0.0
