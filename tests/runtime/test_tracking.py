"""The tracking check (runtime.tracking): reference = lagged command, error above a bound for
longer than a window.  Properties over command sequences: a vehicle that follows its commands the
way a real PX4 does (slower, short of the commanded speed, drifting in height) never trips; one
that stops following trips, and not before the window has passed."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.config import ConfigError, WatchdogConfig
from runtime.contract import ActionLimits, action_to_velocity_flu
from runtime.contract.constants import CONTROL_PERIOD_S, MAX_YAW_RATE_RAD_S
from runtime.contract.frames import quat_from_euler, vehicle_to_world_enu
from runtime.tracking import OverBound, TrackingMonitor, tilt_rad

NS = 1_000_000_000
T0 = 50 * NS
CFG = WatchdogConfig()  # the shipped defaults are what the properties are about
TICK_S = 0.02  # telemetry / watchdog period


def _monitor() -> TrackingMonitor:
    monitor = TrackingMonitor(CFG.tracking_error_max_m_s, CFG.tracking_lag_s, CFG.tracking_window_s)
    monitor.start(T0, np.zeros(3), 0.0)
    return monitor


def _ns(t_s: float) -> int:
    return T0 + int(round(t_s * NS))


def test_reference_is_the_lagged_command_in_the_world_frame():
    monitor = _monitor()
    monitor.command(T0, np.array([2.0, 0.0, 0.0]))
    status = monitor.update(_ns(CFG.tracking_lag_s), np.zeros(3), 0.0)  # one time constant later
    np.testing.assert_allclose(monitor.reference_enu_m_s, [2.0 * (1 - math.exp(-1)), 0, 0], atol=1e-9)
    assert status.error_m_s == pytest.approx(2.0 * (1 - math.exp(-1)))
    # Forward in the vehicle frame is north when the vehicle faces north (yaw pi/2 from east).
    monitor = _monitor()
    monitor.update(T0, np.zeros(3), math.pi / 2)
    monitor.command(T0, np.array([1.0, 0.0, 0.5]))
    monitor.update(_ns(10.0), np.zeros(3), math.pi / 2)
    np.testing.assert_allclose(monitor.reference_enu_m_s, [0.0, 1.0, 0.5], atol=1e-6)


def test_error_above_the_bound_counts_from_when_it_crossed_and_resets_below():
    monitor = _monitor()
    monitor.command(T0, np.array([2.0, 0.0, 0.0]))
    crossed = None
    for k in range(1, 200):
        status = monitor.update(_ns(k * TICK_S), np.zeros(3), 0.0)  # the vehicle does not move
        if status.over_since_ns is not None and crossed is None:
            crossed = k
        assert (status.over_since_ns is not None) == (status.error_m_s > CFG.tracking_error_max_m_s)
    # 2 (1 - exp(-t / lag)) > 0.8 from t = lag ln(2 / 1.2)
    assert crossed * TICK_S == pytest.approx(CFG.tracking_lag_s * math.log(2.0 / 1.2), abs=TICK_S)
    assert status.over_since_ns == _ns(crossed * TICK_S)
    status = monitor.update(_ns(200 * TICK_S), np.array([1.8, 0.0, 0.0]), 0.0)  # moving again
    assert status.over_since_ns is None
    nan = monitor.update(_ns(201 * TICK_S), np.full(3, np.nan), 0.0)  # no measurement: not a tracking error
    assert nan.over_since_ns is None


def test_sustained_peak_is_the_largest_error_held_for_a_whole_window():
    monitor = _monitor()
    errors = [0.3] * 10 + [1.5] * 3 + [0.6] * 60 + [0.2] * 5  # samples 0.1 s apart; window 1 s
    for k, error in enumerate(errors):
        monitor.update(_ns(0.1 * k), np.array([-error, 0.0, 0.0]), 0.0)  # reference stays zero
    assert monitor.sustained_peak_m_s == pytest.approx(0.6)  # the 1.5 spike lasted 0.3 s


def test_tilt():
    assert tilt_rad(quat_from_euler(0.0, 0.0, 2.0)) == pytest.approx(0.0, abs=1e-7)
    assert tilt_rad(quat_from_euler(0.3, 0.0, 1.0)) == pytest.approx(0.3)
    assert tilt_rad(quat_from_euler(0.0, -0.5, -2.0)) == pytest.approx(0.5)
    assert tilt_rad(quat_from_euler(math.pi, 0.0, 0.0)) == pytest.approx(math.pi)
    assert math.isnan(tilt_rad(np.zeros(4)))


@pytest.mark.parametrize(
    "key, value",
    [("tracking_error_max_m_s", 0.05), ("tracking_error_max_m_s", 2.5), ("tracking_window_s", 0.0),
     ("tracking_lag_s", 0.0), ("tracking_lag_s", 3.0), ("tilt_max_deg", 30.0), ("tilt_max_deg", 180.0),
     ("tilt_window_s", -1.0)],
)  # fmt: skip
def test_config_ranges_are_validated(key, value):
    with pytest.raises(ConfigError, match=f"watchdog.{key}"):
        WatchdogConfig(**{key: value})


# ---- properties over command sequences ------------------------------------------------------

# Policy commands: actions held for 1..15 control periods, mapped by the contract.
_actions = st.lists(
    st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1), st.integers(1, 15)), min_size=1, max_size=60
)


def _fly(actions, follow, t_end_s: float, stuck_at_s: float | None = None, min_speed_m_s: float = 0.0):
    """Fly the command sequence against ``follow(vel_enu, target_enu, dt) -> vel_enu``; returns
    (first time over the bound for longer than the window (s) or None, max error, the largest
    error sustained for a window)."""
    monitor = _monitor()
    vel_enu, yaw, t_s, max_error = np.zeros(3), 0.0, 0.0, 0.0
    schedule = []
    for a1, a2, a3, periods in actions:
        cmd = action_to_velocity_flu(np.array([a1, a2, a3]), ActionLimits())
        speed = float(np.linalg.norm(cmd[:3]))
        if speed < min_speed_m_s:  # as slow, in the same direction (forward if it was zero)
            cmd[:3] = cmd[:3] * (min_speed_m_s / speed) if speed > 1e-6 else [min_speed_m_s, 0.0, 0.0]
        schedule += [cmd] * periods
    next_cmd_s, k = 0.0, 0
    cmd = np.zeros(4)
    window_ns = int(CFG.tracking_window_s * NS)
    while t_s < t_end_s:
        if t_s >= next_cmd_s:
            cmd = schedule[min(k, len(schedule) - 1)]
            monitor.command(_ns(t_s), cmd[:3])
            k, next_cmd_s = k + 1, next_cmd_s + CONTROL_PERIOD_S
        t_s += TICK_S
        yaw += cmd[3] * TICK_S
        target = vehicle_to_world_enu(cmd[:3], yaw)
        stuck = stuck_at_s is not None and t_s >= stuck_at_s
        vel_enu = np.zeros(3) if stuck else follow(vel_enu, target, TICK_S)
        status = monitor.update(_ns(t_s), vel_enu, yaw)
        max_error = max(max_error, status.error_m_s)
        if status.over_since_ns is not None and _ns(t_s) - status.over_since_ns > window_ns:
            return t_s, max_error, monitor.sustained_peak_m_s
    return None, max_error, monitor.sustained_peak_m_s


@settings(max_examples=150, deadline=None)
@given(
    actions=_actions,
    lag_s=st.floats(0.2, 0.8),
    gain=st.floats(0.8, 1.0),
    drift_up_m_s=st.floats(-0.3, 0.3),
)
def test_a_vehicle_that_follows_like_px4_never_trips(actions, lag_s, gain, drift_up_m_s):
    """Slower (lag 0.2-0.8 s) and short of the command (80-100 %: PX4 levels 2.0 m/s at ~1.6) with
    a height drift of up to 0.3 m/s (PX4 drifted 1.2-1.5 m in 5 s): no trip."""

    def follow(vel, target, dt):
        goal = gain * target + np.array([0.0, 0.0, drift_up_m_s])
        return goal + (vel - goal) * math.exp(-dt / lag_s)

    trip_s, max_error, sustained_m_s = _fly(actions, follow, t_end_s=10.0)
    assert trip_s is None, f"tripped at {trip_s:.2f} s (max error {max_error:.2f} m/s)"
    assert sustained_m_s <= CFG.tracking_error_max_m_s


@settings(max_examples=100, deadline=None)
@given(
    cruise=st.tuples(st.floats(-1, 1), st.floats(-1, 1)),
    turns=st.lists(st.tuples(st.floats(-1, 1), st.integers(1, 15)), min_size=1, max_size=60),
    stuck_at_s=st.floats(0.0, 6.0),
)
def test_a_vehicle_that_stops_following_trips_after_the_window(cruise, turns, stuck_at_s):
    """Commanded a steady cruise of at least 1 m/s (the goal-seeker's) while turning at any yaw
    rate, and stopped from ``stuck_at_s``: the trip comes after the window (never before: until
    then it followed exactly) and within the time the reference needs to pass the bound, plus the
    window.  (A command that reverses its direction would let the lagged reference pass through
    zero and start its rise again: no bound holds for that, so the speed and inclination are held.)"""
    actions = [(*cruise, yaw_rate, periods) for yaw_rate, periods in turns]

    def follow(vel, target, dt):  # the monitor's own model: zero error until stuck
        return target + (vel - target) * math.exp(-dt / CFG.tracking_lag_s)

    trip_s, _, sustained_m_s = _fly(actions, follow, t_end_s=stuck_at_s + 5.0, stuck_at_s=stuck_at_s, min_speed_m_s=1.0)
    assert trip_s is not None and sustained_m_s > CFG.tracking_error_max_m_s
    assert trip_s > stuck_at_s + CFG.tracking_window_s
    # The reference of a 1 m/s command turning at the contract's top yaw rate settles at amplitude
    # 1 / sqrt(1 + (rate lag)^2) (0.89 m/s); from rest it passes the bound within lag ln(A / (A - bound)).
    amplitude = 1.0 / math.hypot(1.0, MAX_YAW_RATE_RAD_S * CFG.tracking_lag_s)
    rise_s = CFG.tracking_lag_s * math.log(amplitude / (amplitude - CFG.tracking_error_max_m_s))
    assert trip_s <= stuck_at_s + rise_s + CFG.tracking_window_s + 2 * TICK_S


def test_over_bound_holds_only_without_a_break():
    over = OverBound()
    assert not over.held_past(0, 10)
    over.update(100, True)
    over.update(150, True)  # still over: the start stays at 100
    assert over.since_ns == 100 and not over.held_past(60, 160) and over.held_past(60, 161)
    over.update(170, False)  # a break resets it
    assert over.since_ns is None and not over.held_past(0, 10_000)
    over.update(200, True)
    assert over.since_ns == 200
    over.reset()
    assert over.since_ns is None
