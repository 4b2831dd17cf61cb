"""Top-view trajectory plot of one episode, like the paper's trajectory figure: room, obstacles,
flown path, start (blue) and goal (red).  Drawn with OpenCV so it needs no plotting library; where
OpenCV is missing (the offline GPU machine) the plot is skipped with one warning naming the fix."""

from __future__ import annotations

import logging
from pathlib import Path
from types import ModuleType
from typing import Sequence

import numpy as np

from runtime.contract.constants import GOAL_REACHED_RADIUS_M

log = logging.getLogger(__name__)
_warned: set[str] = set()

PX_PER_M = 60
MARGIN_PX = 50
BGR_BLUE = (200, 80, 0)
BGR_RED = (0, 0, 220)
BGR_PATH = (40, 140, 40)
BGR_OBSTACLE = (110, 110, 110)
BGR_WALL = (0, 0, 0)


def opencv_for_drawing(command: str) -> ModuleType | None:
    """cv2 to draw with, or None where OpenCV is missing; then warns once per ``command`` (the
    one to re-run for the plots, e.g. ``cmnav eval policy``) that plots are skipped."""
    try:
        import cv2  # here, not at the top: the offline GPU machine has no OpenCV
    except ImportError:
        if command not in _warned:
            _warned.add(command)
            log.warning("OpenCV is not installed, so plots are skipped: install opencv-python-headless and "
                        "re-run `%s` to draw them", command)  # fmt: skip
        return None
    return cv2


def plot_top_view(
    path_png: str | Path,
    room_size_m: Sequence[float],
    boxes: Sequence[dict],
    start_enu_m: Sequence[float],
    goal_enu_m: Sequence[float],
    trajectory_enu_m: np.ndarray,
    title: str = "",
    collision_enu_m: Sequence[float] | None = None,
    command: str = "cmnav eval policy",
) -> Path | None:
    """Draw the x-y plane (ENU, x to the right, y up) and write a PNG; None (and a warning naming
    ``command`` to re-run) where OpenCV is missing.  Boxes are dicts with ``center_m``,
    ``half_extent_m`` and ``yaw_rad`` as the SITL episode file has them."""
    cv2 = opencv_for_drawing(command)
    if cv2 is None:
        return None
    length_m, width_m = float(room_size_m[0]), float(room_size_m[1])
    w_px = int(round(length_m * PX_PER_M)) + 2 * MARGIN_PX
    h_px = int(round(width_m * PX_PER_M)) + 2 * MARGIN_PX + 30
    image = np.full((h_px, w_px, 3), 255, np.uint8)

    def to_px(xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        u = MARGIN_PX + xy[:, 0] * PX_PER_M
        v = h_px - MARGIN_PX - xy[:, 1] * PX_PER_M
        return np.stack([u, v], axis=1).round().astype(np.int32)

    def pt(xy) -> tuple[int, int]:
        u, v = to_px(xy)[0]
        return int(u), int(v)

    cv2.rectangle(image, pt([0, width_m]), pt([length_m, 0]), BGR_WALL, 2)
    for box in boxes:
        cx, cy = box["center_m"][:2]
        hx, hy = box["half_extent_m"][:2]
        c, s = np.cos(box["yaw_rad"]), np.sin(box["yaw_rad"])
        corners = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
        world = corners @ np.array([[c, s], [-s, c]]) + np.array([cx, cy])
        cv2.fillPoly(image, [to_px(world)], BGR_OBSTACLE)
    trajectory = np.asarray(trajectory_enu_m, dtype=np.float64).reshape(-1, 3)
    if len(trajectory) >= 2:
        cv2.polylines(image, [to_px(trajectory[:, :2])], False, BGR_PATH, 2, cv2.LINE_AA)
    cv2.circle(image, pt(goal_enu_m[:2]), int(GOAL_REACHED_RADIUS_M * PX_PER_M), BGR_RED, 1, cv2.LINE_AA)
    cv2.circle(image, pt(goal_enu_m[:2]), 7, BGR_RED, -1, cv2.LINE_AA)
    cv2.circle(image, pt(start_enu_m[:2]), 7, BGR_BLUE, -1, cv2.LINE_AA)
    if collision_enu_m is not None:
        cv2.drawMarker(image, pt(collision_enu_m[:2]), BGR_RED, cv2.MARKER_TILTED_CROSS, 18, 3)
    bar_start, bar_end = pt([0.0, -0.5]), pt([1.0, -0.5])
    cv2.line(image, bar_start, bar_end, BGR_WALL, 2)
    cv2.putText(image, "1 m", (bar_end[0] + 6, bar_end[1] + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45, BGR_WALL, 1)
    if title:
        cv2.putText(image, title, (MARGIN_PX, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.6, BGR_WALL, 1, cv2.LINE_AA)
    out = Path(path_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), image):
        raise OSError(f"could not write the trajectory plot to {out}: is the directory writable?")
    return out
