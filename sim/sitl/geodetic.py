"""Where the simulated room is on Earth: a fixed geodetic home and a flat-earth map from the
local ENU offset (metres from home) to latitude / longitude / altitude, as PX4's local
projection does over a few hundred metres."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

EARTH_RADIUS_M = 6_371_000.0


@dataclass(frozen=True)
class GeodeticHome:
    """Home in WGS-84 degrees and metres above mean sea level.  Default: PX4 SITL's home
    (Zurich), so logs look familiar next to real PX4 SITL runs."""

    lat_deg: float = 47.397742
    lon_deg: float = 8.545594
    alt_amsl_m: float = 488.0

    def to_geodetic(self, offset_enu_m: np.ndarray) -> tuple[float, float, float]:
        """ENU offset from home (m) -> (lat_deg, lon_deg, alt_amsl_m)."""
        east, north, up = (float(v) for v in offset_enu_m)
        lat = self.lat_deg + math.degrees(north / EARTH_RADIUS_M)
        lon = self.lon_deg + math.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))))
        return lat, lon, self.alt_amsl_m + up

    def to_enu(self, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> np.ndarray:
        """Inverse of :meth:`to_geodetic`: ENU offset from home (m)."""
        north = math.radians(lat_deg - self.lat_deg) * EARTH_RADIUS_M
        east = math.radians(lon_deg - self.lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))
        return np.array([east, north, alt_amsl_m - self.alt_amsl_m])
