"""The world follower: the SITL world without dynamics, following an external autopilot's pose.

It listens for the autopilot's MAVLink (:class:`PoseLink`), waits until the autopilot is armable
and has reported home and a pose, places the room there (:func:`place_room`), writes the episode
JSON (the goal relative to the autopilot's home, in its local ENU frame, which the runtime
shares), then renders the camera at the followed pose (mount transform of ``sim.camera``) and
serves it on the same camera link as our own vehicle (``sim.sitl.camera_server``).  Every pose is
judged (:class:`Judge`); after a contact, every frame carries ``meta["contact"]`` so the runtime
learns of it over the camera link (the autopilot flies on in its empty world and cannot tell).
No frame is served at a pose older than POSE_STALE_S (a dead pose link must look like a dead
camera to the runtime, not like a vehicle hovering still).
Camera faults (``--inject camera-stall@S`` etc., ``sim.follower.faults``) act on the served
frames with our vehicle's hooks (``sim.sitl.faults.VehicleFaults``), S seconds after the
autopilot's first OFFBOARD as the follower sees it in HEARTBEAT; the trace's ``injections`` say when
each first acted, as our vehicle's do.
On stop it writes the trace JSON in our vehicle's format plus the verdict, the placement and
the pose-stream counts.

Threads: the main thread polls the link and judges; the camera renders in its own thread from
the latest followed pose (replaced, never mutated); the frame server sends from its own.
"""

from __future__ import annotations

import dataclasses
import logging
import select
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.camera.frame import Frame
from runtime.contract.frames import euler_from_quat, ned_to_enu, quat_ned_frd_to_enu_flu
from runtime.faults.catalogue import Injection
from sim.camera import CameraModel
from sim.sitl.airframe import LANDING_GEAR_HEIGHT_M
from sim.sitl.camera_feed import DEPTH_MODES, CameraFeed
from sim.sitl.camera_server import FrameServer
from sim.sitl.faults import VehicleFaults
from sim.sitl.kinematics import Kinematics
from sim.sitl.records import Trace, episode_record, write_json_atomic
from sim.world import make_worlds

from .faults import check_follower_injections
from .judge import Judge
from .placement import Placement, place_room
from .pose_link import READY_SYSTEM_STATES, PoseLink

log = logging.getLogger(__name__)

POLL_S = 0.01
WAIT_LOG_PERIOD_S = 5.0
TRACE_PERIOD_S = 0.015  # every pose at the requested 50 Hz, with room for jitter
# A frame rendered at a pose older than this would show the runtime a view that no longer is:
# none is served (the runtime's stale-frame watchdog then trips, as for a dead camera).
POSE_STALE_S = 0.5
# PX4 sends HEARTBEAT at 1 Hz on every link: the mode log sees a change up to this late, and a
# mode held for less may not appear at all (written to the trace for sim.fault_report).
AUTOPILOT_HEARTBEAT_PERIOD_S = 1.0


class FollowerNotReadyError(RuntimeError):
    """The autopilot did not become ready (armable, home, pose) in time."""


@dataclass(frozen=True)
class FollowerConfig:
    """One follower: where the autopilot's MAVLink arrives (host, port), the camera port on
    127.0.0.1, the world (level, seed), output files, camera rate (Hz), depth degradation, the
    offboard time limit the judge applies (s), how long to wait for the autopilot (s) and the
    camera faults to inject (times from the autopilot's first OFFBOARD)."""

    listen_host: str
    listen_port: int
    camera_port: int
    level: int
    seed: int
    episode_json: Path
    trace_json: Path
    status_json: Path | None = None
    camera_hz: float = 15.0
    degrade: str = "none"
    timeout_s: float = 60.0
    ready_timeout_s: float = 60.0
    injections: tuple[Injection, ...] = ()

    def validate(self) -> None:
        """Raise ValueError naming the bad option (an InjectionError for a fault it cannot inject)."""
        check_follower_injections(self.injections)
        if self.degrade not in DEPTH_MODES:
            raise ValueError(f"--degrade {self.degrade!r} must be one of {', '.join(DEPTH_MODES)}")
        if self.level < 0:
            raise ValueError(f"--level {self.level} must be >= 0")
        if not 0.0 < self.camera_hz <= 60.0:
            raise ValueError(f"--camera-hz {self.camera_hz} must be in (0, 60]")
        if not self.timeout_s > 0.0:
            raise ValueError(f"--timeout-s {self.timeout_s} must be > 0")
        if not self.ready_timeout_s > 0.0:
            raise ValueError(f"--ready-timeout-s {self.ready_timeout_s} must be > 0")
        for name, port in (("--autopilot port", self.listen_port), ("--camera-port", self.camera_port)):
            if not 0 <= port < 65536:
                raise ValueError(f"{name} {port} must be a port number in 0..65535")


class WorldFollower:
    """Builds the world and opens the link and camera port in ``__init__``; follows in :meth:`run`."""

    def __init__(self, config: FollowerConfig) -> None:
        config.validate()
        self._config = config
        self._world = make_worlds(config.level, config.seed, 1)
        self._link = PoseLink(config.listen_host, config.listen_port)
        self._server = FrameServer(config.camera_port)
        self._camera = CameraModel()
        self._placement: Placement | None = None
        self._judge: Judge | None = None
        self._kin: Kinematics | None = None
        self._trace = Trace(period_s=TRACE_PERIOD_S)
        self._mode_log: list[tuple[float, str]] = []
        self._events_seen = 0
        self._feed: CameraFeed | None = None
        self._contact: dict | None = None
        self._stale_frames = 0
        self._faults = VehicleFaults(config.injections, config.seed)

    @property
    def link_port(self) -> int:
        return self._link.local_port

    @property
    def camera_port(self) -> int:
        return self._server.port

    @property
    def followed(self) -> Kinematics | None:
        """The latest followed pose in the room (world ENU, body FLU), None before placement."""
        return self._kin

    def run(self, stop: threading.Event) -> None:
        """Wait for the autopilot, place the room, follow until ``stop``; always writes the trace."""
        try:
            self._wait_ready(stop)
            while not stop.is_set():
                self._poll()
        finally:
            if self._feed is not None:
                self._feed.stop()
            self._server.close()
            self._link.close()
            self._write_trace()

    # ---- start ----------------------------------------------------------------------------

    def _wait_ready(self, stop: threading.Event) -> None:
        t_start = time.monotonic()
        t_log = t_start
        while not stop.is_set():
            self._poll()
            missing = self._missing()
            if not missing:
                self._place()
                return
            now = time.monotonic()
            if now - t_start > self._config.ready_timeout_s:
                raise FollowerNotReadyError(
                    f"the autopilot was not ready within {self._config.ready_timeout_s:.0f} s: {', '.join(missing)}. "
                    f"Is it running and sending MAVLink to udp {self._config.listen_host}:{self._link.local_port}?"
                )
            if now - t_log >= WAIT_LOG_PERIOD_S:
                t_log = now
                log.info("waiting for the autopilot: %s", ", ".join(missing))

    def _missing(self) -> list[str]:
        v = self._link.view
        missing = []
        if v.system_id is None:
            missing.append("no HEARTBEAT yet")
        else:
            if v.home_local_ned_m is None:
                missing.append("no HOME_POSITION")
            if v.pose() is None:
                missing.append("no LOCAL_POSITION_NED + ATTITUDE_QUATERNION")
            if v.system_status not in READY_SYSTEM_STATES:
                missing.append(f"still booting (HEARTBEAT system_status {v.system_status}, not STANDBY)")
            if not v.prearm_ok:
                missing.append("pre-arm checks not passed (SYS_STATUS health bit MAV_SYS_STATUS_PREARM_CHECK)")
        return missing

    def _place(self) -> None:
        v = self._link.view
        pose = v.pose()
        heading = float(euler_from_quat(quat_ned_frd_to_enu_flu(pose.quat_ned_frd))[2])
        described = self._world.describe(0)
        self._placement = place_room(ned_to_enu(v.home_local_ned_m), heading, described["start_m"], LANDING_GEAR_HEIGHT_M)
        home_world = self._placement.origin_world_enu_m
        goal_world = np.asarray(described["goal_m"], dtype=np.float64)
        self._judge = Judge(self._world, goal_world, home_world, self._config.timeout_s)
        self._follow_pose()
        # The first frame is rendered (the renderer compiled) before anyone is told to connect.
        self._start_camera()
        c = self._config
        record = episode_record(self._world, home_world, c.level, c.seed, c.listen_port, self._server.port, self._link.local_port)
        # The runtime adds this to its home in its local ENU: the autopilot's frame, not the room's.
        record["goal_rel_home_enu_m"] = self._placement.local_from_world(goal_world - home_world).tolist()
        record["placement"] = self._placement.record()
        record["autopilot"] = {"system_id": v.system_id, "address": list(self._link.peer or ())}
        write_json_atomic(c.episode_json, record)
        log.info("room placed at the autopilot's home %s (local ENU m), heading %.1f deg; goal %s m from home (local ENU)",
                 np.round(self._placement.home_local_enu_m, 2).tolist(), np.degrees(heading),
                 np.round(record["goal_rel_home_enu_m"], 2).tolist())  # fmt: skip

    def _start_camera(self) -> None:
        self._feed = CameraFeed(self._world, self._camera, lambda: self._kin, self._publish, self._config.camera_hz,
                                self._config.degrade, seed=self._config.seed)  # fmt: skip
        self._feed.start()
        self._server.start()

    # ---- following ------------------------------------------------------------------------

    def _poll(self) -> None:
        select.select([self._link], [], [], POLL_S)
        changed = self._link.poll(time.monotonic())
        if "HEARTBEAT" in changed:
            self._note_mode()
            self._trace.note_armed(time.monotonic(), self._link.view.armed)
        if "pose" in changed and self._placement is not None:
            self._follow_pose()
        events = self._link.view.events
        if len(events) > self._events_seen:
            self._trace.events.extend(events[self._events_seen :])
            self._events_seen = len(events)

    def _note_mode(self) -> None:
        mode = self._link.view.mode
        if self._mode_log and self._mode_log[-1][1] == mode:
            return
        t_s = time.monotonic()
        self._mode_log.append((t_s, mode))
        log.info("autopilot mode %s", mode)
        if mode == "OFFBOARD":
            self._faults.note_offboard(t_s)  # only the first entry counts
            if self._judge is not None:
                self._judge.offboard_entered(t_s, self._kin)
        if self._config.status_json is not None:
            write_json_atomic(self._config.status_json, {"mode_log": [[t, m] for t, m in self._mode_log]})

    def _follow_pose(self) -> None:
        v = self._link.view
        kin = self._placement.kinematics(v.pose(), v.on_ground)
        self._kin = kin
        t_s = kin.t_ns * 1e-9
        contact = self._judge.observe(t_s, kin)
        if contact is not None:
            self._contact = contact
            self._trace.record_collision(t_s, kin.pos_enu_m, contact["what"])
        self._trace.sample(t_s, kin.pos_enu_m, kin.vel_enu_m_s, kin.yaw_enu_rad)

    def _publish(self, frame: Frame) -> None:
        """Camera thread: no frame at a stale pose; an injected camera fault acts on what is
        served; after a contact every frame says so (the runtime's only way to know)."""
        kin = self._kin
        # Judged on the rendered frame's stamp, before a fault: a garbage frame stamped in the
        # future is a camera fault to serve, not a stale pose.
        age_s = (frame.t_capture_ns - kin.t_ns) * 1e-9
        if age_s > POSE_STALE_S:
            self._stale_frames += 1
            if self._stale_frames == 1 or self._stale_frames % 100 == 0:
                log.error("the autopilot's pose is %.1f s old: serving no frames (%d withheld so far)", age_s, self._stale_frames)
            return
        frame = self._faults.camera_frame(frame, time.monotonic())
        if frame is None:  # camera-stall: the link stays open and silent
            return
        contact = self._contact
        if contact is not None:
            frame = dataclasses.replace(frame, meta={**frame.meta, "contact": contact})
        self._server.publish(frame)

    # ---- end ------------------------------------------------------------------------------

    def _write_trace(self) -> None:
        v = self._link.view
        record = self._trace.to_record(self._mode_log, self._server.served(), self._faults.injected)
        record["verdict"] = self._judge.verdict.record() if self._judge is not None else None
        record["mode_log_period_s"] = AUTOPILOT_HEARTBEAT_PERIOD_S
        record["placement"] = self._placement.record() if self._placement is not None else None
        rate_hz = v.position_rate_hz()
        record["pose_stream"] = {"position_messages": v.position_messages, "attitude_messages": v.attitude_messages,
                                 "position_rate_hz": None if rate_hz is None else round(rate_hz, 1),
                                 "frames_withheld_stale_pose": self._stale_frames,
                                 "frames_withheld_unphysical": self._feed.withheld_unphysical if self._feed else 0,
                                 "ground_truth_messages": v.truth_messages,
                                 "followed": "ground truth" if v.truth_messages else "estimate",
                                 "bad_datagrams": self._link.bad_datagrams}  # fmt: skip
        write_json_atomic(self._config.trace_json, record)
        log.info("trace written to %s: %d poses, %d frames served, contact %s", self._config.trace_json,
                 len(record["t_s"]), record["frames_served"], record["collision"])  # fmt: skip
