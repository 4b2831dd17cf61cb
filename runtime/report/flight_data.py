"""What a flight report shows, read from one flight log in one streaming pass (no plotting here).

Times are seconds from the episode's start: the watchdog's ``start`` event (logged when
supervision starts, at offboard), else the first policy step, else the first message.  Positions
are local ENU (m); velocities are in the vehicle frame V (ENU turned by the yaw only: forward,
left, up), the frame PX4 reads the runtime's body velocity setpoints in; yaw rates are FLU
(rad/s, positive = turning left).  The invalid-depth fraction is the contract's
(:func:`runtime.contract.images.invalid_depth_fraction`: 0/NaN pixels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..contract.frames import world_enu_to_vehicle
from ..contract.images import invalid_depth_fraction
from ..log.reader import FlightLogReader
from ..log.topics import (
    TOPIC_ACTION,
    TOPIC_COMMAND,
    TOPIC_DEPTH,
    TOPIC_GRAY,
    TOPIC_OBSERVATION,
    TOPIC_STATE,
    TOPIC_STATUS_TEXT,
    TOPIC_TIMING,
    TOPIC_WATCHDOG,
)

REPORT_TOPICS = (TOPIC_DEPTH, TOPIC_GRAY, TOPIC_STATE, TOPIC_OBSERVATION, TOPIC_ACTION, TOPIC_COMMAND, TOPIC_TIMING,
                 TOPIC_WATCHDOG, TOPIC_STATUS_TEXT)  # fmt: skip
THUMB_WIDTH_PX = 320  # camera snapshots are shrunk to this width (a D455 frame is 848 px wide)
DEPTH_RANGE_M = 10.0  # the contract's depth normalisation range: the colour scale of depth snapshots
MAX_TRIP_SNAPSHOTS = 6


@dataclass
class Snapshot:
    """One camera frame at a moment that matters: gray (uint8) and depth (float32 m), shrunk."""

    label: str
    t_s: float
    gray_u8: np.ndarray
    depth_m: np.ndarray
    invalid_frac: float


@dataclass
class FlightData:
    """Everything the report draws; arrays are float64, times in s from the episode's start."""

    path: Path
    metadata: dict[str, str]
    stopped_early: str | None
    t0_unix_s: float
    state_t_s: np.ndarray
    pos_enu_m: np.ndarray  # (N, 3)
    vel_v_m_s: np.ndarray  # (N, 3) forward, left, up
    yaw_rate_flu_rad_s: np.ndarray  # (N,)
    cmd_t_s: np.ndarray
    cmd_v_m_s: np.ndarray  # (M, 3) commanded forward, left, up (sent commands only)
    cmd_yaw_rate_flu_rad_s: np.ndarray
    cmd_source: list[str]
    step_t_s: np.ndarray  # policy steps (capture time)
    step_ms: np.ndarray  # frame taken -> command sent, per step
    missed_deadlines: int
    goals_enu_m: list[list[float]]  # the distinct goals of the policy steps, in order
    frame_t_s: np.ndarray
    invalid_frac: np.ndarray
    snapshots: list[Snapshot]
    watchdog_events: list[dict]
    status_texts: list[dict]
    first_step_t_s: float | None
    last_step_t_s: float | None
    offboard_end_t_s: float | None  # telemetry's first state after the first step out of offboard, or disarmed

    def in_flight(self, t_s: np.ndarray) -> np.ndarray:
        """Mask of times in the flight: from the first policy step until telemetry shows the
        vehicle out of offboard or disarmed (else the last step); all False without steps."""
        if self.first_step_t_s is None or self.last_step_t_s is None:
            return np.zeros(len(t_s), bool)
        end = self.offboard_end_t_s if self.offboard_end_t_s is not None else self.last_step_t_s
        return (t_s >= self.first_step_t_s) & (t_s <= end)

    def numbers(self) -> dict[str, Any]:
        """The report's figures, from the log alone (None where the log has no data for one)."""
        trips = [e for e in self.watchdog_events if e.get("event") == "trip"]
        flown = self.pos_enu_m[self.in_flight(self.state_t_s)]
        flown = flown[np.all(np.isfinite(flown), axis=1)]
        path_m = float(np.linalg.norm(np.diff(flown, axis=0), axis=1).sum()) if len(flown) >= 2 else None
        final_distance_m = None
        if len(flown) and self.goals_enu_m:
            final_distance_m = float(np.linalg.norm(flown[-1] - np.asarray(self.goals_enu_m[-1])))
        fracs = self.invalid_frac[self.in_flight(self.frame_t_s)]
        if len(fracs) == 0:
            fracs = self.invalid_frac
        steps = self.step_ms[np.isfinite(self.step_ms)]
        p50, p99 = (np.percentile(steps, [50, 99]) if len(steps) else (None, None))
        return {
            "steps": int(len(self.step_t_s)),
            "step_ms_p50": _round(p50, 3),
            "step_ms_p99": _round(p99, 3),
            "step_ms_max": _round(steps.max() if len(steps) else None, 3),
            "missed_deadlines": self.missed_deadlines,
            "flight_s": _round(None if self.first_step_t_s is None else self.last_step_t_s - self.first_step_t_s, 3),
            "path_m": _round(path_m, 3),
            "final_distance_m": _round(final_distance_m, 3),
            "invalid_depth_pct_avg": _round(100.0 * fracs.mean() if len(fracs) else None, 2),
            "invalid_depth_pct_min": _round(100.0 * fracs.min() if len(fracs) else None, 2),
            "invalid_depth_pct_max": _round(100.0 * fracs.max() if len(fracs) else None, 2),
            "watchdog_trips": len(trips),
            "goals": len(self.goals_enu_m),
        }


def _round(value: Any, digits: int) -> float | None:
    if value is None or not math.isfinite(float(value)):
        return None
    return round(float(value), digits)


def _floats(values: Any, size: int) -> list[float]:
    if values is None:
        return [math.nan] * size
    return [math.nan if v is None else float(v) for v in values]


def _shrink(image: np.ndarray, nearest: bool) -> np.ndarray:
    height, width = image.shape[:2]
    if width <= THUMB_WIDTH_PX:
        return image.copy()
    size = (THUMB_WIDTH_PX, max(1, round(height * THUMB_WIDTH_PX / width)))
    # Nearest for depth: averaging would blend invalid (0) pixels into valid ones.
    return cv2.resize(image, size, interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


class _Collector:
    """State of the single pass over the log."""

    def __init__(self) -> None:
        self.states: list[tuple[int, list[float], list[float], float, float]] = []
        self.commands: list[tuple[int, list[float], float, str]] = []
        self.steps: list[int] = []
        self.step_ms: list[float] = []
        self.missed = 0
        self.goals: list[list[float]] = []
        self.frames: list[tuple[int, float]] = []
        self.watchdog: list[tuple[int, dict]] = []
        self.status: list[tuple[int, dict]] = []
        self.depth_pending: tuple[int, np.ndarray] | None = None
        self.last_frame: tuple[int, np.ndarray, np.ndarray, float] | None = None  # log time, gray, depth, invalid
        self.first_frame: tuple[int, np.ndarray, np.ndarray, float] | None = None
        self.snapshots: list[tuple[str, int, np.ndarray, np.ndarray, float]] = []
        self.start_taken = False
        # The first state after the first step that is not in offboard, or disarmed (a dry run that
        # landed in offboard stays in it on the ground).
        self.offboard_end: int | None = None
        self.end_frame: tuple[int, np.ndarray, np.ndarray, float] | None = None
        self.worst: tuple[int, np.ndarray, np.ndarray, float] | None = None
        self.pending_worst: tuple[int, np.ndarray, np.ndarray, float] | None = None

    def snapshot(self, label: str, frame: tuple[int, np.ndarray, np.ndarray, float] | None) -> None:
        if frame is not None:
            self.snapshots.append((label, *frame))


def read_flight(path: str | Path) -> FlightData:
    """One pass over the log at ``path``; :class:`runtime.log.reader.ReplayError` if it is not a
    cmnav flight log (a cut end only ends the data: ``stopped_early`` says where)."""
    reader = FlightLogReader(path)
    c = _Collector()
    first_time: int | None = None
    for topic, log_time, msg in reader.messages(REPORT_TOPICS):
        first_time = log_time if first_time is None else first_time
        if topic == TOPIC_DEPTH:
            c.depth_pending = (log_time, reader.image(msg, topic))
        elif topic == TOPIC_GRAY:
            if c.depth_pending is None or c.depth_pending[0] != log_time:
                continue
            depth = c.depth_pending[1]
            c.depth_pending = None
            frac = invalid_depth_fraction(depth)
            c.frames.append((log_time, frac))
            c.last_frame = (log_time, _shrink(reader.image(msg, topic), False), _shrink(depth, True), frac)
            c.first_frame = c.first_frame or c.last_frame
            if c.steps and frac > 0.0 and (c.pending_worst is None or frac > c.pending_worst[3]):
                c.pending_worst = c.last_frame  # counts once a policy step follows it
        elif topic == TOPIC_STATE:
            vel = _floats(msg.get("vel_enu_m_s"), 3)
            yaw = msg.get("yaw_enu_rad")
            rate = _floats(msg.get("angvel_body_flu_rad_s"), 3)[2]
            c.states.append((log_time, _floats(msg.get("pos_enu_m"), 3), vel, math.nan if yaw is None else float(yaw), rate))
            if c.steps and c.offboard_end is None and (msg.get("flight_mode") != "OFFBOARD" or msg.get("armed") is False):
                c.offboard_end = log_time
        elif topic == TOPIC_OBSERVATION:
            goal = _floats(msg.get("goal_enu_m"), 3)
            if not c.goals or not np.allclose(goal, c.goals[-1], atol=1e-6, equal_nan=True):
                c.goals.append(goal)
        elif topic == TOPIC_ACTION:
            c.steps.append(log_time)
            if not c.start_taken:
                c.start_taken = True
                c.snapshot("start (first policy step)", c.last_frame)
            c.end_frame = c.last_frame
            if c.pending_worst is not None and (c.worst is None or c.pending_worst[3] > c.worst[3]):
                c.worst = c.pending_worst
            c.pending_worst = None
        elif topic == TOPIC_TIMING:
            stages = msg.get("stages_ms") or {}
            c.step_ms.append(float(stages["step"]) if stages.get("step") is not None else math.nan)
            c.missed += bool(msg.get("missed_deadline"))
        elif topic == TOPIC_COMMAND:
            if msg.get("sent"):
                c.commands.append((log_time, _floats(msg.get("vel_body_flu_m_s"), 3), float(msg.get("yaw_rate_flu_rad_s") or 0.0),
                                   str(msg.get("source"))))  # fmt: skip
        elif topic == TOPIC_WATCHDOG:
            c.watchdog.append((log_time, dict(msg)))
            if msg.get("event") == "trip" and sum(s[0].startswith("trip") for s in c.snapshots) < MAX_TRIP_SNAPSHOTS:
                c.snapshot(f"trip: {msg.get('cause')}", c.last_frame)
        elif topic == TOPIC_STATUS_TEXT:
            c.status.append((log_time, dict(msg)))
    if reader.stopped_early is None and not reader.metadata:
        reader.check_topics((), "a flight report")  # raises: not a cmnav flight log
    if not c.start_taken and c.first_frame is not None:
        c.snapshot("first frame (no policy step)", c.first_frame)
    if c.worst is not None and (c.end_frame is None or c.worst[0] != c.end_frame[0]):
        c.snapshot(f"most depth invalid ({100 * c.worst[3]:.0f} %)", c.worst)
    c.snapshot("end (last policy step)" if c.steps else "last frame", c.end_frame if c.steps else c.last_frame)
    return _assemble(reader, c, first_time)


def _assemble(reader: FlightLogReader, c: _Collector, first_time: int | None) -> FlightData:
    start_event = next((t for t, e in c.watchdog if e.get("event") == "start"), None)
    t0 = start_event if start_event is not None else (c.steps[0] if c.steps else (first_time or 0))

    def rel(times: list[int]) -> np.ndarray:
        return (np.asarray(times, dtype=np.float64) - t0) * 1e-9

    states = c.states
    pos = np.array([s[1] for s in states], dtype=np.float64).reshape(-1, 3)
    vel_enu = np.array([s[2] for s in states], dtype=np.float64).reshape(-1, 3)
    yaw = np.array([s[3] for s in states], dtype=np.float64)
    step_t = rel(c.steps)
    snapshots = sorted(
        (Snapshot(label, float(rel([t])[0]), gray, depth, frac) for label, t, gray, depth, frac in c.snapshots),
        key=lambda s: s.t_s,
    )
    return FlightData(
        path=reader.path,
        metadata=dict(reader.metadata),
        stopped_early=reader.stopped_early,
        t0_unix_s=t0 * 1e-9,
        state_t_s=rel([s[0] for s in states]),
        pos_enu_m=pos,
        vel_v_m_s=world_enu_to_vehicle(vel_enu, yaw).reshape(-1, 3),
        yaw_rate_flu_rad_s=np.array([s[4] for s in states], dtype=np.float64),
        cmd_t_s=rel([m[0] for m in c.commands]),
        cmd_v_m_s=np.array([m[1] for m in c.commands], dtype=np.float64).reshape(-1, 3),
        cmd_yaw_rate_flu_rad_s=np.array([m[2] for m in c.commands], dtype=np.float64),
        cmd_source=[m[3] for m in c.commands],
        step_t_s=step_t,
        step_ms=np.asarray(c.step_ms, dtype=np.float64),
        missed_deadlines=c.missed,
        goals_enu_m=c.goals,
        frame_t_s=rel([f[0] for f in c.frames]),
        invalid_frac=np.array([f[1] for f in c.frames], dtype=np.float64),
        snapshots=snapshots,
        watchdog_events=[{**e, "log_t_s": round(float(rel([t])[0]), 3)} for t, e in c.watchdog],
        status_texts=[{**m, "log_t_s": round(float(rel([t])[0]), 3)} for t, m in c.status],
        first_step_t_s=float(step_t[0]) if len(step_t) else None,
        last_step_t_s=float(step_t[-1]) if len(step_t) else None,
        # A log that ends in offboard (a dry run that landed in it closes the log at the disarm, maybe
        # before telemetry shows it): the flight lasted to its last state.
        offboard_end_t_s=float(rel([c.offboard_end if c.offboard_end is not None else c.states[-1][0]])[0])
        if c.steps and c.states else None,
    )
