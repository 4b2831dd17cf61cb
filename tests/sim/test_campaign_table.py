"""scripts/campaign-table.py: the outcome table of a campaign, and when each contact came
(take-off, flight, after the goal in offboard, after the goal in Hold/Land), on planted summaries."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def table():
    spec = importlib.util.spec_from_file_location("campaign_table", ROOT / "scripts" / "campaign-table.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _summary(tmp_path: Path, name: str, contact_t: float | None, goal_t: float | None, modes, retreat: str | None = None,
             descent: str | None = None, site: dict | None = None) -> dict:  # fmt: skip
    run_dir = tmp_path / name
    run_dir.mkdir()
    (run_dir / "trace.json").write_text(json.dumps({"mode_log": modes}))
    truth = {"offboard_t_s": 10.0, "goal_reached_t_s": goal_t, "contact": None if contact_t is None else {"t_s": contact_t, "what": "wall"}}
    return {"level": 0, "seed": 1, "outcome": "crash" if contact_t else "success", "ground_truth": truth, "run_dir": str(run_dir),
            "time_s": 6.0, "step_ms": {"p99": 40.0}, "watchdog_trips": [],
            "brake": {"ended": "stopped", "speed_at_hold_m_s": 0.1, **({"retreat": {"ended": retreat}} if retreat else {}),
                      **({"descent": {"ended": descent}} if descent else {}), **({"landing_site": site} if site else {})}}  # fmt: skip


def test_each_contact_is_put_in_its_phase(table, tmp_path):
    modes = [[9.0, "HOLD"], [10.0, "OFFBOARD"], [20.0, "HOLD"], [21.0, "LAND"]]
    cases = {"take-off": 9.5, "flight": 12.0, "after goal, offboard": 18.0, "after goal, landing": 22.0, None: None}
    for phase, t in cases.items():
        summary = _summary(tmp_path, str(phase), t, 16.0, modes)
        assert table.contact_phase(summary) == phase
    assert table.contact_phase(_summary(tmp_path, "no-goal", 18.0, None, modes)) == "flight"


def test_the_table_counts_phases_and_retreats(table, tmp_path, capsys):
    modes = [[10.0, "OFFBOARD"], [20.0, "HOLD"]]
    sites = [{"travel_m": 0.7, "clear": True, "away_heading_enu_rad": 1.571}, {"travel_m": 0.0, "clear": False}]
    rows = [_summary(tmp_path, "a", None, 16.0, modes, "arrived", "disarmed", sites[0]), _summary(tmp_path, "b", 18.0, 16.0, modes, "timeout", site=sites[1]),
            _summary(tmp_path, "c", 12.0, None, modes)]
    rows[0]["approach_cap"], rows[1]["approach_cap"] = {"capped_steps": 7, "least_cap_m_s": 0.84}, {"capped_steps": 0, "least_cap_m_s": None}
    path = tmp_path / "summaries.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    assert table.main(str(path)) == 0
    out = capsys.readouterr().out
    assert "| 0 | 3 | 33 |" in out
    assert "| 0 | 0 | 1 | 1 | 0 | {'arrived': 1, 'timeout': 1} | {'disarmed': 1} | 2 / 1 / 0.35, 0.70 / 1 / 1 | 1 of 2 (0.84) |" in out
