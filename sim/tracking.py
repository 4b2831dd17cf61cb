"""Tracking error of a SITL flight: the runtime's velocity commands (from its MCAP log) against
the velocity the vehicle achieved (ground truth: our vehicle's trace, or the pose an external
autopilot reported to the world follower).

Each policy command (body FLU velocity; the autopilot reads it in the yaw-only vehicle frame V,
as PX4 reads MAV_FRAME_BODY_NED) is compared with the ground-truth velocity one control period
later (when the next command replaces it), rotated into V by the heading at that time.  The
error is the norm of the difference (m/s); the summary gives its p50 / p99 / max, and the ratio
of achieved to commanded forward speed over commands faster than FORWARD_RATIO_MIN_M_S.
This is the raw difference, so an autopilot's own lag and gain deficit show in it; the
watchdog's tracking trip (``runtime.tracking``) compares against a lagged reference instead, to
catch a vehicle that does not follow at all.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader

from runtime.contract import CONTROL_PERIOD_S
from runtime.contract.frames import world_enu_to_vehicle
from runtime.log.topics import TOPIC_COMMAND

log = logging.getLogger(__name__)

FORWARD_RATIO_MIN_M_S = 0.5
METADATA_NAME = "cmnav"


def logged_commands(log_path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The policy commands that went out: (t_s [N] time.monotonic s, vel_body_flu_m_s [N, 3])."""
    times, velocities = [], []
    with open(log_path, "rb") as f:
        reader = make_reader(f)
        offset_ns = 0
        for record in reader.iter_metadata():
            if record.name == METADATA_NAME:
                offset_ns = int(record.metadata["monotonic_to_unix_offset_ns"])
        for _schema, _channel, message in reader.iter_messages(topics=[TOPIC_COMMAND], log_time_order=True):
            command = json.loads(message.data)
            if command.get("source") == "policy" and command.get("sent"):
                times.append((message.log_time - offset_ns) * 1e-9)
                velocities.append(command["vel_body_flu_m_s"])
    return np.asarray(times, dtype=np.float64), np.asarray(velocities, dtype=np.float64).reshape(-1, 3)


def tracking_error(t_cmd_s: np.ndarray, vel_cmd_v_m_s: np.ndarray, trace: dict, lag_s: float = CONTROL_PERIOD_S) -> dict | None:
    """Commanded (vehicle frame V, m/s) vs achieved ``lag_s`` later (trace: t_s, vel_enu_m_s,
    yaw_enu_rad); None when nothing to compare."""
    t_trace = np.asarray(trace.get("t_s", []), dtype=np.float64)
    yaw = np.asarray(trace.get("yaw_enu_rad", []), dtype=np.float64)
    if len(t_cmd_s) == 0 or len(t_trace) < 2 or len(yaw) != len(t_trace):
        return None
    vel = np.asarray(trace["vel_enu_m_s"], dtype=np.float64).reshape(-1, 3)
    t_at = t_cmd_s + lag_s
    inside = (t_at >= t_trace[0]) & (t_at <= t_trace[-1])
    if not inside.any():
        return None
    t_at, commanded = t_at[inside], vel_cmd_v_m_s[inside]
    achieved_enu = np.stack([np.interp(t_at, t_trace, vel[:, k]) for k in range(3)], axis=-1)
    nearest = np.clip(np.searchsorted(t_trace, t_at), 0, len(t_trace) - 1)
    achieved = world_enu_to_vehicle(achieved_enu, yaw[nearest])
    error = np.linalg.norm(achieved - commanded, axis=-1)
    fast = commanded[:, 0] > FORWARD_RATIO_MIN_M_S
    ratio = float(achieved[fast, 0].sum() / commanded[fast, 0].sum()) if fast.any() else None
    return {
        "p50": round(float(np.percentile(error, 50)), 3),
        "p99": round(float(np.percentile(error, 99)), 3),
        "max": round(float(error.max()), 3),
        "n": int(len(error)),
        "forward_ratio": None if ratio is None else round(ratio, 3),
        "lag_s": round(lag_s, 4),
    }


def flight_tracking_error(log_path: str | Path | None, trace: dict) -> dict | None:
    """:func:`tracking_error` of a flight log against a trace; None (logged) if the log is unreadable."""
    if not log_path or not Path(log_path).is_file():
        return None
    try:
        t_cmd, vel_cmd = logged_commands(log_path)
    except (OSError, McapError, ValueError, KeyError) as err:
        log.warning("no tracking error: cannot read the commands in %s (%s)", log_path, err)
        return None
    return tracking_error(t_cmd, vel_cmd, trace)
