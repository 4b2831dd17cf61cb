"""The dry-run episode script, the one sequence both flight programs fly when the runtime arms by
itself: ``cmnav fly`` with ``mission.allow_arm_takeoff = true`` and the SITL flight
(``cmnav sitl``).

connect → wait for health (armable, local position, home) → first camera frame → arm → take off
(and wait for Hold at the takeoff height) → [the program's last check before offboard] → hover
setpoint, offboard → fly the policy (after the last goal: back along the path flown, then down in
offboard, ``FlightLoop.fly``'s ``landing_next``) → pilot check → land, wait for disarm.  With several episodes
(``cmnav fly``'s mission waypoints) the part from the program's check to the pilot check repeats
for each, from Hold, while each reaches its goal.

- The autopilot refuses offboard (or never shows it): the trip is recorded (``offboard_refused``),
  Hold is commanded, the vehicle lands, nothing is flown.
- The program withholds offboard (:class:`OffboardWithheld`, e.g. its flight log cannot be
  written): the vehicle lands, the exception goes on to the program.
- The pilot took over during the episode: nothing more is commanded; the vehicle is theirs.
- A ``vehicle_fault`` trip with the vehicle disarmed (a crash): there is nothing to land.

Every step enters its :class:`runtime.programs.stop.Phase` first, so a stop signal at any moment is
answered with that phase's safe state (``runtime.programs.stop``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Awaitable, Callable, TypeVar

import numpy as np

from ..contract import HOVER
from ..flight import EpisodeResult, FlightLoop
from ..state import MODE_OFFBOARD, VehicleError, VehicleState
from ..vehicle import Vehicle
from ..watchdog import TAKEOFF_HOLD_SHORT_M, TripCause, measured_speed_m_s
from .stop import FlightPhase, Phase

log = logging.getLogger(__name__)

T = TypeVar("T")

DISARM_REPORT_TIMEOUT_S = 1.5  # after a vehicle fault: a crashed vehicle's disarm shows within a HEARTBEAT


class EpisodeError(RuntimeError):
    """The episode could not be run; the message names the cause and what to check."""


class OffboardWithheld(RuntimeError):
    """Raised by a program's check before offboard: land without entering it."""


async def _await(awaitable: Awaitable[T]) -> T:
    return await awaitable


def _log_status(text: str) -> None:
    log.info("%s", text)


class EpisodeScript:
    """The sequence above on one vehicle and flight loop.

    ``status`` reports each step (the field program also tells systemd); ``alive_while`` awaits a
    long wait (each has its own timeout) while the program reports itself alive; ``flight`` is the
    program's phase, read by its stop-signal handler."""

    def __init__(
        self,
        vehicle: Vehicle,
        loop: FlightLoop,
        flight: FlightPhase,
        status: Callable[[str], None] = _log_status,
        alive_while: Callable[[Awaitable], Awaitable] = _await,
    ) -> None:
        self.vehicle = vehicle
        self.loop = loop
        self.flight = flight
        self.status = status
        self.alive_while = alive_while
        self.takeoff_climb: dict | None = None  # FlightLoop.climb's record, once the dry run climbed
        loop.on_landing = self._landing_in_offboard

    def _landing_in_offboard(self) -> None:
        self.flight.enter(Phase.LANDING)
        self.status("dry run: landing in offboard")

    async def start(self, first_frame_timeout_s: float, camera_name: str, no_frame_fix: Callable[[], str]) -> VehicleState:
        """Connect, start the flight loop (camera), wait for health and the first frame;
        :class:`EpisodeError` if no frame comes in time (``no_frame_fix()`` says what to check)."""
        self.status(f"connecting to the autopilot on {self.vehicle.config.url}")
        self.flight.enter(Phase.CONNECTING)
        await self.alive_while(self.vehicle.connect())
        await self.loop.start()
        self.status("waiting for autopilot health (armable, local position, home)")
        self.flight.enter(Phase.WAITING_FOR_HEALTH)
        state = await self.alive_while(self.vehicle.wait_ready())
        log.info("vehicle ready: home %s (local ENU m)", np.round(state.home_enu_m, 2))
        self.flight.enter(Phase.WAITING_FOR_CAMERA)
        self.status(f"waiting for the first {camera_name} camera frame")
        try:
            await self.alive_while(self.loop.wait_first_frame(first_frame_timeout_s))
        except asyncio.TimeoutError as err:
            raise EpisodeError(f"no {camera_name} camera frame within {first_frame_timeout_s} s: {no_frame_fix()}") from err
        return state

    async def dry_run(
        self,
        takeoff_alt_m: float,
        fly: Callable[[VehicleState], Awaitable[EpisodeResult]],
        before_offboard: Callable[[], Awaitable[None] | None],
        on_refused: Callable[[EpisodeResult, int], Awaitable[None]],
        episodes: int = 1,
    ) -> EpisodeResult:
        """Arm, take off (the autopilot's take-off to its Hold, up to ``TAKEOFF_HOLD_SHORT_M`` short),
        ``before_offboard()`` (may raise :class:`OffboardWithheld`: land, re-raise), offboard, the
        rest of the climb (``FlightLoop.climb``, its record in ``takeoff_climb``), ``fly(state in
        offboard)``, pilot check, land.  If the autopilot refuses offboard,
        ``on_refused(result, t_request_ns)`` records the unflown episode before the landing.

        ``episodes`` > 1 (a mission's waypoints): after each episode that reached its goal (the
        flight loop ends it in Hold), ``before_offboard`` and offboard again for the next one, in
        the same flight; any other outcome lands.  Returns the last episode's result."""
        self.status(f"dry run: arming and taking off to {takeoff_alt_m:.2f} m")
        self.flight.enter(Phase.ARMING)
        await self.vehicle.arm()
        self.flight.enter(Phase.TAKING_OFF)
        await self.vehicle.takeoff(takeoff_alt_m)
        await self.alive_while(self.vehicle.wait_takeoff_done(takeoff_alt_m, TAKEOFF_HOLD_SHORT_M))
        for index in range(episodes):
            if index > 0:
                # The telemetry shows a mode change up to a HEARTBEAT late: wait for the Hold, so
                # that the next offboard seen is the new one (an old OFFBOARD would end it at once).
                await self.alive_while(self.vehicle.wait_until(
                    lambda s: s.flight_mode != MODE_OFFBOARD, self.vehicle.config.command_timeout_s, "Hold between episodes"))  # fmt: skip
            try:
                if (pending := before_offboard()) is not None:
                    await pending
            except OffboardWithheld as err:
                log.error("not entering offboard: %s; landing", err)
                await self.land()
                raise
            self.flight.enter(Phase.ENTERING_OFFBOARD)
            t_request_ns = time.monotonic_ns()
            try:
                await self.vehicle.start_offboard(HOVER)
                state = await self.alive_while(
                    self.vehicle.wait_until(lambda s: s.flight_mode == MODE_OFFBOARD, self.vehicle.config.command_timeout_s, "offboard mode")
                )
            except VehicleError as err:
                result = await self._offboard_refused(err, t_request_ns)
                await on_refused(result, t_request_ns)
                await self.land()
                return result
            if index == 0:  # the rest of the take-off, under the runtime's position hold
                self.takeoff_climb = await self.loop.climb(takeoff_alt_m)
                if self.takeoff_climb is None:
                    log.warning("the pilot took over during the climb: not flying, the vehicle is theirs")
                    return self._unflown(TripCause.PILOT_LEFT_OFFBOARD.value)
                state = self.vehicle.state()
            self.flight.enter(Phase.EPISODE)
            result = await fly(state)
            self.flight.enter(Phase.HOLDING)
            if self.loop.watchdog.pilot_took_over or self.loop.handed_over_after_goal:  # in flight, or in the retreat or landing after it
                log.warning("the pilot took over: not landing, the vehicle is theirs")
                return result
            if result.abort_reason == TripCause.VEHICLE_FAULT.value and not await self._still_armed():
                log.warning("the autopilot reported a fault and disarmed: nothing to land")
                return result
            if result.outcome != "success":
                break
        await self.land()
        return result

    async def land(self) -> None:
        """Land where the vehicle is and wait for the disarm (no Land command when the landing in
        offboard, ``FlightLoop.descend``, has already ended in the autopilot's disarm)."""
        self.flight.enter(Phase.LANDING)
        if self.vehicle.state().armed:
            self.status("dry run: landing")
            await self.vehicle.land()
        await self.alive_while(self.vehicle.wait_disarmed())
        self.flight.enter(Phase.DONE)
        log.info("landed and disarmed")

    async def _still_armed(self) -> bool:
        """Armed, as the next HEARTBEAT says (PX4 sends one a second: a disarm may not show yet)."""
        try:
            await self.vehicle.wait_until(lambda s: not s.armed, DISARM_REPORT_TIMEOUT_S, "disarmed")
        except VehicleError:
            return True
        return False

    async def _offboard_refused(self, err: VehicleError, t_request_ns: int) -> EpisodeResult:
        """The autopilot refused offboard (or never showed it): record the trip, make sure the
        vehicle is in Hold (offboard.stop also ends MAVSDK's setpoint re-sending), fly nothing."""
        trip = self.loop.watchdog.refuse_start(TripCause.OFFBOARD_REFUSED, f"offboard did not start: {err}", t_request_ns, time.monotonic_ns())
        await self.vehicle.stop_offboard()
        # The autopilot's Hold may still be climbing on to the take-off's height (PX4 ends the
        # take-off up to NAV_MC_ALT_RAD short): the Land, if one follows, waits for it to settle
        # (half the brake's speed: the estimate lags the vehicle).
        watchdog = self.loop.config.watchdog
        try:
            await self.alive_while(self.vehicle.wait_until(
                lambda s: measured_speed_m_s(s) < 0.5 * watchdog.brake_speed_m_s, watchdog.brake_timeout_s, "settled in Hold"))  # fmt: skip
        except VehicleError as wait_err:
            log.warning("still moving in the autopilot's Hold: %s", wait_err)
        return self._unflown(trip.cause.value)

    def _unflown(self, abort_reason: str) -> EpisodeResult:
        """The record of an episode that never flew the policy."""
        loop = self.loop
        return EpisodeResult(
            outcome="aborted", abort_reason=abort_reason, time_s=0.0, steps=0, frames_received=loop.frames_received,
            missed_deadlines=0, bad_frames=0, step_ms={"p50": None, "p99": None, "max": None, "n": 0}, stage_ms={},
            watchdog_trips=loop.watchdog.records(), final_distance_m=float("nan"), frames_rejected=loop.frames_rejected,
        )  # fmt: skip
