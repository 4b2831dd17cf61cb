"""The left and right IR images of the simulated D455 (8-bit, at the matching resolution).

Each imager sees the scene the renderer draws (:func:`sim.render.render`: procedural albedo x
the room light's Lambert shade) under the room's own IR light, plus the projector's dots where
the projector lights the surface (:mod:`sim.sensor.projector`):

    signal (e-) = reflectance x (ambient_electrons + projector light (e-))

``reflectance`` is the rendered gray / 255 (the scene's albedo under the room light stands in
for its IR reflectance).  A pixel integrates its area: the signal is the mean of
``SUBPIXEL_SAMPLES`` renders whose pixel grids are shifted by a rotated-grid pattern of
quarter-pixel offsets (the renderer samples one point per pixel, so without this a texture edge
would sit on whole pixels in both images and matching could not place it to better than a pixel).
Then lens blur, shot and read noise, one auto-exposure gain for both imagers (as the D455 runs
them), rounding and the 8-bit ceiling (near surfaces saturate, as a D455's do).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..camera import CameraModel, clamp_into_room
from ..render import render
from ..rotations import quat_rotate
from ..world import WorldBatch
from .config import StereoConfig
from .projector import projector_irradiance

# Rotated-grid offsets (pixels, u then v) of the samples each pixel averages: four distinct
# phases along u, the axis disparity is measured on.
SUBPIXEL_SAMPLES = ((-0.375, -0.125), (-0.125, 0.375), (0.125, -0.375), (0.375, 0.125))


@dataclass(frozen=True)
class _ShiftedCamera(CameraModel):
    """The imager with its pixel grid shifted by (shift_u_px, shift_v_px): pixel (u, v) is sampled
    at (u + 0.5 + shift_u_px, v + 0.5 + shift_v_px) of the unshifted grid."""

    shift_u_px: float = 0.0
    shift_v_px: float = 0.0

    @property
    def cx_px(self) -> float:
        return self.width_px / 2.0 - self.shift_u_px

    @property
    def cy_px(self) -> float:
        return self.height_px / 2.0 - self.shift_v_px


@dataclass
class IrPair:
    """left_u8, right_u8 [B, H, W] uint8 IR images at the matching resolution (the left imager is
    the depth's frame); gain [B] the auto-exposure gain used (levels per photo-electron)."""

    left_u8: Tensor
    right_u8: Tensor
    gain: Tensor


def _gaussian_blur(image: Tensor, sigma_px: float) -> Tensor:
    """[B, H, W] float32 images blurred by a Gaussian (edges reflected)."""
    import cv2  # here: importing sim.sensor does not need OpenCV

    out = np.stack([cv2.GaussianBlur(im, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT_101) for im in image.numpy()])
    return torch.from_numpy(out)


def imager_positions(cam_pos_enu_m: Tensor, cam_quat_enu_flu: Tensor, room_size_m: Tensor, y_m: float) -> Tensor:
    """[B, 3] position (world ENU, m) of a point ``y_m`` along the camera's +y_C axis from the left
    imager, held inside the room (a viewpoint pushed through a wall would render it from outside)."""
    shift = torch.tensor([0.0, y_m, 0.0], dtype=cam_pos_enu_m.dtype).expand_as(cam_pos_enu_m)
    return clamp_into_room(cam_pos_enu_m + quat_rotate(cam_quat_enu_flu, shift), room_size_m)


def _signal_electrons(world: WorldBatch, pos: Tensor, quat: Tensor, projector_y_m: float, shadow: Tensor | None,
                      config: StereoConfig) -> Tensor:  # fmt: skip
    """[B, H, W] mean photo-electrons over each pixel's area for the imager at ``pos``, which
    sits ``projector_y_m`` along +y_C from the projector."""
    total = None
    for shift_u, shift_v in SUBPIXEL_SAMPLES:
        camera = _ShiftedCamera(width_px=config.width_px, height_px=config.height_px, hfov_rad=config.hfov_rad,
                                shift_u_px=shift_u, shift_v_px=shift_v)  # fmt: skip
        frame = render(world, pos, quat, camera)
        irradiance = torch.full_like(frame.depth_m, config.ambient_electrons)
        if shadow is not None:
            irradiance = irradiance + projector_irradiance(frame.depth_m, camera, projector_y_m, shadow,
                                                           config.projector_camera, config)  # fmt: skip
        signal = frame.gray_u8.to(torch.float32) * (1.0 / 255.0) * irradiance
        total = signal if total is None else total + signal
    return total * (1.0 / len(SUBPIXEL_SAMPLES))


def render_ir_pair(world: WorldBatch, cam_pos_enu_m: Tensor, cam_quat_enu_flu: Tensor, config: StereoConfig,
                   generator: torch.Generator) -> IrPair:  # fmt: skip
    """Render both IR images for left-imager poses cam_pos_enu_m [B, 3] (m, world ENU) and
    cam_quat_enu_flu [B, 4] (camera frame C -> ENU), on the CPU; noise drawn from ``generator``."""
    config.validate()
    pos = cam_pos_enu_m.detach().cpu().float()
    quat = cam_quat_enu_flu.detach().cpu().float()
    world = world.to("cpu")
    shadow = None
    if config.projector_on:
        projector_pos = imager_positions(pos, quat, world.room_size_m, -config.projector_offset_m)
        shadow = render(world, projector_pos, quat, config.projector_camera).depth_m
    right_pos = imager_positions(pos, quat, world.room_size_m, -config.baseline_m)
    signals = [
        _signal_electrons(world, pos, quat, config.projector_offset_m, shadow, config),
        _signal_electrons(world, right_pos, quat, config.projector_offset_m - config.baseline_m, shadow, config),
    ]
    if config.psf_sigma_px > 0.0:
        signals = [_gaussian_blur(s, config.psf_sigma_px) for s in signals]
    # One exposure for both imagers, set on the left image's mean.
    mean_e = signals[0].flatten(1).mean(dim=1).clamp_min(1e-6)
    gain = (config.ae_target_level / mean_e).clamp_max(config.max_gain_levels_per_electron)
    images = []
    for signal_e in signals:
        sigma_e = torch.sqrt(config.read_noise_electrons**2 + signal_e)
        noisy_e = signal_e + sigma_e * torch.randn(signal_e.shape, generator=generator, dtype=torch.float32)
        images.append(torch.round(noisy_e * gain.view(-1, 1, 1)).clamp(0.0, 255.0).to(torch.uint8))
    return IrPair(left_u8=images[0], right_u8=images[1], gain=gain)
