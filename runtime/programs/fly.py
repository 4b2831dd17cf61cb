"""``cmnav fly --config FILE.toml``: the field program, what systemd runs on the Jetson.

Start-up, in this order, so that a bad config or model never reaches the vehicle: load and
validate the config (``runtime.config_loader``), load the model on its execution providers, then
connect to the autopilot, start the camera, wait for health (armable, local position, home) and
a first frame, and tell systemd READY.

Then, by default (``mission.allow_arm_takeoff = false``) the runtime never arms or takes off: it
streams a hover setpoint (PX4 accepts offboard only with setpoints already streaming) and waits
for the pilot to arm, take off and switch to offboard — a switch *into* offboard it has seen, not
a vehicle that was already there.  It then flies an episode toward the goal (relative to home,
the take-off point; the GRU state resets on entering offboard), commands hover then Hold, and
waits for the next switch to offboard (``mission.max_episodes``, 0 = until stopped).  If the pilot
leaves offboard mid-episode the runtime stops commanding at once.  With ``allow_arm_takeoff =
true`` (SITL dry runs) it flies the episode script (``runtime.programs.episode``, the same as ``cmnav
sitl``): arms, takes off, enters offboard itself, flies one episode, lands and exits; if the
autopilot refuses offboard, the refusal is recorded as the episode and the vehicle lands.

Goals (``mission.goal_source``): ``"config"`` flies to ``mission.goal_rel_home_enu_m``;
``"mission"`` downloads the mission on the autopilot after start-up (a QGroundControl plan,
``runtime.programs.mission_goals``), places its waypoints relative to home and checks them against
the geofence — a mission that cannot be flown exits 2 with the one-line reason before anything is
armed — and then episode k flies waypoint k (in a dry run: all of them in one flight, re-entering
offboard from Hold for each), the current mission item set before each so that a ground station
shows the progress.  ``camera.source = "bag"`` (``--camera-bag FILE``) flies on a RealSense
recording played in real time (``runtime.camera.realsense``); its end is a lost camera.

One MCAP log per episode in ``recorder.log_dir`` (rotated: ``recorder.max_logs`` /
``max_total_gb``).  systemd (``Type=notify``): READY after start-up, a STATUS line per phase, and
WATCHDOG pings from the flight loop's healthy iterations (and from the waiting phases while the
event loop runs), so a stalled loop is killed and restarted.

A stop signal (SIGTERM from ``systemctl stop``, SIGINT) at any moment ends in a state the runtime
commands (``runtime.programs.stop``: in offboard a hover setpoint, then Hold at once; taking off, Hold;
landing goes on), never in the autopilot's offboard-loss failsafe; the summary's ``stop`` records
the signal, the phase it interrupted, the action and the time.

Exit codes: 0 done (episodes flown, a dry run that reached its goal, or stopped by SIGTERM/SIGINT
— hover then Hold first if flying); 1 a failure that a restart may cure (no autopilot or camera
yet, a dry run that did not reach the goal); 2 a failure a restart cannot cure (config, model,
log directory): the unit's ``RestartPreventExitStatus=2`` keeps systemd from retrying it.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import os
import time
from pathlib import Path
from typing import Awaitable, TypeVar

import numpy as np

from ..camera import CameraSource
from ..camera.realsense import RealSenseSource, RealSenseUnavailableError, RecordingError
from ..camera.replay_source import ReplayCameraSource
from ..camera.sim_source import SimCameraSource
from ..config import BagCameraConfig, CameraConfig, RuntimeConfig
from ..config_loader import ConfigError, load_config
from ..contract import HOVER, ContractMismatchError
from ..flight import EpisodeResult, FlightLoop
from ..log.reader import ReplayError
from ..log.recorder import Recorder, RecorderError
from ..log.rotation import new_log_path, rotate_logs
from ..model import ModelLoadError, PolicyModel, check_outputs_finite, resolve_providers
from ..report.worker import ReportWorker
from ..service.affinity import prepare_control_process
from ..service.sdnotify import SystemdNotifier
from ..service.shutdown import close_step, in_daemon_thread, run_bounded
from ..service.signals import StopSignals, cancel_on_stop_signals, ignore_stop_signals
from ..state import MODE_OFFBOARD, VehicleError, VehicleState
from ..vehicle import Vehicle
from .episode import EpisodeError, EpisodeScript, OffboardWithheld
from .mission_goals import MissionError, MissionWaypoint, check_geofence, mission_waypoints
from .stop import FlightPhase, Phase, stop_on_signal

log = logging.getLogger(__name__)

T = TypeVar("T")

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_CONFIG = 2
# While waiting for the pilot: check the vehicle state and send a hover setpoint this often.  PX4
# accepts offboard only with setpoints streaming (> 2 Hz), and MAVSDK stops its own 20 Hz
# re-sending at the first HEARTBEAT that shows another mode, so the runtime streams them itself.
PILOT_POLL_S = 0.1
ALIVE_PERIOD_S = 0.25  # how often the waiting phases report the event loop alive
REPORT_WAIT_S = 120.0  # at exit, how long the flight reports still being drawn are waited for


class RecorderRefusal(OffboardWithheld):
    """The flight log cannot be written and ``recorder.required`` is true: no offboard."""


class FlyError(RuntimeError):
    """``cmnav fly`` cannot go on; ``exit_code`` says whether a restart may help (1) or not (2)."""

    def __init__(self, exit_code: int, message: str) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def load_model(config: RuntimeConfig) -> PolicyModel:
    """The configured model (``policy.variant`` of it) on the configured execution providers,
    warmed up; :class:`FlyError` (exit 2) if it is refused (not loadable, wrong signature,
    contract or variant, provider unavailable, TensorRT engine cache not writable)."""
    policy = config.policy
    try:
        providers = resolve_providers(policy.providers, policy.provider_fallback)
        model = PolicyModel(policy.model_file, providers, policy.intra_op_threads, policy.tensorrt, policy.variant)
        model.warm_up(policy.warmup_steps)  # before READY: a TensorRT engine is built (or loaded) here
        check_outputs_finite(model)  # on the ground, before anything is armed
    except (ModelLoadError, ContractMismatchError) as err:
        raise FlyError(EXIT_CONFIG, f"model refused, nothing armed: {err}") from err
    return model


def make_camera(config: CameraConfig) -> CameraSource:
    """The configured camera source (not started)."""
    if config.source == "realsense":
        return RealSenseSource(config.realsense)
    if config.source == "sim":
        return SimCameraSource(config.sim.port)
    if config.source == "bag":
        assert config.bag.path is not None  # CameraConfig checks it
        return RealSenseSource(config.realsense, recording=config.bag.path)
    assert config.replay.path is not None  # CameraConfig checks it
    return ReplayCameraSource(config.replay.path)


class FieldProgram:
    """One ``cmnav fly`` run: start-up, then pilot-driven episodes or a dry run."""

    def __init__(self, config: RuntimeConfig, notifier: SystemdNotifier) -> None:
        self.config = config
        self.notifier = notifier
        self.summary: dict = {"episodes": [], "logs": [], "error": None, "stop": None, "log_error": None}
        self.flight = FlightPhase()  # what a stop signal interrupts (runtime.programs.stop)
        self.signals: StopSignals | None = None  # set by the entry point
        self._t_start_ns = time.monotonic_ns()
        self._reports = ReportWorker()  # flight reports being drawn (runtime.report)
        self.waypoints: list[MissionWaypoint] | None = None  # mission.goal_source = "mission": episode k flies waypoint k

    async def run(self) -> int:
        """Everything from model load to exit; returns the exit code (see the module docstring)."""
        # In a worker thread: building a TensorRT engine can take minutes, and systemd's watchdog
        # may already be counting.
        model = await self._alive_while(asyncio.get_running_loop().run_in_executor(None, load_model, self.config))
        self.summary["model"] = model.log_metadata()
        log_dir = self.config.recorder.log_dir
        if log_dir is not None:
            try:
                log_dir.mkdir(parents=True, exist_ok=True)
            except OSError as err:
                raise FlyError(EXIT_CONFIG, f"recorder.log_dir {log_dir} cannot be created: {err}") from err
            if not os.access(log_dir, os.W_OK | os.X_OK):
                raise FlyError(EXIT_CONFIG, f"recorder.log_dir {log_dir} is not writable by this user: "
                                            "chown it to the service user (see systemd/README.md)")  # fmt: skip
        try:
            camera = make_camera(self.config.camera)
        except ReplayError as err:
            raise FlyError(EXIT_CONFIG, f"camera.replay.path: {err}") from err
        vehicle = Vehicle(self.config.vehicle)
        loop = FlightLoop(self.config, model, vehicle, camera, recorder=None, on_alive=self.notifier.loop_alive)
        script = EpisodeScript(vehicle, loop, self.flight, self._status, self._alive_while)
        try:
            await self._start(script)
            if self.config.mission.goal_source == "mission":
                self.waypoints = await self._load_mission(vehicle)
            if self.config.mission.allow_arm_takeoff:
                return await self._dry_run(script, model)
            return await self._pilot_episodes(vehicle, loop, model)
        except VehicleError as err:
            raise FlyError(EXIT_FAILED, f"vehicle: {err}") from err
        except RecordingError as err:  # the file will not change on a restart
            raise FlyError(EXIT_CONFIG, f"camera: {err}") from err
        except (RealSenseUnavailableError, ReplayError) as err:
            raise FlyError(EXIT_FAILED, f"camera: {err}") from err
        except asyncio.CancelledError:
            await self.stop(loop, vehicle)
            raise
        finally:
            await close_step("the flight loop and camera", loop.close)
            await close_step("MAVSDK", vehicle.close)
            if pending := self._reports.pending():
                await close_step("the flight reports", lambda: asyncio.gather(*pending), REPORT_WAIT_S)

    # ------------------------------------------------------------------ start-up

    async def stop(self, loop: FlightLoop | None, vehicle: Vehicle | None) -> None:
        """The safe stop after a stop signal, once (``runtime.programs.stop``); records ``summary["stop"]``."""
        if self.summary["stop"] is not None or self.signals is None:
            return
        self.summary["stop"] = await stop_on_signal(self.signals, self.flight, loop, vehicle, self._t_start_ns)

    async def _start(self, script: EpisodeScript) -> None:
        try:
            await script.start(self.config.camera.first_frame_timeout_s, self.config.camera.source,
                               lambda: "is the camera connected and streaming?")  # fmt: skip
        except EpisodeError as err:
            raise FlyError(EXIT_FAILED, str(err)) from err
        self.notifier.ready("started: connected, healthy, camera streaming")
        log.info("started: connected, healthy, camera streaming")

    async def _load_mission(self, vehicle: Vehicle) -> list[MissionWaypoint]:
        """The mission on the autopilot as episode goals (``mission.goal_source = "mission"``),
        checked against the geofence on the ground: :class:`FlyError` (exit 2) with the one-line
        reason if it cannot be flown; nothing is armed."""
        self._status("downloading the mission from the autopilot")
        items = await self._alive_while(vehicle.download_mission())
        home_lat_deg, home_lon_deg = await vehicle.home_geodetic_deg()
        try:
            waypoints = mission_waypoints(items, home_lat_deg, home_lon_deg)
            check_geofence(waypoints, self.config.watchdog)
        except MissionError as err:
            raise FlyError(EXIT_CONFIG, f"mission refused, nothing armed: {err}") from err
        if self.config.mission.max_episodes > 0:
            waypoints = waypoints[: self.config.mission.max_episodes]
        self.summary["mission"] = [{"seq": w.seq, "goal_rel_home_enu_m": list(w.goal_rel_home_enu_m)} for w in waypoints]
        log.info("mission: %d waypoint(s) to fly, relative to home (ENU m): %s", len(waypoints),
                 [(w.seq, w.goal_rel_home_enu_m) for w in waypoints])  # fmt: skip
        return waypoints

    def _goal_rel_home_enu_m(self, episode: int) -> np.ndarray:
        """Episode ``episode``'s goal relative to home (ENU, m): the configured one, or waypoint k."""
        if self.waypoints is None:
            assert self.config.mission.goal_rel_home_enu_m is not None  # the config loader checks it
            return np.asarray(self.config.mission.goal_rel_home_enu_m, dtype=np.float64)
        return np.asarray(self.waypoints[episode - 1].goal_rel_home_enu_m, dtype=np.float64)

    async def _report_progress(self, vehicle: Vehicle, episode: int) -> None:
        """Make episode ``episode``'s waypoint the current mission item, so every ground station
        shows it (MISSION_CURRENT).  A refusal costs the display, not the flight: logged."""
        if self.waypoints is None:
            return
        seq = self.waypoints[episode - 1].seq
        try:
            await vehicle.set_current_mission_item(seq)
        except VehicleError as err:
            log.error("the ground station will not show mission item %d as current: %s", seq, err)

    # ------------------------------------------------------------------ the two ways to fly

    async def _pilot_episodes(self, vehicle: Vehicle, loop: FlightLoop, model: PolicyModel) -> int:
        """Wait for the pilot's switch to offboard, fly, repeat (``mission.max_episodes``)."""
        max_episodes = self.config.mission.max_episodes if self.waypoints is None else len(self.waypoints)
        episode = 0
        while max_episodes == 0 or episode < max_episodes:
            episode += 1
            state = await self._wait_for_offboard(vehicle, episode)
            try:
                recorder = self._open_recorder(model, episode)
            except RecorderRefusal as err:
                # The pilot's switch cannot be prevented, only answered: hover, then Hold at once.
                log.error("episode %d refused, hover then Hold: %s", episode, err)
                self.flight.enter(Phase.ENTERING_OFFBOARD)
                await loop.safe_stop()
                self.flight.enter(Phase.HOLDING)
                self.summary["episodes"].append({"episode": episode, "outcome": "refused", "abort_reason": str(err)})
                self.notifier.status(f"episode {episode}: refused ({err})")
                continue
            await self._report_progress(vehicle, episode)
            await self._episode(loop, model, episode, state, recorder)
        return EXIT_OK

    async def _dry_run(self, script: EpisodeScript, model: PolicyModel) -> int:
        """The episode script (``runtime.programs.episode``): arm, take off, enter offboard, fly one
        episode, land (``mission.allow_arm_takeoff``).  With a mission, one flight: an episode per
        waypoint, each with its own log, re-entering offboard from Hold for the next one."""
        loop = script.loop
        recorder: Recorder | None = None
        episode = 0
        episodes = 1 if self.waypoints is None else len(self.waypoints)

        async def before_offboard() -> None:  # the log opens before offboard: it records the request too
            nonlocal recorder, episode
            episode += 1
            recorder = self._open_recorder(model, episode)
            loop.recorder = recorder
            await self._report_progress(script.vehicle, episode)

        async def refused(result: EpisodeResult, t_request_ns: int) -> None:
            loop.recorder = None
            if recorder is not None:
                await self._close_log(recorder)
            self._record_episode(result, episode, recorder)

        try:
            await script.dry_run(
                self.config.mission.takeoff_alt_m,
                # the last episode lands after it: a goal reached is followed by the retreat and the landing
                lambda state: self._episode(loop, model, episode, state, recorder, landing_next=episode == episodes),
                before_offboard=before_offboard,
                on_refused=refused,
                episodes=episodes,
            )
        except RecorderRefusal as err:
            self.summary["error"] = f"offboard refused: {err}"
            return EXIT_CONFIG
        finally:
            self.summary["takeoff_climb"] = script.takeoff_climb
        if loop.watchdog.pilot_took_over:
            return EXIT_FAILED
        flown = self.summary["episodes"]
        return EXIT_OK if len(flown) == episodes and all(e["outcome"] == "success" for e in flown) else EXIT_FAILED

    async def _wait_for_offboard(self, vehicle: Vehicle, episode: int) -> VehicleState:
        """Stream hover setpoints and wait until the pilot switches *into* offboard, armed and in the air."""
        seen_outside = False
        last_status = ""
        self.flight.enter(Phase.WAITING_FOR_PILOT)
        while True:
            await vehicle.set_velocity_body(HOVER)  # ignored outside offboard; lets the pilot select it
            state = vehicle.state()
            if state.flight_mode != MODE_OFFBOARD:
                seen_outside = True
            elif seen_outside and state.armed and state.in_air:
                log.info("the pilot switched to offboard: episode %d", episode)
                return state
            if not seen_outside:
                status = "the vehicle is already in offboard: switch out of it and back to hand it to cmnav"
            else:
                status = (f"episode {episode}: waiting for the pilot to arm, take off and switch to offboard "
                          f"(armed {state.armed}, in air {state.in_air}, mode {state.flight_mode})")  # fmt: skip
            if status != last_status:
                self._status(status)
                last_status = status
            self.notifier.loop_alive()
            await asyncio.sleep(PILOT_POLL_S)

    async def _episode(
        self, loop: FlightLoop, model: PolicyModel, episode: int, state: VehicleState, recorder: Recorder | None,
        landing_next: bool = False,
    ) -> EpisodeResult:  # fmt: skip
        """One offboard episode toward the goal (relative to home), recorded to its own log;
        ``landing_next``: a dry run's last episode (``FlightLoop.fly``: the retreat and landing after a goal reached)."""
        assert state.home_enu_m is not None
        goal_enu_m = state.home_enu_m + self._goal_rel_home_enu_m(episode)
        loop.recorder = recorder
        self.flight.enter(Phase.EPISODE)
        item = "" if self.waypoints is None else f" (mission item {self.waypoints[episode - 1].seq})"
        self._status(f"episode {episode}: flying to the goal {np.round(goal_enu_m - state.home_enu_m, 2).tolist()} m from home{item}")
        try:
            result = await loop.fly(goal_enu_m, self.config.mission.episode_timeout_s, landing_next)
            self.flight.enter(Phase.HOLDING)
        except asyncio.CancelledError:
            # A stop signal: the safe stop now, while this episode's log is still open to record it.
            await self.stop(loop, loop.vehicle)
            if loop.interrupted is not None:
                self._record_episode(loop.interrupted, episode, recorder, abort_reason=f"stopped by {self.summary['stop']['cause']}")
            raise
        finally:
            loop.recorder = None
            if recorder is not None:
                await self._close_log(recorder)
        self._record_episode(result, episode, recorder)
        log.info("episode %d: %s in %.2f s (%d steps, final distance %.2f m, trips %s)", episode, result.outcome,
                 result.time_s, result.steps, result.final_distance_m, [t["cause"] for t in result.watchdog_trips])  # fmt: skip
        self.notifier.status(f"episode {episode}: {result.outcome}" + (f" ({result.abort_reason})" if result.abort_reason else ""))
        return result

    def _record_episode(self, result: EpisodeResult, episode: int, recorder: Recorder | None, abort_reason: str | None = None) -> None:
        record = result.summary()
        record.update(episode=episode, log=str(recorder.path) if recorder else None,
                      goal_rel_home_enu_m=self._goal_rel_home_enu_m(episode).round(3).tolist())  # fmt: skip
        if self.waypoints is not None:
            record["mission_item"] = self.waypoints[episode - 1].seq
        if recorder is not None:
            record.update(log_error=recorder.stats.log_error, log_records_written=recorder.stats.written,
                          log_records_dropped=recorder.stats.dropped)  # fmt: skip
        if abort_reason is not None:
            record["abort_reason"] = abort_reason
        self.summary["episodes"].append(record)
        if recorder is not None:
            self._start_report(recorder.path, record)

    def _start_report(self, log_path: Path, record: dict) -> None:
        """Draw the episode's report beside its log (``runtime.report``) on the report thread: the
        next episode may already be flying.  A failure is a warning, never the flight's."""
        self._reports.submit(log_path, record)

    def _open_recorder(self, model: PolicyModel, episode: int) -> Recorder | None:
        """The episode's log, opened (and its first record written) before offboard.  If it cannot
        be written: :class:`RecorderRefusal` (``recorder.required``), else None (flies unrecorded)."""
        cfg = self.config.recorder
        if cfg.log_dir is None:
            return None
        try:
            rotate_logs(cfg.log_dir, cfg.max_logs, cfg.max_total_gb)
            path = new_log_path(cfg.log_dir, episode)
            recorder = Recorder(path, cfg, metadata={**model.log_metadata(), "entry": "fly", "episode": str(episode)})
        except (OSError, RecorderError) as err:
            self.summary["log_error"] = str(err)
            if cfg.required:
                raise RecorderRefusal(f"the flight log cannot be written ({err}); recorder.required = true "
                                      "refuses to fly unrecorded (free disk space, or set it false)") from err  # fmt: skip
            log.error("episode %d is not recorded (recorder.required = false): %s", episode, err)
            return None
        self.summary["logs"].append(str(path))
        return recorder

    async def _close_log(self, recorder: Recorder) -> None:
        await close_step("the flight log", lambda: in_daemon_thread("recorder-close", recorder.close))
        if recorder.stats.log_error is not None:
            self.summary["log_error"] = recorder.stats.log_error

    # ------------------------------------------------------------------ helpers

    def _status(self, text: str) -> None:
        log.info("%s", text)
        self.notifier.status(text)

    async def _alive_while(self, awaitable: Awaitable[T]) -> T:
        """Await ``awaitable`` (which has its own timeout) while reporting the event loop alive."""
        task = asyncio.ensure_future(awaitable)
        try:
            while not task.done():
                self.notifier.loop_alive()
                await asyncio.wait({task}, timeout=ALIVE_PERIOD_S)
            return task.result()
        finally:
            task.cancel()  # nothing when done; stops the inner wait when we are cancelled


async def _main(program: FieldProgram) -> int:
    program.signals = cancel_on_stop_signals()
    try:
        return await program.run()
    except FlyError as err:
        log.error("%s", err)
        program.summary["error"] = str(err)
        return err.exit_code
    except asyncio.CancelledError:
        await program.stop(None, None)  # stopped before the vehicle existed: recorded, nothing to command
        program.summary["error"] = f"stopped by {program.summary['stop']['cause']}"
        return EXIT_OK


def with_camera_bag(config: RuntimeConfig, path: str | Path) -> RuntimeConfig:
    """``config`` with its camera replaced by a RealSense recording (``cmnav fly --camera-bag``);
    :class:`ConfigError` if the file is missing or not a recording."""
    path = Path(path).absolute()
    if not path.is_file():
        raise ConfigError(f"--camera-bag {path}: no such file (a recording from realsense-viewer or rs.recorder)")
    try:
        camera = dataclasses.replace(config.camera, source="bag", bag=BagCameraConfig(path=path))
    except ValueError as err:  # CameraConfig's checks, naming the key
        raise ConfigError(f"--camera-bag: {err}") from err
    return dataclasses.replace(config, camera=camera)


def run_fly(config_path: str | Path, print_json: bool = False, check_only: bool = False, camera_bag: str | Path | None = None) -> int:
    """Entry of ``cmnav fly``: returns the exit code; with ``print_json`` the summary (episodes,
    logs, error) is printed as one JSON line on stdout at exit.  ``check_only``: validate the
    config and load the model, then exit (0 or 2) without touching the vehicle or camera.
    ``camera_bag``: fly on this RealSense recording instead of the configured camera."""
    try:
        config = load_config(config_path)
        if camera_bag is not None:
            config = with_camera_bag(config, camera_bag)
        prepare_control_process(config.runtime.cpu_affinity)  # before any thread of ONNX Runtime or MAVSDK exists
        if check_only:
            model = load_model(config)
    except (ConfigError, FlyError) as err:
        message = str(err) if str(err).startswith(str(config_path)) else f"{config_path}: {err}"
        log.error("config refused, nothing started: %s", message)
        if print_json:
            print(json.dumps({"episodes": [], "logs": [], "error": f"config: {message}"}))
        return EXIT_CONFIG
    if check_only:
        print(f"{config_path}: config valid; model {model.path} loads on {list(model.providers)} "
              f"(sha256 {model.sha256}); " + (f"goal {list(config.mission.goal_rel_home_enu_m or ())} m from home"
              if config.mission.goal_source == "config" else "goals: the mission's waypoints on the autopilot"))  # fmt: skip
        return EXIT_OK
    notifier = SystemdNotifier() if config.systemd.notify else SystemdNotifier({})
    program = FieldProgram(config, notifier)
    try:
        code = run_bounded(_main(program))
    finally:
        ignore_stop_signals()
        notifier.stopping()
        notifier.close()
    if print_json:
        print(json.dumps(program.summary, default=str))
    return code
