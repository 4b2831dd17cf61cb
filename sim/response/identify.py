"""Identify an autopilot's velocity response from a run of the identification sequence.

Per step (one axis, from one commanded value to another), in the yaw-only vehicle frame V:
``delay_s`` (command change to 5 % of the change), ``tau_s`` (5 % to 63.2 %: a first-order time
constant), ``gain`` (steady state over the last second / the command, rising steps), and the
largest acceleration (m/s^2; rad/s^2 for yaw) over a 0.1 s slope.  Per axis: medians of delay and
time constant, the gain at each commanded value, the largest acceleration and deceleration.
Besides: the height drift while only horizontal motion is commanded (m/s, + = up), the tracking
error of the whole sequence and of its policy-like stretch (``sim.tracking``: each command
against the velocity one control period later), and the landing: speed when Land was commanded
and the horizontal drift from there to touch-down.
"""

from __future__ import annotations

import numpy as np

from runtime.contract.frames import world_enu_to_vehicle
from sim.tracking import tracking_error

from .sequence import AXES, policy_like_segments

STEADY_WINDOW_S = 1.0
SLOPE_WINDOW_S = 0.1
PRE_STEP_S = 0.3


def vehicle_frame_response(samples: dict) -> tuple[np.ndarray, np.ndarray]:
    """(t_s [N], response [N, 4]): forward, left, up velocity (m/s, frame V) and yaw rate (rad/s)."""
    t_s = np.asarray(samples["t_s"], dtype=np.float64)
    vel = np.asarray(samples["vel_enu_m_s"], dtype=np.float64).reshape(-1, 3)
    yaw = np.unwrap(np.asarray(samples["yaw_enu_rad"], dtype=np.float64))
    vel_v = world_enu_to_vehicle(vel, yaw)
    yaw_rate = np.gradient(yaw, t_s) if len(t_s) > 2 else np.zeros_like(t_s)
    return t_s, np.column_stack([vel_v, yaw_rate])


def _slope(t_s: np.ndarray, y: np.ndarray) -> np.ndarray:
    """dy/dt over SLOPE_WINDOW_S (a centred difference across the window)."""
    out = np.zeros_like(y)
    for i, t in enumerate(t_s):
        lo = np.searchsorted(t_s, t - SLOPE_WINDOW_S / 2)
        hi = min(np.searchsorted(t_s, t + SLOPE_WINDOW_S / 2), len(t_s) - 1)
        if hi > lo:
            out[i] = (y[hi] - y[lo]) / (t_s[hi] - t_s[lo])
    return out


def identify_step(t_s: np.ndarray, y: np.ndarray, t_step_s: float, t_end_s: float, before: float, after: float) -> dict | None:
    """One step's delay, time constant, gain and largest acceleration; None if it has no samples."""
    pre = (t_s >= t_step_s - PRE_STEP_S) & (t_s < t_step_s)
    window = (t_s >= t_step_s) & (t_s <= t_end_s)
    steady = (t_s >= t_end_s - STEADY_WINDOW_S) & (t_s <= t_end_s)
    if pre.sum() < 2 or window.sum() < 5 or steady.sum() < 2:
        return None
    y0, y_ss = float(y[pre].mean()), float(y[steady].mean())
    change = y_ss - y0
    record = {"before": before, "after": after, "start": round(y0, 3), "steady": round(y_ss, 3),
              "gain": round(y_ss / after, 3) if after != 0.0 else None}  # fmt: skip
    tw, yw = t_s[window], y[window]
    if abs(change) > 0.1 * abs(after - before):
        progress = (yw - y0) / change
        reached5, reached63 = np.flatnonzero(progress >= 0.05), np.flatnonzero(progress >= 0.632)
        if len(reached5) and len(reached63):
            delay = float(tw[reached5[0]] - t_step_s)
            record["delay_s"] = round(delay, 3)
            record["tau_s"] = round(float(tw[reached63[0]] - tw[reached5[0]]), 3)
    record["accel_max"] = round(float(np.abs(_slope(tw, yw)).max()), 3)
    return record


def _median(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return round(float(np.median(values)), 3) if values else None


def identify(run: dict) -> dict:
    """The identified response of one run (see the module doc)."""
    t_s, response = vehicle_frame_response(run["samples"])
    sent_t_s = np.asarray(run["commands"]["t_s"], dtype=np.float64)
    command_v = np.asarray(run["commands"]["command_v"], dtype=np.float64).reshape(-1, 4)
    period_s = float(run["control_period_s"])
    # Each scheduled step at the time its command really went out.
    scheduled_t_s = np.arange(len(command_v)) * period_s
    per_axis: dict[str, dict] = {axis: {"steps": []} for axis in AXES}
    drift_up = []
    for step in run["steps"]:
        k = AXES.index(step["axis"])
        i0 = int(np.clip(np.searchsorted(scheduled_t_s, step["t_s"] - 1e-6), 0, len(sent_t_s) - 1))
        i1 = int(np.clip(np.searchsorted(scheduled_t_s, step["t_end_s"] - 1e-6), 0, len(sent_t_s) - 1))
        t0, t1 = sent_t_s[i0], sent_t_s[i1] if i1 > i0 else sent_t_s[-1]
        found = identify_step(t_s, response[:, k], t0, t1, step["before"], step["after"])
        if found is not None:
            per_axis[step["axis"]]["steps"].append(found)
        if step["axis"] in ("forward", "left") and step["after"] != 0.0:
            on = (t_s >= t0) & (t_s <= t1)
            if on.any():
                drift_up.append(float(response[on, 2].mean()))
    for axis, found in per_axis.items():
        steps = found["steps"]
        rising = [s for s in steps if abs(s["after"]) > abs(s["before"])]
        falling = [s for s in steps if abs(s["after"]) < abs(s["before"])]
        found["delay_s"] = _median([s.get("delay_s") for s in steps])
        found["tau_rise_s"] = _median([s.get("tau_s") for s in rising])
        found["tau_fall_s"] = _median([s.get("tau_s") for s in falling])
        found["gain_at"] = {f"{s['after']:g}": s["gain"] for s in rising}
        found["accel_max"] = max((s["accel_max"] for s in rising), default=None)
        found["decel_max"] = max((s["accel_max"] for s in falling), default=None)
    trace = {"t_s": t_s.tolist(), "vel_enu_m_s": run["samples"]["vel_enu_m_s"], "yaw_enu_rad": run["samples"]["yaw_enu_rad"]}
    policy_like_n = sum(int(round(s.duration_s / period_s)) for s in policy_like_segments())
    stretch = slice(len(sent_t_s) - policy_like_n, len(sent_t_s))
    return {
        "axes": per_axis,
        "height_drift_m_s": {"mean": _median(drift_up), "max_abs": round(max(map(abs, drift_up)), 3) if drift_up else None},
        "tracking_error_m_s": tracking_error(sent_t_s, command_v[:, :3], trace),
        "tracking_error_policy_like_m_s": tracking_error(sent_t_s[stretch], command_v[stretch, :3], trace),
        "landing": landing(run, t_s),
    }


def landing(run: dict, t_s: np.ndarray) -> dict | None:
    """Speed when Land was commanded and the horizontal drift (m) from there to touch-down."""
    end = run.get("end")
    if not end or "t_land_s" not in end:
        return None
    pos = np.asarray(run["samples"]["pos_enu_m"], dtype=np.float64).reshape(-1, 3)
    in_air = np.asarray(run["samples"]["in_air"], dtype=bool)
    after = np.flatnonzero(t_s >= end["t_land_s"])
    if len(after) == 0:
        return None
    landed = [i for i in after if not in_air[i]]
    touch = landed[0] if landed else after[-1]
    start = np.asarray(end["pos_at_land_enu_m"], dtype=np.float64)
    drift = float(np.linalg.norm(pos[touch, :2] - start[:2]))
    vel = np.asarray(run["samples"]["vel_enu_m_s"], dtype=np.float64).reshape(-1, 3)
    descent = slice(after[0], touch + 1)
    return {
        "ending": end["ending"],
        "speed_at_hold_m_s": end.get("speed_at_hold_m_s"),
        "speed_at_land_m_s": end["speed_at_land_m_s"],
        "drift_m": round(drift, 3),
        "descent_s": round(float(t_s[touch] - end["t_land_s"]), 2),
        "horizontal_speed_max_m_s": round(float(np.linalg.norm(vel[descent, :2], axis=-1).max()), 3),
        "brake_s": round(end["t_hold_s"] - end["t_brake_s"], 2) if "t_brake_s" in end else None,
    }


def compare_table(identified: dict[str, dict]) -> str:
    """A markdown table: one row per identified quantity, one column per run."""
    names = list(identified)
    rows: list[tuple[str, list]] = []
    for axis in AXES:
        for key in ("delay_s", "tau_rise_s", "tau_fall_s", "accel_max", "decel_max"):
            rows.append((f"{axis} {key}", [identified[n]["axes"][axis][key] for n in names]))
        values = sorted({v for n in names for v in identified[n]["axes"][axis]["gain_at"]}, key=float)
        for value in values:
            rows.append((f"{axis} gain at {value}", [identified[n]["axes"][axis]["gain_at"].get(value) for n in names]))
    rows.append(("height drift mean (m/s)", [identified[n]["height_drift_m_s"]["mean"] for n in names]))
    for key in ("tracking_error_m_s", "tracking_error_policy_like_m_s"):
        for stat in ("p50", "p99", "forward_ratio"):
            rows.append((f"{key} {stat}", [(identified[n][key] or {}).get(stat) for n in names]))
    for stat in ("ending", "speed_at_land_m_s", "drift_m", "descent_s", "brake_s"):
        rows.append((f"landing {stat}", [(identified[n]["landing"] or {}).get(stat) for n in names]))
    lines = ["| quantity | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    lines += [f"| {label} | " + " | ".join("—" if v is None else str(v) for v in values) + " |" for label, values in rows]
    return "\n".join(lines)
