"""The flight report: one self-contained HTML page (every image inline as base64 PNG) and one PNG
of its plots, drawn from :class:`runtime.report.flight_data.FlightData`.

matplotlib is the optional extra ``report`` (``pip install 'cmnav[report]'``): imported here, on
use, through its object API (no pyplot: no global state, no display), so a flight process that
renders a report changes nothing else in matplotlib's settings.
"""

from __future__ import annotations

import base64
import html
import io
import json
import logging
import math
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from ..contract.constants import GOAL_REACHED_RADIUS_M
from .flight_data import DEPTH_RANGE_M, FlightData, read_flight

log = logging.getLogger(__name__)

AXES = (("forward", "m/s"), ("left", "m/s"), ("up", "m/s"), ("yaw rate, left +", "rad/s"))
# The figures the page shows beside the summary's, as (key in FlightData.numbers(), key in the summary, label).
COMPARED = (
    ("steps", "frames", "policy steps"),
    ("step_ms_p50", ("step_ms", "p50"), "step latency p50 (ms)"),
    ("step_ms_p99", ("step_ms", "p99"), "step latency p99 (ms)"),
    ("step_ms_max", ("step_ms", "max"), "step latency max (ms)"),
    ("missed_deadlines", "missed_deadlines", "missed step deadlines"),
    ("watchdog_trips", "watchdog_trips", "watchdog trips"),
    ("flight_s", "time_s", "flight time (s)"),
    ("path_m", "path_m", "path length (m)"),
    ("final_distance_m", "final_distance_m", "final distance to goal (m)"),
    ("invalid_depth_pct_avg", ("invalid_depth_pct", "avg"), "invalid depth avg (%)"),
    ("invalid_depth_pct_min", ("invalid_depth_pct", "min"), "invalid depth min (%)"),
    ("invalid_depth_pct_max", ("invalid_depth_pct", "max"), "invalid depth max (%)"),
)


class ReportUnavailableError(RuntimeError):
    """The report cannot be drawn here; the message says what to install."""


def _matplotlib() -> tuple[Any, Any]:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as err:
        raise ReportUnavailableError(
            f"matplotlib is not installed ({err}): `pip install 'cmnav[report]'` to draw flight reports"
        ) from err
    return Figure, FigureCanvasAgg


def _summary_value(summary: dict, key: str | tuple[str, str]) -> Any:
    if isinstance(key, tuple):
        inner = summary.get(key[0])
        return inner.get(key[1]) if isinstance(inner, dict) else None
    value = summary.get(key)
    return len(value) if isinstance(value, list) else value


def _room_in_local(room: dict) -> tuple[np.ndarray, list[dict]]:
    """The room's corners and boxes moved into the runtime's local frame: the SITL world's ENU
    minus home (the autopilot's local origin is its home)."""
    home = np.asarray(room.get("home_enu_m", (0.0, 0.0, 0.0)), dtype=np.float64)
    length_m, width_m = float(room["room_size_m"][0]), float(room["room_size_m"][1])
    corners = np.array([[0, 0], [length_m, 0], [length_m, width_m], [0, width_m], [0, 0]], dtype=np.float64) - home[:2]
    boxes = []
    for box in room.get("boxes", []):
        cx, cy = np.asarray(box["center_m"][:2], dtype=np.float64) - home[:2]
        hx, hy = box["half_extent_m"][:2]
        c, s = math.cos(box["yaw_rad"]), math.sin(box["yaw_rad"])
        local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy], [hx, hy]])
        boxes.append({"xy": local @ np.array([[c, s], [-s, c]]) + np.array([cx, cy])})
    return corners, boxes


def draw_figure(data: FlightData, room: dict | None, title: str) -> bytes:
    """The plots as one PNG: top view, commanded vs achieved velocity per axis, step latency
    histogram, invalid-depth fraction over time with the watchdog's events."""
    Figure, FigureCanvasAgg = _matplotlib()
    fig = Figure(figsize=(14, 13), dpi=90, layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(4, 3)
    fig.suptitle(title, fontsize=13)
    events = [e for e in data.watchdog_events if e.get("event") in ("trip", "hold")]

    top = fig.add_subplot(grid[0:2, 0:2])
    if room is not None:
        corners, boxes = _room_in_local(room)
        top.plot(corners[:, 0], corners[:, 1], color="black", lw=2, label="room walls")
        for box in boxes:
            top.fill(box["xy"][:, 0], box["xy"][:, 1], color="0.55")
    pos, flying = data.pos_enu_m, data.in_flight(data.state_t_s)
    top.plot(pos[:, 0], pos[:, 1], color="0.75", lw=1, label="whole log")
    if flying.any():
        top.plot(pos[flying, 0], pos[flying, 1], color="tab:green", lw=2.5, label="policy flight")
        start = pos[flying][0]
        top.plot(start[0], start[1], "o", color="tab:blue", ms=10, label="start")
    for k, goal in enumerate(data.goals_enu_m):
        top.add_patch(_circle(goal[:2], GOAL_REACHED_RADIUS_M))
        top.plot(goal[0], goal[1], "o", color="tab:red", ms=9, label="goal" if k == 0 else None)
        if len(data.goals_enu_m) > 1:
            top.annotate(str(k + 1), (goal[0], goal[1]), textcoords="offset points", xytext=(6, 6), color="tab:red")
    for event in events:
        if event.get("event") == "trip":
            at = _position_at(data, float(event["log_t_s"]))
            if at is not None:
                top.plot(at[0], at[1], "X", color="tab:red", ms=12, label=f"trip {event.get('cause')}")
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel("x east (m, local ENU)")
    top.set_ylabel("y north (m, local ENU)")
    top.set_title("top view" + (" (room from the SITL episode)" if room is not None else ""))
    top.grid(alpha=0.3)
    top.legend(loc="best", fontsize=8)

    hist = fig.add_subplot(grid[0, 2])
    steps = data.step_ms[np.isfinite(data.step_ms)]
    if len(steps):
        p50, p99 = np.percentile(steps, [50, 99])
        hist.hist(steps, bins=min(40, max(5, len(steps) // 4)), color="tab:blue", alpha=0.8)
        hist.axvline(p50, color="black", ls="--", label=f"p50 {p50:.2f} ms")
        hist.axvline(p99, color="tab:red", ls="--", label=f"p99 {p99:.2f} ms")
        hist.legend(fontsize=8)
    hist.set_title(f"step latency ({len(steps)} steps)")
    hist.set_xlabel("frame taken -> command sent (ms)")
    hist.set_ylabel("steps")

    invalid = fig.add_subplot(grid[1, 2])
    invalid.plot(data.frame_t_s, 100.0 * data.invalid_frac, color="tab:purple", lw=1)
    invalid.set_ylim(-2, 102)
    invalid.set_title("invalid depth per frame")
    invalid.set_xlabel("s from episode start")
    invalid.set_ylabel("% pixels")
    _mark_events(invalid, events, data)

    achieved = np.column_stack([data.vel_v_m_s, data.yaw_rate_flu_rad_s[:, None]]) if len(data.state_t_s) else np.zeros((0, 4))
    commanded = np.column_stack([data.cmd_v_m_s, data.cmd_yaw_rate_flu_rad_s[:, None]]) if len(data.cmd_t_s) else np.zeros((0, 4))
    window = _plot_window(data)
    for k, (name, unit) in enumerate(AXES):
        ax = fig.add_subplot(grid[2 + k // 2, k % 2])
        ax.step(data.cmd_t_s, commanded[:, k], where="post", color="tab:orange", lw=1.5, label="commanded")
        ax.plot(data.state_t_s, achieved[:, k], color="tab:blue", lw=1, label="achieved (telemetry)")
        if window is not None:
            ax.set_xlim(*window)
        ax.set_title(f"{name} ({unit}), vehicle frame V")
        ax.set_xlabel("s from episode start")
        ax.grid(alpha=0.3)
        _mark_events(ax, events, data)
        if k == 0:
            ax.legend(fontsize=8)
    notes = fig.add_subplot(grid[2:4, 2])
    notes.axis("off")
    numbers = data.numbers()
    lines = [f"{label}: {numbers[key] if numbers[key] is not None else '-'}" for key, _, label in COMPARED]
    lines += ["", "watchdog events:"] + [f"  {e['log_t_s']:+.2f} s {e.get('event')} {e.get('cause') or ''}" for e in events[:12]]
    notes.text(0.0, 1.0, "\n".join(lines), va="top", family="monospace", fontsize=9)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return buffer.getvalue()


def _circle(center: Sequence[float], radius_m: float) -> Any:
    from matplotlib.patches import Circle

    return Circle((float(center[0]), float(center[1])), radius_m, fill=False, color="tab:red", ls=":")


def _position_at(data: FlightData, t_s: float) -> np.ndarray | None:
    if len(data.state_t_s) == 0:
        return None
    k = int(np.clip(np.searchsorted(data.state_t_s, t_s), 0, len(data.state_t_s) - 1))
    return data.pos_enu_m[k] if np.all(np.isfinite(data.pos_enu_m[k, :2])) else None


def _plot_window(data: FlightData) -> tuple[float, float] | None:
    if data.first_step_t_s is None:
        return None
    end = max(data.last_step_t_s, data.offboard_end_t_s or data.last_step_t_s)
    return data.first_step_t_s - 1.0, end + 1.0


def _mark_events(ax: Any, events: list[dict], data: FlightData) -> None:
    for event in events:
        ax.axvline(float(event["log_t_s"]), color="tab:red" if event.get("event") == "trip" else "0.4", ls=":", lw=1)


def _png_base64(png: bytes) -> str:
    return base64.b64encode(png).decode("ascii")


def _frame_png(gray_u8: np.ndarray, depth_m: np.ndarray) -> bytes:
    """Gray beside depth (turbo colour map over 0..10 m, invalid pixels black)."""
    scaled = np.clip(np.nan_to_num(depth_m, nan=0.0) / DEPTH_RANGE_M, 0.0, 1.0)
    colour = cv2.applyColorMap((255 * scaled).astype(np.uint8), cv2.COLORMAP_TURBO)
    colour[~(np.isfinite(depth_m) & (depth_m > 0))] = 0
    gray = cv2.cvtColor(gray_u8, cv2.COLOR_GRAY2BGR)
    if gray.shape != colour.shape:
        colour = cv2.resize(colour, (gray.shape[1], gray.shape[0]), interpolation=cv2.INTER_NEAREST)
    ok, png = cv2.imencode(".png", np.hstack([gray, np.full((gray.shape[0], 4, 3), 255, np.uint8), colour]))
    if not ok:
        raise RuntimeError("OpenCV could not encode a camera snapshot as PNG")
    return png.tobytes()


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:g}"
    return html.escape(str(value))


def render_html(data: FlightData, figure_png: bytes, summary: dict | None, title: str) -> str:
    """The page: verdicts, figures (from the log, and the summary's beside them), the plots, the
    camera at the moments that matter, watchdog events and the autopilot's messages."""
    numbers = data.numbers()
    esc = html.escape
    rows = []
    for key, summary_key, label in COMPARED:
        theirs = _summary_value(summary, summary_key) if summary else None
        rows.append(f'<tr><td>{esc(label)}</td><td id="log-{key}" data-value="{_cell(numbers[key])}">{_cell(numbers[key])}</td>'
                    f'<td id="summary-{key}">{_cell(theirs)}</td></tr>')  # fmt: skip
    verdicts = []
    if summary is not None:
        episodes = summary.get("episodes") if isinstance(summary.get("episodes"), list) else [summary]
        for k, ep in enumerate(episodes):
            verdicts.append(
                f'<tr><td>{esc(str(ep.get("episode", k + 1)))}</td><td class="verdict" id="verdict-{k}">{esc(str(ep.get("outcome")))}</td>'
                f'<td>{_cell(ep.get("abort_reason"))}</td><td>{_cell(ep.get("time_s"))}</td><td>{_cell(ep.get("final_distance_m"))}</td></tr>'
            )  # fmt: skip
    events = "".join(
        f"<tr><td>{e['log_t_s']:+.3f}</td><td>{_cell(e.get('event'))}</td><td>{_cell(e.get('cause'))}</td>"
        f"<td>{_cell(e.get('detect_ms'))}</td><td>{_cell(e.get('response'))}</td><td class='detail'>{_cell(e.get('detail'))}</td></tr>"
        for e in data.watchdog_events
    )  # fmt: skip
    texts = "".join(f"<tr><td>{m['log_t_s']:+.3f}</td><td>{_cell(m.get('severity'))}</td><td>{_cell(m.get('text'))}</td></tr>"
                    for m in data.status_texts)  # fmt: skip
    frames = "".join(
        f'<figure><img alt="{esc(s.label)}" src="data:image/png;base64,{_png_base64(_frame_png(s.gray_u8, s.depth_m))}">'
        f"<figcaption>{esc(s.label)} at {s.t_s:+.2f} s, depth invalid {100 * s.invalid_frac:.1f} %</figcaption></figure>"
        for s in data.snapshots
    )  # fmt: skip
    goals = "".join(f"<li>goal {k + 1}: {[round(v, 2) for v in g]} m (local ENU)</li>" for k, g in enumerate(data.goals_enu_m))
    meta = {k: v for k, v in data.metadata.items() if k != "monotonic_to_unix_offset_ns"}
    cut = f'<p class="warn">The log {esc(data.stopped_early)}: the report shows what came before.</p>' if data.stopped_early else ""
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{esc(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; color: #222; background: #fff; }}
table {{ border-collapse: collapse; margin: 0.5em 0 1.5em; }}
td, th {{ border: 1px solid #bbb; padding: 0.2em 0.6em; text-align: left; font-size: 0.92em; }}
th {{ background: #eee; }}
td.detail {{ max-width: 40em; overflow-wrap: anywhere; font-size: 0.8em; }}
td.verdict {{ font-weight: bold; }}
figure {{ display: inline-block; margin: 0.4em; }}
figcaption {{ font-size: 0.85em; }}
img.plots {{ max-width: 100%; }}
.warn {{ color: #a00; font-weight: bold; }}
</style></head><body>
<h1>{esc(title)}</h1>
<p>Log <code>{esc(str(data.path))}</code>; times in seconds from the episode's start (supervision start at offboard).</p>
{cut}
<h2>Verdicts</h2>
{"<table><tr><th>episode</th><th>outcome</th><th>abort reason</th><th>time (s)</th><th>final distance (m)</th></tr>" + "".join(verdicts) + "</table>" if verdicts else "<p>No summary found beside the log: the verdict is the watchdog's events below.</p>"}
<ul>{goals}</ul>
<h2>Figures</h2>
<table><tr><th></th><th>from the log</th><th>from the summary</th></tr>{"".join(rows)}</table>
<h2>Plots</h2>
<img class="plots" alt="flight plots" src="data:image/png;base64,{_png_base64(figure_png)}">
<h2>Camera at the moments that matter</h2>
<p>Gray beside depth (0 to {DEPTH_RANGE_M:g} m, blue near, red far; invalid pixels black).</p>
<div>{frames or "<p>The log has no camera frames.</p>"}</div>
<h2>Watchdog events</h2>
<table><tr><th>t (s)</th><th>event</th><th>cause</th><th>detect (ms)</th><th>response</th><th>detail</th></tr>{events}</table>
<h2>Autopilot messages (STATUSTEXT)</h2>
<table><tr><th>t (s)</th><th>severity</th><th>text</th></tr>{texts}</table>
<h2>Log metadata</h2>
<pre>{esc(json.dumps(meta, indent=1))}</pre>
</body></html>
"""


def report_paths(log_path: str | Path, html_path: str | Path | None = None) -> tuple[Path, Path]:
    """(HTML, PNG): ``html_path`` (default: the log's name with .html) and the PNG beside it."""
    html_out = Path(html_path) if html_path is not None else Path(log_path).with_suffix(".html")
    return html_out, html_out.with_suffix(".png")


def find_companions(log_path: str | Path) -> tuple[dict | None, dict | None]:
    """The summary and the SITL episode (room) that ``cmnav sitl`` writes beside its log
    (``summary.json``, ``episode.json``), where present and readable."""
    found = []
    for name in ("summary.json", "episode.json"):
        path = Path(log_path).parent / name
        try:
            found.append(json.loads(path.read_text()))
        except (OSError, json.JSONDecodeError):
            found.append(None)
    summary, episode = found
    if summary is not None and summary.get("log") not in (None, str(log_path), str(Path(log_path).resolve())):
        if Path(str(summary.get("log"))).name != Path(log_path).name:
            summary = None  # the summary of another log in the same folder
    return summary, episode


def write_report(
    log_path: str | Path, html_path: str | Path | None = None, summary: dict | None = None, room: dict | None = None
) -> tuple[Path, Path]:
    """Read the flight log, write the HTML page and the PNG; returns their paths.  Raises
    :class:`ReportUnavailableError` without matplotlib, ``ReplayError`` for a file that is not a
    cmnav flight log, ``OSError`` when the output cannot be written."""
    _matplotlib()  # before reading a long log
    data = read_flight(log_path)
    outcome = (summary or {}).get("outcome")
    title = f"cmnav flight report: {Path(log_path).name}" + (f" ({outcome})" if outcome else "")
    png = draw_figure(data, room, title)
    html_out, png_out = report_paths(log_path, html_path)
    html_out.parent.mkdir(parents=True, exist_ok=True)
    png_out.write_bytes(png)
    html_out.write_text(render_html(data, png, summary, title))
    log.info("flight report written to %s (plots %s)", html_out, png_out)
    return html_out, png_out


def write_report_quietly(log_path: str | Path | None, summary: dict | None = None, room: dict | None = None) -> Path | None:
    """What the flight programs call after a flight: the report beside the log, or a warning
    naming the cause; never raises (a report must not fail a flight)."""
    if log_path is None or not Path(log_path).exists():
        return None
    try:
        html_out, _ = write_report(log_path, None, summary, room)
    except ReportUnavailableError as err:
        log.warning("no flight report: %s", err)
        return None
    except Exception as err:  # noqa: BLE001 - whatever breaks the drawing, the flight's result stands
        log.warning("no flight report for %s (%s: %s); `cmnav report %s` retries it", log_path, type(err).__name__, err, log_path)
        return None
    return html_out
