"""The validation curve of a CMWAE run: at every checkpoint, the validation MSE at 0 % and 50 %
corruption and their ratio (Table I's criterion) are appended to ``val_curve.json`` in the
checkpoint directory and drawn, against the step, in ``val_curve.png`` (with OpenCV; skipped,
with one warning, where it is missing).  A resumed run keeps the points before its step."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sim.plot import opencv_for_drawing

CURVE_JSON = "val_curve.json"
CURVE_PNG = "val_curve.png"
RERUN = "cmnav train cmwae"


def record_val_point(out_dir: Path, step: int, val: dict[str, float]) -> list[dict]:
    """Append this checkpoint's validation point (dropping points at or after ``step``, which a
    resumed run replaces), rewrite the JSON and the plot; returns the curve."""
    path = out_dir / CURVE_JSON
    points = json.loads(path.read_text()) if path.is_file() else []
    points = [p for p in points if p["step"] < step]
    points.append({"step": step, "mse_0pct": val["val/mse_0pct"], "mse_50pct": val["val/mse_50pct"],
                   "ratio_50_over_0": val["val/mse_ratio_50_over_0"]})  # fmt: skip
    path.write_text(json.dumps(points, indent=1))
    curve_plot(out_dir / CURVE_PNG, points)
    return points


def curve_plot(path: Path, points: list[dict]) -> Path | None:
    """Two panels against the step: MSE (x1e-3) at 0 % and 50 %, and their ratio."""
    cv2 = opencv_for_drawing(RERUN)
    if cv2 is None or not points:
        return None
    width, panel, margin = 720, 260, 60
    image = np.full((2 * panel + 40, width, 3), 255, np.uint8)
    steps = np.array([p["step"] for p in points], dtype=np.float64)
    s_lo, s_hi = float(steps.min()), float(steps.max())
    s_span = s_hi - s_lo if s_hi > s_lo else 1.0

    def x(step: float) -> int:
        return int(margin + (step - s_lo) / s_span * (width - 2 * margin))

    panels = [
        ("validation MSE x1e-3: 0 % (blue), 50 % (red)", [("mse_0pct", (200, 80, 0)), ("mse_50pct", (0, 0, 200))], 1e3),
        ("MSE at 50 % / MSE at 0 %", [("ratio_50_over_0", (0, 120, 0))], 1.0),
    ]
    for k, (title, series, scale) in enumerate(panels):
        top = k * panel + 20
        values = np.array([[p[key] * scale for p in points] for key, _ in series])
        lo, hi = float(values.min()), float(values.max())
        span = hi - lo if hi > lo else 1.0

        def y(v: float, top: int = top, lo: float = lo, span: float = span) -> int:
            return int(top + panel - margin / 2 - (v - lo) / span * (panel - margin))

        cv2.putText(image, title, (margin, top + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
        for v in np.linspace(lo, hi, 4):
            cv2.putText(image, f"{v:.3g}", (5, y(float(v)) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
        for row, (_, color) in zip(values, series):
            pts = np.array([[x(s), y(v)] for s, v in zip(steps, row)], np.int32)
            cv2.polylines(image, [pts], False, color, 2)
            for px, py in pts:
                cv2.circle(image, (int(px), int(py)), 3, color, -1)
    for s in np.linspace(s_lo, s_hi, 5):
        cv2.putText(image, f"{s:.0f}", (x(float(s)) - 15, 2 * panel + 32), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.imwrite(str(path), image)
    return path
