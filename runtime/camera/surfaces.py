"""What the depth frames of an episode showed below the vehicle, in the estimate's local ENU
frame: where a dry run may land (``runtime.watchdog.choose_landing_site``).  The path flown is
free at the height it was flown, not below it: on PX4 SIH a flight that passed over a 2.9 m post at
4.3 m retreated 1.5 m along its path, stopped 0.38 m from the post and touched it while landing
(level 6, seed 7003).  And the way back to a site passes what the path passed: at level 15 two
retreats touched a thin post or a slab's edge beside the path (0.2-0.3 m of estimate drift and
tracking error on a path that had cleared them by 0.4-0.5 m).  Each step's frame adds the surfaces
it shows (walls, obstacles; not the floor) to a horizontal grid, with the heights they were seen at.
"""

from __future__ import annotations

import numpy as np

from ..contract.camera import depth_points_flu
from ..contract.frames import quat_rotate

SEEN_CELL_M = 0.1  # the grid's cell side
SEEN_SAMPLE_COLS, SEEN_SAMPLE_ROWS = 53, 30  # pixels sampled per frame (the sim's 212 x 120 at a stride of 4)
# Beyond this range a D455's depth error (about 2 % at 4 m, growing with the square of range) and
# the pose's put a point in the wrong cell or the floor among the surfaces.
SEEN_MAX_DEPTH_M = 5.0
# A point within SEEN_FLOOR_BAND_M + SEEN_FLOOR_BAND_PER_M x its range of the floor is the floor:
# seen through PX4 SIH's estimate (its height, its attitude, the frame taken before the step's
# state), floor points lay up to 0.42 / 0.52 / 0.65 / 0.72 m above it at 2-3 / 3-4 / 4-5 / 5-6 m
# range (p99.9 of 416,000 on 20 flights at level 0).
SEEN_FLOOR_BAND_M = 0.2
SEEN_FLOOR_BAND_PER_M = 0.1
# ... and rarer ones beyond: a cell is a surface once that many frames showed one in it (an obstacle
# in view is in tens of frames, each with several points).
SEEN_MIN_FRAMES = 3
# The heights a cell holds surfaces at, in bins of this size (a post below and the ceiling above
# share a column: the way back at the height between them passes neither).
SEEN_BIN_M = 0.1
_BIN_OFFSET, _BINS = 40, 160  # bins from 4 m below the local origin to 12 m above it


class SeenSurfaces:
    """Surfaces (not the floor) the depth frames of an episode showed, in each cell of a horizontal
    grid of ``SEEN_CELL_M`` (local ENU, the estimate's frame): the lowest height seen and the
    heights seen, in bins of ``SEEN_BIN_M``."""

    def __init__(self) -> None:
        # per cell: the lowest height seen (m), the height bins seen (a bit mask), how many frames showed a surface in it
        self._cells: dict[tuple[int, int], tuple[float, int, int]] = {}

    def _surfaces(self) -> dict[tuple[int, int], tuple[float, int]]:
        """The cells that are surfaces (shown by SEEN_MIN_FRAMES frames): their lowest height and height bins."""
        return {cell: (low, bins) for cell, (low, bins, frames) in self._cells.items() if frames >= SEEN_MIN_FRAMES}

    def __len__(self) -> int:
        return len(self._surfaces())

    def add_frame(self, depth_m: np.ndarray, pos_enu_m: np.ndarray, quat_enu_flu: np.ndarray, floor_z_m: float) -> int:
        """Add the surfaces frame ``depth_m`` shows from the camera at ``pos_enu_m`` with attitude
        ``quat_enu_flu`` (the camera at the body origin, looking along body +x: the contract's
        mount), the floor at height ``floor_z_m``; returns how many points were surfaces."""
        points = depth_points_flu(depth_m, SEEN_SAMPLE_COLS, SEEN_SAMPLE_ROWS, SEEN_MAX_DEPTH_M)
        world = np.asarray(pos_enu_m, dtype=np.float64) + quat_rotate(np.asarray(quat_enu_flu, dtype=np.float64), points)
        band_m = SEEN_FLOOR_BAND_M + SEEN_FLOOR_BAND_PER_M * np.linalg.norm(points, axis=1)
        world = world[world[:, 2] > floor_z_m + band_m]
        if len(world) == 0:
            return 0
        cells, inverse = np.unique(np.floor(world[:, :2] / SEEN_CELL_M).astype(np.int64), axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        lowest = np.full(len(cells), np.inf)
        np.minimum.at(lowest, inverse, world[:, 2])
        bins = [0] * len(cells)
        for k, b in np.unique(np.stack([inverse, _height_bin(world[:, 2])], axis=1), axis=0).tolist():
            bins[k] |= 1 << b
        for (i, j), low, seen_bins in zip(cells.tolist(), lowest.tolist(), bins):
            low_before, bins_before, frames = self._cells.get((i, j), (np.inf, 0, 0))
            self._cells[(i, j)] = (min(low, low_before), bins_before | seen_bins, frames + 1)
        return len(world)

    def cells_xy_m(self, below_z_m: float, above_z_m: float | None = None) -> np.ndarray:
        """(K, 2) the centres of the cells with a surface seen below height ``below_z_m`` (with
        ``above_z_m``: between the two heights, to a bin)."""
        if above_z_m is None:
            cells = [cell for cell, (low, _) in self._surfaces().items() if low < below_z_m]
        else:
            first, last = (int(b) for b in _height_bin(np.array([above_z_m, below_z_m])))
            band = ((1 << (last + 1)) - 1) ^ ((1 << first) - 1)
            cells = [cell for cell, (_, bins) in self._surfaces().items() if bins & band]
        return (np.array(cells, dtype=np.float64).reshape(-1, 2) + 0.5) * SEEN_CELL_M

    def clearance_m(self, points_xy_m: np.ndarray, below_z_m: float, above_z_m: float | None = None) -> np.ndarray:
        """[N] horizontal distance from each point (N, 2) to the nearest of :meth:`cells_xy_m`;
        inf where there is none."""
        return nearest_m(points_xy_m, self.cells_xy_m(below_z_m, above_z_m))


def _height_bin(z_m: np.ndarray) -> np.ndarray:
    """The height bin of each height (m, local ENU), clamped to the bins kept."""
    return np.clip(np.floor(np.asarray(z_m) / SEEN_BIN_M).astype(np.int64) + _BIN_OFFSET, 0, _BINS - 1)


def nearest_m(points_xy_m: np.ndarray, cells_xy_m: np.ndarray) -> np.ndarray:
    """[N] horizontal distance from each point (N, 2) to the nearest of ``cells_xy_m`` (K, 2); inf if K = 0."""
    points = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    if len(cells_xy_m) == 0:
        return np.full(len(points), np.inf)
    return np.sqrt(((points[:, None, :] - cells_xy_m[None, :, :]) ** 2).sum(axis=2).min(axis=1))
