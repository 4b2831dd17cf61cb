#!/usr/bin/env python3
"""The outcome table of a campaign (scripts/sitl-campaign.sh, scripts/px4-campaign.sh) from its
summaries.jsonl (one `cmnav sitl --json` summary per line): per level the success rate with its
Wilson 95 % interval, crashes, time limits, the watchdog's trips (false ones: trips in flights that
did not crash, nothing being injected), crashes caught within 1.5 s, the largest sustained
tracking error, contacts after the goal (an autopilot that drifts on after the episode), the
speed when the runtime commanded Hold, the median tracking error p99 against the command, and
where the dry runs landed (runtime.watchdog.choose_landing_site).

    python scripts/campaign-table.py runs/px4-campaign/default/summaries.jsonl
"""

from __future__ import annotations

import collections
import json
import statistics
import sys
from pathlib import Path

from training.stats import wilson_interval


def _median(values: list) -> float:
    return statistics.median(values) if values else float("nan")


def contact_after_goal(r: dict) -> bool:
    truth = r.get("ground_truth") or {}
    contact, goal_t = truth.get("contact"), truth.get("goal_reached_t_s")
    return bool(contact and goal_t is not None and contact["t_s"] >= goal_t)


def contact_while_landing(r: dict) -> bool:
    """The contact came after the goal, once the autopilot was landing (the trace's mode log)."""
    if not contact_after_goal(r) or not r.get("run_dir"):
        return False
    try:
        modes = json.loads((Path(r["run_dir"]) / "trace.json").read_text())["mode_log"]
    except (OSError, ValueError, KeyError):
        return False
    t_contact = r["ground_truth"]["contact"]["t_s"]
    return any(mode == "LAND" and t <= t_contact for t, mode in modes)


def contact_phase(r: dict) -> str | None:
    """When ground truth saw the contact: "take-off" (before offboard, as the follower's 1 Hz mode
    log sees it, or during the runtime's climb that ends the take-off in offboard), "flight" (offboard, before the goal), "after goal, offboard" (the brake, the dry
    run's retreat or its landing in offboard), "after goal, landing" (PX4's Hold or Land); None
    without one."""
    truth = r.get("ground_truth") or {}
    contact = truth.get("contact")
    if not contact:
        return None
    offboard_t, goal_t = truth.get("offboard_t_s"), truth.get("goal_reached_t_s")
    climb_s = (r.get("takeoff_climb") or {}).get("duration_s") or 0.0
    if offboard_t is None or contact["t_s"] < offboard_t + climb_s:
        return "take-off"
    if goal_t is None or contact["t_s"] < goal_t:
        return "flight"
    if not r.get("run_dir"):
        return "after goal"
    try:
        modes = json.loads((Path(r["run_dir"]) / "trace.json").read_text())["mode_log"]
    except (OSError, ValueError, KeyError):
        return "after goal"
    left = [t for t, mode in modes if offboard_t < t and mode != "OFFBOARD"]
    return "after goal, offboard" if not left or contact["t_s"] < left[0] else "after goal, landing"


def main(path: str) -> int:
    rows = [json.loads(line) for line in open(path) if line.strip().startswith("{")]
    by_level = collections.defaultdict(list)
    all_trips = collections.Counter()
    for r in rows:
        by_level[r["level"]].append(r)
    print("| level | flights | success % | 95 % interval | crash % | timeout % | other | time_s (success, median) | "
          "step p99 ms (median) | watchdog trips | trips without a crash | crashes caught <= 1.5 s | crash_detect_ms (median) | "
          "tracking error sustained, m/s (max, no crash) | contact after goal (of it while landing) | speed at Hold m/s (max) | tracking error p99 m/s (median) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for level, rs in sorted(by_level.items()):
        n = len(rs)
        count = collections.Counter(r["outcome"] for r in rs)
        times = [r["time_s"] for r in rs if r["outcome"] == "success"]
        p99 = [r["step_ms"]["p99"] for r in rs if (r.get("step_ms") or {}).get("p99") is not None]
        other = n - count["success"] - count["crash"] - count["timeout"]
        trips = sum(len(r.get("watchdog_trips", [])) for r in rs)
        false_trips = [t["cause"] for r in rs if r["outcome"] != "crash" for t in r.get("watchdog_trips", [])]
        detect = [r["crash_detect_ms"] for r in rs if r["outcome"] == "crash" and r.get("crash_detect_ms") is not None]
        caught = sum(ms <= 1500.0 for ms in detect)
        peaks = [r["tracking_error_peak_m_s"] for r in rs if r["outcome"] != "crash" and r.get("tracking_error_peak_m_s") is not None]
        after_goal = sum(contact_after_goal(r) for r in rs)
        landing = sum(contact_while_landing(r) for r in rs)
        hold_speeds = [r["brake"]["speed_at_hold_m_s"] for r in rs if (r.get("brake") or {}).get("speed_at_hold_m_s") is not None]
        tracking = [r["tracking_error_m_s"]["p99"] for r in rs if (r.get("tracking_error_m_s") or {}).get("p99") is not None]
        low, high = wilson_interval(count["success"], n)
        print(f"| {level} | {n} | {100 * count['success'] / n:.0f} | {100 * low:.0f}–{100 * high:.0f} | {100 * count['crash'] / n:.0f} | "
              f"{100 * count['timeout'] / n:.0f} | {other} | {_median(times):.1f} | {_median(p99):.1f} | {trips} | {len(false_trips)} | "
              f"{caught}/{count['crash']} | {_median(detect):.0f} | {max(peaks) if peaks else float('nan'):.2f} | {after_goal} ({landing}) | "
              f"{max(hold_speeds) if hold_speeds else float('nan'):.2f} | {_median(tracking):.2f} |")
        all_trips.update(t["cause"] for r in rs for t in r.get("watchdog_trips", []))
    print("watchdog trips by cause:", dict(all_trips) or "none")
    print()
    print("| level | contacts: take-off | in flight before the goal | after the goal, offboard (brake, retreat, landing) | "
          "after the goal, PX4's Hold/Land | retreats (ended: count) | landings in offboard (ended: count) | "
          "landing sites: chosen / where it stopped / travel median, max (m) / stepped away from the path / none clear | "
          "approaches slowed near what was seen (least cap m/s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for level, rs in sorted(by_level.items()):
        phases = collections.Counter(contact_phase(r) for r in rs)
        retreats = collections.Counter(((r.get("brake") or {}).get("retreat") or {}).get("ended") for r in rs)
        descents = collections.Counter(((r.get("brake") or {}).get("descent") or {}).get("ended") for r in rs)
        retreats.pop(None, None)
        descents.pop(None, None)
        sites = [(r.get("brake") or {}).get("landing_site") for r in rs]
        sites = [s for s in sites if s is not None]
        # (sites recorded before the way back was checked have a back_m, no travel_m: "-")
        travels = [s["travel_m"] for s in sites if "travel_m" in s]
        travel = f"{sum(t == 0.0 for t in travels)} / {_median(travels):.2f}, {max(travels):.2f}" if travels else "- / -"
        print(f"| {level} | {phases['take-off']} | {phases['flight']} | {phases['after goal, offboard']} | "
              f"{phases['after goal, landing'] + phases['after goal']} | {dict(retreats) or '-'} | {dict(descents) or '-'} | "
              f"{len(sites)} / {travel} / {sum(s.get('away_heading_enu_rad') is not None for s in sites)} / "
              f"{sum(not s['clear'] for s in sites)} | {_approaches(rs)} |")
    return 0


def _approaches(rs: list[dict]) -> str:
    """How many flights' approach to the goal was slowed (runtime.watchdog.cap_approach) and the least cap."""
    caps = [r["approach_cap"] for r in rs if r.get("approach_cap")]
    slowed = [c["least_cap_m_s"] for c in caps if c["capped_steps"] > 0]
    return f"{len(slowed)} of {len(caps)} ({min(slowed):.2f})" if slowed else (f"0 of {len(caps)}" if caps else "-")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
