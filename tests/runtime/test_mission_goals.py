"""Mission items to goals relative to home, and the geofence check made on the ground."""

import pytest

from runtime.config import WatchdogConfig
from runtime.programs.mission_goals import (
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_FRAME_LOCAL_ENU,
    MissionError,
    RawMissionItem,
    check_geofence,
    enu_from_geodetic,
    mission_waypoints,
)

MAV_CMD_NAV_TAKEOFF = 22


def test_waypoints_in_order_as_goals_relative_to_home_and_other_items_skipped():
    lat0, lon0 = 47.397742, 8.545594
    east, north = enu_from_geodetic(lat0 + 1e-4, lon0 + 2e-4, lat0, lon0)
    assert 11.0 < north < 11.2 and 15.0 < east < 15.2  # 1e-4 deg of latitude = 11.1 m
    items = [
        RawMissionItem(2, MAV_FRAME_LOCAL_ENU, MAV_CMD_NAV_WAYPOINT, 1.0, 2.0, 3.0),
        RawMissionItem(0, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, MAV_CMD_NAV_TAKEOFF, 0, 0, 2.0),
        RawMissionItem(1, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, MAV_CMD_NAV_WAYPOINT, round((lat0 + 1e-4) * 1e7),
                       round((lon0 + 2e-4) * 1e7), 2.5),
    ]  # fmt: skip
    waypoints = mission_waypoints(items, lat0, lon0)
    assert [w.seq for w in waypoints] == [1, 2]
    assert waypoints[0].goal_rel_home_enu_m == pytest.approx((east, north, 2.5), abs=0.02)
    assert waypoints[1].goal_rel_home_enu_m == (1.0, 2.0, 3.0)


def test_missions_that_cannot_be_flown_are_refused_with_the_fix():
    with pytest.raises(MissionError, match="no mission: upload a plan"):
        mission_waypoints([], 0.0, 0.0)
    with pytest.raises(MissionError, match="hold no waypoint"):
        mission_waypoints([RawMissionItem(0, MAV_FRAME_LOCAL_ENU, MAV_CMD_NAV_TAKEOFF, 0, 0, 2)], 0.0, 0.0)
    with pytest.raises(MissionError, match="mission item 0: waypoint frame 0 is not supported"):
        mission_waypoints([RawMissionItem(0, 0, MAV_CMD_NAV_WAYPOINT, 0, 0, 2)], 0.0, 0.0)
    low = mission_waypoints([RawMissionItem(0, MAV_FRAME_LOCAL_ENU, MAV_CMD_NAV_WAYPOINT, 1.0, 0.0, 9.5)], 0.0, 0.0)
    with pytest.raises(MissionError, match=r"mission item 0 is at 9\.5 m above home, outside the altitude band 0\.2\.\.8 m"):
        check_geofence(low, WatchdogConfig())
