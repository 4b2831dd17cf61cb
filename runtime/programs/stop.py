"""Stopping a flight program on SIGTERM / SIGINT, whatever it is doing: the one place that decides
what the vehicle is told, for ``cmnav fly`` and the SITL dry run (``runtime.programs.sitl``) alike.

The programs say which :class:`Phase` they are in *before* each step (``FlightPhase.enter``), and
nothing resets it in cleanup code: the decision reads the phase the signal interrupted, plus the
flight mode telemetry reports (offboard is left safely whoever entered it).

- in offboard, entering it or in an episode (its brake and retreat after the goal included): hover
  setpoint, then Hold at once (``FlightLoop.safe_stop``);
- taking off: Hold where the vehicle is (the climb stops);
- arming: disarm if armed and still on the ground;
- landing: the autopilot's landing is the safe state and goes on; where the runtime was landing in
  offboard (``FlightLoop.descend``), the autopilot's Land is commanded to finish it;
- connecting, waiting for health / the camera / the pilot, after Hold: nothing to command;
- the pilot took over: nothing (the vehicle is theirs).

Never left to the autopilot's offboard-loss failsafe: PX4's default (COM_OBL_RC_ACT = 0, Position
mode) lands a vehicle that has no RC input where it is.
"""

from __future__ import annotations

import logging
import time
from enum import Enum
from typing import TYPE_CHECKING

from ..state import MODE_OFFBOARD, VehicleError

if TYPE_CHECKING:
    from ..flight import FlightLoop
    from ..service.signals import StopSignals
    from ..vehicle import Vehicle

log = logging.getLogger(__name__)


class Phase(str, Enum):
    """What a flight program is doing (``stop.phase`` in its summary)."""

    STARTING = "starting"  # config, model, log directory
    CONNECTING = "connecting"
    WAITING_FOR_HEALTH = "waiting_for_health"
    WAITING_FOR_CAMERA = "waiting_for_camera"
    WAITING_FOR_PILOT = "waiting_for_pilot"
    ARMING = "arming"
    TAKING_OFF = "taking_off"
    ENTERING_OFFBOARD = "entering_offboard"
    EPISODE = "episode"
    HOLDING = "holding"  # the episode ended and Hold was commanded
    LANDING = "landing"
    DONE = "done"


class Action(str, Enum):
    """What the runtime commanded on the stop (``stop.action``)."""

    HOVER_THEN_HOLD = "hover_then_hold"
    HOLD = "hold"
    DISARM = "disarm"
    LANDING_CONTINUES = "landing_continues"
    PILOT_HAS_IT = "none_pilot_has_the_vehicle"
    NOTHING = "none"


class FlightPhase:
    """The current phase, entered before each step and never cleared by cleanup code."""

    def __init__(self) -> None:
        self.phase = Phase.STARTING

    def enter(self, phase: Phase) -> None:
        if phase != self.phase:
            log.debug("phase %s -> %s", self.phase.value, phase.value)
            self.phase = phase


async def command_safe_state(phase: Phase, loop: FlightLoop | None, vehicle: Vehicle | None) -> Action:
    """Command the safe state for a stop that interrupted ``phase`` (see the module doc); every
    command has the vehicle's command timeout, so this returns within a few seconds."""
    if loop is None or vehicle is None:
        return Action.NOTHING
    if loop.gate.released or loop.watchdog.pilot_took_over:
        return Action.PILOT_HAS_IT
    state = vehicle.state()
    try:
        # Where the runtime commanded the mode itself it trusts its command: telemetry shows a mode
        # change up to one HEARTBEAT (1 s) late, and a landing must not be turned into a Hold.
        if phase in (Phase.ENTERING_OFFBOARD, Phase.EPISODE):
            await loop.safe_stop()
            return Action.HOVER_THEN_HOLD
        if phase == Phase.TAKING_OFF:
            await vehicle.hold()
            return Action.HOLD
        if phase == Phase.LANDING:
            if loop.landing_in_offboard and state.armed:
                await vehicle.land()  # the runtime's own landing in offboard: the autopilot's Land finishes it
            return Action.LANDING_CONTINUES
        if phase == Phase.ARMING and state.armed and not state.in_air:
            await vehicle.disarm()
            return Action.DISARM
        if phase != Phase.ARMING and state.flight_mode == MODE_OFFBOARD:
            # Offboard that a pilot selected, or one just left (a repeated Hold is harmless).
            await loop.safe_stop()
            return Action.HOVER_THEN_HOLD
    except VehicleError as err:
        log.error("the safe stop's command failed (%s): the autopilot's own failsafe decides now", err)
    return Action.NOTHING


async def stop_on_signal(
    signals: StopSignals, flight: FlightPhase, loop: FlightLoop | None, vehicle: Vehicle | None, t_start_ns: int
) -> dict:
    """The safe stop after a stop signal: command the safe state, log it (text log and, when an
    episode is being recorded, the flight log's ``/watchdog`` channel) and return the summary's
    ``stop`` record ``{cause, phase, action, t_s (s since t_start_ns), time_unix_s}``."""
    phase = flight.phase
    cause = signals.received or "cancelled"
    log.warning("stopping on %s while %s: %s", cause, phase.value, _DOING.get(phase, "nothing to command"))
    action = await command_safe_state(phase, loop, vehicle)
    t_ns = signals.t_monotonic_ns or time.monotonic_ns()
    record = {
        "cause": cause,
        "phase": phase.value,
        "action": action.value,
        "t_s": round((t_ns - t_start_ns) / 1e9, 3),
        "time_unix_s": round(signals.t_unix_s or time.time(), 6),  # microseconds: a handler can run within 1 ms of the signal
    }
    log.warning("stopped on %s while %s: %s", cause, phase.value, action.value)
    if loop is not None and loop.recorder is not None:
        loop.recorder.log_watchdog(time.monotonic_ns(), {
            "event": "stop", "cause": cause, "detail": f"stop signal while {phase.value}", "t_s": record["t_s"],
            "detect_ms": None, "response": action.value, "hold_t_s": None,
        })  # fmt: skip
    flight.enter(Phase.DONE)
    return record


_DOING = {
    Phase.ENTERING_OFFBOARD: "hover, then Hold",
    Phase.EPISODE: "hover, then Hold",
    Phase.TAKING_OFF: "Hold where the vehicle is",
    Phase.ARMING: "disarm if still on the ground",
    Phase.LANDING: "the autopilot goes on landing (its Land, where the runtime landed in offboard)",
}
