"""What the depth frames of an episode showed below the vehicle, in the estimate's local ENU
frame: where a dry run may land (``runtime.watchdog.choose_landing_site``).  The path flown is
free at the height it was flown, not below it: on PX4 SIH a flight that passed over a 2.9 m post at
4.3 m retreated 1.5 m along its path, stopped 0.38 m from the post and touched it while landing
(level 6, seed 7003).  And the way back to a site passes what the path passed: at level 15 two
retreats touched a thin post or a slab's edge beside the path (0.2-0.3 m of estimate drift and
tracking error on a path that had cleared them by 0.4-0.5 m).  Each step's frame adds the surfaces
it shows (walls, obstacles; not the floor) to a horizontal grid, with the heights they were seen at,
and the free space its rays pass on their way to them, which clears what earlier frames showed
there (stereo mismatches, surfaces seen through an estimate since drifted).  The approach to a dry
run's last goal is slowed by what lies ahead (``runtime.watchdog.cap_approach``).
"""

from __future__ import annotations

import math

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
# Free space: what a frame sees through is not a surface.  With the simulated D455's stereo depth
# and PX4 SIH's estimate, 10-50 % of the cells seen at the flight height lay more than 0.3 m from
# any surface (stereo mismatches, and surfaces seen again from an estimate that has drifted): they
# blocked landing sites and steps that were free.  The rays of the sampled pixels clear the
# cells (of a height bin) they pass on their way to what they hit (the same pixels), short of it by
# SEEN_FREE_MARGIN_M + SEEN_FREE_MARGIN_PER_M2 x range^2 (the cell's diagonal, and 3 sigma of a
# D455's depth error: 2 % at 4 m, growing with the square of range), except the cell bins next to
# one the frame shows (a ray grazing a wall runs through the wall's cells before its hit); a cell
# bin stops being a surface once more frames saw through it than showed a surface in it.  Invalid
# depth clears nothing.
SEEN_FREE_STEP_M = 0.1  # spacing of the points along a ray whose cells it clears
SEEN_FREE_START_M = 0.1  # where along a ray its clearing begins (m from the camera)
SEEN_FREE_MARGIN_M = 0.15
SEEN_FREE_MARGIN_PER_M2 = 0.015


class SeenSurfaces:
    """Surfaces (not the floor) the depth frames of an episode showed, in the height bins
    (``SEEN_BIN_M``) of the cells of a horizontal grid of ``SEEN_CELL_M`` (local ENU, the estimate's
    frame): per cell bin, how many frames showed a surface in it, how many saw through it, and the
    lowest height seen in it."""

    def __init__(self) -> None:
        # per cell bin, sorted by its key (_bin_keys): frames that showed a surface in it, frames
        # that saw through it, the lowest height seen in it (m)
        self._keys = np.zeros(0, dtype=np.int64)
        self._shown = np.zeros(0, dtype=np.int64)
        self._through = np.zeros(0, dtype=np.int64)
        self._low_m = np.zeros(0, dtype=np.float64)

    def _surface(self) -> np.ndarray:
        """[bins] whether each cell bin is a surface: shown by SEEN_MIN_FRAMES frames, seen through
        by no more frames than showed it."""
        return (self._shown >= SEEN_MIN_FRAMES) & (self._through <= self._shown)

    def __len__(self) -> int:
        """How many cells hold a surface."""
        return len(np.unique(self._keys[self._surface()] >> 8))

    def add_frame(self, depth_m: np.ndarray, pos_enu_m: np.ndarray, quat_enu_flu: np.ndarray, floor_z_m: float) -> int:
        """Add the surfaces frame ``depth_m`` shows from the camera at ``pos_enu_m`` with attitude
        ``quat_enu_flu`` (the camera at the body origin, looking along body +x: the contract's
        mount), the floor at height ``floor_z_m``, and the free space it sees through; returns how
        many points were surfaces."""
        origin = np.asarray(pos_enu_m, dtype=np.float64)
        quat = np.asarray(quat_enu_flu, dtype=np.float64)
        points = depth_points_flu(depth_m, SEEN_SAMPLE_COLS, SEEN_SAMPLE_ROWS, SEEN_MAX_DEPTH_M)
        world = origin + quat_rotate(quat, points)
        band_m = SEEN_FLOOR_BAND_M + SEEN_FLOOR_BAND_PER_M * np.linalg.norm(points, axis=1)
        world = world[world[:, 2] > floor_z_m + band_m]
        shown, inverse = np.unique(_bin_keys(world), return_inverse=True)
        lowest_m = np.full(len(shown), np.inf)
        np.minimum.at(lowest_m, inverse.reshape(-1), world[:, 2])
        # The bins already holding a surface that this frame's rays pass, but for those next to one
        # it showed (a ray that grazes a wall passes the wall's cells on its way to its hit).
        passed = self._indices(_bin_keys(origin + _free_points_enu(depth_m, quat)))
        beside = self._indices((shown[:, None] + _NEIGHBOUR_KEY_OFFSETS[None, :]).reshape(-1))
        self._through[np.setdiff1d(passed, beside)] += 1
        known = self._indices(shown, unique=False)
        new = known < 0
        self._shown[known[~new]] += 1
        self._low_m[known[~new]] = np.minimum(self._low_m[known[~new]], lowest_m[~new])
        at = np.searchsorted(self._keys, shown[new])
        self._keys = np.insert(self._keys, at, shown[new])
        self._shown = np.insert(self._shown, at, 1)
        self._through = np.insert(self._through, at, 0)
        self._low_m = np.insert(self._low_m, at, lowest_m[new])
        return len(world)

    def _indices(self, keys: np.ndarray, unique: bool = True) -> np.ndarray:
        """The indices of the held cell bins among ``keys``: each once (``unique``), else one per
        key, -1 where a key is not held."""
        at = np.minimum(np.searchsorted(self._keys, keys), max(len(self._keys) - 1, 0))
        held = (self._keys[at] == keys) if len(self._keys) else np.zeros(len(keys), dtype=bool)
        return np.unique(at[held]) if unique else np.where(held, at, -1)

    def cells_xy_m(self, below_z_m: float, above_z_m: float | None = None) -> np.ndarray:
        """(K, 2) the centres of the cells with a surface seen below height ``below_z_m`` (with
        ``above_z_m``: between the two heights, to a bin)."""
        surface = self._surface()
        if above_z_m is None:
            surface &= self._low_m < below_z_m
        else:
            first, last = (int(b) for b in _height_bin(np.array([above_z_m, below_z_m])))
            surface &= ((self._keys & 0xFF) >= first) & ((self._keys & 0xFF) <= last)
        return (_cells_ij(np.unique(self._keys[surface] >> 8 << 8)).astype(np.float64) + 0.5) * SEEN_CELL_M

    def free_ahead_m(self, from_xy_m: np.ndarray, heading_enu_rad: float, half_width_m: float, below_z_m: float,
                     above_z_m: float, max_m: float) -> float:  # fmt: skip
        """How far (m, horizontally) from ``from_xy_m`` along ``heading_enu_rad`` (local ENU, from
        +x toward +y) a corridor ``half_width_m`` either side runs before the centre of a cell with
        a surface seen between the two heights; ``max_m`` where none is nearer."""
        offsets = self.cells_xy_m(below_z_m, above_z_m) - np.asarray(from_xy_m, dtype=np.float64)[:2]
        along = offsets @ np.array([math.cos(heading_enu_rad), math.sin(heading_enu_rad)])
        across = offsets @ np.array([-math.sin(heading_enu_rad), math.cos(heading_enu_rad)])
        ahead = along[(along > 0.0) & (np.abs(across) <= half_width_m)]
        return float(min(ahead.min(initial=max_m), max_m))

    def clearance_m(self, points_xy_m: np.ndarray, below_z_m: float, above_z_m: float | None = None) -> np.ndarray:
        """[N] horizontal distance from each point (N, 2) to the nearest of :meth:`cells_xy_m`;
        inf where there is none."""
        return nearest_m(points_xy_m, self.cells_xy_m(below_z_m, above_z_m))


def _height_bin(z_m: np.ndarray) -> np.ndarray:
    """The height bin of each height (m, local ENU), clamped to the bins kept."""
    return np.clip(np.floor(np.asarray(z_m) / SEEN_BIN_M).astype(np.int64) + _BIN_OFFSET, 0, _BINS - 1)


_KEY_BITS = 24  # per cell index (cells within +-838 km of the origin); the height bin in the low byte


def _bin_keys(world_enu_m: np.ndarray) -> np.ndarray:
    """[N] int64 key of the cell bin of each point (N, 3): (cell i, cell j, height bin) packed."""
    cells = np.floor(world_enu_m[:, :2] / SEEN_CELL_M).astype(np.int64) + (1 << (_KEY_BITS - 1))
    return (cells[:, 0] << (_KEY_BITS + 8)) | (cells[:, 1] << 8) | _height_bin(world_enu_m[:, 2])


def _cells_ij(keys: np.ndarray) -> np.ndarray:
    """(N, 2) the cell indices (i, j) of each key of :func:`_bin_keys`."""
    half = 1 << (_KEY_BITS - 1)
    return np.stack([(keys >> (_KEY_BITS + 8)) - half, ((keys >> 8) & ((1 << _KEY_BITS) - 1)) - half], axis=1).reshape(-1, 2)


# The key offsets of a cell bin's 26 neighbours and itself (cells +-1 in i and j, bins +-1).
_NEIGHBOUR_KEY_OFFSETS = np.array([(di << (_KEY_BITS + 8)) + (dj << 8) + db for di in (-1, 0, 1) for dj in (-1, 0, 1) for db in (-1, 0, 1)],
                                  dtype=np.int64)  # fmt: skip


def _free_points_enu(depth_m: np.ndarray, quat_enu_flu: np.ndarray) -> np.ndarray:
    """(M, 3) points (world-ENU offsets from the camera, m) every ``SEEN_FREE_STEP_M`` along the
    rays of the sampled pixels (``SEEN_SAMPLE_COLS`` x ``SEEN_SAMPLE_ROWS``), from ``SEEN_FREE_START_M``
    to short of what each hit by the margin (at most ``SEEN_MAX_DEPTH_M`` out)."""
    hits = quat_rotate(quat_enu_flu, depth_points_flu(depth_m, SEEN_SAMPLE_COLS, SEEN_SAMPLE_ROWS, np.inf))
    range_m = np.linalg.norm(hits, axis=1)
    clear_m = np.minimum(range_m - SEEN_FREE_MARGIN_M - SEEN_FREE_MARGIN_PER_M2 * range_m**2, SEEN_MAX_DEPTH_M)
    keep = clear_m > SEEN_FREE_START_M
    units, clear_m = hits[keep] / range_m[keep, None], clear_m[keep]
    along_m = np.arange(SEEN_FREE_START_M, SEEN_MAX_DEPTH_M + 1e-9, SEEN_FREE_STEP_M)
    ray, step = np.nonzero(along_m[None, :] <= clear_m[:, None])
    return units[ray] * along_m[step, None]


def nearest_m(points_xy_m: np.ndarray, cells_xy_m: np.ndarray) -> np.ndarray:
    """[N] horizontal distance from each point (N, 2) to the nearest of ``cells_xy_m`` (K, 2); inf if K = 0."""
    points = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    if len(cells_xy_m) == 0:
        return np.full(len(points), np.inf)
    return np.sqrt(((points[:, None, :] - cells_xy_m[None, :, :]) ** 2).sum(axis=2).min(axis=1))
