"""Runtime settings as typed dataclasses, with every default in this one file.

The contract (control period, action scaling, goal radius) is not configurable: it comes from
``runtime.contract``.  What a deployment may choose lives here: tighter action limits, watchdog
thresholds, MAVLink connection, camera, mission, timeouts, logging.  Every value is validated
when the dataclass is built; a bad value raises :class:`ConfigError` naming the key and the
allowed range.  The TOML file of ``cmnav fly`` maps onto these dataclasses one to one (a table per
dataclass, a key per field): ``runtime.config_loader.load_config``; ``examples/cmnav.toml``
documents every key.
"""

from __future__ import annotations

import ipaddress
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from .contract import CONTROL_PERIOD_S, ActionLimits
from .tracking import VELOCITY_BIAS_WINDOW_RANGE_S
from .contract.constants import CAMERA_HEIGHT_PX, CAMERA_RATE_HZ, CAMERA_WIDTH_PX, MAX_INCLINATION_RAD, MAX_SPEED_M_S


class ConfigError(ValueError):
    """A configuration value is out of range; the message names the key and the allowed range."""


def _require(ok: bool, key: str, value: object, allowed: str) -> None:
    if not ok:
        raise ConfigError(f"{key}={value!r} is invalid: must be {allowed}")


def _positive(key: str, value: float) -> None:
    _require(isinstance(value, (int, float)) and math.isfinite(value) and value > 0, key, value, "a finite number > 0")


def _within(key: str, value: float, low: float, high: float, unit: str, why: str) -> None:
    """``value`` in [low, high]: the upper bounds keep each safety check able to fire (a watchdog
    period of an hour is a watchdog switched off) and the process sane."""
    _require(isinstance(value, (int, float)) and low <= value <= high, key, value, f"in [{low:g}, {high:g}] {unit} ({why})")


# Upper bounds (and a few lower ones) of the numeric keys, with why; see _within.
_CONTROL_MS = 1000.0 * CONTROL_PERIOD_S
_WATCHDOG_RANGES = {
    "period_s": (0.001, CONTROL_PERIOD_S, "s", "checked at least once per control period"),
    "frame_stale_ms": (_CONTROL_MS, 1000.0, "ms", "from one control period to a second of frames"),
    "step_trip_ms": (_CONTROL_MS, 1000.0, "ms", "from one control period to a second"),
    "telemetry_stale_ms": (20.0, 1000.0, "ms", "PX4 streams position and attitude at 30-50 Hz"),
    "depth_invalid_max_s": (CONTROL_PERIOD_S, 10.0, "s", "blind flight is cut short"),
    "hold_grace_s": (0.0, 5.0, "s", "the hover before Hold ends"),
    "brake_speed_m_s": (0.05, 1.0, "m/s", "a vehicle that is still moving is not stopped"),
    "brake_timeout_s": (0.0, 8.0, "s", "inside systemd's 15 s stop timeout"),
    "brake_gain": (0.0, 2.0, "", "0 = a zero-velocity setpoint; above 2 the delay makes it reverse"),
    "brake_setpoint_max_m_s": (0.1, MAX_SPEED_M_S, "m/s", "no faster than the policy may fly"),
    "offboard_loss_s": (0.1, 60.0, "s", "PX4's COM_OF_LOSS_T range"),
    "geofence_radius_m": (0.0, 200.0, "m", "a fence the vehicle can reach"),
    "altitude_max_m": (0.0, 120.0, "m", "a band below the usual 120 m ceiling"),
    "tracking_window_s": (CONTROL_PERIOD_S, 5.0, "s", "a stuck vehicle is caught within seconds"),
    "tilt_window_s": (0.0, 2.0, "s", "a flip is caught before the vehicle falls"),
}
_VEHICLE_TIMEOUT_MAX_S = {"connect_timeout_s": 600.0, "command_timeout_s": 10.0, "health_timeout_s": 600.0,
                          "takeoff_timeout_s": 300.0, "land_timeout_s": 600.0}  # fmt: skip
URL_MAX_CHARS = 256


@dataclass(frozen=True)
class WatchdogConfig:
    """Thresholds of the safety watchdog (DESIGN §3).

    Times are in milliseconds or seconds as named; positions are metres in the local ENU frame,
    altitudes are above home.
    """

    frame_stale_ms: float = 250.0  # no fresh camera frame for this long -> trip (~3.75 frames)
    # A step (frame taken -> command sent) longer than this trips; steps longer than the control
    # period but shorter than this only count as missed deadlines.  The same limit applies to the
    # time since the last policy command (a stalled loop: MAVSDK keeps re-sending the last one).
    step_trip_ms: float = 2000.0 * CONTROL_PERIOD_S
    telemetry_stale_ms: float = 500.0  # no position/attitude update for this long -> trip
    depth_invalid_frac_max: float = 0.9  # raw depth invalid fraction above this ...
    depth_invalid_max_s: float = 3.0  # ... for longer than this -> trip
    geofence_radius_m: float = 20.0  # horizontal distance from where offboard started
    altitude_min_m: float = 0.2  # band above home
    altitude_max_m: float = 8.0
    # Every end of an episode (goal, time limit, trip, stop signal) brakes before leaving offboard:
    # for at least hold_grace_s and until the measured speed is below brake_speed_m_s (or
    # brake_timeout_s has passed), then offboard.stop() (PX4 Hold).  The brake's setpoint opposes
    # the measured velocity, -brake_gain x v (at most brake_setpoint_max_m_s), while that velocity
    # is fresh, and is zero otherwise (or with brake_gain = 0).  PX4 does not stop on a zero
    # setpoint alone: its velocity integral keeps pushing, and in the PX4 campaign the vehicle
    # stopped 1.9 m past where it braked, into the wall behind the goal; against its identified
    # response (sim.dynamics.PX4_SIH_V1_16) gain 1 stops it in 1.3 m, with no reversal.
    hold_grace_s: float = 1.0
    brake_speed_m_s: float = 0.2
    brake_timeout_s: float = 4.0
    brake_gain: float = 1.0
    brake_setpoint_max_m_s: float = 1.5
    # PX4's COM_OF_LOSS_T: with the link down this long, the autopilot's offboard-loss failsafe
    # takes the vehicle out of offboard; a mode change after such a gap is that failsafe
    # (offboard_loss_failsafe), not a pilot.  Set it to the autopilot's COM_OF_LOSS_T.
    offboard_loss_s: float = 1.0
    period_s: float = 0.02  # how often the watchdog task checks the time-based trips
    # Tracking (runtime.tracking): the measured velocity against the command passed through a
    # first-order lag of tracking_lag_s; an error (vehicle frame, m/s) above tracking_error_max_m_s
    # for longer than tracking_window_s trips.  Tuned on SITL flights of the default model (levels 0
    # and 3, mostly at 2 m/s: error p95 0.33 m/s, max 0.35 m/s; the largest error held for a whole
    # window 0.14-0.18 m/s) and the goal-seeker, with room for a real PX4: 2.0 m/s commanded levels
    # at ~1.6 m/s and the height drifts ~0.3 m/s (0.5 m/s together; tests/runtime/test_tracking.py
    # flies that model); a stuck vehicle commanded the goal-seeker's 1 m/s cruise shows 1 m/s.
    tracking_error_max_m_s: float = 0.8
    tracking_window_s: float = 1.0
    tracking_lag_s: float = 0.5
    # Attitude: tilt (body up axis vs world up) above this for longer than tilt_window_s trips: the
    # vehicle is flipped or tumbling.  PX4's failure detector uses the same defaults (FD_FAIL_R/P
    # 60 deg, FD_FAIL_R/P_TTRI 0.3 s); the contract's inclination limit (45 deg) is the floor.
    tilt_max_deg: float = 60.0
    tilt_window_s: float = 0.3

    def __post_init__(self) -> None:
        for key in (
            "frame_stale_ms",
            "step_trip_ms",
            "telemetry_stale_ms",
            "depth_invalid_max_s",
            "geofence_radius_m",
            "altitude_max_m",
            "hold_grace_s",
            "brake_speed_m_s",
            "period_s",
            "tracking_window_s",
            "tilt_window_s",
        ):
            _positive(f"watchdog.{key}", getattr(self, key))
        _require(
            isinstance(self.tracking_error_max_m_s, (int, float)) and 0.1 <= self.tracking_error_max_m_s <= MAX_SPEED_M_S,
            "watchdog.tracking_error_max_m_s",
            self.tracking_error_max_m_s,
            f"in [0.1, {MAX_SPEED_M_S}] m/s (the contract's top speed: a larger bound could never trip)",
        )
        _require(
            isinstance(self.tracking_lag_s, (int, float)) and 0.05 <= self.tracking_lag_s <= 2.0,
            "watchdog.tracking_lag_s",
            self.tracking_lag_s,
            "in [0.05, 2] s (the velocity controller's time constant)",
        )
        _require(
            isinstance(self.tilt_max_deg, (int, float)) and math.degrees(MAX_INCLINATION_RAD) <= self.tilt_max_deg < 180.0,
            "watchdog.tilt_max_deg",
            self.tilt_max_deg,
            f"in [{math.degrees(MAX_INCLINATION_RAD):.0f}, 180) deg (no lower than the contract's inclination limit)",
        )
        _require(
            self.step_trip_ms >= 1000.0 * CONTROL_PERIOD_S,
            "watchdog.step_trip_ms",
            self.step_trip_ms,
            f">= the control period ({1000.0 * CONTROL_PERIOD_S:.1f} ms)",
        )
        _require(
            0.0 < self.depth_invalid_frac_max <= 1.0,
            "watchdog.depth_invalid_frac_max",
            self.depth_invalid_frac_max,
            "in (0, 1]",
        )
        _require(
            0.0 <= self.altitude_min_m < self.altitude_max_m,
            "watchdog.altitude_min_m",
            self.altitude_min_m,
            f"in [0, altitude_max_m={self.altitude_max_m})",
        )
        for key, (low, high, unit, why) in _WATCHDOG_RANGES.items():
            _within(f"watchdog.{key}", getattr(self, key), low, high, unit, why)
        _require(
            self.brake_timeout_s >= self.hold_grace_s,
            "watchdog.brake_timeout_s",
            self.brake_timeout_s,
            f">= watchdog.hold_grace_s={self.hold_grace_s} (the brake lasts at least the hover)",
        )


# Connection URL schemes MAVSDK 4 understands.
MAVSDK_URL_SCHEMES = ("udpin", "udpout", "tcpin", "tcpout", "serial", "serial_flowcontrol")
_HOSTNAME = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")


def mavsdk_url_problem(url: object) -> str | None:
    """What is wrong with a MAVSDK connection URL (None: nothing): ``udpin|udpout|tcpin|tcpout://HOST:PORT``
    with an IP address or host name and a port in 1..65535, or ``serial[_flowcontrol]:///dev/X[:BAUD]``."""
    if not isinstance(url, str):
        return "not a string"
    if len(url) > URL_MAX_CHARS:
        return f"longer than {URL_MAX_CHARS} characters"
    scheme, sep, rest = url.partition("://")
    if not sep or scheme not in MAVSDK_URL_SCHEMES:
        return f"unknown scheme {scheme!r}" if sep else "no scheme://"
    if scheme.startswith("serial"):
        device, _, baud = rest.partition(":")
        if not device.startswith("/dev/") or len(device) <= len("/dev/"):
            return f"serial device {device!r} is not a /dev path"
        if baud and not (baud.isdigit() and 1200 <= int(baud) <= 10_000_000):
            return f"baud rate {baud!r} is not a number in [1200, 10000000]"
        return None
    host, colon, port = rest.rpartition(":")
    if not colon or not host:
        return "no HOST:PORT after the scheme"
    if not (port.isdigit() and 0 < int(port) < 65536):
        return f"port {port!r} is not in 1..65535"
    try:
        ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        if not _HOSTNAME.match(host):
            return f"host {host[:40]!r} is neither an IP address nor a host name"
    return None


@dataclass(frozen=True)
class VehicleConfig:
    """MAVLink connection and the timeouts of every await that talks to the autopilot (s)."""

    url: str = "udpin://127.0.0.1:14540"
    connect_timeout_s: float = 10.0  # until the first autopilot heartbeat
    command_timeout_s: float = 5.0  # one MAVSDK command (arm, takeoff, offboard start, ...)
    health_timeout_s: float = 30.0  # until armable with a local position
    takeoff_timeout_s: float = 30.0  # until the takeoff altitude is reached and Hold shows
    land_timeout_s: float = 60.0  # until disarmed after land
    # Fly the command, not the estimate: measure the autopilot's velocity error against the rate
    # of its own position estimate over this window and correct for it (runtime.tracking.VelocityBias).
    velocity_bias_correction: bool = True
    velocity_bias_window_s: float = 0.3

    def __post_init__(self) -> None:
        problem = mavsdk_url_problem(self.url)
        _require(
            problem is None,
            "vehicle.url",
            self.url if not isinstance(self.url, str) or len(self.url) <= 80 else f"{self.url[:80]}... ({len(self.url)} characters)",
            f'a MAVSDK connection URL such as "udpin://127.0.0.1:14540" or "serial:///dev/ttyTHS1:921600" '
            f"(schemes: {', '.join(MAVSDK_URL_SCHEMES)}): {problem}",
        )
        for key in ("connect_timeout_s", "command_timeout_s", "health_timeout_s", "takeoff_timeout_s", "land_timeout_s"):
            _positive(f"vehicle.{key}", getattr(self, key))
            _within(f"vehicle.{key}", getattr(self, key), 0.0, _VEHICLE_TIMEOUT_MAX_S[key], "s", "a wait that ends")
        _within("vehicle.velocity_bias_window_s", self.velocity_bias_window_s, *VELOCITY_BIAS_WINDOW_RANGE_S, "s",
                "a few estimates (PX4 sends ODOMETRY at ~10 Hz or faster)")  # fmt: skip


# The exported model's variants (``cmnav export --variants``): fp32 is the file ``model_path``
# names; the others sit next to it as ``<stem>.<variant>.onnx`` (:func:`variant_path`).
MODEL_VARIANTS = ("fp32", "fp16", "int8")


def variant_path(path: str | Path, variant: str) -> Path:
    """Where ``variant`` of the model ``path`` is: ``model.onnx`` -> ``model.int8.onnx`` (fp32: ``path``)."""
    path = Path(path)
    if variant == "fp32":
        return path
    return path.with_name(f"{path.stem}.{variant}{path.suffix or '.onnx'}")


@dataclass(frozen=True)
class TensorRtConfig:
    """The TensorRT execution provider (Jetson): used when ``policy.providers`` names it.

    TensorRT builds an engine for the model at the first step (minutes on a Jetson), so the
    runtime warms the model up before it tells systemd READY, and keeps the engine in
    ``engine_cache_dir`` so that later starts load it in seconds.  The directory must be writable
    by the service (``ReadWritePaths=`` / ``StateDirectory=``, systemd/README.md)."""

    fp16: bool = True  # let TensorRT run layers in fp16 (the model file stays fp32)
    engine_cache_dir: Path = Path("/var/lib/cmnav/trt-engines")
    max_workspace_mb: int = 1024  # TensorRT builder workspace

    def __post_init__(self) -> None:
        _require(
            isinstance(self.max_workspace_mb, int) and 64 <= self.max_workspace_mb <= 65536,
            "policy.tensorrt.max_workspace_mb",
            self.max_workspace_mb,
            "an integer in [64, 65536] MB",
        )


@dataclass(frozen=True)
class PolicyModelConfig:
    """The ONNX model, where it runs, and the deployment's action limits."""

    model_path: Path = Path("model.onnx")
    model_sha256: str | None = None  # when set, the model file must have this SHA-256 (hex)
    # Which export of the model flies: "fp32" (model_path itself), "fp16" or "int8" (the file next
    # to it, model.int8.onnx); its metadata must name the same variant.
    variant: str = "fp32"
    providers: tuple[str, ...] = ("CPUExecutionProvider",)  # in order of preference
    provider_fallback: bool = False  # drop unavailable providers (logged) instead of refusing to start
    intra_op_threads: int = 0  # 0 = ONNX Runtime's default
    warmup_steps: int = 3  # steps run on blank inputs at load, before READY (a TensorRT engine is built here)
    tensorrt: TensorRtConfig = field(default_factory=TensorRtConfig)
    limits: ActionLimits = field(default_factory=ActionLimits)

    @property
    def model_file(self) -> Path:
        """The file that flies: ``model_path`` or its ``variant`` next to it."""
        return variant_path(self.model_path, self.variant)

    def __post_init__(self) -> None:
        _require(self.variant in MODEL_VARIANTS, "policy.variant", self.variant, f"one of {', '.join(MODEL_VARIANTS)}")
        _require(
            isinstance(self.warmup_steps, int) and 0 <= self.warmup_steps <= 100,
            "policy.warmup_steps",
            self.warmup_steps,
            "an integer in [0, 100]",
        )
        _require(len(self.providers) > 0, "policy.providers", self.providers, "a non-empty list of execution providers")
        _require(
            self.model_sha256 is None
            or (len(self.model_sha256) == 64 and all(ch in "0123456789abcdef" for ch in self.model_sha256.lower())),
            "policy.model_sha256",
            self.model_sha256,
            "64 hexadecimal digits (`sha256sum MODEL`)",
        )
        cpus = len(os.sched_getaffinity(0))  # the CPUs this process may run on
        _require(
            isinstance(self.intra_op_threads, int) and 0 <= self.intra_op_threads <= cpus,
            "policy.intra_op_threads",
            self.intra_op_threads,
            f"an integer in [0, {cpus}] (0 = ONNX Runtime's default; at most the CPUs this process may run on)",
        )


@dataclass(frozen=True)
class RecorderConfig:
    """The MCAP flight log."""

    log_dir: Path | None = Path("logs")  # None = do not record
    flush_period_s: float = 0.5  # a killed process loses at most about this much
    queue_size: int = 64  # records waiting for the writer thread; beyond that they are dropped
    # Rotation (cmnav fly: one log per offboard episode): before a log starts, the oldest are
    # deleted so that at most max_logs remain and the older ones take at most max_total_gb.
    max_logs: int = 50
    max_total_gb: float = 20.0
    # The log cannot be written (full disk, I/O error) before offboard: true = refuse offboard
    # (a dry run lands; a pilot's switch gets hover, then Hold), false = fly unrecorded.
    required: bool = True

    def __post_init__(self) -> None:
        _require(isinstance(self.required, bool), "recorder.required", self.required, "true or false")
        _require(
            isinstance(self.flush_period_s, (int, float)) and 0.0 < self.flush_period_s <= 1.0,
            "recorder.flush_period_s",
            self.flush_period_s,
            "in (0, 1] s",
        )
        _require(
            isinstance(self.queue_size, int) and self.queue_size >= 8,
            "recorder.queue_size",
            self.queue_size,
            "an integer >= 8",
        )
        _require(isinstance(self.max_logs, int) and self.max_logs >= 1, "recorder.max_logs", self.max_logs, "an integer >= 1")
        _positive("recorder.max_total_gb", self.max_total_gb)
        _within("recorder.queue_size", self.queue_size, 8, 4096, "records", "memory the writer may fall behind by")
        _within("recorder.max_logs", self.max_logs, 1, 100_000, "logs", "a directory listing that stays quick")
        _within("recorder.max_total_gb", self.max_total_gb, 0.0, 100_000.0, "GB", "a disk")


# D455 modes with both depth and color at 15 fps and (within 1 %) the contract's 848:480 aspect.
D455_MODES = ((848, 480), (424, 240), (1280, 720), (640, 360), (480, 270))
FRAME_TIMEOUT_MAX_MS = 5000  # a longer wait hides a dead camera from the start-up checks


@dataclass(frozen=True)
class RealSenseConfig:
    """D455 stream settings (the ``[camera.realsense]`` table of the runtime config)."""

    width_px: int = CAMERA_WIDTH_PX
    height_px: int = CAMERA_HEIGHT_PX
    fps: int = int(CAMERA_RATE_HZ)
    emitter_enabled: bool = True  # IR projector; off = the paper's degraded-depth condition
    serial: str | None = None  # None = the first device found
    frame_timeout_ms: int = 1000

    def __post_init__(self) -> None:
        if self.fps != int(CAMERA_RATE_HZ):
            raise ValueError(f"camera.realsense.fps={self.fps!r} is invalid: must be {int(CAMERA_RATE_HZ)} (the policy runs at the camera rate)")
        if (self.width_px, self.height_px) not in D455_MODES:
            modes = ", ".join(f"{w}x{h}" for w, h in D455_MODES)
            raise ValueError(
                f"camera.realsense.width_px x height_px = {self.width_px}x{self.height_px} is invalid: must be a D455 "
                f"mode (depth and color at 15 fps) with the contract's aspect {CAMERA_WIDTH_PX}:{CAMERA_HEIGHT_PX}: {modes}"
            )
        if not 0 < self.frame_timeout_ms <= FRAME_TIMEOUT_MAX_MS:
            raise ValueError(f"camera.realsense.frame_timeout_ms={self.frame_timeout_ms!r} is invalid: must be in (0, {FRAME_TIMEOUT_MAX_MS}] ms")


@dataclass(frozen=True)
class SimCameraConfig:
    """The SITL vehicle's camera link (TCP on 127.0.0.1)."""

    port: int = 0  # required with camera.source = "sim"


@dataclass(frozen=True)
class ReplayCameraConfig:
    """Camera frames played back from an earlier flight log (bench runs without a camera)."""

    path: Path | None = None  # required with camera.source = "replay"


@dataclass(frozen=True)
class BagCameraConfig:
    """A RealSense recording played by librealsense's playback device through the live camera's
    code path (bench runs with a field recording): ``.bag`` (realsense-viewer / rs.recorder up to
    librealsense 2.57) or ``.db3`` (ROS 2 bag, what rs.recorder writes from 2.58 on)."""

    path: Path | None = None  # required with camera.source = "bag"


RECORDING_SUFFIXES = (".bag", ".db3")
CAMERA_SOURCES = ("realsense", "sim", "replay", "bag")


@dataclass(frozen=True)
class CameraConfig:
    """Which camera source the runtime reads (DESIGN §3), and its settings."""

    source: str = "realsense"
    first_frame_timeout_s: float = 10.0  # start-up fails if no frame comes in this long
    realsense: RealSenseConfig = field(default_factory=RealSenseConfig)
    sim: SimCameraConfig = field(default_factory=SimCameraConfig)
    replay: ReplayCameraConfig = field(default_factory=ReplayCameraConfig)
    bag: BagCameraConfig = field(default_factory=BagCameraConfig)

    def __post_init__(self) -> None:
        _require(self.source in CAMERA_SOURCES, "camera.source", self.source, f"one of {', '.join(CAMERA_SOURCES)}")
        _positive("camera.first_frame_timeout_s", self.first_frame_timeout_s)
        _within("camera.first_frame_timeout_s", self.first_frame_timeout_s, 0.0, 120.0, "s", "start-up fails instead of hanging")
        if self.source == "sim":
            _require(0 < self.sim.port < 65536, "camera.sim.port", self.sim.port, 'a TCP port in 1..65535 with source = "sim"')
        if self.source == "replay":
            _require(self.replay.path is not None, "camera.replay.path", self.replay.path, 'a flight log path with source = "replay"')
        if self.source == "bag":
            _require(
                self.bag.path is not None and Path(self.bag.path).suffix.lower() in RECORDING_SUFFIXES,
                "camera.bag.path",
                self.bag.path,
                'a RealSense recording (.bag or .db3, from realsense-viewer or rs.recorder) with source = "bag"',
            )


GOAL_SOURCES = ("config", "mission")


@dataclass(frozen=True)
class MissionConfig:
    """What ``cmnav fly`` does once connected.

    ``goal_rel_home_enu_m``: the goal relative to home (the take-off point; PX4 sets home at
    arming), ENU metres (east, north, up).  Without ``allow_arm_takeoff`` the runtime waits for
    the pilot to arm, take off and switch to offboard, flies an episode, commands Hold, and waits
    for the next switch to offboard (``max_episodes``, 0 = until stopped).  With it (SITL dry runs)
    the runtime arms, takes off to ``takeoff_alt_m`` above home, flies one episode, lands and exits.

    ``goal_source = "mission"``: the goals are the waypoints of the mission uploaded to the
    autopilot (a QGroundControl plan), downloaded after start-up and checked against the
    watchdog's geofence before anything is armed; episode k flies waypoint k (the pilot's k-th
    switch to offboard; a dry run flies them all in one flight, re-entering offboard for each), and
    the current mission item is set before each so the ground station shows the progress.
    ``max_episodes`` > 0 flies only the first ``max_episodes`` waypoints.
    """

    goal_source: str = "config"  # "config": goal_rel_home_enu_m; "mission": the autopilot's mission waypoints
    goal_rel_home_enu_m: tuple[float, float, float] | None = None  # required by cmnav fly with goal_source = "config"
    episode_timeout_s: float = 60.0  # offboard flight time limit of one episode
    allow_arm_takeoff: bool = False
    takeoff_alt_m: float = 1.5  # m above home, with allow_arm_takeoff
    max_episodes: int = 0  # 0 = fly every time the pilot selects offboard, until stopped
    # With allow_arm_takeoff: after the goal (the last one), land at the point of the way back (from
    # where the vehicle stopped, back along the path flown, at most land_site_search_m back) nearest
    # land_retreat_m back along the path whose column down to the floor is land_clearance_m (m,
    # horizontal) clear of the surfaces the episode's depth frames showed, and whose way there keeps
    # land_way_clearance_m from those at the height flown (runtime.watchdog.choose_landing_site;
    # PX4's Hold and Land drift up to ~1.1 m while descending, docs/px4-sitl.md §8).  Where the frames
    # showed no surface at all: land_retreat_m back, unchecked; likewise always with land_site_search_m = 0.
    land_retreat_m: float = 1.5
    land_site_search_m: float = 5.0
    land_clearance_m: float = 1.0  # the vehicle's radius 0.2 m + the landing's true drift (PX4 SIH: 0.67-0.74 m at most) + the cells' 0.1 m
    # the vehicle's radius 0.2 m + PX4's estimate drift and the retreat's tracking error (0.2-0.3 m
    # on PX4 SIH) + what a thin obstacle seen from afar is off (a post seen 0.53 m off was 0.28 m)
    land_way_clearance_m: float = 0.6
    # With allow_arm_takeoff: then land under the runtime's own control (offboard, descending while
    # it holds its position estimate where the descent began) instead of the autopilot's Land, which
    # holds the position *estimate* and drifted 0.2-1 m with it while descending on PX4 SIH.
    land_in_offboard: bool = True
    # With allow_arm_takeoff: within 3 m of the (last) goal, cap the horizontal command so that the
    # brake after the goal stops 0.5 m short of the surfaces the depth frames showed ahead
    # (runtime.watchdog.cap_approach; never below 0.3 m/s).  false: the policy's command as it is.
    approach_cap: bool = True

    def __post_init__(self) -> None:
        _require(self.goal_source in GOAL_SOURCES, "mission.goal_source", self.goal_source, f"one of {', '.join(GOAL_SOURCES)}")
        _require(
            self.goal_source == "config" or self.goal_rel_home_enu_m is None,
            "mission.goal_rel_home_enu_m",
            self.goal_rel_home_enu_m,
            'unset with goal_source = "mission" (the goals are the waypoints of the mission on the autopilot): '
            "remove it, or set goal_source = \"config\"",
        )
        if self.goal_rel_home_enu_m is not None:
            _require(
                len(self.goal_rel_home_enu_m) == 3 and all(math.isfinite(v) for v in self.goal_rel_home_enu_m),
                "mission.goal_rel_home_enu_m",
                self.goal_rel_home_enu_m,
                "three finite numbers [east, north, up] in metres from home",
            )
        _positive("mission.episode_timeout_s", self.episode_timeout_s)
        _within("mission.episode_timeout_s", self.episode_timeout_s, 0.0, 600.0, "s", "an episode that ends")
        _within("mission.max_episodes", self.max_episodes, 0, 100_000, "", "0 = until stopped")
        _require(0.0 < self.takeoff_alt_m <= 50.0, "mission.takeoff_alt_m", self.takeoff_alt_m, "in (0, 50] m above home")
        _within("mission.land_retreat_m", self.land_retreat_m, 0.0, 10.0, "m", "0 = where the vehicle stopped")
        _within("mission.land_site_search_m", self.land_site_search_m, 0.0, 20.0, "m", "0 = land_retreat_m back, unchecked")
        _within("mission.land_clearance_m", self.land_clearance_m, 0.2, 3.0, "m", "the vehicle's radius and the landing's drift")
        _within("mission.land_way_clearance_m", self.land_way_clearance_m, 0.2, 3.0, "m", "the vehicle's radius and the retreat's drift")
        _require(isinstance(self.land_in_offboard, bool), "mission.land_in_offboard", self.land_in_offboard, "true or false")
        _require(isinstance(self.approach_cap, bool), "mission.approach_cap", self.approach_cap, "true or false")
        _require(
            isinstance(self.max_episodes, int) and self.max_episodes >= 0,
            "mission.max_episodes",
            self.max_episodes,
            "an integer >= 0 (0 = until stopped)",
        )
        if self.allow_arm_takeoff and self.goal_source == "config":
            _require(
                self.max_episodes in (0, 1),
                "mission.max_episodes",
                self.max_episodes,
                "0 or 1 with allow_arm_takeoff = true (a dry run flies once, lands and exits)",
            )


@dataclass(frozen=True)
class ProcessConfig:
    """The runtime process on its computer (TOML table ``[runtime]``).

    ``cpu_affinity``: the CPU ids the whole process (every thread: event loop, ONNX Runtime's
    step, MAVSDK, the camera driver) is pinned to at start, before the model loads; empty = no
    pinning.  Each must be one of the CPUs this process may run on (``os.sched_getaffinity``;
    under systemd, what ``CPUAffinity=`` left it).  Pin the runtime to a core nothing else is
    given, with ``policy.intra_op_threads = 1`` (one core, one thread)."""

    cpu_affinity: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        allowed = sorted(os.sched_getaffinity(0))
        ids = self.cpu_affinity
        _require(
            all(isinstance(i, int) and not isinstance(i, bool) for i in ids) and len(set(ids)) == len(ids),
            "runtime.cpu_affinity",
            list(ids),
            "a list of distinct integer CPU ids",
        )
        _require(
            all(i in allowed for i in ids),
            "runtime.cpu_affinity",
            list(ids),
            f"CPU ids this process may run on: {allowed} (os.sched_getaffinity; systemd's CPUAffinity= narrows it)",
        )


@dataclass(frozen=True)
class SystemdConfig:
    """Talking to systemd (``Type=notify``): READY, STATUS lines and WATCHDOG pings on
    ``$NOTIFY_SOCKET``; nothing is sent when systemd did not set it."""

    notify: bool = True


@dataclass(frozen=True)
class RuntimeConfig:
    """Everything the flight loop needs besides the contract."""

    policy: PolicyModelConfig = field(default_factory=PolicyModelConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    mission: MissionConfig = field(default_factory=MissionConfig)
    systemd: SystemdConfig = field(default_factory=SystemdConfig)
    runtime: ProcessConfig = field(default_factory=ProcessConfig)

    def __post_init__(self) -> None:
        pinned = self.runtime.cpu_affinity
        _require(
            not pinned or self.policy.intra_op_threads <= len(pinned),
            "policy.intra_op_threads",
            self.policy.intra_op_threads,
            f"<= the {len(pinned)} CPU(s) of runtime.cpu_affinity (more threads than pinned cores only take turns; 1 on one core)",
        )
        goal = self.mission.goal_rel_home_enu_m
        if goal is None:
            return
        fence = self.watchdog
        _require(
            math.hypot(goal[0], goal[1]) < fence.geofence_radius_m,
            "mission.goal_rel_home_enu_m",
            goal,
            f"horizontally within watchdog.geofence_radius_m = {fence.geofence_radius_m} m of home",
        )
        _require(
            fence.altitude_min_m <= goal[2] <= fence.altitude_max_m,
            "mission.goal_rel_home_enu_m",
            goal,
            f"at a height inside the watchdog's band [{fence.altitude_min_m}, {fence.altitude_max_m}] m above home",
        )
