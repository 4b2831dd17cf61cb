"""The gray camera (sim.sensor.gray): auto-exposure and gain as the scene darkens, shot + read
noise of the stated size, motion blur as long as the camera's motion over the exposure, and the
same frames from the same seed."""

from __future__ import annotations

import math

import pytest
import torch

from sim.camera import CameraModel
from sim.sensor.gray import GrayCamera, GrayCameraConfig, image_flow_px_s, sample_brightness

H, W = 120, 212


def _capture(radiance: torch.Tensor, brightness: float, angvel_cam=(0.0, 0.0, 0.0), vel_cam=(0.0, 0.0, 0.0), seed: int = 0,
             config: GrayCameraConfig = GrayCameraConfig(), depth_m: float = 3.0):  # fmt: skip
    b = radiance.shape[0]
    return GrayCamera(config).capture(radiance, torch.full((b, H, W), depth_m), torch.full((b,), brightness),
                                      torch.tensor([vel_cam] * b), torch.tensor([angvel_cam] * b),
                                      torch.Generator().manual_seed(seed))  # fmt: skip


def _uniform(level: int, batch: int = 2) -> torch.Tensor:
    return torch.full((batch, H, W), level, dtype=torch.uint8)


def test_same_seed_same_frame_other_seed_other_noise():
    scene = torch.randint(0, 256, (2, H, W), generator=torch.Generator().manual_seed(1), dtype=torch.int64).to(torch.uint8)
    a, b, c = (_capture(scene, 0.5, (0.0, 0.0, 1.0), seed=s).gray_u8 for s in (3, 3, 4))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_bright_scene_reaches_the_exposure_target_with_shot_and_read_noise():
    config = GrayCameraConfig()
    frame = _capture(_uniform(128), brightness=1.0)
    assert torch.allclose(frame.gain, torch.ones(2))  # enough light: no gain
    assert float(frame.exposure_s.max()) < config.max_exposure_s
    image = frame.gray_u8.float()
    assert float(image.mean()) == pytest.approx(config.ae_target_level, abs=0.5)
    signal_e = config.ae_target_level / config.levels_per_electron
    expected_std = math.sqrt((signal_e + config.read_noise_electrons**2) * config.levels_per_electron**2 + 1 / 12)  # + rounding
    assert float(image.std()) == pytest.approx(expected_std, rel=0.08)


def test_dark_scene_gets_the_longest_exposure_then_gain_and_more_noise():
    config = GrayCameraConfig()
    bright = _capture(_uniform(128), brightness=1.0)
    dim = _capture(_uniform(128), brightness=0.01)
    assert torch.allclose(dim.exposure_s, torch.full((2,), config.max_exposure_s))
    assert float(dim.gain.min()) > 2.0
    # The mean still reaches the target (gain), but from fewer electrons: noisier.
    assert float(dim.gray_u8.float().mean()) == pytest.approx(config.ae_target_level, abs=1.0)
    assert float(dim.gray_u8.float().std()) > 1.5 * float(bright.gray_u8.float().std())
    # Darker than max gain can lift: the image darkens.
    darkest = _capture(_uniform(128), brightness=1e-4)
    assert torch.allclose(darkest.gain, torch.full((2,), config.max_gain))
    assert float(darkest.gray_u8.float().mean()) < 0.5 * config.ae_target_level


def _edge_width_px(gray_u8: torch.Tensor) -> int:
    """Columns of the row-averaged image strictly between the two sides' levels (10 % margins)."""
    profile = gray_u8.float().mean(dim=(0, 1))
    low, high = float(profile[:20].mean()), float(profile[-20:].mean())
    span = high - low
    return int(((profile > low + 0.1 * span) & (profile < high - 0.1 * span)).sum())


def test_motion_blur_grows_with_the_yaw_rate_as_focal_length_x_rate_x_exposure():
    scene = torch.full((1, H, W), 40, dtype=torch.uint8)
    scene[:, :, W // 2:] = 200  # a vertical edge at the image centre
    widths, expected = [], []
    for rate in (0.0, 1.0, 2.0, 4.0):
        frame = _capture(scene, brightness=0.05, angvel_cam=(0.0, 0.0, rate))  # dim: a long exposure
        widths.append(_edge_width_px(frame.gray_u8))
        expected.append(CameraModel().fx_px * rate * float(frame.exposure_s[0]))
    assert widths[0] <= 2
    assert widths == sorted(widths) and widths[-1] > widths[1] > widths[0]
    # The streak of a point at the centre: fx * rate * exposure (80 % of it between the 10 % marks).
    for width, streak in zip(widths[1:], expected[1:]):
        assert width == pytest.approx(0.8 * streak, abs=1.5 + 0.2 * streak)


def test_flow_directions_follow_the_camera_frame():
    camera = CameraModel()
    depth = torch.full((1, H, W), 2.0)
    # Turning left (+z in C): the scene moves right in the image (+u) at the centre.
    turn = image_flow_px_s(depth, camera, torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]))
    assert float(turn[0, H // 2, W // 2, 0]) == pytest.approx(camera.fx_px, rel=0.01)
    # Flying forward: the scene expands from the centre, twice as fast at half the depth.
    forward = image_flow_px_s(depth, camera, torch.tensor([[1.0, 0.0, 0.0]]), torch.zeros(1, 3))
    assert float(forward[0, H // 2, -1, 0]) > 0 > float(forward[0, H // 2, 0, 0])
    near = image_flow_px_s(depth / 2, camera, torch.tensor([[1.0, 0.0, 0.0]]), torch.zeros(1, 3))
    assert float(near[0, H // 2, -1, 0]) == pytest.approx(2 * float(forward[0, H // 2, -1, 0]), rel=1e-4)


def test_brightness_is_log_uniform_in_its_range_and_bad_configs_are_refused():
    config = GrayCameraConfig(brightness_range=(0.01, 1.0))
    b = sample_brightness(config, 4000, torch.Generator().manual_seed(0))
    assert float(b.min()) >= 0.01 and float(b.max()) <= 1.0
    assert float((b < 0.1).float().mean()) == pytest.approx(0.5, abs=0.03)  # half the decades below 0.1
    with pytest.raises(ValueError, match="brightness_range"):
        GrayCameraConfig(brightness_range=(0.0, 1.0)).validate()
    with pytest.raises(ValueError, match="exposure range"):
        GrayCameraConfig(min_exposure_s=0.05, max_exposure_s=0.01).validate()
