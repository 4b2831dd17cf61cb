"""Runtime settings as typed dataclasses, with every default in this one file.

The contract (control period, action scaling, goal radius) is not configurable: it comes from
``runtime.contract``.  What a deployment may choose lives here: tighter action limits, watchdog
thresholds, MAVLink connection, timeouts, logging.  Every value is validated when the dataclass
is built; a bad value raises :class:`ConfigError` naming the key and the allowed range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from .contract import CONTROL_PERIOD_S, ActionLimits


class ConfigError(ValueError):
    """A configuration value is out of range; the message names the key and the allowed range."""


def _require(ok: bool, key: str, value: object, allowed: str) -> None:
    if not ok:
        raise ConfigError(f"{key}={value!r} is invalid: must be {allowed}")


def _positive(key: str, value: float) -> None:
    _require(isinstance(value, (int, float)) and math.isfinite(value) and value > 0, key, value, "a finite number > 0")


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
    hold_grace_s: float = 1.0  # hover this long after a trip, then offboard.stop() (PX4 Hold)
    period_s: float = 0.02  # how often the watchdog task checks the time-based trips

    def __post_init__(self) -> None:
        for key in (
            "frame_stale_ms",
            "step_trip_ms",
            "telemetry_stale_ms",
            "depth_invalid_max_s",
            "geofence_radius_m",
            "altitude_max_m",
            "hold_grace_s",
            "period_s",
        ):
            _positive(f"watchdog.{key}", getattr(self, key))
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


@dataclass(frozen=True)
class VehicleConfig:
    """MAVLink connection and the timeouts of every await that talks to the autopilot (s)."""

    url: str = "udpin://127.0.0.1:14540"
    connect_timeout_s: float = 10.0  # until the first autopilot heartbeat
    command_timeout_s: float = 5.0  # one MAVSDK command (arm, takeoff, offboard start, ...)
    health_timeout_s: float = 30.0  # until armable with a local position
    takeoff_timeout_s: float = 30.0  # until the takeoff altitude is reached and Hold shows
    land_timeout_s: float = 60.0  # until disarmed after land

    def __post_init__(self) -> None:
        _require(
            isinstance(self.url, str) and "://" in self.url,
            "vehicle.url",
            self.url,
            'a MAVSDK connection URL such as "udpin://127.0.0.1:14540"',
        )
        for key in ("connect_timeout_s", "command_timeout_s", "health_timeout_s", "takeoff_timeout_s", "land_timeout_s"):
            _positive(f"vehicle.{key}", getattr(self, key))


@dataclass(frozen=True)
class PolicyConfig:
    """The ONNX model, where it runs, and the deployment's action limits."""

    model_path: Path = Path("model.onnx")
    providers: tuple[str, ...] = ("CPUExecutionProvider",)
    intra_op_threads: int = 0  # 0 = ONNX Runtime's default
    limits: ActionLimits = field(default_factory=ActionLimits)

    def __post_init__(self) -> None:
        _require(len(self.providers) > 0, "policy.providers", self.providers, "a non-empty list of execution providers")
        _require(
            isinstance(self.intra_op_threads, int) and self.intra_op_threads >= 0,
            "policy.intra_op_threads",
            self.intra_op_threads,
            "an integer >= 0",
        )


@dataclass(frozen=True)
class RecorderConfig:
    """The MCAP flight log."""

    log_dir: Path | None = Path("logs")  # None = do not record
    flush_period_s: float = 0.5  # a killed process loses at most about this much
    queue_size: int = 64  # records waiting for the writer thread; beyond that they are dropped

    def __post_init__(self) -> None:
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


@dataclass(frozen=True)
class RuntimeConfig:
    """Everything the flight loop needs besides the contract."""

    policy: PolicyConfig = field(default_factory=PolicyConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
