"""The SITL vehicle's two JSON files: the episode (written once everything listens) and the
trace (ground truth of what happened, written at shutdown).  Times in the trace are
time.monotonic() seconds, the clock every process on the host shares."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.faults.catalogue import FaultKind
from sim.world import WorldBatch

from .camera_server import ServedFrame
from .commander import Event


def write_json_atomic(path: Path, record: dict) -> None:
    """Write JSON so that a reader polling for ``path`` never sees it half written."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(record, indent=1))
    os.replace(tmp, path)


def episode_record(
    world: WorldBatch, home_enu_m: np.ndarray, level: int, seed: int, mavlink_port: int, camera_port: int,
    vehicle_mavlink_port: int,
) -> dict:  # fmt: skip
    """The episode as the runtime and ``cmnav sitl`` need it (world ENU metres).

    takeoff_alt_m is relative to home (PX4's MIS_TAKEOFF_ALT): take-off ends at start_enu_m's
    height.  vehicle_mavlink_port is the vehicle's own UDP port, for a second MAVLink client
    (e.g. a test playing the pilot).
    """
    described = world.describe(0)
    start = np.asarray(described["start_m"], dtype=np.float64)
    goal = np.asarray(described["goal_m"], dtype=np.float64)
    return {
        "home_enu_m": home_enu_m.tolist(),
        "start_enu_m": start.tolist(),
        "goal_enu_m": goal.tolist(),
        "goal_rel_home_enu_m": (goal - home_enu_m).tolist(),
        "takeoff_alt_m": float(start[2] - home_enu_m[2]),
        "room_size_m": described["room_size_m"],
        "boxes": described["boxes"],
        "level": level,
        "seed": seed,
        "mavlink_port": mavlink_port,
        "camera_port": camera_port,
        "vehicle_mavlink_port": vehicle_mavlink_port,
    }


@dataclass
class Trace:
    """Ground truth collected while flying: position and velocity every ``period_s``, the
    collision, events, and when the autopilot armed and disarmed (``armed_log``: a dry run that
    lands in offboard ends its flight with the disarm, in offboard)."""

    period_s: float = 0.05
    t_s: list[float] = field(default_factory=list)
    pos_enu_m: list[list[float]] = field(default_factory=list)
    vel_enu_m_s: list[list[float]] = field(default_factory=list)
    yaw_enu_rad: list[float] = field(default_factory=list)
    collision: dict | None = None
    events: list[tuple[float, str]] = field(default_factory=list)
    armed_log: list[tuple[float, bool]] = field(default_factory=list)

    def note_armed(self, t_s: float, armed: bool) -> None:
        """The autopilot's armed state at ``t_s``, kept where it changed."""
        if not self.armed_log or self.armed_log[-1][1] != armed:
            self.armed_log.append((t_s, bool(armed)))

    def sample(self, t_s: float, pos_enu_m: np.ndarray, vel_enu_m_s: np.ndarray, yaw_enu_rad: float = 0.0) -> None:
        """Record position (world ENU, m), velocity (m/s) and heading (rad, counter-clockwise
        from east) if ``period_s`` has passed since the last sample."""
        if not self.t_s or t_s - self.t_s[-1] >= self.period_s:
            self.t_s.append(t_s)
            self.pos_enu_m.append([round(float(v), 4) for v in pos_enu_m])
            self.vel_enu_m_s.append([round(float(v), 4) for v in vel_enu_m_s])
            self.yaw_enu_rad.append(round(float(yaw_enu_rad), 5))

    def record_collision(self, t_s: float, pos_enu_m: np.ndarray, what: str) -> None:
        if self.collision is None:
            self.collision = {"t_s": t_s, "pos_enu_m": [float(v) for v in pos_enu_m], "what": what}

    def record_events(self, events: list[Event]) -> None:
        self.events.extend((e.t_s, e.text) for e in events)

    def to_record(
        self, mode_log: list[tuple[float, str]], served: list[ServedFrame], injected: dict[FaultKind, float]
    ) -> dict:
        """JSON-ready; ``injections`` lists each injected fault with the time it first acted."""
        return {
            "t_s": self.t_s,
            "pos_enu_m": self.pos_enu_m,
            "vel_enu_m_s": self.vel_enu_m_s,
            "yaw_enu_rad": self.yaw_enu_rad,
            "collision": self.collision,
            "mode_log": [[t, mode] for t, mode in mode_log],
            "events": [[t, text] for t, text in self.events],
            "armed_log": [[t, armed] for t, armed in self.armed_log],
            "frame_t_s": [f.t_capture_ns * 1e-9 for f in served],
            "invalid_depth_frac": [f.invalid_depth_frac for f in served],
            "frames_served": len(served),
            "injections": [{"kind": kind.value, "t_s": t_s} for kind, t_s in injected.items()],
        }
