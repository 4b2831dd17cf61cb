"""Fault injection on fake clocks: every trip -> hover at once, Hold after the grace period."""

import asyncio
import dataclasses

import numpy as np
import pytest

from runtime.command_gate import CommandGate
from runtime.config import ConfigError, WatchdogConfig
from runtime.contract import HOVER, VelocityBodyYawspeed
from runtime.contract.frames import quat_from_euler
from runtime.state import STATUS_TEXTS_KEPT, StatusText, append_status_text
from runtime.state import VehicleState
from runtime.watchdog import Response, TripCause, WatchInputs, Watchdog

MS = 1_000_000
T0 = 10_000 * MS
CFG = WatchdogConfig(
    frame_stale_ms=250.0, step_trip_ms=133.0, telemetry_stale_ms=500.0, depth_invalid_frac_max=0.9,
    depth_invalid_max_s=1.0, geofence_radius_m=10.0, altitude_min_m=0.3, altitude_max_m=5.0, hold_grace_s=1.0,
)  # fmt: skip


class FakeVehicle:
    def __init__(self):
        self.calls: list[tuple[str, object]] = []

    async def set_velocity_body(self, cmd: VelocityBodyYawspeed) -> None:
        self.calls.append(("setpoint", cmd))

    async def stop_offboard(self) -> None:
        self.calls.append(("hold", None))


def _state(t_ns: int, pos=(1.0, 2.0, 1.5), mode="OFFBOARD", t_mode_ns=None) -> VehicleState:
    return VehicleState(
        pos_enu_m=np.array(pos), vel_enu_m_s=np.zeros(3), t_posvel_ns=t_ns, t_att_ns=t_ns, t_angvel_ns=t_ns,
        flight_mode=mode, t_mode_ns=T0 if t_mode_ns is None else t_mode_ns, armed=True, in_air=True,
        home_enu_m=np.array([1.0, 2.0, 0.0]),
    )  # fmt: skip


class Rig:
    """A watchdog supervising a healthy flight from T0; ``healthy(now)`` = fresh frame and telemetry."""

    def __init__(self, config=CFG):
        self.vehicle = FakeVehicle()
        self.events: list[dict] = []
        self.watchdog = Watchdog(config, CommandGate(self.vehicle), on_event=self.events.append)
        self.watchdog.start(T0, _state(T0))

    def inputs(self, now, frame_ns=None, step_ns=0, **state_changes) -> WatchInputs:
        state = dataclasses.replace(_state(now), **state_changes)
        return WatchInputs(now_ns=now, t_last_frame_capture_ns=now if frame_ns is None else frame_ns,
                           t_step_started_ns=step_ns, vehicle=state)  # fmt: skip

    async def tick(self, now, **kw):
        return await self.watchdog.tick(self.inputs(now, **kw))


def run(coro):
    return asyncio.run(coro)


def _assert_hover_then_hold(rig: Rig, trip, t_trip_ns: int):
    assert trip is not None and trip.response == Response.HOVER_THEN_HOLD
    assert rig.vehicle.calls == [("setpoint", HOVER)]  # hover at once
    assert not rig.watchdog.gate.policy_open


async def _finish_grace(rig: Rig, t_trip_ns: int, **kw):
    await rig.tick(t_trip_ns + 900 * MS, **kw)
    assert ("hold", None) not in rig.vehicle.calls  # still inside the grace period
    await rig.tick(t_trip_ns + 1_001 * MS, **kw)
    calls = rig.vehicle.calls  # hover at once, the brake's setpoints at the control rate, Hold
    assert calls[0] == ("setpoint", HOVER) and calls[-1] == ("hold", None), calls
    assert len(calls) > 2 and all(kind == "setpoint" for kind, _ in calls[1:-1]), calls
    assert rig.watchdog.tripped.hold_t_ns == t_trip_ns + 1_001 * MS
    assert [e["event"] for e in rig.events] == ["trip", "hold"]


def test_healthy_flight_never_trips():
    async def main():
        rig = Rig()
        for k in range(200):
            assert await rig.tick(T0 + k * 20 * MS) is None
        assert rig.vehicle.calls == [] and rig.watchdog.gate.policy_open

    run(main())


def test_stale_frame():
    async def main():
        rig = Rig()
        last_frame = T0 + 100 * MS
        assert await rig.tick(T0 + 340 * MS, frame_ns=last_frame) is None
        now = T0 + 360 * MS
        trip = await rig.tick(now, frame_ns=last_frame)
        assert trip.cause == TripCause.STALE_FRAME
        assert trip.detect_ms == pytest.approx(10.0)  # threshold crossed at 350 ms, seen at 360 ms
        _assert_hover_then_hold(rig, trip, now)
        await _finish_grace(rig, now, frame_ns=last_frame)
        assert rig.events[0]["cause"] == "stale_frame" and rig.events[0]["t_s"] == pytest.approx(0.36)

    run(main())


def test_no_frame_at_all_after_start():
    async def main():
        rig = Rig()
        trip = await rig.tick(T0 + 260 * MS, frame_ns=0)
        assert trip.cause == TripCause.STALE_FRAME and trip.detect_ms == pytest.approx(10.0)

    run(main())


def test_nan_and_inf_action():
    for bad in (np.nan, np.inf):

        async def main():
            rig = Rig()
            action = np.array([0.1, bad, 0.0])
            assert await rig.watchdog.check_action(np.zeros(3), T0, T0 + 5 * MS) is None
            trip = await rig.watchdog.check_action(action, T0 + 100 * MS, T0 + 110 * MS)
            assert trip.cause == TripCause.BAD_ACTION and trip.detect_ms == 0.0
            _assert_hover_then_hold(rig, trip, T0 + 110 * MS)
            await _finish_grace(rig, T0 + 110 * MS)

        run(main())


def test_step_over_deadline_at_check_and_while_hung():
    async def main():
        rig = Rig()
        trip = await rig.watchdog.check_action(np.zeros(3), T0, T0 + 150 * MS)
        assert trip.cause == TripCause.STEP_DEADLINE and trip.detect_ms == pytest.approx(17.0)
        _assert_hover_then_hold(rig, trip, T0 + 150 * MS)

        hung = Rig()  # the step never returns: the periodic check catches it
        assert await hung.tick(T0 + 120 * MS, step_ns=T0) is None
        trip = await hung.tick(T0 + 140 * MS, step_ns=T0)
        assert trip.cause == TripCause.STEP_DEADLINE and trip.detect_ms == pytest.approx(7.0)
        await _finish_grace(hung, T0 + 140 * MS, step_ns=T0)

    run(main())


def test_stale_telemetry():
    async def main():
        rig = Rig()
        t_tel = T0 + 50 * MS
        trip = await rig.tick(T0 + 560 * MS, t_posvel_ns=t_tel, t_att_ns=T0 + 540 * MS)
        assert trip.cause == TripCause.STALE_TELEMETRY and trip.detect_ms == pytest.approx(10.0)
        _assert_hover_then_hold(rig, trip, T0 + 560 * MS)

    run(main())


def test_pilot_left_offboard_stops_commanding_at_once():
    async def main():
        rig = Rig()
        t_mode = T0 + 2_000 * MS
        assert await rig.tick(T0 + 1_990 * MS) is None
        trip = await rig.tick(T0 + 2_015 * MS, flight_mode="POSCTL", t_mode_ns=t_mode)
        assert trip.cause == TripCause.PILOT_LEFT_OFFBOARD and trip.response == Response.STOP_COMMANDING
        assert trip.detect_ms == pytest.approx(15.0)
        assert rig.watchdog.gate.released and rig.vehicle.calls == []
        # Nothing more is sent: no hover, no Hold, no policy setpoint, whatever else goes wrong.
        assert not await rig.watchdog.gate.send_policy(HOVER)
        for k in range(100):
            await rig.tick(T0 + 2_020 * MS + k * 50 * MS, frame_ns=T0, flight_mode="POSCTL", t_mode_ns=t_mode)
        assert rig.vehicle.calls == []
        assert [e["cause"] for e in rig.events] == ["pilot_left_offboard"]

    run(main())


def test_pilot_takeover_during_grace_cancels_hold():
    async def main():
        rig = Rig()
        trip = await rig.tick(T0 + 300 * MS, frame_ns=T0)
        assert trip.cause == TripCause.STALE_FRAME
        await rig.tick(T0 + 500 * MS, frame_ns=T0, flight_mode="ALTCTL", t_mode_ns=T0 + 480 * MS)
        await rig.tick(T0 + 2_000 * MS, frame_ns=T0, flight_mode="ALTCTL", t_mode_ns=T0 + 480 * MS)
        assert rig.vehicle.calls == [("setpoint", HOVER)]
        assert rig.watchdog.pilot_took_over

    run(main())


def test_mode_lag_right_after_offboard_start_is_not_a_takeover():
    async def main():
        rig = Rig()
        rig.watchdog.start(T0, _state(T0, mode="HOLD", t_mode_ns=T0 - 500 * MS))
        assert await rig.tick(T0 + 100 * MS, flight_mode="HOLD", t_mode_ns=T0 - 500 * MS) is None
        assert await rig.tick(T0 + 300 * MS, flight_mode="OFFBOARD", t_mode_ns=T0 + 290 * MS) is None
        trip = await rig.tick(T0 + 400 * MS, flight_mode="HOLD", t_mode_ns=T0 + 390 * MS)
        assert trip.cause == TripCause.PILOT_LEFT_OFFBOARD

    run(main())


def test_our_own_hold_is_not_a_takeover():
    async def main():
        rig = Rig()
        now = T0 + 300 * MS
        await rig.tick(now, frame_ns=T0)
        await rig.tick(now + 1_100 * MS, frame_ns=T0)
        assert rig.vehicle.calls[-1] == ("hold", None)
        assert await rig.tick(now + 1_300 * MS, frame_ns=T0, flight_mode="HOLD", t_mode_ns=now + 1_200 * MS) is None
        assert not rig.watchdog.pilot_took_over

    run(main())


def test_depth_invalid_too_long():
    async def main():
        rig = Rig()
        for k in range(10):  # mostly invalid, but a good frame resets the timer
            rig.watchdog.note_depth(T0 + k * 66 * MS, 0.95 if k != 5 else 0.2)
            assert await rig.tick(T0 + k * 66 * MS) is None
        t_bad = T0 + 6 * 66 * MS
        for k in range(6, 30):
            rig.watchdog.note_depth(T0 + k * 66 * MS, 0.97)
        assert await rig.tick(t_bad + 990 * MS) is None
        trip = await rig.tick(t_bad + 1_012 * MS)
        assert trip.cause == TripCause.DEPTH_INVALID and trip.detect_ms == pytest.approx(12.0)
        _assert_hover_then_hold(rig, trip, t_bad + 1_012 * MS)

    run(main())


@pytest.mark.parametrize(
    "pos, detail",
    [((12.0, 2.0, 1.5), "from start"), ((1.0, 2.0, 0.1), "above home"), ((1.0, 2.0, 6.0), "above home")],
)
def test_geofence(pos, detail):
    async def main():
        rig = Rig()
        now = T0 + 500 * MS
        trip = await rig.tick(now, pos_enu_m=np.array(pos), t_posvel_ns=now - 3 * MS)
        assert trip.cause == TripCause.GEOFENCE and detail in trip.detail
        assert trip.detect_ms == pytest.approx(3.0)
        _assert_hover_then_hold(rig, trip, now)

    run(main())


def test_only_first_fault_sets_the_response_and_stop_ends_supervision():
    async def main():
        rig = Rig()
        await rig.tick(T0 + 300 * MS, frame_ns=T0)
        later = await rig.watchdog.check_action(np.array([np.nan, 0, 0]), T0 + 310 * MS, T0 + 320 * MS)
        assert later.response == Response.ALREADY_TRIPPED
        assert rig.vehicle.calls == [("setpoint", HOVER)]
        assert rig.watchdog.tripped.cause == TripCause.STALE_FRAME

        quiet = Rig()
        quiet.watchdog.stop()
        assert await quiet.tick(T0 + 10_000 * MS, frame_ns=0, flight_mode="HOLD", t_mode_ns=T0 + 9_000 * MS) is None
        assert quiet.vehicle.calls == []

    run(main())


def test_start_needs_position_and_home():
    rig = Rig()
    with pytest.raises(ValueError, match="home position"):
        rig.watchdog.start(T0, dataclasses.replace(_state(T0), home_enu_m=None))


def test_only_rejected_frames_trip_as_bad_frames():
    async def main():
        rig = Rig()
        last_valid = T0 + 100 * MS
        inputs = dataclasses.replace(rig.inputs(T0 + 360 * MS, frame_ns=last_valid), frames_rejected=4,
                                     last_rejection="capture time 10.000 s in the future")  # fmt: skip
        trip = await rig.watchdog.tick(inputs)
        assert trip.cause == TripCause.BAD_FRAMES and trip.detect_ms == pytest.approx(10.0)
        assert "4 frames rejected" in trip.detail and "in the future" in trip.detail
        _assert_hover_then_hold(rig, trip, T0 + 360 * MS)

    run(main())


@pytest.mark.parametrize("goal, detail", [((12.0, 2.0, 1.5), "from start"), ((1.0, 2.0, 7.0), "goal height")])
def test_goal_outside_the_geofence_is_refused_at_start(goal, detail):
    async def main():
        rig = Rig()
        assert await rig.watchdog.check_goal(np.array([9.0, 5.0, 1.5]), T0) is None  # inside
        trip = await rig.watchdog.check_goal(np.array(goal), T0 + 1 * MS)
        assert trip.cause == TripCause.GEOFENCE and detail in trip.detail and "refused" in trip.detail
        _assert_hover_then_hold(rig, trip, T0 + 1 * MS)
        await _finish_grace(rig, T0 + 1 * MS)

    run(main())


def test_shrunk_geofence_trips_on_the_next_position():
    async def main():
        rig = Rig()
        pos = np.array([3.0, 2.0, 1.5])  # 2 m from the start (1, 2)
        assert await rig.tick(T0 + 100 * MS, pos_enu_m=pos) is None
        rig.watchdog.set_geofence_radius(1.0)
        trip = await rig.tick(T0 + 120 * MS, pos_enu_m=pos, t_posvel_ns=T0 + 115 * MS)
        assert trip.cause == TripCause.GEOFENCE and "> 1.0 m" in trip.detail
        np.testing.assert_array_equal(rig.watchdog.start_xy_enu_m, [1.0, 2.0])
        with pytest.raises(ConfigError, match="watchdog.geofence_radius_m"):
            rig.watchdog.set_geofence_radius(0.0)

    run(main())


def test_refused_start_is_recorded_without_commanding():
    rig = Rig()
    t_request = T0 + 5_000 * MS
    trip = rig.watchdog.refuse_start(TripCause.OFFBOARD_REFUSED, "offboard denied", t_request, t_request + 42 * MS)
    assert trip.response == Response.HOLD and trip.detect_ms == pytest.approx(42.0)
    assert rig.watchdog.records() == [{"cause": "offboard_refused", "detail": "offboard denied", "t_s": 0.042,
                                       "detect_ms": 42.0, "response": "hold", "hold_t_s": None}]  # fmt: skip
    assert rig.vehicle.calls == [] and not rig.watchdog.supervising
    assert [e["event"] for e in rig.events] == ["trip"]


# ---- the outcome: tracking, attitude, the autopilot's own word -------------------------------


def test_tracking_trips_once_the_error_stayed_above_the_bound_for_the_window():
    async def main():
        rig = Rig()
        rig.watchdog.note_command(T0, np.array([2.0, 0.0, 0.0, 0.0]))  # 2 m/s forward; the vehicle stays put
        # The lagged reference passes the bound at lag ln(2 / (2 - bound)).
        t_over = T0 + int(CFG.tracking_lag_s * np.log(2.0 / (2.0 - CFG.tracking_error_max_m_s)) * 1e9)
        t_trip = t_over + int(CFG.tracking_window_s * 1e9)
        now, trip = T0, None
        while trip is None:
            now += 20 * MS
            trip = await rig.tick(now)
            assert trip is None or now > t_trip
        assert now - t_trip <= 20 * MS + 20 * MS  # the first check past the window (over_since is a sample time)
        assert trip.cause == TripCause.TRACKING and "does not follow" in trip.detail
        assert trip.detect_ms <= 40.0
        _assert_hover_then_hold(rig, trip, now)
        await _finish_grace(rig, now)

    run(main())


def test_tracking_error_that_recovers_inside_the_window_does_not_trip():
    async def main():
        rig = Rig()
        rig.watchdog.note_command(T0, np.array([2.0, 0.0, 0.0, 0.0]))
        for k in range(1, 60):  # 1.2 s standing still: over the bound for ~0.95 s < the window
            assert await rig.tick(T0 + k * 20 * MS) is None
        for k in range(60, 400):  # then it flies at 1.6 m/s (a real PX4's level for 2.0 m/s)
            assert await rig.tick(T0 + k * 20 * MS, vel_enu_m_s=np.array([1.6, 0.0, 0.0])) is None

    run(main())


def test_attitude_beyond_the_tilt_bound_trips_after_its_window():
    async def main():
        rig = Rig()
        leaning = quat_from_euler(np.radians(CFG.tilt_max_deg - 5.0), 0.0, 0.3)
        for k in range(1, 100):
            assert await rig.tick(T0 + k * 20 * MS, quat_enu_flu=leaning) is None
        flipped = quat_from_euler(np.radians(170.0), 0.0, 0.3)
        t_flip = T0 + 100 * 20 * MS
        now, trip = t_flip, None
        while trip is None:
            trip = await rig.tick(now, quat_enu_flu=flipped)
            assert trip is None or now - t_flip > CFG.tilt_window_s * 1e9
            now += 20 * MS
        assert trip.cause == TripCause.ATTITUDE and "170 deg" in trip.detail
        _assert_hover_then_hold(rig, trip, now)

    run(main())


def test_critical_status_text_is_a_vehicle_fault_at_once():
    async def main():
        rig = Rig()
        old = (StatusText(1, T0 - 5 * MS, "CRITICAL", "before the episode"),)  # not this episode's
        rig.watchdog.start(T0, dataclasses.replace(_state(T0), status_texts=old))
        texts = (*old, StatusText(2, T0 + 100 * MS, "WARNING", "low battery"))
        assert await rig.tick(T0 + 120 * MS, status_texts=texts) is None
        texts = (*texts, StatusText(3, T0 + 200 * MS, "CRITICAL", "collision: obstacle 1"))
        trip = await rig.tick(T0 + 215 * MS, status_texts=texts)
        assert trip.cause == TripCause.VEHICLE_FAULT and trip.detail == "autopilot CRITICAL: collision: obstacle 1"
        assert trip.detect_ms == pytest.approx(15.0)
        _assert_hover_then_hold(rig, trip, T0 + 215 * MS)
        await _finish_grace(rig, T0 + 215 * MS, status_texts=texts)

    run(main())


def test_disarm_in_flight_is_a_vehicle_fault():
    async def main():
        rig = Rig()
        assert await rig.tick(T0 + 100 * MS) is None
        trip = await rig.tick(T0 + 140 * MS, armed=False, t_armed_ns=T0 + 130 * MS)
        assert trip.cause == TripCause.VEHICLE_FAULT and "disarmed" in trip.detail
        assert trip.detect_ms == pytest.approx(10.0)

    run(main())


def test_status_text_severities():
    assert [StatusText(1, 0, s, "").is_fault for s in ("EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING", "INFO")] == [
        True, True, True, False, False, False]  # fmt: skip
    kept = ()
    for k in range(40):
        kept = append_status_text(kept, k, "INFO", f"m{k}")
    assert len(kept) == STATUS_TEXTS_KEPT and kept[-1].seq == 40 and kept[0].text == f"m{40 - STATUS_TEXTS_KEPT}"


def test_offboard_left_after_a_link_gap_past_com_of_loss_t_is_the_autopilots_failsafe():
    """The link (telemetry and, with it, the setpoints) was down longer than offboard_loss_s:
    the mode change seen when it returns is the autopilot's offboard-loss failsafe, not a pilot."""

    async def main():
        rig = Rig()
        t_last = T0 + 1_000 * MS
        assert await rig.tick(T0 + 1_000 * MS, t_posvel_ns=t_last, t_att_ns=t_last) is None
        stale = await rig.tick(T0 + 1_520 * MS, t_posvel_ns=t_last, t_att_ns=t_last)
        assert stale.cause == TripCause.STALE_TELEMETRY
        t_back = T0 + 2_300 * MS  # 1.3 s without telemetry
        trip = await rig.tick(T0 + 2_310 * MS, t_posvel_ns=t_back, t_att_ns=t_back, flight_mode="POSCTL", t_mode_ns=t_back)
        assert trip.cause == TripCause.OFFBOARD_LOSS_FAILSAFE and trip.response == Response.VEHICLE_FAILSAFE
        assert rig.watchdog.gate.released and not rig.watchdog.pilot_took_over
        assert ("hold", None) not in rig.vehicle.calls

    run(main())


def test_a_short_gap_then_a_mode_change_is_still_the_pilot():
    async def main():
        rig = Rig()
        t_last = T0 + 1_000 * MS
        assert await rig.tick(T0 + 1_000 * MS, t_posvel_ns=t_last, t_att_ns=t_last) is None
        await rig.tick(T0 + 1_520 * MS, t_posvel_ns=t_last, t_att_ns=t_last)  # stale: tripped
        t_back = T0 + 1_600 * MS  # 0.6 s gap < offboard_loss_s
        trip = await rig.tick(T0 + 1_610 * MS, t_posvel_ns=t_back, t_att_ns=t_back, flight_mode="POSCTL", t_mode_ns=t_back)
        assert trip.cause == TripCause.PILOT_LEFT_OFFBOARD

    run(main())
