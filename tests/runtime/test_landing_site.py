"""Where the dry run lands (runtime.camera.surfaces, runtime.watchdog.choose_landing_site): the
path flown is free at the height flown, not below it (on PX4 SIH a flight that passed over a post
retreated onto it and touched it while landing), and the way back passes what the path passed (two
retreats at level 15 touched a thin post or a slab's edge beside the path).  The contract's camera
against the sim's, the surfaces seen in rendered frames, the choice of the site, then the flight
loop landing clear of the wall behind its goal and of a post beside its path."""

import asyncio
import math
import time

import numpy as np
import pytest
import torch

from export.goal_seeker import export_goal_seeker
from runtime.camera import Frame
from runtime.config import ConfigError, MissionConfig
from runtime.contract import CONTROL_PERIOD_S
from runtime.contract.camera import depth_points_flu, focal_length_px
from runtime.contract.constants import CAMERA_HFOV_RAD
from runtime.contract.frames import quat_from_euler
from runtime.camera.surfaces import SEEN_CELL_M, SEEN_FLOOR_BAND_M, SEEN_MAX_DEPTH_M, SEEN_MIN_FRAMES, SeenSurfaces, _cells_ij
from runtime.watchdog import (
    APPROACH_DECEL_M_S2,
    APPROACH_DELAY_S,
    APPROACH_GOAL_M,
    APPROACH_MARGIN_M,
    APPROACH_MIN_M_S,
    LANDING_AWAY_MAX_M,
    approach_speed_cap_m_s,
    cap_approach,
    choose_landing_site,
    landing_way,
)
from sim.camera import CameraModel
from sim.render import render
from sim.sensor import StereoDepthSensor
from sim.world import WorldBatch
from tests.runtime.test_flight_loop import START
from tests.runtime.test_retreat import LandingVehicle, _fly_and_retreat

POST_XY_M = np.array([2.8, 1.0])  # under the goal seeker's path
POST_TOP_M = 1.0  # 0.5 m below the height it flies at (START)
TALL_M = 2.5  # a post that reaches above the flight height
CAMERA = CameraModel()


def _room(*posts: tuple[float, float, float]) -> WorldBatch:
    """An 8 x 5 x 3 m room with 0.1 m posts from the floor, each (x, y, top) in metres."""
    boxes = [(x, y, top / 2.0) for x, y, top in posts] or [(0.0, 0.0, 0.0)]
    return WorldBatch(
        room_size_m=torch.tensor([[8.0, 5.0, 3.0]]),
        box_center_m=torch.tensor([boxes], dtype=torch.float32),
        box_half_extent_m=torch.tensor([[[0.05, 0.05, z] for _, _, z in boxes]]),
        box_yaw_rad=torch.zeros(1, len(boxes)),
        box_valid=torch.tensor([[bool(posts)] * len(boxes)]),
        start_m=torch.tensor([START.tolist()], dtype=torch.float32),
        goal_m=torch.tensor([[5.0, 1.0, 1.5]]),
        texture_seed=torch.tensor([7]),
    )


LOW_POST = (*POST_XY_M, POST_TOP_M)


def _depth(world: WorldBatch, pos_enu_m: np.ndarray, yaw_rad: float) -> np.ndarray:
    q = quat_from_euler(0.0, 0.0, yaw_rad)
    out = render(world, torch.tensor(np.array([pos_enu_m]), dtype=torch.float32), torch.tensor(np.array([q]), dtype=torch.float32), CAMERA)
    return out.depth_m[0].numpy()


def test_the_contracts_camera_is_the_sims():
    assert focal_length_px(CAMERA.width_px) == CAMERA.fx_px
    # A wall 2 m ahead: every point 2 m forward; the outermost columns at the field of view's edge.
    depth = np.full((CAMERA.height_px, CAMERA.width_px), 2.0, np.float32)
    points = depth_points_flu(depth, CAMERA.width_px, CAMERA.height_px, SEEN_MAX_DEPTH_M)
    assert points.shape == (CAMERA.width_px * CAMERA.height_px, 3) and np.all(points[:, 0] == 2.0)
    assert 2 * math.atan(points[:, 1].max() / 2.0) == pytest.approx(CAMERA_HFOV_RAD, abs=2.0 / CAMERA.fx_px)
    assert points[:, 1].max() == pytest.approx(-points[:, 1].min()) and points[:, 2].max() == pytest.approx(-points[:, 2].min())
    # Invalid depth (0, NaN, inf) and depth beyond the range asked give no point.
    depth[0, :], depth[1, :], depth[2, :], depth[3, :] = 0.0, np.nan, np.inf, SEEN_MAX_DEPTH_M + 1.0
    assert len(depth_points_flu(depth, CAMERA.width_px, CAMERA.height_px, SEEN_MAX_DEPTH_M)) == CAMERA.width_px * (CAMERA.height_px - 4)


def test_rendered_frames_show_the_post_and_the_walls_not_the_floor():
    seen = SeenSurfaces()
    for x in np.arange(0.5, 1.51, 0.1):  # flying +x at 1.5 m toward the post, 11 frames
        assert seen.add_frame(_depth(_room(LOW_POST), np.array([x, 1.0, 1.5]), 0.0), np.array([x, 1.0, 1.5]), quat_from_euler(0.0, 0.0, 0.0), 0.0) > 0
    # The post's cells hold it, the lowest point seen on it near its foot's visible part (above the floor band)
    post_clearance = seen.clearance_m(POST_XY_M[None], POST_TOP_M + 0.1)
    assert post_clearance[0] <= 0.1, post_clearance
    # Nothing between the camera and the post; the floor (seen 2-6 m ahead) is not a surface.
    assert seen.clearance_m(np.array([[1.5, 1.0]]), 3.0)[0] >= 0.9
    assert seen._low_m.min() > SEEN_FLOOR_BAND_M
    # ... and the heights it spans: below a flight at 1.5 m, not beside it.
    assert seen.clearance_m(POST_XY_M[None], 1.8, 1.2)[0] > 0.5
    # The far wall (x = 8 m) lies beyond SEEN_MAX_DEPTH_M from x <= 1.5: unseen; the side walls are seen.
    assert seen.clearance_m(np.array([[7.9, 2.5]]), 3.0)[0] > 0.5
    assert seen.clearance_m(np.array([[3.0, 0.05]]), 3.0)[0] <= SEEN_CELL_M
    # A depth frame with nothing valid adds nothing.
    assert seen.add_frame(np.zeros((120, 212), np.float32), np.array([1.0, 1.0, 1.5]), quat_from_euler(0.0, 0.0, 0.0), 0.0) == 0


def test_a_surface_counts_once_frames_show_it_and_the_floor_never_through_an_estimate_off_by_degrees():
    pose = np.array([1.0, 1.0, 1.5])
    depth = _depth(_room(LOW_POST), pose, 0.0)
    seen = SeenSurfaces()
    for n in range(1, SEEN_MIN_FRAMES + 1):
        seen.add_frame(depth, pose, quat_from_euler(0.0, 0.0, 0.0), 0.0)
        assert (seen.clearance_m(POST_XY_M[None], 3.0)[0] <= 0.1) == (n >= SEEN_MIN_FRAMES), n
    # The floor, 1.5-5 m ahead, seen through an estimate 0.15 m low and pitched or rolled 3 degrees
    # off (PX4 SIH's floor points lay within 0.2 m + 0.1 x range of it): not a surface.
    room = _room()
    seen = SeenSurfaces()
    for roll, pitch in ((0.0, 0.05), (0.0, -0.05), (0.05, 0.0), (-0.05, 0.0)):
        for _ in range(SEEN_MIN_FRAMES):
            seen.add_frame(_depth(room, pose, 0.0), pose - [0.0, 0.0, 0.15], quat_from_euler(roll, pitch, 0.0), 0.0)
    floor_ahead = np.array([[x, 1.0] for x in np.arange(2.5, 6.0, 0.1)])
    assert np.all(seen.clearance_m(floor_ahead, 1.8) > 0.5)  # (the ceiling, at 3 m, is a surface: above it)


def test_what_later_frames_see_through_stops_being_a_surface_and_what_they_show_stays():
    pose, level = np.array([1.0, 1.0, 1.5]), quat_from_euler(0.0, 0.0, 0.0)
    room = _room(LOW_POST)
    true_depth = _depth(room, pose, 0.0)
    # A stereo mismatch: a patch 2.5 m ahead at the flight height, where the room is free, in 4 frames.
    phantom = true_depth.copy()
    rows, cols = phantom.shape
    phantom[rows // 2 - 6 : rows // 2 + 6, cols // 2 - 8 : cols // 2 + 8] = 2.5
    seen = SeenSurfaces()
    for _ in range(4):
        seen.add_frame(phantom, pose, level, 0.0)
    ahead = np.array([[3.5, 1.0]])
    assert seen.clearance_m(ahead, 1.8, 1.2)[0] <= SEEN_CELL_M
    # Frames that look through it to the wall beyond: once more of them than showed it, it is gone.
    for n in range(1, 6):
        seen.add_frame(true_depth, pose, level, 0.0)
        assert (seen.clearance_m(ahead, 1.8, 1.2)[0] > 0.5) == (n > 4), n  # (the side wall: 0.95 m off)
    # The post below the flight height, the walls beside it, seen in every frame: still there.
    assert seen.clearance_m(POST_XY_M[None], POST_TOP_M + 0.1)[0] <= 0.1
    # the rays that graze the side walls on their way do not clear them: every bin of theirs held is a surface
    y_m = (_cells_ij(seen._keys)[:, 1] + 0.5) * SEEN_CELL_M
    walls = (y_m < 0.2) | (y_m > 4.8)
    assert walls.sum() > 100 and np.all(seen._through[walls] == 0)
    # A wall seen through an estimate 0.4 m behind the truth (as PX4's drifted), then through the
    # true one: the copy 0.4 m in front of the wall is seen through and goes; the wall stays.
    wall_room = _room()
    seen = SeenSurfaces()
    near_wall = np.array([5.0, 2.5, 1.5])  # 3 m from the wall at x = 8 m
    for _ in range(5):
        seen.add_frame(_depth(wall_room, near_wall, 0.0), near_wall - [0.4, 0.0, 0.0], level, 0.0)
    assert seen.clearance_m(np.array([[7.6, 2.5]]), 1.8, 1.2)[0] <= SEEN_CELL_M
    for _ in range(6):
        seen.add_frame(_depth(wall_room, near_wall, 0.0), near_wall, level, 0.0)
    at_flight_height = seen.cells_xy_m(1.8, 1.2)
    facing = at_flight_height[np.abs(at_flight_height[:, 1] - 2.5) < 0.5]
    assert facing[:, 0].max() >= 7.9 and facing[:, 0].min() >= 7.9 - 2 * SEEN_CELL_M, facing[:, 0].min()


def test_a_post_seen_by_the_stereo_camera_stays_a_surface_as_the_rays_beside_it_clear_the_room():
    """The simulated D455 (sim.sensor) flying toward a thin post: the rays that pass beside it to
    the wall clear the cells around it, not the post."""
    room = _room((3.0, 1.0, TALL_M))
    sensor = StereoDepthSensor(threads=1)
    generator = torch.Generator().manual_seed(0)
    seen = SeenSurfaces()
    for x in np.arange(0.5, 2.01, 0.1):
        pose = np.array([x, 1.0, 1.5])
        q = quat_from_euler(0.0, 0.0, 0.0)
        frame = sensor.measure(room, torch.tensor(pose[None], dtype=torch.float32), torch.tensor(q[None], dtype=torch.float32), generator)
        seen.add_frame(frame.depth_m[0].numpy(), pose, q, 0.0)
    assert seen.clearance_m(np.array([[3.0, 1.0]]), 1.8, 1.2)[0] <= SEEN_CELL_M
    assert seen.clearance_m(np.array([[2.2, 1.0]]), 1.8, 1.2)[0] >= 0.6  # and nothing in front of it


def _seen_along(path: np.ndarray, room: WorldBatch) -> SeenSurfaces:
    seen = SeenSurfaces()
    for p in path:
        seen.add_frame(_depth(room, p, 0.0), p, quat_from_euler(0.0, 0.0, 0.0), 0.0)
    return seen


def _site(room: WorldBatch, end_x_m: float, overshoot_m: float = 0.4, back_m: float = 1.5, way_clearance_m: float = 0.5):
    """The site chosen after flying +x at 1.5 m along y = 1 m (2 m/s, 15 Hz) from x = 1 m to
    ``end_x_m``, stopped ``overshoot_m`` beyond, preferring ``back_m`` back, 0.8 m clear:
    (the site, the way back, its point)."""
    path = np.array([[x, 1.0, 1.5] for x in np.arange(1.0, end_x_m + 1e-9, 0.13)])
    way = landing_way(path, path[-1] + [overshoot_m, 0.0, 0.0], 5.0)
    site = choose_landing_site(way, _seen_along(path, room), back_m, 0.8, way_clearance_m)
    return site, way, site.path_enu_m[-1]


def test_the_site_is_the_preferred_one_unless_a_surface_seen_below_is_too_near():
    site, way, point = _site(_room(), 4.3)
    assert site.clear and site.travel_m == pytest.approx(1.9) and site.clearance_m > 0.8 and site.way_clearance_m > 0.8
    np.testing.assert_allclose(point, [4.3 - 1.5, 1.0, 1.5], atol=0.07)
    # The post flown over lies 1.5 m back: the nearest point to it that is 0.8 m clear.
    site, way, point = _site(_room(LOW_POST), 4.3)
    assert site.clear and site.clearance_m >= 0.8 and abs(point[0] - POST_XY_M[0]) >= 0.8 - SEEN_CELL_M
    assert abs(site.travel_m - 1.9) <= 0.9  # 0.8 m either side of the post, and a cell
    # Surfaces seen only above the vehicle (the ceiling at 3 m) are not in the way down.
    seen = _seen_along(way[1:][::-1], _room(LOW_POST))
    assert seen.clearance_m(np.array([[4.8, 1.0]]), 3.5)[0] <= 2 * SEEN_CELL_M and seen.clearance_m(np.array([[4.8, 1.0]]), 1.8)[0] > 0.8


def test_preferring_where_it_stopped_the_site_keeps_clear_of_the_wall_behind_the_goal():
    site, _, point = _site(_room(), 6.9, back_m=0.0)  # stopped 0.7 m from the far wall (x = 8)
    assert site.clear and 0.0 < site.travel_m <= 0.4 and site.clearance_m >= 0.8
    assert 8.0 - point[0] >= 0.8 - SEEN_CELL_M  # the wall's cells hold what was seen up to x = 8 m


def test_the_way_back_keeps_its_clearance_from_a_post_beside_the_path():
    # A tall post 0.6 m beside the path, 0.2 m before its end: passed 0.6 m off, taken.
    site, _, point = _site(_room((6.7, 1.6, TALL_M)), 6.9)
    assert site.clear and site.way_clearance_m >= 0.5 and point[0] == pytest.approx(6.9 - 1.5, abs=0.07)
    # 0.3 m beside it: the way past it is not taken; the clearest point before it, said not clear.
    site, _, point = _site(_room((6.7, 1.3, TALL_M)), 6.9)
    assert not site.clear and point[0] > 6.7 and site.way_clearance_m >= 0.5
    # (asked for less clearance on the way, it goes past the post)
    site, _, point = _site(_room((6.7, 1.3, TALL_M)), 6.9, way_clearance_m=0.2)
    assert site.clear and point[0] == pytest.approx(6.9 - 1.5, abs=0.07) and site.way_clearance_m < 0.5
    # A post of the same place 0.5 m below the flight height is flown over, not passed by.
    site, _, point = _site(_room((6.7, 1.3, POST_TOP_M)), 6.9)
    assert site.clear and site.way_clearance_m > 0.5


def test_a_surface_already_near_where_it_stopped_does_not_hold_it_there():
    # The brake ended 0.4 m from a post (beside the path's end): the way back passes it no nearer.
    site, _, point = _site(_room((7.1, 1.35, TALL_M)), 6.9)
    assert site.clear and point[0] == pytest.approx(6.9 - 1.5, abs=0.07) and site.way_clearance_m < 0.5


def test_stopped_at_the_wall_with_the_way_back_past_a_post_it_steps_straight_away():
    # Stopped 0.2 m from the far wall (x = 8), a tall post 0.3 m beside the path's end: no point of
    # the way back is both reached and 0.8 m clear (PX4 SIH with the stereo camera landed such
    # flights where they stopped and drifted into the wall on the way down).
    room = _room((7.0, 2.8, TALL_M))
    path = np.array([[x, 2.5, 1.5] for x in np.arange(1.0, 7.45, 0.13)])
    stop = np.array([7.8, 2.5, 1.5])
    way = landing_way(path, stop, 5.0)
    seen = _seen_along(path, room)
    site = choose_landing_site(way, seen, 1.5, 0.8, 0.5)
    assert site.clear and site.away_heading_enu_rad is not None, site
    # a straight step from where it stopped, no longer than it needs, to a point clear of the wall and the post
    step = site.path_enu_m
    assert len(step) == 2 and np.allclose(step[0], stop) and np.linalg.norm(step[1] - stop) == pytest.approx(site.travel_m, abs=1e-6)
    assert 0.6 <= site.travel_m <= LANDING_AWAY_MAX_M and step[1][2] == 1.5
    assert 8.0 - step[1][0] >= 0.8 - SEEN_CELL_M and np.hypot(*(step[1][:2] - [7.0, 2.8])) >= 0.8 - SEEN_CELL_M
    # on its way it keeps the clearance asked from the post, which the way back did not
    along = step[0] + np.linspace(0.0, 1.0, 20)[:, None] * (step[1] - step[0])
    assert np.hypot(along[:, 0] - 7.0, along[:, 1] - 2.8).min() >= 0.5 - SEEN_CELL_M
    assert site.record()["away_heading_enu_rad"] == site.away_heading_enu_rad and "path_enu_m" not in site.record()
    # Without the post the way back is taken, as before.
    site = choose_landing_site(way, _seen_along(path, _room()), 1.5, 0.8, 0.5)
    assert site.clear and site.away_heading_enu_rad is None and site.path_enu_m[-1][0] == pytest.approx(7.45 - 1.5, abs=0.15)


def test_a_camera_that_showed_nothing_lands_land_retreat_m_back_unchecked():
    path = np.array([[x, 1.0, 1.5] for x in np.arange(1.0, 4.31, 0.13)])
    way = landing_way(path, path[-1] + [0.4, 0.0, 0.0], 5.0)
    site = choose_landing_site(way, SeenSurfaces(), 1.5, 0.8, 0.5)
    assert site.record() == {"travel_m": pytest.approx(1.9), "clearance_m": None, "way_clearance_m": None, "clear": True, "surface_cells": 0,
                             "away_heading_enu_rad": None}
    assert choose_landing_site(way, SeenSurfaces(), 0.0, 0.8, 0.5).travel_m == 0.0  # land_retreat_m = 0: where it stopped


def test_the_site_search_and_clearance_are_mission_keys_with_bounds():
    assert MissionConfig().land_site_search_m == 5.0 and MissionConfig().land_clearance_m == 1.0
    assert MissionConfig().land_way_clearance_m == 0.6
    with pytest.raises(ConfigError, match="mission.land_way_clearance_m"):
        MissionConfig(land_way_clearance_m=0.0)
    with pytest.raises(ConfigError, match="mission.land_site_search_m"):
        MissionConfig(land_site_search_m=-1.0)
    with pytest.raises(ConfigError, match="mission.land_clearance_m"):
        MissionConfig(land_clearance_m=0.1)


def test_the_approach_to_the_last_goal_is_no_faster_than_the_brake_stops_in_before_what_was_seen():
    # The cap's law: the brake's delay and deceleration use up the free distance less the margin.
    for free_m in (1.5, 2.0, 3.0, 4.0):
        v = approach_speed_cap_m_s(free_m)
        assert v * APPROACH_DELAY_S + v**2 / (2.0 * APPROACH_DECEL_M_S2) == pytest.approx(free_m - APPROACH_MARGIN_M)
    assert approach_speed_cap_m_s(APPROACH_MARGIN_M) == approach_speed_cap_m_s(0.0) == APPROACH_MIN_M_S
    # Flying +x toward the far wall (x = 8 m) of a rendered room, the goal 0.5 m before it.
    room = _room()
    seen = _seen_along(np.array([[x, 2.5, 1.5] for x in np.arange(3.0, 5.01, 0.13)]), room)
    goal, at = np.array([7.5, 2.5, 1.5]), np.array([5.5, 2.5, 1.5])
    toward = np.array([2.0, 0.0, 0.0, 0.1])  # forward 2 m/s (yaw 0: +x), a yaw rate
    capped, cap = cap_approach(toward, at, 0.0, goal, seen)
    free_m = 8.0 - at[0]  # to the wall's cells, to a cell
    assert cap == pytest.approx(approach_speed_cap_m_s(free_m), abs=0.1) and cap < 2.0
    np.testing.assert_allclose(capped, [cap, 0.0, 0.0, 0.1])  # the yaw rate and the vertical speed kept
    # The same command with the vehicle yawed 90 degrees runs along the wall (+y, 2.5 m free): less capped.
    _, along = cap_approach(toward, at, math.pi / 2, goal, seen)
    assert along is None or along > cap
    # Farther than APPROACH_GOAL_M from the goal, or no surface seen: the policy's command.
    assert cap_approach(toward, goal - [APPROACH_GOAL_M + 0.1, 0.0, 0.0], 0.0, goal, seen)[1] is None
    assert cap_approach(toward, at, 0.0, goal, SeenSurfaces())[1] is None
    # Stopped already (no horizontal command): nothing to cap.
    assert cap_approach(np.array([0.0, 0.0, 0.5, 0.0]), at, 0.0, goal, seen)[1] is None
    assert MissionConfig().approach_cap is True
    with pytest.raises(ConfigError, match="mission.approach_cap"):
        MissionConfig(approach_cap="off")


class RenderingCamera:
    """15 Hz frames of ``world`` rendered from the vehicle's pose as it flies."""

    def __init__(self, world: WorldBatch, vehicle):
        self.world, self.vehicle = world, vehicle
        _depth(world, START, 0.0)  # the renderer's first call compiles it: not inside the flight

    async def start(self):
        pass

    async def frames(self):
        seq = 0
        while True:
            seq += 1
            depth = _depth(self.world, self.vehicle.pos.copy(), self.vehicle.yaw)
            yield Frame(time.monotonic_ns(), depth, np.full(depth.shape, 128, np.uint8), seq)
            await asyncio.sleep(CONTROL_PERIOD_S)

    async def close(self):
        pass


# The flights below ask for 0.8 m of clearance (mission.land_clearance_m), which the 1 m from the
# side wall of their path leaves, and 0.5 m on the way (past the post 0.6 m off).
SITE = {"land_site_search_m": 5.0, "land_clearance_m": 0.8, "land_way_clearance_m": 0.5}


@pytest.mark.flight
def test_the_dry_run_lands_clear_of_the_wall_and_of_a_post_beside_its_way_back(goal_seeker):
    goal = START + np.array([6.0, 0.0, 0.0])  # 1 m from the far wall (x = 8)
    post = (6.5, 1.6, TALL_M)  # 0.6 m beside the path, 0.5 m before the goal
    vehicle = LandingVehicle()
    result, landed, _ = asyncio.run(_fly_and_retreat(goal_seeker, vehicle, goal, 1.5, RenderingCamera(_room(post), vehicle),
                                                     land_in_offboard=True, **SITE))  # fmt: skip
    assert result.outcome == "success", result
    site, retreat, descent = result.brake["landing_site"], result.brake["retreat"], result.brake["descent"]
    assert site["clear"] and site["clearance_m"] >= 0.8 and site["way_clearance_m"] >= 0.5 and site["travel_m"] > 0.0, result.brake
    assert retreat["ended"] == "arrived" and descent["ended"] == "disarmed", result.brake
    # The retreat arrives within 0.15 m; the cells hold what was seen up to a cell's side off.
    assert 8.0 - landed[0] >= 0.8 - 0.15 - SEEN_CELL_M and np.hypot(landed[0] - post[0], landed[1] - post[1]) >= 0.8 - 0.15 - SEEN_CELL_M, landed
    # Over the low post 1.5 m back from its end: the site moves off it.
    vehicle = LandingVehicle()
    result, landed, _ = asyncio.run(_fly_and_retreat(goal_seeker, vehicle, START + np.array([4.0, 0.0, 0.0]), 1.5,
                                                     RenderingCamera(_room(LOW_POST), vehicle), land_in_offboard=True, **SITE))  # fmt: skip
    site = result.brake["landing_site"]
    assert site["clear"] and result.brake["descent"]["ended"] == "disarmed", result.brake
    assert np.linalg.norm(landed[:2] - POST_XY_M) >= 0.8 - 0.15 - SEEN_CELL_M, landed


class NearestToTheWall(LandingVehicle):
    """A landing vehicle that keeps the farthest +x it reached (the far wall is at x = 8 m), its
    fastest speed from ``from_x_m`` on, and the +x where the brake began there (the first command
    not forward: the goal reached); the runtime flies it along +x."""

    def __init__(self, from_x_m: float):
        super().__init__()
        self.from_x_m, self.max_x_m, self.speed_there_m_s = from_x_m, -math.inf, 0.0
        self.brake_from_x_m: float | None = None

    async def set_velocity_body(self, cmd) -> None:
        await super().set_velocity_body(cmd)
        if self.brake_from_x_m is None and self.pos[0] >= self.from_x_m and self.cmd_flu[0] <= 0.0:
            self.brake_from_x_m = float(self.pos[0])

    @property
    def overshoot_m(self) -> float:
        """How far the vehicle went on along +x after the brake began (m)."""
        assert self.brake_from_x_m is not None, f"every command past x = {self.from_x_m} m was forward: the brake never began"
        return self.max_x_m - self.brake_from_x_m

    def state(self):
        self.max_x_m = max(self.max_x_m, float(self.pos[0]))
        if self.pos[0] >= self.from_x_m:
            self.speed_there_m_s = max(self.speed_there_m_s, float(np.linalg.norm(self.vel_enu[:2])))
        return super().state()


@pytest.mark.flight
def test_the_approach_to_a_goal_near_the_wall_slows_so_that_the_brake_stops_short_of_it(tmp_path, monkeypatch):
    # A goal seeker that flies at the goal at 2 m/s to 0.5 m from it, as a policy may.
    monkeypatch.setattr("export.goal_seeker.CRUISE_SPEED_M_S", 2.0)
    monkeypatch.setattr("export.goal_seeker.SLOWDOWN_RADIUS_M", 0.5)
    goal_seeker = tmp_path / "fast-goal-seeker.onnx"
    export_goal_seeker(str(goal_seeker))
    goal = START + np.array([6.5, 0.0, 0.0])  # 0.5 m before the far wall
    vehicle = NearestToTheWall(goal[0] - 1.0)
    result, _, _ = asyncio.run(_fly_and_retreat(goal_seeker, vehicle, goal, 1.5, RenderingCamera(_room(), vehicle), land_in_offboard=True, **SITE))
    assert result.outcome == "success" and result.approach_cap["capped_steps"] > 0, result
    assert result.approach_cap["least_cap_m_s"] < 1.5, result.approach_cap
    capped_overshoot_m, capped_speed_m_s = vehicle.overshoot_m, vehicle.speed_there_m_s
    # The policy's command as it was (mission.approach_cap off): the brake carries the vehicle nearer the wall.
    vehicle = NearestToTheWall(goal[0] - 1.0)
    result, _, _ = asyncio.run(_fly_and_retreat(goal_seeker, vehicle, goal, 1.5, RenderingCamera(_room(), vehicle), land_in_offboard=True,
                                                approach_cap=False, **SITE))  # fmt: skip
    assert result.outcome == "success" and result.approach_cap == {"capped_steps": 0, "least_cap_m_s": None}, result
    # Seen here (a vehicle lagging 0.8 s behind its command), beside a training run on both cores:
    # 1.73-1.74 m/s at most in the goal's 1 m and 0.65-0.67 m on after the brake began, against
    # 1.98 m/s and 0.78 m.  The gap left to the wall is not compared: where the brake begins moves by
    # a control period's travel (0.13 m at 2 m/s), 6.51-6.61 m in those flights, and CI saw 0.75 m
    # capped against 0.67 m.
    assert capped_overshoot_m < vehicle.overshoot_m - 0.06 and capped_speed_m_s < vehicle.speed_there_m_s - 0.1, (
        capped_overshoot_m, vehicle.overshoot_m, capped_speed_m_s, vehicle.speed_there_m_s)
