"""Only physical frames leave the camera feed (issue 27): a body pose under the floor, above the
ceiling or outside the walls (PX4 SIH's estimate knows no room) renders depth a sensor could
report, and a frame with negative, infinite or NaN depth is withheld, never published."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from sim.camera import CameraModel, clamp_into_room
from sim.sitl.camera_feed import CameraFeed, unphysical_depth
from sim.sitl.kinematics import Kinematics
from sim.world import make_worlds


def _kin(pos_enu_m, yaw_rad: float = 0.0) -> Kinematics:
    quat = np.array([np.cos(yaw_rad / 2), 0.0, 0.0, np.sin(yaw_rad / 2)])
    return Kinematics(time.monotonic_ns(), np.asarray(pos_enu_m, dtype=np.float64), np.zeros(3), quat, np.zeros(3), True)


@pytest.fixture(scope="module")
def world():
    return make_worlds(3, 11, 1)


def _room(world) -> np.ndarray:
    return world.room_size_m[0].numpy().astype(np.float64)


@pytest.mark.parametrize("where", ["under the floor", "on the floor", "above the ceiling", "behind the start wall",
                                   "outside a side wall", "beyond the far corner"])
def test_a_camera_outside_the_room_renders_only_physical_depth(world, where):
    length, width, height = _room(world)
    pos = {
        "under the floor": (1.5, width / 2, -0.30),
        "on the floor": (1.5, width / 2, 0.0),
        "above the ceiling": (1.5, width / 2, height + 0.5),
        "behind the start wall": (-0.4, width / 2, 1.5),
        "outside a side wall": (3.0, width + 1.0, 1.5),
        "beyond the far corner": (length + 2.0, width + 2.0, height + 2.0),
    }[where]
    feed = CameraFeed(world, CameraModel(), lambda: None, lambda frame: None, 15.0)
    frame = feed.render_frame(_kin(pos))
    assert unphysical_depth(frame.depth_m) is None
    assert np.all(np.isfinite(frame.depth_m)) and float(frame.depth_m.min()) >= 0.0
    assert frame.meta["invalid_depth_frac"] < 1.0  # it still sees the room


def test_inside_the_room_the_camera_is_not_moved(world):
    room = world.room_size_m
    inside = torch.tensor([[2.0, 1.0, 1.5]])
    assert torch.equal(clamp_into_room(inside, room), inside)
    clamped = clamp_into_room(torch.tensor([[-1.0, 1.0, -0.2]]), room)
    assert clamped[0, 0].item() == pytest.approx(0.02) and clamped[0, 2].item() == pytest.approx(0.02)


def test_unphysical_depth_names_what_is_wrong():
    good = np.full((4, 4), 3.0, dtype=np.float32)
    good[0, 0] = 0.0  # the invalid value a sensor reports
    assert unphysical_depth(good) is None
    for bad_value in (-0.1, np.inf, np.nan):
        bad = good.copy()
        bad[1, 2] = bad_value
        assert "1 depth pixels" in unphysical_depth(bad)


def test_an_unphysical_frame_is_withheld_not_published(world, monkeypatch):
    published = []
    feed = CameraFeed(world, CameraModel(), lambda: _kin((1.5, 2.0, 1.5)), published.append, 15.0)
    feed._render_and_publish()
    assert len(published) == 1 and feed.withheld_unphysical == 0
    real_render = feed.render_frame

    def broken(kin):
        frame = real_render(kin)
        frame.depth_m[5, 5] = -np.inf
        return frame

    monkeypatch.setattr(feed, "render_frame", broken)
    feed._render_and_publish()
    assert len(published) == 1 and feed.withheld_unphysical == 1


def test_the_stereo_camera_serves_matched_depth_on_the_cameras_grid(world):
    """--degrade stereo: the simulated D455's depth (sim.sensor), decimated to the served grid.
    Near the rendered depth where both see a surface within 4 m; with the projector off, more
    of it lost (the texture check)."""
    pose = _kin((1.0, float(_room(world)[1]) / 2, 1.5))
    clean = CameraFeed(world, CameraModel(), lambda: None, lambda frame: None, 15.0).render_frame(pose)
    served = {}
    for mode in ("stereo", "stereo-projector-off"):
        served[mode] = CameraFeed(world, CameraModel(), lambda: None, lambda frame: None, 15.0, depth_mode=mode, seed=3).render_frame(pose)
        depth = served[mode].depth_m
        assert depth.shape == clean.depth_m.shape == served[mode].gray_u8.shape and unphysical_depth(depth) is None
    on, off = served["stereo"].depth_m, served["stereo-projector-off"].depth_m
    near = (clean.depth_m > 0.6) & (clean.depth_m < 4.0) & (on > 0.0)
    assert near.mean() > 0.3
    relative = np.abs(on[near] - clean.depth_m[near]) / clean.depth_m[near]
    assert np.median(relative) < 0.02
    assert (off == 0.0).mean() > (on == 0.0).mean()
    assert not np.array_equal(on, clean.depth_m)  # matched, not the rendered map
    with pytest.raises(ValueError, match="depth mode"):
        CameraFeed(world, CameraModel(), lambda: None, lambda frame: None, 15.0, depth_mode="lidar")
