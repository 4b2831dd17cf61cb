"""A bad radio day: `cmnav fly` dry runs through degraded links (``sim.linkfault``), the real
processes over loopback, each link script starting when the vehicle first reports OFFBOARD.

| scenario | expected |
|---|---|
| MAVLink: 20 % loss, 100 ms ± 30 ms delay, 10 % duplicated, 10 % held back 40 ms, both ways | the flight completes, no trip |
| MAVLink: 0.8 s blackout both ways (> telemetry_stale_ms, < COM_OF_LOSS_T) | stale_telemetry trip, hover, Hold once the link is back, no command sent after the trip |
| MAVLink: 2 s blackout both ways (> COM_OF_LOSS_T) | stale_telemetry trip, then the vehicle's own failsafe (Position mode), and the summary says so |
| camera: 2 lost frames, a partial frame, a reconnect, a 0.5 s stall | a gap over frame_stale_ms trips stale_frame, a shorter one does not; the log is complete and replays |

Whether a trip was due is judged from the flight log (gaps between valid frames, the age of the
state each command was computed from) against the configured limits, never against this
machine's speed.  The duplicated/reordered-telemetry rule (the state never goes back in time) is
checked on the vehicle adapter in ``tests/runtime/test_vehicle_ordering.py``.
"""

from __future__ import annotations

import re


import numpy as np
import pytest

from runtime.config import WatchdogConfig
from runtime.programs.replay import replay_log
from sim.linkfault import DROP_FRAMES, PARTIAL_FRAME, RECONNECT, STALL, Impairment, StreamFault
from tests.e2e.link_helpers import LinkFlight, fly_degraded, read_episode

pytestmark = pytest.mark.timeout(150)

WATCHDOG = WatchdogConfig()
COM_OF_LOSS_T_S = 1.0  # PX4's default offboard-loss time, as the SITL vehicle applies it
NS_PER_MS = 1_000_000


def _replays_completely(flight: LinkFlight) -> None:
    episode = flight.episode
    assert read_episode(episode["log"]).stopped_early is None
    report = replay_log(episode["log"])
    assert report.same_model and report.steps == episode["frames"] and report.stopped_early is None
    assert report.steps == 0 or report.max_abs_diff <= 1e-5


def _blackout_s(flight: LinkFlight) -> tuple[float, float]:
    """(first, last) datagram the MAVLink blackout swallowed toward the runtime (time.monotonic, s)."""
    stats = flight.mavlink.stats
    return stats.blackout_first_s["to_runtime"], stats.blackout_last_s["to_runtime"]


def test_lossy_delayed_duplicating_link_flies_without_a_false_trip(goal_seeker, tmp_path):
    lossy = Impairment(drop_frac=0.2, delay_ms=100.0, jitter_ms=30.0, duplicate_frac=0.1, reorder_frac=0.1)
    flight = fly_degraded(goal_seeker, tmp_path, [lossy], seed=3)
    assert flight.code == 0, f"exit {flight.code}: {flight.summary}\n{flight.log_text[-4000:]}"
    episode = flight.episode
    assert episode["outcome"] == "success" and episode["watchdog_trips"] == [], episode
    stats = flight.mavlink.stats
    for direction in ("to_runtime", "to_vehicle"):  # the link really was that bad, both ways
        assert 0.1 < stats.lost[direction] / stats.received[direction] < 0.3, stats
        assert stats.duplicated[direction] > 0 and stats.overtaken[direction] > 0, stats
    assert "landed and disarmed" in flight.log_text and "Traceback" not in flight.log_text
    _replays_completely(flight)


def test_blackout_past_telemetry_stale_trips_hovers_and_holds_once_the_link_is_back(goal_seeker, tmp_path):
    blackout_s = 0.8
    assert WATCHDOG.telemetry_stale_ms / 1000.0 < blackout_s < COM_OF_LOSS_T_S
    # From 3 s after the OFFBOARD entry: the climb's last metre (about 1 s, FlightLoop.climb) is over
    # and the episode flies.
    flight = fly_degraded(goal_seeker, tmp_path, [Impairment(start_s=3.0, end_s=3.0 + blackout_s, blackout=True)])
    episode = flight.episode
    assert episode["abort_reason"] == "stale_telemetry", f"{episode}\n{flight.log_text[-4000:]}"
    trip = episode["watchdog_trips"][0]
    assert (trip["cause"], trip["response"]) == ("stale_telemetry", "hover_then_hold") and trip["hold_t_s"] is not None
    assert len(episode["watchdog_trips"]) == 1, episode["watchdog_trips"]  # no pilot take-over, no failsafe

    logged = read_episode(episode["log"])
    (t_trip_ns, _), = logged.trips
    (t_hold_ns, _), = logged.holds
    _, t_last_lost_s = _blackout_s(flight)
    # Hold was commanded once the link was back (its command got through: the vehicle shows HOLD).
    assert t_hold_ns > t_last_lost_s * 1e9
    modes = flight.sitl.modes()
    assert modes[modes.index("OFFBOARD") + 1:] == ["HOLD", "LAND"], modes
    # No command after the trip, and none computed from state older than telemetry_stale_ms: the
    # policy step checks the state's age itself before it computes (runtime.flight).
    assert all(t_cmd < t_trip_ns for _, t_cmd, _ in logged.sent)
    ages = [age for t_step, _, age in logged.sent if age is not None]
    assert ages and max(ages) <= WATCHDOG.telemetry_stale_ms, max(ages)
    assert "landed and disarmed" in flight.log_text
    _replays_completely(flight)


def test_blackout_past_com_of_loss_t_ends_in_the_vehicles_failsafe(goal_seeker, tmp_path):
    flight = fly_degraded(goal_seeker, tmp_path, [Impairment(start_s=1.5, end_s=3.5, blackout=True)])
    episode = flight.episode
    trips = episode["watchdog_trips"]
    assert episode["abort_reason"] == "stale_telemetry" and trips[0]["cause"] == "stale_telemetry", f"{episode}\n{flight.log_text[-4000:]}"
    # The vehicle saw no setpoint for COM_OF_LOSS_T: its failsafe (Position mode, PX4's default
    # COM_OBL_RC_ACT) took it out of OFFBOARD before the runtime's Hold could arrive.
    modes = flight.sitl.modes()
    after = modes[modes.index("OFFBOARD") + 1:]
    assert after and after[0] == "POSCTL" and "HOLD" not in after, modes
    assert trips[0]["hold_t_s"] is None  # the runtime's Hold never took effect
    assert len(trips) == 2, trips
    # The summary says which happened: the autopilot's failsafe, not a pilot; and the dry run,
    # not handing over to anyone, lands the vehicle.
    assert (trips[1]["cause"], trips[1]["response"]) == ("offboard_loss_failsafe", "vehicle_failsafe"), trips
    assert "landed and disarmed" in flight.log_text
    _replays_completely(flight)


def test_camera_link_faults_are_rejected_or_tripped_by_the_watchdogs_rules(goal_seeker, tmp_path):
    # Least disruptive first: whichever fault trips ends the episode.
    faults = [StreamFault(0.5, DROP_FRAMES, count=2), StreamFault(1.3, RECONNECT), StreamFault(2.1, PARTIAL_FRAME),
              StreamFault(2.9, STALL, duration_s=0.5)]  # fmt: skip
    flight = fly_degraded(goal_seeker, tmp_path, stream_faults=faults)
    episode = flight.episode
    applied = [kind for kind, _ in flight.camera.stats.applied]
    trips = episode["watchdog_trips"]
    logged = read_episode(episode["log"])
    t_end_ns = logged.trips[0][0] if logged.trips else max(logged.frames_ns)
    frames = [t for t in logged.frames_ns if logged.t_start_ns <= t <= t_end_ns]
    gaps_ms = np.diff([logged.t_start_ns, *frames, t_end_ns]) / NS_PER_MS
    if trips:
        # Tripped on the camera, and only when the newest frame it had was older than the limit. The
        # log stamps frames with their capture time: a frame held back on its way (the stall
        # blocking the sender, or a runtime starved of CPU on loaded cores) is logged with no gap
        # before it, so the age is the watchdog's own, from the trip's detail.
        assert trips[0]["cause"] == "stale_frame" and trips[0]["response"] == "hover_then_hold", trips
        age_ms = float(re.match(r"newest frame (\d+) ms old", trips[0]["detail"]).group(1))
        assert age_ms >= WATCHDOG.frame_stale_ms, trips[0]
        assert np.all(gaps_ms[:-1] <= WATCHDOG.frame_stale_ms + 2 * 1000.0 * WATCHDOG.period_s), gaps_ms
        assert trips[0]["hold_t_s"] is not None
    else:
        assert episode["outcome"] == "success", episode
        assert np.all(gaps_ms <= WATCHDOG.frame_stale_ms + 2 * 1000.0 * WATCHDOG.period_s), gaps_ms
    # The faults acted in order; a torn frame is refused as not a frame and the link re-opened.
    assert applied == [f.kind for f in faults][: len(applied)] and applied[:2] == [DROP_FRAMES, RECONNECT], applied
    assert flight.camera.stats.connections >= 2
    if PARTIAL_FRAME in applied:
        assert "decode errors so far: 1" in flight.log_text
    assert "landed and disarmed" in flight.log_text and "Traceback" not in flight.log_text
    _replays_completely(flight)
