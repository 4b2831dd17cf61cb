"""The parametric D455 (sim.sensor.approx) on synthetic depth maps: the occlusion shadow's width
is the disparity step, nothing nearer than the minimum range survives, the range error grows with
z^2, the projector off loses more of a low-texture surface, lost regions come in blobs, and a
seed replays the frame.  Its error against the stereo path: bench/stereo_approx.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sim.camera import CameraModel
from sim.sensor.approx import StereoApproxConfig, approx_stereo_depth, loss_probability, occlusion_mask

CAMERA = CameraModel()  # 212 x 120, as the SITL camera and the batched env
FX = CAMERA.fx_px


def _wall(z_m: float, batch: int = 8) -> torch.Tensor:
    return torch.full((batch, CAMERA.height_px, CAMERA.width_px), z_m)


def _textured_gray(batch: int = 8, std: float = 20.0, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (100.0 + std * torch.randn(batch, CAMERA.height_px, CAMERA.width_px, generator=g)).clamp(0, 255).to(torch.uint8)


def test_the_occlusion_shadow_is_as_wide_as_the_disparity_step_left_of_a_near_object():
    depth = _wall(5.0, 1)
    depth[:, :, 100:130] = 1.0  # a post 1 m away in front of a wall 5 m away
    mask = occlusion_mask(depth, FX, StereoApproxConfig())[0]
    step_px = FX * 0.095 * (1 / 1.0 - 1 / 5.0)
    shadow = np.nonzero(mask[60].numpy())[0]
    assert shadow.max() == 99 and len(shadow) == pytest.approx(step_px, abs=1.0)  # just left of the post
    assert not mask[:, 100:].any()


def test_nothing_nearer_than_the_minimum_range_is_measured():
    depth = approx_stereo_depth(_wall(0.4), _textured_gray(), FX, StereoApproxConfig(), torch.Generator().manual_seed(0))
    assert float(depth.max()) == 0.0


def test_the_range_error_grows_with_z_squared():
    g = torch.Generator().manual_seed(1)
    config = StereoApproxConfig()
    sigma = {}
    for z in (1.0, 4.0):
        depth = approx_stereo_depth(_wall(z, 32), _textured_gray(32), FX, config, g)
        rel = ((depth[depth > 0] - z) / z).numpy()
        sigma[z] = 1.4826 * np.median(np.abs(rel - np.median(rel)))
    assert sigma[4.0] / sigma[1.0] == pytest.approx(4.0, rel=0.3)  # relative error ~ z: absolute ~ z^2
    assert 0.002 < sigma[1.0] < 0.006  # the stereo path: 0.2-0.4 % at 1-2 m


def test_the_projector_off_loses_more_of_a_low_texture_wall():
    g = torch.Generator().manual_seed(2)
    flat = _textured_gray(std=0.5)
    lost = {}
    for on in (True, False):
        depth = approx_stereo_depth(_wall(2.0), flat, FX, StereoApproxConfig(projector_on=on), g)
        lost[on] = float((depth == 0).float().mean())
    assert lost[False] > 0.6 > 0.3 > lost[True]
    p_textured = loss_probability(_wall(2.0), _textured_gray(std=30.0), FX, StereoApproxConfig(projector_on=False)).mean()
    assert float(p_textured) < lost[False] - 0.2  # texture keeps passive matching alive


def test_lost_regions_come_in_blobs_and_a_seed_replays_the_frame():
    config = StereoApproxConfig()
    a = approx_stereo_depth(_wall(3.0), _textured_gray(), FX, config, torch.Generator().manual_seed(5))
    b = approx_stereo_depth(_wall(3.0), _textured_gray(), FX, config, torch.Generator().manual_seed(5))
    assert torch.equal(a, b)
    lost = (a == 0).numpy()
    share = lost.mean()
    assert 0.02 < share < 0.5
    # The pixel 4 px to the right of a lost one is lost far more often than the share: regions, not speckle.
    assert lost[:, :, 4:][lost[:, :, :-4]].mean() > 3 * share
