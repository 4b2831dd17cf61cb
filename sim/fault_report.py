"""How a faulted SITL flight went, measured on ground truth (the SITL vehicle's trace) rather
than on what the runtime believed: for each injected fault, when it acted, which trip it caused
and how fast, what the response was, and when the vehicle had stopped and entered Hold.

All times in the inputs are time.monotonic seconds (the host clock both processes share):
the trace's ``t_s`` / ``mode_log`` / ``injections``, the runtime summary's ``t_episode_start_s``
(zero of its trips' ``t_s``) and ``injections``, and the orchestrator's signal time
(:class:`RuntimeSignal`) — save the runtime's stop record, stamped on the wall clock
(``time_unix_s``), which the signal's ``t_unix_s`` is compared with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.faults.catalogue import FaultKind, FaultSite, Injection

# Ground-truth speed below this counts as stopped (m/s): the fault tests' bound.
STOPPED_SPEED_M_S = 0.2
# A trip is matched to the first fault injected at most this long after it (s): the two clocks
# are one, but the trace samples positions every 50 ms.
MATCH_TOLERANCE_S = 0.05
VEHICLE_FAILSAFE_CAUSE = "offboard_loss_failsafe"
VEHICLE_FAILSAFE_RESPONSE = "vehicle_failsafe"
STOP_SIGNAL_CAUSE = "stop_signal"
_MEASURED = ("t_inject_s", "cause", "detect_ms", "response", "trip_after_inject_ms", "stopped_within_s",
             "stopped_after_trip_s", "hold_entered_s", "hold_commanded_s")  # fmt: skip


@dataclass(frozen=True)
class RuntimeSignal:
    """The signal ``cmnav sitl`` sent the runtime for an orchestrator fault (``runtime-kill``:
    SIGKILL, ``runtime-stop``: SIGTERM): when, on the monotonic clock (s) and the wall clock
    (unix s, the clock of the runtime's stop record)."""

    kind: FaultKind
    t_s: float
    t_unix_s: float


def fault_records(
    injections: tuple[Injection, ...], trace: dict, flight: dict, signal: RuntimeSignal | None
) -> list[dict]:
    """One record per injection: ``{kind, injected, t_inject_s, cause, detect_ms, response,
    trip_after_inject_ms, stopped_within_s, stopped_after_trip_s, hold_entered_s, hold_commanded_s}``.

    ``t_inject_s``: when the fault first acted, s after the vehicle entered OFFBOARD (0 for
    offboard-refused: the moment it refused).  ``detect_ms``: the runtime's own figure (condition
    true -> trip); ``trip_after_inject_ms``: injection -> trip on the common clock (includes the
    configured limit, e.g. the stale-frame time).  ``stopped_within_s``: injection -> the first
    moment from which the ground-truth speed stays below STOPPED_SPEED_M_S until the vehicle is
    commanded to land (or the trace ends); ``stopped_after_trip_s``: the same from the trip (0 if
    it had stopped before).  ``hold_entered_s``: injection -> the vehicle's first Hold after it,
    as its mode log shows; ``hold_commanded_s``: injection -> the runtime's Hold command that the
    autopilot accepted (its trip's ``hold_t_s``; null when it sent none: kill, stop, pilot).
    A mode log read from an external autopilot's HEARTBEAT (the follower's trace says
    ``mode_log_period_s``) sees each change up to one period late and misses a Hold shorter than a
    period (the runtime lands right after it): there ``hold_commanded_s`` says when Hold came, and
    the landing counts from the later of its sighting minus one period and the runtime's Hold
    (the runtime lands only after it).
    A fault whose time never came (the flight ended first) has ``injected`` false and nulls.
    runtime-kill's trip is the vehicle's own offboard-loss failsafe (the mode COM_OBL_RC_ACT selects;
    PX4's default Position mode lands a vehicle without RC), read from the mode log.
    runtime-stop's trip is the runtime's own stop (:func:`runtime_stop_trip`); its record adds
    ``stop``, the runtime's stop record (phase interrupted, action commanded).
    """
    t = np.asarray(trace["t_s"], dtype=np.float64)
    speed = np.linalg.norm(np.asarray(trace["vel_enu_m_s"], dtype=np.float64).reshape(-1, 3), axis=1)
    mode_log = [(float(tm), str(mode)) for tm, mode in trace["mode_log"]]
    t_offboard = next((tm for tm, mode in mode_log if mode == "OFFBOARD"), None)
    mode_log_period_s = float(trace.get("mode_log_period_s") or 0.0)
    acted = {
        FaultSite.VEHICLE: {d["kind"]: d["t_s"] for d in trace.get("injections", [])},
        FaultSite.RUNTIME: {d["kind"]: d["t_s"] for d in flight.get("injections", [])},
        FaultSite.ORCHESTRATOR: {} if signal is None else {signal.kind.value: signal.t_s},
    }
    records = []
    for injection in injections:
        t_inject = acted[injection.site].get(injection.kind.value)
        record: dict = {"kind": injection.kind.value, "at_s": injection.at_s, "injected": t_inject is not None}
        if t_inject is None:
            records.append(record | dict.fromkeys(_MEASURED))
            continue
        if injection.kind == FaultKind.RUNTIME_KILL:
            trip, t_trip = vehicle_failsafe_trip(mode_log, t_inject)
        elif injection.kind == FaultKind.RUNTIME_STOP:
            trip, t_trip = runtime_stop_trip(flight, signal)
            record["stop"] = flight.get("stop")
        else:
            trip, t_trip = runtime_trip_after(flight, t_inject)
        t_hold_commanded = None
        if trip is not None and trip.get("hold_t_s") is not None and trip["response"] != VEHICLE_FAILSAFE_RESPONSE:
            t_hold_commanded = float(flight["t_episode_start_s"]) + float(trip["hold_t_s"])
        t_land = _landing_commanded(mode_log, t_inject)
        if mode_log_period_s > 0.0 and math.isfinite(t_land):
            t_land = max(t_land - mode_log_period_s, t_inject, t_hold_commanded or -math.inf)
        t_stop = _stopped_from(t, speed, t_inject, t_land)
        t_hold = _hold_from(mode_log, t_inject)
        record.update(
            t_inject_s=_round(t_inject - t_offboard if t_offboard is not None else 0.0),
            cause=None if trip is None else trip["cause"],
            detect_ms=None if trip is None else trip["detect_ms"],
            response=None if trip is None else trip["response"],
            trip_after_inject_ms=None if t_trip is None else _round(1000.0 * (t_trip - t_inject)),
            stopped_within_s=None if t_stop is None else _round(t_stop - t_inject),
            stopped_after_trip_s=None if t_stop is None or t_trip is None else _round(max(0.0, t_stop - t_trip)),
            hold_entered_s=None if t_hold is None else _round(t_hold - t_inject),
            hold_commanded_s=None if t_hold_commanded is None else _round(t_hold_commanded - t_inject),
        )
        records.append(record)
    return records


def vehicle_failsafe_trip(mode_log: list[tuple[float, str]], t_kill_s: float) -> tuple[dict | None, float | None]:
    """The vehicle's own reaction to the runtime's death: its first mode change out of OFFBOARD
    after the kill (the offboard-loss failsafe: the mode COM_OBL_RC_ACT selects), as a trip record
    (``t_s`` from the kill, s; ``detect_ms`` kill -> failsafe; ``mode``: the failsafe's mode) and
    its time; (None, None) if it never left OFFBOARD."""
    change = next(((tm, mode) for tm, mode in mode_log if mode != "OFFBOARD" and tm >= t_kill_s), None)
    if change is None:
        return None, None
    t_failsafe, mode = change
    return {
        "cause": VEHICLE_FAILSAFE_CAUSE,
        "detail": "runtime killed (SIGKILL): setpoints stopped, the vehicle's offboard-loss failsafe "
        f"(COM_OF_LOSS_T, COM_OBL_RC_ACT) switched to {mode}; recorded by cmnav sitl from the vehicle's mode log",
        "t_s": _round(t_failsafe - t_kill_s),
        "detect_ms": _round(1000.0 * (t_failsafe - t_kill_s)),
        "response": VEHICLE_FAILSAFE_RESPONSE,
        "mode": mode,
        "hold_t_s": _round(t_failsafe - t_kill_s) if mode == "HOLD" else None,
    }, t_failsafe


def runtime_stop_trip(flight: dict, signal: RuntimeSignal) -> tuple[dict | None, float | None]:
    """The runtime's own stop on the orchestrator's SIGTERM, as a trip record: ``cause``
    STOP_SIGNAL_CAUSE, ``response`` the action it commanded (hover_then_hold in an episode),
    ``phase`` it interrupted, ``t_s`` / ``detect_ms`` signal sent -> the runtime's handler ran (wall clock);
    and that moment on the monotonic clock.  (None, None) if it recorded no stop (it had ended
    before the signal, or died)."""
    stop = flight.get("stop")
    if not stop or stop.get("time_unix_s") is None:
        return None, None
    delay_s = float(stop["time_unix_s"]) - signal.t_unix_s
    return {
        "cause": STOP_SIGNAL_CAUSE,
        "detail": f"{stop['cause']} from cmnav sitl (runtime-stop) while {stop['phase']}: the runtime's stop "
        f"handling commanded {stop['action']}",
        "phase": stop["phase"],
        "t_s": _round(delay_s),  # from the signal, as the failsafe's from the kill
        "detect_ms": _round(1000.0 * delay_s),
        "response": stop["action"],
        "hold_t_s": None,  # the vehicle's Hold is measured on ground truth: the record's hold_entered_s
    }, signal.t_s + delay_s


def runtime_trip_after(flight: dict, t_inject: float) -> tuple[dict | None, float | None]:
    """The runtime's first response-setting trip at or after ``t_inject``, and its time."""
    t0 = flight.get("t_episode_start_s")
    if t0 is None:
        return None, None
    for trip in flight.get("watchdog_trips", []):
        t_abs = t0 + trip["t_s"]
        if trip["response"] != "already_tripped" and t_abs >= t_inject - MATCH_TOLERANCE_S:
            return trip, t_abs
    return None, None


def _hold_from(mode_log: list[tuple[float, str]], t_from: float) -> float | None:
    """When the vehicle was in Hold at or after ``t_from`` (``t_from`` itself if it already was)."""
    current = [mode for tm, mode in mode_log if tm <= t_from][-1:]
    if current == ["HOLD"]:
        return t_from
    return next((tm for tm, mode in mode_log if mode == "HOLD" and tm >= t_from), None)


def _landing_commanded(mode_log: list[tuple[float, str]], t_from: float) -> float:
    """When the vehicle was next told to land after ``t_from`` (it then moves on purpose), else inf."""
    return next((tm for tm, mode in mode_log if mode == "LAND" and tm >= t_from), float("inf"))


def _stopped_from(t: np.ndarray, speed: np.ndarray, t_from: float, t_until: float) -> float | None:
    """The first time >= t_from from which speed < STOPPED_SPEED_M_S holds until t_until
    (exclusive) or the end of the trace; the sample just before t_from counts (t_from itself is
    returned when the vehicle was already stopped)."""
    first = max(int(np.searchsorted(t, t_from, side="right")) - 1, 0)
    window = np.arange(len(t)) >= first
    window &= t < t_until
    if not window.any():
        return None
    times, moving = t[window], speed[window] >= STOPPED_SPEED_M_S
    if moving[-1]:
        return None
    last_moving = np.flatnonzero(moving)
    return max(float(times[last_moving[-1] + 1] if len(last_moving) else times[0]), t_from)


def _round(value: float) -> float:
    return round(float(value), 3)
