"""Where a dry run lands after its goal: a point back along the path flown whose column down to
the floor is clear of what the depth camera saw during the episode.

The path flown is free at the height it was flown, not below it: on PX4 SIH a flight that passed
over a 2.9 m post at 4.3 m retreated 1.5 m along its path, stopped 0.38 m from the post and touched
it while landing (level 6, seed 7003).  So every step's depth frame adds the surfaces it shows
(walls, obstacles; not the floor) to a horizontal grid (:class:`SeenSurfaces`, in the estimate's
local ENU frame, which the path and the landing use too), and :func:`choose_landing_site` picks the
point of the path, within ``mission.land_site_search_m`` of its end, nearest to
``mission.land_retreat_m`` back whose distance to every surface seen below the landing height is at
least ``mission.land_clearance_m`` (the vehicle's radius plus the landing's drift: 0.58 m of true
drift at p90 and 0.74 m at most on 58 PX4 SIH landings).  If none is, the clearest.  A camera that
showed nothing (all depth invalid) leaves every point clear: the retreat of ``land_retreat_m``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .contract.camera import depth_points_flu
from .contract.frames import quat_rotate
from .watchdog import arc_lengths_m, path_point, retreat_path

SEEN_CELL_M = 0.1  # the grid's cell side
SEEN_SAMPLE_COLS, SEEN_SAMPLE_ROWS = 53, 30  # pixels sampled per frame (the sim's 212 x 120 at a stride of 4)
# Beyond this range a D455's depth error (about 2 % at 4 m, growing with the square of range) and
# the attitude's (1 degree: 0.1 m at 6 m) put a point in the wrong cell or the floor among obstacles.
SEEN_MAX_DEPTH_M = 6.0
# Points this close to the floor are the floor: PX4's height estimate drifts by ~0.1-0.2 m.
SEEN_FLOOR_BAND_M = 0.3
LANDING_SITE_STEP_M = 0.1  # the candidates' spacing along the path
LANDING_HEIGHT_MARGIN_M = 0.3  # surfaces seen up to this far above the landing height are in its way


class SeenSurfaces:
    """Surfaces (not the floor) the depth frames of an episode showed, as the lowest height seen
    in each cell of a horizontal grid of ``SEEN_CELL_M`` (local ENU, the estimate's frame)."""

    def __init__(self) -> None:
        self._lowest_m: dict[tuple[int, int], float] = {}

    def __len__(self) -> int:
        return len(self._lowest_m)

    def add_frame(self, depth_m: np.ndarray, pos_enu_m: np.ndarray, quat_enu_flu: np.ndarray, floor_z_m: float) -> int:
        """Add the surfaces frame ``depth_m`` shows from the camera at ``pos_enu_m`` with attitude
        ``quat_enu_flu`` (the camera at the body origin, looking along body +x: the contract's
        mount), the floor at height ``floor_z_m``; returns how many points were surfaces."""
        points = depth_points_flu(depth_m, SEEN_SAMPLE_COLS, SEEN_SAMPLE_ROWS, SEEN_MAX_DEPTH_M)
        world = np.asarray(pos_enu_m, dtype=np.float64) + quat_rotate(np.asarray(quat_enu_flu, dtype=np.float64), points)
        world = world[world[:, 2] > floor_z_m + SEEN_FLOOR_BAND_M]
        if len(world) == 0:
            return 0
        cells, inverse = np.unique(np.floor(world[:, :2] / SEEN_CELL_M).astype(np.int64), axis=0, return_inverse=True)
        lowest = np.full(len(cells), np.inf)
        np.minimum.at(lowest, inverse.reshape(-1), world[:, 2])
        for (i, j), z in zip(cells.tolist(), lowest.tolist()):
            if z < self._lowest_m.get((i, j), np.inf):
                self._lowest_m[(i, j)] = z
        return len(world)

    def clearance_m(self, points_xy_m: np.ndarray, below_z_m: float) -> np.ndarray:
        """[N] horizontal distance from each point (N, 2) to the nearest cell centre with a surface
        seen below height ``below_z_m``; inf where there is none."""
        points = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
        cells = [cell for cell, z in self._lowest_m.items() if z < below_z_m]
        if not cells:
            return np.full(len(points), np.inf)
        centres = (np.array(cells, dtype=np.float64) + 0.5) * SEEN_CELL_M
        return np.sqrt(((points[:, None, :] - centres[None, :, :]) ** 2).sum(axis=2).min(axis=1))


@dataclass(frozen=True)
class LandingSite:
    """Where to land: ``back_m`` of horizontal length back along the path flown; its clearance to
    the surfaces seen (m; None: none seen), whether that meets the clearance asked, how many cells
    of the grid held a surface."""

    back_m: float
    clearance_m: float | None
    clear: bool
    surface_cells: int

    def record(self) -> dict:
        return asdict(self)


def choose_landing_site(
    flown_enu_m: np.ndarray,
    seen: SeenSurfaces,
    height_z_m: float,
    preferred_back_m: float,
    search_back_m: float,
    clearance_m: float,
) -> LandingSite:
    """The landing site on the path flown (positions in order, local ENU m, (N, 3)), for a vehicle
    now at height ``height_z_m``: among the points every ``LANDING_SITE_STEP_M`` up to
    ``search_back_m`` back from its end (the whole path if shorter), the one nearest to
    ``preferred_back_m`` back whose clearance is at least ``clearance_m``; else the clearest
    (nearest to ``preferred_back_m`` among equals)."""
    path = retreat_path(np.asarray(flown_enu_m, dtype=np.float64).reshape(-1, 3), max(search_back_m, preferred_back_m))
    at_m = arc_lengths_m(path)
    backs_m = np.arange(0.0, at_m[-1] + 1e-9, LANDING_SITE_STEP_M)
    points = np.array([path_point(path, at_m, b)[:2] for b in backs_m])
    clearances = seen.clearance_m(points, height_z_m + LANDING_HEIGHT_MARGIN_M)
    order = np.argsort(np.abs(backs_m - min(preferred_back_m, at_m[-1])), kind="stable")
    ok = clearances[order] >= clearance_m
    best = order[int(np.argmax(ok))] if ok.any() else order[int(np.argmax(clearances[order]))]
    clearance = float(clearances[best])
    return LandingSite(
        back_m=round(float(backs_m[best]), 3),
        clearance_m=round(clearance, 3) if np.isfinite(clearance) else None,
        clear=bool(clearances[best] >= clearance_m),
        surface_cells=len(seen),
    )
