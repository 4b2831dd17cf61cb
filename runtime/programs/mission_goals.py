"""Goals from the ground station: the waypoints of the mission uploaded to the autopilot (a
QGroundControl plan) as episode goals relative to home, checked against the watchdog's geofence
on the ground.  Pure data in, data out: the MAVSDK download belongs to ``runtime.vehicle`` (the
only MAVSDK module) and hands over each item's MISSION_ITEM_INT fields.

Frames: a waypoint in MAV_FRAME_GLOBAL_RELATIVE_ALT(_INT) (QGroundControl's default) is latitude /
longitude (degE7 in the _INT frames) and altitude above home; it becomes an ENU offset from home by
the local flat-earth projection PX4 uses over a few hundred metres.  MAV_FRAME_LOCAL_ENU takes
x east, y north, z up from home directly.  Items other than NAV_WAYPOINT (take-off, land, RTL,
speed changes) are not goals and are skipped, each with a log line.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..config import WatchdogConfig

log = logging.getLogger(__name__)

EARTH_RADIUS_M = 6_371_000.0
MAV_CMD_NAV_WAYPOINT = 16
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3
MAV_FRAME_LOCAL_ENU = 4
MAV_FRAME_GLOBAL_RELATIVE_ALT_INT = 6
INT_FRAMES = (MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,)


class MissionError(ValueError):
    """The mission cannot be flown; one line naming the item, the cause and the fix."""


@dataclass(frozen=True)
class RawMissionItem:
    """One MISSION_ITEM_INT, as MAVSDK's mission_raw hands it over (x, y degE7 in the _INT frames)."""

    seq: int
    frame: int
    command: int
    x: float
    y: float
    z: float


@dataclass(frozen=True)
class MissionWaypoint:
    """One goal: the mission item it came from and the goal relative to home (ENU, m)."""

    seq: int
    goal_rel_home_enu_m: tuple[float, float, float]


def enu_from_geodetic(lat_deg: float, lon_deg: float, home_lat_deg: float, home_lon_deg: float) -> tuple[float, float]:
    """(east, north) metres from home by the local flat-earth projection."""
    north = math.radians(lat_deg - home_lat_deg) * EARTH_RADIUS_M
    east = math.radians(lon_deg - home_lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg))
    return east, north


def mission_waypoints(items: Sequence[RawMissionItem], home_lat_deg: float, home_lon_deg: float) -> list[MissionWaypoint]:
    """The NAV_WAYPOINTs of ``items`` in order, as goals relative to home; :class:`MissionError`
    for an empty mission, a waypoint in a frame we cannot place, or no waypoint at all."""
    if not items:
        raise MissionError("the autopilot has no mission: upload a plan with waypoints from the ground station "
                           "(QGroundControl: Plan, Upload), or set mission.goal_source = \"config\"")  # fmt: skip
    waypoints = []
    for item in sorted(items, key=lambda i: i.seq):
        if item.command != MAV_CMD_NAV_WAYPOINT:
            log.info("mission item %d: command %d is not a waypoint, skipped", item.seq, item.command)
            continue
        if item.frame in (MAV_FRAME_GLOBAL_RELATIVE_ALT, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT):
            scale = 1e-7 if item.frame in INT_FRAMES else 1.0
            east, north = enu_from_geodetic(item.x * scale, item.y * scale, home_lat_deg, home_lon_deg)
            goal = (east, north, float(item.z))
        elif item.frame == MAV_FRAME_LOCAL_ENU:
            goal = (float(item.x), float(item.y), float(item.z))
        else:
            raise MissionError(f"mission item {item.seq}: waypoint frame {item.frame} is not supported: plan it with "
                               "altitude relative to home (MAV_FRAME_GLOBAL_RELATIVE_ALT, QGroundControl's default)")  # fmt: skip
        if not all(math.isfinite(v) for v in goal):
            raise MissionError(f"mission item {item.seq}: waypoint position {goal} is not a number: re-plan it")
        waypoints.append(MissionWaypoint(item.seq, tuple(round(v, 3) for v in goal)))
    if not waypoints:
        raise MissionError(f"the mission's {len(items)} item(s) hold no waypoint (NAV_WAYPOINT): add waypoints to the plan")
    return waypoints


def check_geofence(waypoints: Sequence[MissionWaypoint], fence: WatchdogConfig) -> None:
    """Refuse, before arming, a waypoint the watchdog's geofence would trip on: farther from home
    than ``geofence_radius_m`` horizontally, or outside the ``altitude_min_m``..``altitude_max_m``
    band above home.  :class:`MissionError` names the first such waypoint, by how much, and the fix."""
    for wp in waypoints:
        east, north, up = wp.goal_rel_home_enu_m
        distance_m = float(np.hypot(east, north))
        if distance_m > fence.geofence_radius_m:
            raise MissionError(f"mission item {wp.seq} is {distance_m:.1f} m from home, outside the geofence "
                               f"(watchdog.geofence_radius_m = {fence.geofence_radius_m:g} m): move the waypoint in "
                               "or widen the fence")  # fmt: skip
        if not fence.altitude_min_m <= up <= fence.altitude_max_m:
            raise MissionError(f"mission item {wp.seq} is at {up:.1f} m above home, outside the altitude band "
                               f"{fence.altitude_min_m:g}..{fence.altitude_max_m:g} m (watchdog.altitude_min_m/"
                               "altitude_max_m): change its altitude or the band")  # fmt: skip
