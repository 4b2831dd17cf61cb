"""The D455's gray image as its camera takes it: auto-exposure, gain, motion blur over the
exposure, shot and read noise, 8 bits.

The renderer's gray (:func:`sim.render.render`: albedo x the room light's shade, 0..255) is
taken as the scene's radiance: a pixel of level L collects

    rate (e-/s) = brightness x electrons_per_s_at_255 x L / 255

photo-electrons per second, ``brightness`` being the room's light (drawn per episode in
``brightness_range``: a dim room needs a long exposure and gain).  Auto-exposure sets the
exposure time so that the mean signal reaches ``ae_target_level`` at unity gain, within
[min_exposure_s, max_exposure_s]; what the longest exposure cannot reach, analog gain makes up
(at most ``max_gain``).  During the exposure the camera moves: each pixel integrates the scene
along its optical flow (camera linear and angular velocity in the camera frame, the rendered
depth giving the translation's parallax), sampled at ``blur_samples`` instants.  Then shot noise
(Poisson, as Gaussian with variance = signal), read noise, the full well, gain, rounding and the
8-bit ceiling.

Numbers: the D455's colour imager is an OmniVision OV9782 (1 MP global shutter, 3 um pixels).
Its full well and read noise are not in Intel's datasheet; ``full_well_electrons`` 9000 and
``read_noise_electrons`` 4 are assumptions typical of a 3 um global-shutter pixel, the exposure
range (the RealSense RGB auto-exposure stays under the frame time; 33 ms assumed so 15 Hz keeps
headroom), the gain limit (16x), the AE target (40 % of full scale) and the brightness range (a
20x span, bright office to dim hall) likewise.  None was measured on our camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.nn import functional as F

from ..camera import CameraModel


@dataclass(frozen=True)
class GrayCameraConfig:
    """The gray camera's exposure, gain and noise (see the module doc; all assumptions)."""

    full_well_electrons: float = 9000.0  # signal at 255 levels with unity gain
    read_noise_electrons: float = 4.0
    # A reflectance-1 surface under the brightest room light (brightness 1): with the renderer's
    # mean gray near 100 this needs ~5 ms at unity gain.
    electrons_per_s_at_255: float = 1.8e6
    brightness_range: tuple[float, float] = (0.05, 1.0)  # per episode, log-uniform
    ae_target_level: float = 100.0  # mean image level auto-exposure aims at (0..255)
    min_exposure_s: float = 1e-4
    max_exposure_s: float = 0.033
    max_gain: float = 16.0
    blur_samples: int = 8  # instants over the exposure each pixel averages

    def validate(self) -> None:
        for key in ("full_well_electrons", "electrons_per_s_at_255", "ae_target_level", "min_exposure_s"):
            if not getattr(self, key) > 0.0:
                raise ValueError(f"GrayCameraConfig.{key}={getattr(self, key)} must be > 0")
        if self.read_noise_electrons < 0.0:
            raise ValueError(f"GrayCameraConfig.read_noise_electrons={self.read_noise_electrons} must be >= 0")
        low, high = self.brightness_range
        if not 0.0 < low <= high:
            raise ValueError(f"GrayCameraConfig.brightness_range={self.brightness_range} must satisfy 0 < low <= high")
        if not self.min_exposure_s <= self.max_exposure_s <= 1.0:
            raise ValueError(f"GrayCameraConfig exposure range [{self.min_exposure_s}, {self.max_exposure_s}] s must be "
                             f"increasing and at most 1 s")  # fmt: skip
        if self.max_gain < 1.0 or self.blur_samples < 1 or not 0.0 < self.ae_target_level < 255.0:
            raise ValueError("GrayCameraConfig: max_gain must be >= 1, blur_samples >= 1, ae_target_level in (0, 255)")

    @property
    def levels_per_electron(self) -> float:
        """8-bit levels per photo-electron at unity gain."""
        return 255.0 / self.full_well_electrons


@dataclass
class GrayFrame:
    """gray_u8 [B, H, W] uint8 as the camera gives it; exposure_s [B], gain [B] (x unity) chosen
    by auto-exposure; blur_px [B] the longest blur streak in the image (pixels)."""

    gray_u8: Tensor
    exposure_s: Tensor
    gain: Tensor
    blur_px: Tensor


def sample_brightness(config: GrayCameraConfig, batch_size: int, generator: torch.Generator) -> Tensor:
    """[batch_size] room brightness per episode, log-uniform in ``config.brightness_range``."""
    low, high = config.brightness_range
    u = torch.rand(batch_size, generator=generator)
    return torch.exp(math.log(low) + (math.log(high) - math.log(low)) * u)


def image_flow_px_s(depth_m: Tensor, camera: CameraModel, vel_cam_m_s: Tensor, angvel_cam_rad_s: Tensor) -> Tensor:
    """[B, H, W, 2] optical flow (du/dt, dv/dt in px/s) of the static scene at z-depths depth_m
    [B, H, W] (m) for a camera moving at vel_cam_m_s [B, 3] and turning at angvel_cam_rad_s [B, 3],
    both in camera frame C (x forward, y left, z up; image u = -y, v = -z)."""
    rays = camera.ray_directions(depth_m.device, depth_m.dtype) / camera.z_factor(depth_m.device, depth_m.dtype).unsqueeze(-1)
    point = rays.unsqueeze(0) * depth_m.clamp_min(0.05).unsqueeze(-1)  # [B, H, W, 3], x = z-depth
    # A static point seen from a moving camera: dP/dt = -v - w x P.
    omega = angvel_cam_rad_s.view(-1, 1, 1, 3).expand_as(point)
    dpoint = -vel_cam_m_s.view(-1, 1, 1, 3) - torch.linalg.cross(omega, point, dim=-1)
    x, y, z = point.unbind(-1)
    dx, dy, dz = dpoint.unbind(-1)
    # u = cx - fx y / x, v = cy - fy z / x.
    du = -camera.fx_px * (dy * x - y * dx) / x.square()
    dv = -camera.fy_px * (dz * x - z * dx) / x.square()
    return torch.stack([du, dv], dim=-1)


def _motion_blur(signal: Tensor, flow_px: Tensor, samples: int) -> Tensor:
    """[B, H, W] ``signal`` averaged along each pixel's streak flow_px [B, H, W, 2] (the motion
    over the exposure, centred on the frame's instant)."""
    if samples == 1:
        return signal
    batch, height, width = signal.shape
    v, u = torch.meshgrid(torch.arange(height, dtype=signal.dtype, device=signal.device) + 0.5,
                          torch.arange(width, dtype=signal.dtype, device=signal.device) + 0.5, indexing="ij")  # fmt: skip
    base = torch.stack([u, v], dim=-1).unsqueeze(0)  # [1, H, W, 2] pixel centres
    scale = torch.tensor([2.0 / width, 2.0 / height], dtype=signal.dtype, device=signal.device)
    image = signal.unsqueeze(1)
    total = torch.zeros_like(signal)
    for k in range(samples):
        s = (k + 0.5) / samples - 0.5  # instants spread evenly over the exposure
        grid = (base - flow_px * s) * scale - 1.0
        total = total + F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=False)[:, 0]
    return total / samples


class GrayCamera:
    """Batched gray camera (see the module doc).  Noise comes from the generator passed to
    :meth:`capture`, so a seed replays the same frames."""

    def __init__(self, config: GrayCameraConfig = GrayCameraConfig(), camera: CameraModel = CameraModel()) -> None:
        config.validate()
        self.config = config
        self.camera = camera

    def capture(self, radiance_u8: Tensor, depth_m: Tensor, brightness: Tensor, vel_cam_m_s: Tensor,
                angvel_cam_rad_s: Tensor, generator: torch.Generator) -> GrayFrame:  # fmt: skip
        """The camera's frame of a scene rendered as radiance_u8 [B, H, W] (the renderer's gray)
        with z-depth depth_m [B, H, W] (m), under room ``brightness`` [B], the camera moving at
        vel_cam_m_s [B, 3] (m/s) and turning at angvel_cam_rad_s [B, 3] (rad/s), camera frame C."""
        c = self.config
        dev = radiance_u8.device
        rate_e_s = radiance_u8.float() * (c.electrons_per_s_at_255 / 255.0) * brightness.to(dev).view(-1, 1, 1)
        target_e = c.ae_target_level / c.levels_per_electron
        mean_rate = rate_e_s.flatten(1).mean(dim=1).clamp_min(1e-3)
        exposure_s = (target_e / mean_rate).clamp(c.min_exposure_s, c.max_exposure_s)
        gain = (target_e / (mean_rate * exposure_s)).clamp(1.0, c.max_gain)
        flow_px = image_flow_px_s(depth_m.float(), self.camera, vel_cam_m_s.float(), angvel_cam_rad_s.float())
        streak_px = flow_px * exposure_s.view(-1, 1, 1, 1)
        signal_e = _motion_blur(rate_e_s * exposure_s.view(-1, 1, 1), streak_px, c.blur_samples)
        sigma_e = torch.sqrt(signal_e + c.read_noise_electrons**2)
        noise = torch.randn(signal_e.shape, generator=generator, dtype=torch.float32).to(dev)
        electrons = (signal_e + sigma_e * noise).clamp(0.0, c.full_well_electrons)
        levels = electrons * (c.levels_per_electron * gain.view(-1, 1, 1))
        gray_u8 = torch.round(levels).clamp(0.0, 255.0).to(torch.uint8)
        blur_px = torch.linalg.vector_norm(streak_px, dim=-1).flatten(1).amax(dim=1)
        return GrayFrame(gray_u8=gray_u8, exposure_s=exposure_s, gain=gain, blur_px=blur_px)
