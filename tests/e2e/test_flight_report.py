"""The flight report of a real SITL flight, as a person sees it: `cmnav sitl` writes it beside the
log, headless Chromium renders the page, and its figures agree with the flight's summary."""

import html
import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from export.goal_seeker import export_goal_seeker

pytestmark = pytest.mark.timeout(240)

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync")  # fmt: skip


def _screenshot(page: Path, out: Path, profile: Path) -> np.ndarray:
    proc = subprocess.run(
        [str(CHROMIUM), *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--window-size=1280,2400",
         f"--screenshot={out}", page.resolve().as_uri()],
        capture_output=True, text=True, timeout=90,
    )  # fmt: skip
    image = cv2.imread(str(out))
    assert image is not None, f"chromium wrote no screenshot (exit {proc.returncode}):\n{proc.stderr[-2000:]}"
    return image


def _cells(page: str, prefix: str) -> dict[str, str]:
    return {key: html.unescape(text) for key, text in re.findall(rf'<td id="{prefix}-([a-z0-9_]+)"[^>]*>([^<]*)</td>', page)}


def _number(text: str) -> float | None:
    return None if text == "-" else float(text)


@pytest.mark.skipif(not CHROMIUM.exists(), reason="headless Chromium (/usr/bin/chromium) is not installed: apt-get install chromium")
def test_sitl_flight_report_renders_and_matches_the_summary(tmp_path):
    pytest.importorskip("matplotlib", reason="the report extra (matplotlib) is not installed: pip install 'cmnav[report]'")
    model = tmp_path / "goal-seeker.onnx"
    export_goal_seeker(str(model))
    # Projector off: the depth loses pixels, so the invalid-depth figures are not all zero.
    proc = subprocess.run(
        [sys.executable, "-m", "cmnav", "sitl", "--model", str(model), "--out", str(tmp_path / "runs"), "--json",
         "--level", "0", "--seed", "3", "--timeout", "40", "--degrade", "projector-off"],
        capture_output=True, text=True, timeout=200,
    )  # fmt: skip
    lines = proc.stdout.strip().splitlines()
    summary = json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}
    assert proc.returncode == 0 and summary, f"exit {proc.returncode}; stderr:\n{proc.stderr[-3000:]}"
    report = Path(summary["report"])
    assert report == Path(summary["log"]).with_suffix(".html") and report.with_suffix(".png").is_file()
    assert json.loads((report.parent / "summary.json").read_text())["report"] == str(report)

    page = report.read_text()
    assert "src=\"http" not in page and "<script" not in page  # self-contained: nothing to fetch
    assert page.count("data:image/png;base64,") >= 3  # the plots and at least start and end frames

    ours, theirs = _cells(page, "log"), _cells(page, "summary")
    assert int(ours["steps"]) == summary["frames"] == int(theirs["steps"])
    for key in ("p50", "p99", "max"):
        # The log keeps each step's time to 1e-4 ms; the summary rounds its percentiles to 1e-3.
        assert abs(float(ours[f"step_ms_{key}"]) - summary["step_ms"][key]) <= 2e-3, key
    assert int(ours["watchdog_trips"]) == len(summary["watchdog_trips"])
    assert int(ours["missed_deadlines"]) == summary["missed_deadlines"]
    # Telemetry in the log against the vehicle's ground truth, and the frames the runtime received
    # against those the vehicle served while in offboard: the same flight, not the same samples.
    assert abs(float(ours["path_m"]) - summary["path_m"]) <= 0.1 * summary["path_m"]
    invalid = summary["invalid_depth_pct"]
    assert invalid["avg"] > 5.0
    assert abs(float(ours["invalid_depth_pct_avg"]) - invalid["avg"]) <= 3.0
    assert _number(theirs["invalid_depth_pct_avg"]) == invalid["avg"]
    assert re.search(r'id="verdict-0">success<', page)

    shot = _screenshot(report, tmp_path / "shot.png", tmp_path / "chromium-profile")
    hsv = cv2.cvtColor(shot, cv2.COLOR_BGR2HSV)
    not_white = np.mean(np.any(shot < 235, axis=2))
    coloured = np.mean((hsv[..., 1] > 80) & (hsv[..., 2] > 60))  # plot lines, markers, the depth colour map
    assert not_white > 0.05, f"the page looks blank: {100 * not_white:.1f} % of its pixels are not white"
    assert coloured > 0.005, f"no plots or camera frames drawn: {100 * coloured:.2f} % coloured pixels"
