"""The flight loop: asyncio tasks joined by latest-value slots (DESIGN §3).

- camera task: the source's frames, checked (``runtime.camera.validate``: unfit ones are counted
  and dropped, so garbage trips the watchdog as "no valid frame") -> the latest-frame slot (+ the
  flight log); a frame whose meta reports a contact in a simulated world (``sim.follower``)
  trips ``sim_contact``;
- policy task: on each new frame, preprocess (runtime.contract.images), observation state, ONNX
  step with the GRU hidden state, clip, action -> velocity (ActionLimits), send through the
  command gate; deadline = the control period (missed deadlines counted; the watchdog trips
  past ``step_trip_ms``); goal reached (within GOAL_REACHED_RADIUS_M) ends the episode;
- watchdog task: the time-based trips and the hover -> Hold response;
- state task: vehicle telemetry into the flight log at 10 Hz, and each of the autopilot's
  STATUSTEXTs once.

:class:`FlightLoop` knows nothing about how offboard was entered: the SITL entry point arms, takes
off and starts offboard itself; a field entry point waits for the pilot to switch to offboard.
Either then calls :meth:`FlightLoop.fly`, which resets the GRU state (offboard (re)entered),
refuses a goal outside the geofence (a trip at once) and flies until the goal, the time limit, a
watchdog trip or the pilot taking over.
"""

from __future__ import annotations

import asyncio
import ctypes
import dataclasses
import functools
import gc
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from .camera import CameraSource, Frame
from .camera.validate import FrameValidator
from .command_gate import CommandedVehicle, CommandGate
from .config import RuntimeConfig
from .contract import (
    CONTROL_PERIOD_S,
    HOVER,
    ImageContractError,
    action_to_velocity_flu,
    invalid_depth_fraction,
    mavsdk_to_velocity_flu,
    velocity_flu_to_mavsdk,
)
from .contract.constants import GOAL_REACHED_RADIUS_M
from .contract.frames import world_enu_to_vehicle
from .camera.surfaces import SeenSurfaces
from .log.recorder import Recorder
from .model import PolicyModel
from .policy_step import PolicyMemory, StepResult, compute_step
from .service.shutdown import wait_within
from .slots import LatestSlot
from .state import MODE_OFFBOARD, VehicleError, VehicleState
from .timing import StageTimes
from .watchdog import (
    LAND_DESCENT_M_S,
    LAND_DISARM_WAIT_S,
    RETREAT_SPEED_M_S,
    TAKEOFF_CLIMB_MAX_M_S,
    TAKEOFF_CLIMB_REACHED_M,
    TAKEOFF_CLIMB_TIME_MARGIN_S,
    RetreatTracker,
    TripCause,
    WatchInputs,
    Watchdog,
    blind_travel_m,
    brake_ended,
    brake_record,
    brake_setpoint,
    cap_approach,
    choose_landing_site,
    climb_speed_m_s,
    cut_path,
    descent_time_limit_s,
    hold_setpoint,
    landing_way,
)

log = logging.getLogger(__name__)

_NS_PER_MS = 1_000_000
_NS_PER_S = 1_000_000_000
STATE_LOG_PERIOD_S = 0.1
ALIVE_SLEEP_SLICE_S = 0.1  # how often on_alive is called while the loop sleeps on purpose
RETREAT_TIME_MARGIN_S = 4.0  # a retreat may take twice its reference's time, plus this


class VehicleLink(CommandedVehicle, Protocol):
    """What the loop needs from the vehicle (``runtime.vehicle.Vehicle`` implements it)."""

    def state(self) -> VehicleState: ...


@dataclass
class EpisodeResult:
    """How one offboard episode ended.  Times in seconds from :meth:`FlightLoop.fly`'s start."""

    outcome: str  # "success" | "timeout" | "aborted"
    abort_reason: str | None
    time_s: float  # to the goal (success) or to the end
    steps: int  # policy steps run (the summary's "frames")
    frames_received: int  # by the camera task since FlightLoop.start
    missed_deadlines: int
    bad_frames: int
    step_ms: dict
    stage_ms: dict
    watchdog_trips: list[dict] = field(default_factory=list)
    final_distance_m: float = float("nan")  # to the goal at the last step (before the brake and any retreat)
    frames_rejected: int = 0  # unfit camera frames since FlightLoop.start (runtime.camera.validate)
    tracking_error_peak_m_s: float = 0.0  # the largest tracking error sustained a whole window (runtime.tracking)
    # How the brake before Hold ended ({ended: stopped | brake_timeout, duration_s, speed_at_hold_m_s};
    # runtime.watchdog.brake_record); None when no brake ran (the pilot took over, nothing flown).
    brake: dict | None = None
    # The approach to a dry run's last goal (runtime.watchdog.cap_approach): {capped_steps,
    # least_cap_m_s}; None on other goals.
    approach_cap: dict | None = None

    def summary(self) -> dict:
        """The episode's JSON record: the keys of an episode in ``cmnav fly``'s summary and of the
        SITL flight's summary (``steps`` keeps its published key, ``frames``)."""
        record = dataclasses.asdict(self)
        return {("frames" if key == "steps" else key): value for key, value in record.items()}


def settle_heap() -> None:
    """Collect, give the freed memory back to the system, then freeze what exists now (the model,
    the config, the imported libraries: it lives for the whole flight) out of the garbage
    collector's sight, so that a collection during a step stays short.  Before an episode's clock
    starts: a full collection of a large heap blocks the loop (seen: > 250 ms in a long test
    process), which must not read as a stale camera.  Again right after, it is cheap (the heap is
    frozen).  The episode's end unfreezes it."""
    gc.collect()
    _malloc_trim()
    gc.freeze()


def _malloc_trim() -> None:
    """glibc's ``malloc_trim(0)``: free pages inside the allocator's arenas go back to the system.
    Without it a service flying episode after episode keeps the fragments of every episode's
    buffers (frames, logs, reports) in its RSS (soak: +0.1 MB an episode).  Nothing elsewhere."""
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    """The C library when it is glibc (it has malloc_trim); None elsewhere (macOS, musl)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
    except (OSError, AttributeError):
        return None
    return libc


class FlightLoop:
    """Camera, policy, watchdog and logging tasks around one model, vehicle and camera."""

    def __init__(
        self,
        config: RuntimeConfig,
        model: PolicyModel,
        vehicle: VehicleLink,
        camera: CameraSource,
        recorder: Recorder | None = None,
        on_alive: Callable[[], None] | None = None,
    ) -> None:
        """``on_alive`` is called on every healthy iteration: each policy step whose command went
        out, each watchdog check while a trip response runs, and while hovering before Hold at the
        end of an episode.  A stalled loop stops calling it (the field program feeds systemd's
        watchdog from it)."""
        self.config = config
        self.model = model
        self.vehicle = vehicle
        self.camera = camera
        self.recorder = recorder
        self.on_alive = on_alive
        self.gate = CommandGate(vehicle)
        self.watchdog = Watchdog(config.watchdog, self.gate, on_event=self._on_watchdog_event)
        self.frames: LatestSlot[Frame] = LatestSlot("frames")  # valid frames only
        self.frames_received = 0
        self.frames_rejected = 0  # unfit frames (runtime.camera.validate), never stepped on
        self._validator = FrameValidator()
        self._rejected_since_valid = 0
        self._last_rejection = ""
        self._goal_enu_m = np.zeros(3)
        self._memory = PolicyMemory(model)
        self._step_started_ns = 0
        self._flown_enu_m: list[np.ndarray] = []  # the estimate at each step of the episode (local ENU m)
        self._seen = SeenSurfaces()  # what its depth frames showed, where it may land (runtime.camera.surfaces)
        self.handed_over_after_goal = False  # a mode other than offboard came during the last retreat or landing
        self.landing_in_offboard = False  # the last episode's landing in offboard began (:meth:`descend`)
        self.on_landing: Callable[[], None] | None = None  # called when it begins (a program's phase)
        self._background: list[asyncio.Task] = []
        # The result of the last :meth:`fly` that was cancelled (None if it returned).
        self.interrupted: EpisodeResult | None = None
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="policy_step")

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Start the camera and the state-logging tasks (they run until :meth:`close`).

        ``recorder`` may be swapped (or set to None) between episodes: the tasks log to whichever
        is set (``cmnav fly`` writes one log per offboard episode)."""
        await self.camera.start()
        self._background = [
            asyncio.create_task(self._camera_task(), name="camera"),
            asyncio.create_task(self._state_log_task(), name="state_log"),
        ]
        for task in self._background:
            task.add_done_callback(log_task_failure)

    async def close(self) -> None:
        for task in self._background:
            task.cancel()
        await asyncio.gather(*self._background, return_exceptions=True)
        self._background.clear()
        await self.camera.close()
        # A hung inference thread must not hang shutdown too.
        self._executor.shutdown(wait=False, cancel_futures=True)

    async def safe_stop(self) -> None:
        """Leave offboard safely when the program must stop mid-flight: brake (hover until stopped,
        ``brake_timeout_s`` at most), then Hold.

        Does nothing if the pilot took over.  Used on shutdown (e.g. SIGTERM), outside :meth:`fly`.
        """
        self.watchdog.stop()
        try:
            await self.brake_then_hold()
        except VehicleError as err:
            log.error("safe stop failed (%s): MAVSDK stops re-sending on close, PX4's offboard-loss failsafe follows", err)

    async def brake_then_hold(self, land_site: bool = False, land: bool = False) -> dict | None:
        """Brake (``runtime.watchdog.brake_setpoint`` at the control rate) until the vehicle has
        stopped (``runtime.watchdog.brake_ended``), then Hold; returns the brake's record (None if
        the pilot has the vehicle: nothing sent).  With ``land_site`` and the vehicle stopped, go
        to the landing site (``runtime.watchdog.choose_landing_site``: the point of the way back
        along the path flown nearest ``mission.land_retreat_m`` back that is clear of what the depth
        frames showed, reached clear of it, else the nearest such point of a straight step away from
        where it stopped; the record's ``landing_site``;
        ``mission.land_site_search_m`` = 0: ``mission.land_retreat_m`` back, unchecked) by
        :meth:`retreat`, and brake again before the Hold (the record's ``retreat``).  With ``land`` and the vehicle stopped, :meth:`descend` instead of the Hold
        (the record's ``descent``); Hold only if it did not reach the ground.  Raises VehicleError
        if a command fails."""
        record = await self._brake()
        if record is None:
            return None
        if land_site and record["ended"] == "stopped":
            mission = self.config.mission
            flown = np.array(self._flown_enu_m).reshape(-1, 3)
            way = landing_way(flown, self.vehicle.state().pos_enu_m, max(mission.land_site_search_m, mission.land_retreat_m))
            site = None
            if mission.land_site_search_m > 0.0:
                site = choose_landing_site(way, self._seen, mission.land_retreat_m, mission.land_clearance_m, mission.land_way_clearance_m)
                (log.info if site.clear else log.warning)("landing site: %s", site)
                path = site.path_enu_m
            else:
                path = cut_path(way, blind_travel_m(way, mission.land_retreat_m))
            if len(path) > 1:
                retreat = await self.retreat(path)
                if retreat is None or (record := await self._brake()) is None:
                    return None
                record["retreat"] = retreat
            if site is not None:
                record["landing_site"] = site.record()
        if land and record["ended"] == "stopped":
            descent = await self.descend()
            if descent is None:
                return None
            record["descent"] = descent
            if descent["ended"] in ("landed", "disarmed"):
                return record
        await self.gate.hold()
        return record

    async def _brake(self) -> dict | None:
        """The brake until it ends (``runtime.watchdog.brake_ended``): its record, or None once the
        pilot has the vehicle."""
        t_brake_ns = time.monotonic_ns()
        if not await self.gate.hover():
            return None
        self._log_hover("brake")
        t_sent_ns = t_brake_ns
        while (ended := brake_ended(self.vehicle.state(), t_brake_ns, now_ns := time.monotonic_ns(), self.config.watchdog)) is None:
            if self.gate.released:  # the pilot took over while it braked: the vehicle is theirs
                return None
            if now_ns - t_sent_ns >= CONTROL_PERIOD_S * _NS_PER_S:
                t_sent_ns = now_ns
                await self.gate.send_own(brake_setpoint(self.vehicle.state(), now_ns, self.config.watchdog))
            await self._sleep_alive(self.config.watchdog.period_s)
        record = brake_record(ended, t_brake_ns, time.monotonic_ns(), self.vehicle.state())
        log.info("braked: %s", record)
        return record

    async def retreat(self, path_enu_m: np.ndarray) -> dict | None:
        """Fly ``path_enu_m`` (local ENU m, (N, 3), from where the vehicle is: the way to the
        landing site, ``runtime.watchdog.LandingSite.path_enu_m``), heading unchanged, at the control rate
        (``runtime.watchdog.RetreatTracker``: a reference point moving along it at
        ``RETREAT_SPEED_M_S``, followed with a P term, and an integral where the estimate's velocity
        is not corrected; slowing down near the end).  Blind but on a path just flown (or a step
        clear of what the camera showed); it ends
        once the vehicle is at the path's end ("arrived"), after twice the time the reference
        needs plus ``RETREAT_TIME_MARGIN_S`` ("timeout"), or when the estimate goes stale
        ("stale_telemetry").  Returns its record {ended, retreated_m, duration_s}, None once the
        pilot has the vehicle (the gate released, or a mode other than offboard reported during
        it: then nothing more is sent)."""
        start = self.vehicle.state().pos_enu_m.copy()
        path = np.asarray(path_enu_m, dtype=np.float64)
        # Its integral term cancels an autopilot's velocity error, which the runtime already takes out
        # when it corrects the estimate (runtime.tracking.VelocityBias): then it would only wind up on the lag.
        tracker = RetreatTracker(path, integral=not self.config.vehicle.velocity_bias_correction)
        t0_ns = time.monotonic_ns()
        limit_ns = t0_ns + int((2.0 * tracker.length_m / RETREAT_SPEED_M_S + RETREAT_TIME_MARGIN_S) * _NS_PER_S)
        stale_ns = int(self.config.watchdog.telemetry_stale_ms * _NS_PER_MS)
        ended, t_last_ns = "arrived", t0_ns
        log.info("retreating %.2f m to the landing site (%d points)", tracker.length_m, len(path))
        while len(path) > 1:
            state, now_ns = self.vehicle.state(), time.monotonic_ns()
            elapsed_s = (now_ns - t0_ns) / _NS_PER_S
            if self._handed_over(state, t0_ns, "retreat"):
                return None
            if now_ns - state.t_telemetry_ns > stale_ns:
                ended = "stale_telemetry"
                break
            if tracker.arrived(state.pos_enu_m, elapsed_s):
                break
            if now_ns >= limit_ns:
                ended = "timeout"
                break
            vel_enu = tracker.velocity_enu(state.pos_enu_m, elapsed_s, (now_ns - t_last_ns) / _NS_PER_S)
            t_last_ns = now_ns
            cmd_flu = np.array([*world_enu_to_vehicle(vel_enu, state.yaw_enu_rad), 0.0])
            cmd = velocity_flu_to_mavsdk(cmd_flu)
            sent = await self.gate.send_own(cmd)
            if self.recorder is not None:
                self.recorder.log_command(time.monotonic_ns(), None, cmd_flu, cmd, "retreat", sent)
            await self._sleep_alive(CONTROL_PERIOD_S)
        record = {"ended": ended, "retreated_m": round(float(np.linalg.norm(self.vehicle.state().pos_enu_m[:2] - start[:2])), 3),
                  "duration_s": round((time.monotonic_ns() - t0_ns) / _NS_PER_S, 3)}  # fmt: skip
        log.info("retreat: %s", record)
        return record

    async def climb(self, height_above_home_m: float) -> dict | None:
        """After the autopilot's take-off, in offboard and before the first episode: up to
        ``height_above_home_m`` (PX4 ends its take-off up to 0.8 m short and climbs the rest slowly
        in Hold, drifting: ``runtime.watchdog.TAKEOFF_HOLD_SHORT_M``), at :func:`runtime.watchdog.climb_speed_m_s`,
        horizontally holding the position estimate where it began (``runtime.watchdog.hold_setpoint``,
        the landing's law).  Ends "reached" within ``TAKEOFF_CLIMB_REACHED_M``, "timeout" after
        (height to go) / ``TAKEOFF_CLIMB_MAX_M_S`` + ``TAKEOFF_CLIMB_TIME_MARGIN_S``, "stale_telemetry";
        the episode follows in any case (the policy flies from that height).  Returns its record
        {ended, from_m, to_m (heights above home, by the estimate), drift_m, duration_s}; None once
        the pilot has the vehicle."""
        start = self.vehicle.state()
        t0_ns = time.monotonic_ns()
        limit_ns = t0_ns + int((max(height_above_home_m - start.height_above_home_m, 0.0) / TAKEOFF_CLIMB_MAX_M_S
                                + TAKEOFF_CLIMB_TIME_MARGIN_S) * _NS_PER_S)  # fmt: skip
        stale_ns = int(self.config.watchdog.telemetry_stale_ms * _NS_PER_MS)
        while True:
            state, now_ns = self.vehicle.state(), time.monotonic_ns()
            if self._handed_over(state, t0_ns, "climb after the take-off"):
                return None
            to_go_m = height_above_home_m - state.height_above_home_m
            if to_go_m <= TAKEOFF_CLIMB_REACHED_M:
                ended = "reached"
                break
            if now_ns - state.t_telemetry_ns > stale_ns:
                ended = "stale_telemetry"
                break
            if now_ns >= limit_ns:
                ended = "timeout"
                break
            cmd = hold_setpoint(state, start.pos_enu_m, climb_speed_m_s(to_go_m), now_ns, self.config.watchdog)
            sent = await self.gate.send_own(cmd)
            if self.recorder is not None:
                self.recorder.log_command(time.monotonic_ns(), None, mavsdk_to_velocity_flu(cmd), cmd, "climb", sent)
            await self._sleep_alive(CONTROL_PERIOD_S)
        end = self.vehicle.state()
        record = {"ended": ended, "from_m": round(float(start.height_above_home_m), 3), "to_m": round(float(end.height_above_home_m), 3),
                  "drift_m": round(float(np.linalg.norm(end.pos_enu_m[:2] - start.pos_enu_m[:2])), 3),
                  "duration_s": round((time.monotonic_ns() - t0_ns) / _NS_PER_S, 3)}  # fmt: skip
        (log.info if ended == "reached" else log.warning)("climb after the take-off to %.2f m: %s", height_above_home_m, record)
        return record

    async def descend(self) -> dict | None:
        """Land under the runtime's control (``runtime.watchdog.hold_setpoint``): down at
        ``LAND_DESCENT_M_S``, horizontally holding the position estimate where it began, at the control
        rate, until the autopilot disarms on its land detector ("disarmed"), or ``LAND_DISARM_WAIT_S``
        after it reported the touch-down without disarming ("landed": the dry run's Land disarms
        it); "timeout" when no touch-down is reported within :func:`runtime.watchdog.descent_time_limit_s`,
        "stale_telemetry" when the estimate goes stale (both: Hold follows, then the dry run's Land).  Returns its record
        {ended, drift_m (horizontal, by the estimate), duration_s}; None once the pilot has the
        vehicle (the gate released, or a mode other than offboard reported during it)."""
        self.landing_in_offboard = True
        if self.on_landing is not None:
            self.on_landing()
        start = self.vehicle.state()
        t0_ns = time.monotonic_ns()
        limit_ns = t0_ns + int(descent_time_limit_s(start) * _NS_PER_S)
        stale_ns = int(self.config.watchdog.telemetry_stale_ms * _NS_PER_MS)
        t_landed_ns = None
        log.info("landing in offboard from %.2f m above home at %.2f m/s", start.height_above_home_m, LAND_DESCENT_M_S)
        while True:
            state, now_ns = self.vehicle.state(), time.monotonic_ns()
            if self._handed_over(state, t0_ns, "landing"):
                return None
            if not state.armed:
                ended = "disarmed"
                break
            if t_landed_ns is None and not state.in_air:
                t_landed_ns = now_ns
                log.info("touch-down reported after %.2f s", (now_ns - t0_ns) / _NS_PER_S)
            if t_landed_ns is not None and now_ns - t_landed_ns >= LAND_DISARM_WAIT_S * _NS_PER_S:
                ended = "landed"
                break
            if t_landed_ns is None and now_ns >= limit_ns:
                ended = "timeout"
                break
            if now_ns - state.t_telemetry_ns > stale_ns:
                ended = "stale_telemetry"
                break
            cmd = hold_setpoint(state, start.pos_enu_m, -LAND_DESCENT_M_S, now_ns, self.config.watchdog)
            sent = await self.gate.send_own(cmd)
            if self.recorder is not None:
                self.recorder.log_command(time.monotonic_ns(), None, mavsdk_to_velocity_flu(cmd), cmd, "landing", sent)
            await self._sleep_alive(CONTROL_PERIOD_S)
        end = self.vehicle.state()
        record = {"ended": ended, "drift_m": round(float(np.linalg.norm(end.pos_enu_m[:2] - start.pos_enu_m[:2])), 3),
                  "duration_s": round((time.monotonic_ns() - t0_ns) / _NS_PER_S, 3)}  # fmt: skip
        log.info("landing in offboard: %s", record)
        return record

    def _handed_over(self, state: VehicleState, t0_ns: int, what: str) -> bool:
        """Whether the vehicle stopped being the runtime's during ``what`` (the take-off's climb, the
        retreat or the landing, begun at ``t0_ns``): the gate released, or a mode other than
        offboard reported since.  A pilot (or the autopilot's failsafe) took it: nothing more is
        sent, no Hold either."""
        if self.gate.released:
            return True
        if state.flight_mode != MODE_OFFBOARD and state.t_mode_ns > t0_ns:
            log.warning("flight mode %s during the %s: the vehicle is no longer the runtime's", state.flight_mode, what)
            self.gate.release()
            self.handed_over_after_goal = True
            return True
        return False

    def set_goal(self, goal_enu_m: np.ndarray) -> None:
        """New goal (local ENU, m): the GRU state resets."""
        self._goal_enu_m = np.asarray(goal_enu_m, dtype=np.float64).copy()
        self.reset_hidden()

    def reset_hidden(self) -> None:
        """Zero the GRU state and the previous action (offboard (re)entered, or a new goal)."""
        self._memory.reset()

    async def wait_first_frame(self, timeout_s: float) -> Frame:
        """The first camera frame; ``asyncio.TimeoutError`` if none comes in time."""
        return (await self.frames.wait_newer(0, timeout_s)).value

    # ------------------------------------------------------------------ one episode

    async def fly(self, goal_enu_m: np.ndarray, timeout_s: float, landing_next: bool = False) -> EpisodeResult:
        """Fly the policy from now (offboard active) to ``goal_enu_m`` (local ENU, m).  With
        ``landing_next`` (a dry run's last goal), a goal reached is followed by the brake, a retreat
        back along the path flown to the landing site (:meth:`retreat`: the point of the way back
        nearest ``mission.land_retreat_m`` back clear of what the depth frames showed, reached
        clear of it), the brake again,
        then the landing in offboard (:meth:`descend`, ``mission.land_in_offboard``) or Hold."""
        self.set_goal(goal_enu_m)
        settle_heap()
        episode = _Episode(t0_ns=time.monotonic_ns(), timeout_s=timeout_s, landing_next=landing_next)
        self._flown_enu_m = []
        self._seen = SeenSurfaces()
        self.handed_over_after_goal = self.landing_in_offboard = False
        self.watchdog.start(episode.t0_ns, self.vehicle.state())
        self._on_watchdog_event({"event": "start", "detail": repr(self.config.watchdog), "t_s": 0.0})
        log.info("episode start: goal %s (local ENU m), time limit %.1f s", np.round(self._goal_enu_m, 2), timeout_s)
        await self.watchdog.check_goal(self._goal_enu_m, time.monotonic_ns())
        policy = asyncio.create_task(self._policy_task(episode), name="policy")
        watchdog = asyncio.create_task(self._watchdog_task(), name="watchdog")
        self.interrupted = None
        try:
            await self._supervise(episode, policy, watchdog)
        except asyncio.CancelledError:
            # Stopped from outside (a stop signal): keep what was flown for the summary.
            episode.finish("aborted", "stopped", time.monotonic_ns())
            self.interrupted = self._result(episode)
            raise
        finally:
            for task in (policy, watchdog):
                task.cancel()
            await asyncio.gather(policy, watchdog, return_exceptions=True)
            # What was frozen at the start (the last episode's report being drawn, its closing
            # log, ...) may be garbage by now: collectable again, or it would pile up by the episode.
            gc.unfreeze()
        return self._result(episode)

    async def _supervise(self, episode: "_Episode", policy: asyncio.Task, watchdog: asyncio.Task) -> None:
        timeout_at = episode.t0_ns + int(episode.timeout_s * _NS_PER_S)
        pending: set[asyncio.Future] = {policy, watchdog, episode.ended}
        while not episode.ended.done():
            remaining_s = (timeout_at - time.monotonic_ns()) / _NS_PER_S
            if remaining_s <= 0.0:
                episode.finish("timeout", None, time.monotonic_ns())
                break
            done, pending = await asyncio.wait(pending, timeout=remaining_s, return_when=asyncio.FIRST_COMPLETED)
            for task in done & {policy, watchdog}:
                if task.exception() is not None:
                    log.error("%s task failed", task.get_name(), exc_info=task.exception())
                if task.exception() is not None and self.watchdog.tripped is None:
                    now = time.monotonic_ns()
                    await self.watchdog.trip(TripCause.POLICY_ERROR, f"{task.get_name()} task failed: {task.exception()!r}", now, now)
            if self.watchdog.tripped is not None or self.watchdog.pilot_took_over:
                episode.finish("aborted", self.watchdog.trips[0].cause.value, time.monotonic_ns())
                await self._finish_trip_response(watchdog)
                return
            if watchdog in done:
                # The watchdog task ended without a trip: only a bug does that; fly no further.
                episode.finish("aborted", "watchdog task ended", time.monotonic_ns())
                break
        # Goal reached or out of time: brake, then Hold, as the watchdog would (but not a trip).
        self.watchdog.stop()
        try:
            landing = episode.outcome == "success" and episode.landing_next
            mission = self.config.mission
            episode.brake = await self.brake_then_hold(landing, landing and mission.land_in_offboard)
        except VehicleError as err:
            log.error("hover/Hold at the end of the episode failed: %s", err)
            episode.abort_reason = f"end of episode hover/Hold failed: {err}"

    async def _finish_trip_response(self, watchdog: asyncio.Task) -> None:
        """Let the watchdog finish its response (Hold after the grace period, or nothing if released)."""
        limit_s = self.config.watchdog.brake_timeout_s + 2.0 * self.config.vehicle.command_timeout_s + 1.0
        if watchdog.done():
            if watchdog.exception() is None:
                return
            # The watchdog task itself failed: command Hold here so the vehicle is not left hovering in offboard.
            await self._sleep_alive(self.config.watchdog.hold_grace_s)
            try:
                await self.gate.hold()
            except VehicleError as err:
                log.error("Hold after the trip failed: %s; the vehicle hovers in offboard", err)
            return
        try:
            await wait_within(asyncio.shield(watchdog), limit_s)
        except asyncio.TimeoutError:
            log.error("the watchdog could not command Hold within %.1f s; the vehicle hovers in offboard", limit_s)

    # ------------------------------------------------------------------ tasks

    async def _camera_task(self) -> None:
        async for frame in self.camera.frames():
            self.frames_received += 1
            problem = self._validator.problem(frame, time.monotonic_ns())
            if problem is not None:
                self.frames_rejected += 1
                self._rejected_since_valid += 1
                self._last_rejection = problem
                if self._rejected_since_valid == 1 or self.frames_rejected % 100 == 0:
                    log.error("camera frame %d rejected: %s (%d rejected so far)", frame.seq, problem, self.frames_rejected)
                continue
            self._rejected_since_valid = 0
            self.frames.put(frame)
            if self.recorder is not None:
                self.recorder.log_frame(frame)
            await self._check_sim_contact(frame)

    async def _check_sim_contact(self, frame: Frame) -> None:
        """A SITL world that follows an external autopilot reports a contact in the frame's meta
        (``sim.follower``): end the episode as any trip does (hover, then Hold)."""
        contact = frame.meta.get("contact") if isinstance(frame.meta, dict) else None
        if contact is None or not self.watchdog.supervising or self.watchdog.tripped is not None:
            return
        what = contact.get("what", "?") if isinstance(contact, dict) else str(contact)
        now = time.monotonic_ns()
        await self.watchdog.trip(TripCause.SIM_CONTACT, f"the simulated world reports contact: {what}", frame.t_capture_ns, now)

    async def _state_log_task(self) -> None:
        status_seq_logged = 0
        while True:
            state = self.vehicle.state()
            if self.recorder is not None:
                self.recorder.log_state(time.monotonic_ns(), state)
                for text in state.status_texts:
                    if text.seq > status_seq_logged:
                        self.recorder.log_status_text(text)
            status_seq_logged = state.status_texts[-1].seq if state.status_texts else status_seq_logged
            await asyncio.sleep(STATE_LOG_PERIOD_S)

    async def _watchdog_task(self) -> None:
        period_s = self.config.watchdog.period_s
        while True:
            latest = self.frames.latest()
            await self.watchdog.tick(
                WatchInputs(
                    now_ns=time.monotonic_ns(),
                    t_last_frame_capture_ns=latest.value.t_capture_ns if latest else 0,
                    t_step_started_ns=self._step_started_ns,
                    vehicle=self.vehicle.state(),
                    frames_rejected=self._rejected_since_valid,
                    last_rejection=self._last_rejection,
                )
            )
            trip = self.watchdog.tripped
            if self.gate.released or (trip is not None and trip.hold_t_ns is not None):
                return  # the pilot or the autopilot's failsafe has the vehicle, or Hold was sent
            if trip is not None and self.on_alive is not None:
                self.on_alive()  # the response (hover, then Hold) is running: the loop is doing its job
            await asyncio.sleep(period_s)

    async def _policy_task(self, episode: "_Episode") -> None:
        seq = self.frames.latest().seq if self.frames.latest() else 0
        # The episode's end stops it too, not only its cancellation: a step may be under way.
        while self.gate.policy_open and not episode.ended.done():
            try:
                stamped = await self.frames.wait_newer(seq, timeout_s=CONTROL_PERIOD_S)
            except asyncio.TimeoutError:
                continue  # no frame: the watchdog's stale-frame check decides
            seq = stamped.seq
            if await self._step(stamped.value, episode):
                episode.finish("success", None, time.monotonic_ns())
                return

    async def _step(self, frame: Frame, episode: "_Episode") -> bool:
        """One control step on ``frame``; True when the goal is reached."""
        t_start = time.monotonic_ns()
        self._step_started_ns = t_start
        try:
            return await self._step_inner(frame, episode, t_start)
        finally:
            self._step_started_ns = 0

    async def _step_inner(self, frame: Frame, episode: "_Episode", t_start: int) -> bool:
        state = self.vehicle.state()
        if await self.watchdog.check_telemetry(state, time.monotonic_ns()) is not None:
            return False
        self._flown_enu_m.append(state.pos_enu_m.copy())  # the retreat's path (fresh: checked above)
        inputs = self._memory.inputs(state, self._goal_enu_m)
        limit_s = self.config.watchdog.step_trip_ms / 1000.0 - (time.monotonic_ns() - t_start) / _NS_PER_S
        loop = asyncio.get_running_loop()
        try:
            result = await wait_within(
                loop.run_in_executor(self._executor, compute_step, self.model, frame, inputs),
                max(limit_s, 0.0),
            )
        except ImageContractError as err:
            episode.bad_frames += 1
            log.error("frame %d skipped: %s", frame.seq, err)
            return False
        except asyncio.TimeoutError:
            now = time.monotonic_ns()
            await self.watchdog.trip(
                TripCause.STEP_DEADLINE,
                f"the policy step did not finish within the step limit {self.config.watchdog.step_trip_ms:.0f} ms",
                t_start + int(self.config.watchdog.step_trip_ms * _NS_PER_MS), now,
            )  # fmt: skip
            return False
        t_resumed = time.monotonic_ns()
        if await self.watchdog.check_action(result.output.action, t_start, t_resumed) is not None:
            self._after_command(frame, result)
            return False
        cmd_flu = action_to_velocity_flu(result.action_clipped, self.config.policy.limits)
        # A dry run's last goal keeps what its frames show (where it lands); the floor is at home's height.
        maps_surfaces = episode.landing_next and state.home_enu_m is not None
        if maps_surfaces and self.config.mission.approach_cap:  # the brake after the last goal must stop short of what was seen
            cmd_flu, cap_m_s = cap_approach(cmd_flu, state.pos_enu_m, state.yaw_enu_rad, self._goal_enu_m, self._seen)
            episode.note_approach_cap(cap_m_s)
        cmd = velocity_flu_to_mavsdk(cmd_flu)
        t_checked = time.monotonic_ns()
        try:
            sent = await self.gate.send_policy(cmd)
        except VehicleError as err:
            now = time.monotonic_ns()
            await self.watchdog.trip(TripCause.POLICY_ERROR, f"velocity command failed: {err}", now, now)
            return False
        t_cmd = time.monotonic_ns()
        if sent:
            self.watchdog.note_command(t_cmd, cmd_flu)
        self._after_command(frame, result)
        if maps_surfaces:
            self._seen.add_frame(frame.depth_m, state.pos_enu_m, state.quat_enu_flu, float(state.home_enu_m[2]))
        self._memory.advance(result)
        stages_ms = {
            "delivery": (frame.t_grab_ns - frame.t_capture_ns) / _NS_PER_MS,  # capture -> the source handed it over
            "pickup": (t_start - frame.t_grab_ns) / _NS_PER_MS,  # handed over -> the loop began the step
            "frame_age_at_step": (t_start - frame.t_capture_ns) / _NS_PER_MS,  # delivery + pickup
            "executor_in": (result.t_started_ns - t_start) / _NS_PER_MS,  # telemetry snapshot + hop to the worker thread
            "preprocess": (result.t_preprocessed_ns - result.t_started_ns) / _NS_PER_MS,
            "observation": (result.t_observed_ns - result.t_preprocessed_ns) / _NS_PER_MS,
            "inference": (result.t_inferred_ns - result.t_observed_ns) / _NS_PER_MS,
            "executor_out": (t_resumed - result.t_inferred_ns) / _NS_PER_MS,  # back to the event loop (asyncio scheduling)
            "checks": (t_checked - t_resumed) / _NS_PER_MS,  # NaN/Inf check, action -> velocity
            "send": (t_cmd - t_checked) / _NS_PER_MS,  # the MAVSDK call, its executor hop included
            "command": (t_cmd - result.t_inferred_ns) / _NS_PER_MS,  # executor_out + checks + send
            "step": (t_cmd - t_start) / _NS_PER_MS,
            "grab_to_command": (t_cmd - frame.t_grab_ns) / _NS_PER_MS,  # the runtime's share: pickup + step
            "frame_age": (t_cmd - frame.t_capture_ns) / _NS_PER_MS,  # end to end: capture -> command
        }
        missed = stages_ms["step"] > CONTROL_PERIOD_S * 1000.0
        episode.steps += 1
        episode.missed_deadlines += int(missed)
        episode.timing.add(stages_ms)
        if self.recorder is not None:
            self.recorder.log_command(t_cmd, frame, cmd_flu, cmd, "policy", sent)
            self.recorder.log_timing(frame, stages_ms, missed)
        if self.on_alive is not None:
            self.on_alive()
        episode.last_distance_m = float(np.linalg.norm(self._goal_enu_m - inputs.pos_enu_m))
        return episode.last_distance_m < GOAL_REACHED_RADIUS_M

    def _after_command(self, frame: Frame, result: StepResult) -> None:
        """Off the command's path (issue 15): the step's record and the depth statistics, once the
        command went out (or the step was refused)."""
        if self.recorder is not None:
            self.recorder.log_step(frame, result)
        self.watchdog.note_depth(frame.t_capture_ns, invalid_depth_fraction(frame.depth_m))

    async def _sleep_alive(self, duration_s: float) -> None:
        """Sleep ``duration_s`` (hovering before Hold) while still reporting the loop alive."""
        deadline = time.monotonic() + duration_s
        while (remaining_s := deadline - time.monotonic()) > 0.0:
            if self.on_alive is not None:
                self.on_alive()
            await asyncio.sleep(min(remaining_s, ALIVE_SLEEP_SLICE_S))

    # ------------------------------------------------------------------ results and logging

    def _on_watchdog_event(self, event: dict) -> None:
        if self.recorder is not None:
            now = time.monotonic_ns()
            self.recorder.log_watchdog(now, event)
            if event.get("event") == "trip" and event.get("response") == "hover_then_hold":
                self._log_hover("watchdog_hover")

    def _log_hover(self, source: str) -> None:
        if self.recorder is not None:
            self.recorder.log_command(time.monotonic_ns(), None, mavsdk_to_velocity_flu(HOVER), HOVER, source, True)

    def _result(self, episode: "_Episode") -> EpisodeResult:
        # At the episode's end (its last step), before the brake and any retreat; the estimate now if no step ran.
        final_distance_m = episode.last_distance_m
        if not np.isfinite(final_distance_m):
            final_distance_m = float(np.linalg.norm(self._goal_enu_m - self.vehicle.state().pos_enu_m))
        stage_ms = episode.timing.summary()
        return EpisodeResult(
            outcome=episode.outcome or "aborted",
            abort_reason=episode.abort_reason,
            time_s=round(((episode.t_end_ns or time.monotonic_ns()) - episode.t0_ns) / _NS_PER_S, 3),
            steps=episode.steps,
            frames_received=self.frames_received,
            missed_deadlines=episode.missed_deadlines,
            bad_frames=episode.bad_frames,
            step_ms=stage_ms.get("step", {"p50": None, "p99": None, "max": None, "n": 0}),
            stage_ms=stage_ms,
            watchdog_trips=self.watchdog.records(),
            final_distance_m=round(final_distance_m, 3),
            frames_rejected=self.frames_rejected,
            tracking_error_peak_m_s=round(self.watchdog.tracking_sustained_peak_m_s, 3),
            brake=episode.brake or self.watchdog.brake,
            approach_cap={"capped_steps": episode.approach_capped_steps,
                          "least_cap_m_s": None if episode.approach_least_cap_m_s is None else round(episode.approach_least_cap_m_s, 3)}
            if episode.landing_next else None,
        )


def log_task_failure(task: asyncio.Task) -> None:
    """Done-callback: log a background task that ended on an exception (its consequence, e.g.
    stale frames or telemetry, is the watchdog's to handle)."""
    if not task.cancelled() and task.exception() is not None:
        log.error("task %s failed", task.get_name(), exc_info=task.exception())


@dataclass
class _Episode:
    """Book-keeping of one :meth:`FlightLoop.fly`."""

    t0_ns: int
    timeout_s: float
    steps: int = 0
    missed_deadlines: int = 0
    bad_frames: int = 0
    last_distance_m: float = float("nan")
    outcome: str | None = None
    abort_reason: str | None = None
    t_end_ns: int | None = None
    timing: StageTimes = field(default_factory=StageTimes)
    brake: dict | None = None
    landing_next: bool = False  # a dry run's last goal (FlightLoop.fly)
    approach_capped_steps: int = 0  # steps whose command runtime.watchdog.cap_approach slowed
    approach_least_cap_m_s: float | None = None
    ended: asyncio.Future = field(default_factory=lambda: asyncio.get_running_loop().create_future())

    def note_approach_cap(self, cap_m_s: float | None) -> None:
        if cap_m_s is not None:
            self.approach_capped_steps += 1
            least = self.approach_least_cap_m_s
            self.approach_least_cap_m_s = cap_m_s if least is None else min(cap_m_s, least)

    def finish(self, outcome: str, reason: str | None, t_ns: int) -> None:
        if self.outcome is None:
            self.outcome, self.abort_reason, self.t_end_ns = outcome, reason, t_ns
            if not self.ended.done():
                self.ended.set_result(outcome)
