"""The SITL vehicle: world + airframe + PX4-like autopilot over MAVLink + camera server, stepped
in real time.

Threads: the main thread runs the physics and MAVLink loop (one thread, so the autopilot needs no
locks): it waits on the MAVLink socket until the next physics deadline, handles what arrived,
then steps.  Deadlines advance by whole periods from a fixed origin (no drift); if the loop
falls more than MAX_LAG_S behind it re-phases and logs the overrun.  The camera renders in its
own thread from the latest pose, and the frame server sends from its own threads.
"""

from __future__ import annotations

import logging
import math
import select
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from runtime.camera.frame import Frame
from runtime.faults.catalogue import Injection
from sim.camera import CameraModel
from sim.dynamics import PX4_SIH_V1_16, DynamicsParams
from sim.episode_args import check_level_seed
from sim.world import make_worlds

from .airframe import Airframe
from .autopilot import Autopilot
from .camera_feed import DEPTH_MODES, CameraFeed
from .camera_server import FrameServer
from .commander import Commander
from .estimate import ESTIMATES, SitlEstimate
from .faults import VehicleFaults
from .flight_tasks import VelocityCommand
from .geodetic import GeodeticHome
from .kinematics import Kinematics
from .mavlink_endpoint import COMPONENT_ID, SYSTEM_ID, MavlinkEndpoint
from .mission import MissionServer
from .params import ParamTable
from .px4 import OFFBOARD, POSCTL
from .records import Trace, episode_record, write_json_atomic
from .streams import StreamScheduler
from .telemetry import Telemetry

log = logging.getLogger(__name__)


MAX_LAG_S = 0.25
# What the velocity controller gets while the vehicle-stuck fault acts (sim.sitl.faults).
STUCK_COMMAND = VelocityCommand(vel_enu_m_s=np.zeros(3), yaw_rate_enu_rad_s=0.0)


# The vehicle's velocity response, by name (SitlConfig.dynamics, --dynamics).
DYNAMICS = {"px4": PX4_SIH_V1_16, "ideal": DynamicsParams()}

@dataclass(frozen=True)
class SitlConfig:
    """One SITL vehicle: ports on 127.0.0.1, the world (curriculum level, seed), output files,
    physics and camera rates (Hz), the faults to inject on itself, where to keep a live status
    (mode log) that others can poll (None: nowhere), whether it stands in for an external
    autopilot, and its second MAVLink link's port."""

    mavlink_port: int
    camera_port: int | None
    level: int
    seed: int
    episode_json: Path
    trace_json: Path
    physics_hz: float = 100.0
    camera_hz: float = 15.0
    injections: tuple[Injection, ...] = ()
    status_json: Path | None = None
    degrade: str = "none"  # the served depth: one of sim.sitl.camera_feed.DEPTH_MODES
    # A stand-in for an external autopilot (PX4 SIH) in tests of the world follower: no camera
    # server, no room (walls, ceiling, obstacles) to hit, only the floor.
    stand_in: bool = False
    # A second MAVLink link (as PX4's GCS link to 14550), to 127.0.0.1:pose_port; None = none.
    pose_port: int | None = None
    # Heading at spawn, degrees counter-clockwise from the room's +x (PX4 SIH starts facing
    # north: 90 in ENU); 0 faces the goal side, as in training.
    heading_deg: float = 0.0
    # PX4's start-up (UNINIT, then STANDBY, then the pre-arm checks passing) at this fraction of
    # its recorded 4.25 s / 5.27 s (sim.sitl.commander): 1.0 as PX4, 0 ready at once.
    boot_time_scale: float = 0.2
    # The velocity response: "px4" (PX4 v1.16 SIH as identified, sim.dynamics.PX4_SIH_V1_16) or
    # "ideal" (the batched sim's vehicle the shipped policies were trained on).
    dynamics: str = "px4"
    # What the autopilot knows of its state: "exact" (the truth) or "px4" (PX4 SIH's EKF2 as
    # measured, and flown: sim.sitl.estimate).
    estimate: str = "exact"

    def validate(self) -> None:
        """Raise ValueError naming the bad option."""
        if self.estimate not in ESTIMATES:
            raise ValueError(f"--estimate {self.estimate!r} must be one of {', '.join(ESTIMATES)}")
        if self.degrade not in DEPTH_MODES:
            raise ValueError(f"--degrade {self.degrade!r} must be one of {', '.join(DEPTH_MODES)}")
        if self.dynamics not in DYNAMICS:
            raise ValueError(f"--dynamics {self.dynamics!r} must be one of {sorted(DYNAMICS)}")
        if not 0.0 <= self.boot_time_scale <= 1.0:
            raise ValueError(f"--boot-time-scale {self.boot_time_scale} must be in [0, 1]")
        if not -360.0 <= self.heading_deg <= 360.0:
            raise ValueError(f"--heading-deg {self.heading_deg} must be in [-360, 360]")
        check_level_seed(self.level, self.seed)
        if not 10.0 <= self.physics_hz <= 1000.0:
            raise ValueError(f"--physics-hz {self.physics_hz} must be in [10, 1000]")
        if not 0.0 < self.camera_hz <= 60.0:
            raise ValueError(f"--camera-hz {self.camera_hz} must be in (0, 60]")
        ports = [("--mavlink-port", self.mavlink_port), ("--camera-port", self.camera_port), ("--pose-port", self.pose_port)]
        if self.camera_port is None and not self.stand_in:
            raise ValueError("--camera-port is needed (only a --stand-in vehicle runs without a camera)")
        for name, port in ports:
            if port is not None and not 0 < port < 65536:
                raise ValueError(f"{name} {port} must be a port number in 1..65535")


class SitlVehicle:
    """Builds the world and opens both ports in ``__init__``; serves and flies in :meth:`run`."""

    def __init__(self, config: SitlConfig) -> None:
        config.validate()
        self._config = config
        self._t_boot_ns = time.monotonic_ns()
        t_s = self._t_boot_ns * 1e-9
        self._world = make_worlds(config.level, config.seed, 1)
        start = self._world.start_m[0].double().numpy()
        self._airframe = Airframe(self._world, start[:2], yaw_enu_rad=math.radians(config.heading_deg),
                                  params=DYNAMICS[config.dynamics], world_contact=not config.stand_in)  # fmt: skip
        self._home_enu_m = self._airframe.home_enu_m
        self._kin = self._airframe.kinematics(self._t_boot_ns)  # the truth: camera, trace, contacts
        self._estimate = None if config.estimate == "exact" else SitlEstimate(self._kin, 1.0 / config.physics_hz, config.seed)
        geo = GeodeticHome()
        params = ParamTable(takeoff_alt_m=float(start[2] - self._home_enu_m[2]))
        self._faults = VehicleFaults(config.injections, config.seed)
        self._commander = Commander(
            params, self._home_enu_m, self._kin, t_s,
            offboard_allowed=self._faults.offboard_allowed if self._faults.refuses_offboard else None,
            boot_time_scale=config.boot_time_scale,
        )  # fmt: skip
        self._modes_reported = 0
        self._server = None if config.stand_in else FrameServer(config.camera_port)
        self._endpoint = MavlinkEndpoint(config.mavlink_port)
        telemetry = Telemetry(self._home_enu_m, geo, self._t_boot_ns)
        # The mission store and its protocol, on the main link (the ground station's and the runtime's).
        self._mission = MissionServer(self._endpoint.send, SYSTEM_ID, COMPONENT_ID)
        self._autopilot = Autopilot(
            self._endpoint, self._commander, params, telemetry, StreamScheduler(t_s, max_rate_hz=config.physics_hz),
            geo, self._t_boot_ns,
        )  # fmt: skip
        # PX4 runs one MAVLink instance per link, each with its own streams; the commander is shared.
        self._pose_endpoint = None if config.pose_port is None else MavlinkEndpoint(config.pose_port)
        self._pose_autopilot = None if self._pose_endpoint is None else Autopilot(
            self._pose_endpoint, self._commander, params, telemetry, StreamScheduler(t_s, max_rate_hz=config.physics_hz),
            geo, self._t_boot_ns,
        )  # fmt: skip
        self._trace = Trace()
        # The render thread reads self._kin: it is replaced each tick, never mutated, so the
        # reference it gets is always one consistent state.
        self._feed = None
        if self._server is not None:
            publish = self._publish_faulty if self._faults.camera_faults else self._server.publish
            self._feed = CameraFeed(self._world, CameraModel(), lambda: self._kin, publish, config.camera_hz,
                                    config.degrade, seed=config.seed)  # fmt: skip
        self.overruns = 0

    def run(self, stop: threading.Event) -> None:
        """Serve until ``stop`` is set, then close everything and write the trace."""
        try:
            if self._feed is not None:
                self._feed.start()
                self._server.start()
            self._write_episode()
            self._loop(stop)
        finally:
            if self._feed is not None:
                self._feed.stop()
                self._server.close()
            self._endpoint.close()
            if self._pose_endpoint is not None:
                self._pose_endpoint.close()
            self._write_trace()

    def _write_episode(self) -> None:
        c = self._config
        record = episode_record(
            self._world, self._home_enu_m, c.level, c.seed, c.mavlink_port, self._server and self._server.port,
            self._endpoint.local_port,
        )  # fmt: skip
        record["pose_port"] = c.pose_port
        record["stand_in"] = c.stand_in
        write_json_atomic(c.episode_json, record)
        log.info("episode written to %s: goal %s m from home", c.episode_json, [round(v, 2) for v in record["goal_rel_home_enu_m"]])

    def _write_trace(self) -> None:
        served = self._server.served() if self._server is not None else []
        record = self._trace.to_record(self._commander.mode_log, served, self._faults.injected)
        write_json_atomic(self._config.trace_json, record)
        log.info(
            "trace written to %s: %d positions, %d frames served, collision %s; %d physics overruns, "
            "%d camera deadlines skipped",
            self._config.trace_json, len(record["t_s"]), record["frames_served"], record["collision"], self.overruns,
            self._feed.skipped_deadlines if self._feed is not None else 0,
        )  # fmt: skip

    def _loop(self, stop: threading.Event) -> None:
        period_s = 1.0 / self._config.physics_hz
        next_s = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            if now < next_s:
                readable, _, _ = select.select(self._endpoints(), [], [], next_s - now)
                if readable:
                    self._receive(readable)
                continue
            self._tick(period_s)
            next_s += period_s
            lag_s = time.monotonic() - next_s
            if lag_s > MAX_LAG_S:
                self.overruns += 1
                log.warning("physics loop %.0f ms behind real time; re-phasing (overrun %d)", lag_s * 1e3, self.overruns)
                next_s = time.monotonic()

    @property
    def _known(self) -> Kinematics:
        """What the autopilot knows of its state: the truth, or its estimate (``--estimate``)."""
        return self._kin if self._estimate is None else self._estimate.kinematics

    def _endpoints(self) -> list[MavlinkEndpoint]:
        return [self._endpoint] if self._pose_endpoint is None else [self._endpoint, self._pose_endpoint]

    def _receive(self, readable: list[MavlinkEndpoint]) -> None:
        t_s = time.monotonic()
        for endpoint, autopilot in ((self._endpoint, self._autopilot), (self._pose_endpoint, self._pose_autopilot)):
            if endpoint in readable:
                for msg in endpoint.receive():
                    if endpoint is self._endpoint and self._mission.handle(msg, t_s):
                        continue
                    autopilot.handle(msg, self._known, t_s)

    def _tick(self, dt_s: float) -> None:
        t_ns = time.monotonic_ns()
        t_s = t_ns * 1e-9
        self._commander.update(t_s, self._known)
        self._apply_faults(t_s)
        command = self._commander.velocity_command(t_s, self._known) if self._commander.armed else None
        if command is not None and self._commander.mode == OFFBOARD and self._faults.stuck(t_s):
            command = STUCK_COMMAND
        if command is not None and self._estimate is not None and not self._kin.on_ground:
            command = self._estimate.flown(command)
        hit = self._airframe.step(command, dt_s)
        self._kin = self._airframe.kinematics(t_ns)
        if self._estimate is not None:
            self._estimate.update(self._kin)
        if hit is not None:
            self._commander.crash(t_s, hit)
            self._trace.record_collision(t_s, self._kin.pos_enu_m, hit)
        events = self._autopilot.publish(self._known, t_s)
        self._mission.update(t_s)
        if self._pose_autopilot is not None:
            self._pose_autopilot.publish(self._known, t_s, events)
        self._trace.record_events(events)
        self._trace.sample(t_s, self._kin.pos_enu_m, self._kin.vel_enu_m_s, self._kin.yaw_enu_rad)
        self._trace.note_armed(t_s, self._commander.armed)
        if len(self._commander.mode_log) != self._modes_reported:
            self._write_status()

    def _apply_faults(self, t_s: float) -> None:
        if self._commander.mode == OFFBOARD:
            self._faults.note_offboard(self._commander.mode_log[-1][0])
        if self._faults.pilot_takes_over(t_s):
            self._commander.rc_mode_switch(t_s, self._kin, POSCTL)
        self._endpoint.tx_silent = self._faults.telemetry_lost(t_s)
        if self._pose_endpoint is not None:
            self._pose_endpoint.tx_silent = self._endpoint.tx_silent

    def _publish_faulty(self, frame: Frame) -> None:
        """Camera thread: publish what the faulted camera delivers instead of ``frame``."""
        delivered = self._faults.camera_frame(frame, time.monotonic())
        if delivered is not None:
            self._server.publish(delivered)

    def _write_status(self) -> None:
        """The live status file: the mode log so far (time.monotonic s, MAVSDK mode names)."""
        self._modes_reported = len(self._commander.mode_log)
        if self._config.status_json is not None:
            write_json_atomic(self._config.status_json, {"mode_log": [[t, m] for t, m in self._commander.mode_log]})


def start_world_process() -> threading.Event:
    """What a camera-world process (our vehicle, the follower) does first: log to stderr, one
    intra-op torch thread (it shares two cores with the runtime, and a 212x120 render or a batch-1
    dynamics step gains nothing from more), and SIGTERM/SIGINT set the returned event."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)
    stop = threading.Event()

    def on_signal(signum: int, _frame) -> None:
        log.info("%s received: shutting down", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    return stop
