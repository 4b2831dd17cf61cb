"""Pinhole model of the D455 as mounted (the contract's HFOV and the sim's reduced raw size).

Camera frame C is FLU-aligned like the body: x = optical axis (forward), y = left, z = up.
Image axes: u (columns) to the right = -y_C, v (rows) down = -z_C; pixel (u, v) covers
[u, u+1) x [v, v+1), so its centre is (u + 0.5, v + 0.5).  The camera sits at the body origin
plus ``mount_offset_body_flu_m`` and looks along body +x; an optional mount jitter (sampled per
env) shifts and tilts it.  Depth is z-depth: ray length x ``z_factor`` (cosine of the ray's angle
to the optical axis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from runtime.contract.camera import focal_length_px
from runtime.contract.constants import CAMERA_HFOV_RAD, SIM_CAMERA_HEIGHT_PX, SIM_CAMERA_WIDTH_PX

from .rotations import quat_from_euler, quat_multiply, quat_rotate


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with square pixels and the principal point at the image centre."""

    width_px: int = SIM_CAMERA_WIDTH_PX
    height_px: int = SIM_CAMERA_HEIGHT_PX
    hfov_rad: float = CAMERA_HFOV_RAD
    mount_offset_body_flu_m: tuple[float, float, float] = (0.1, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.width_px < 2 or self.height_px < 2:
            raise ValueError(f"CameraModel needs at least 2x2 pixels, got {self.width_px}x{self.height_px}")
        if not 0.0 < self.hfov_rad < math.pi:
            raise ValueError(f"CameraModel.hfov_rad={self.hfov_rad} must be in (0, pi)")

    @property
    def fx_px(self) -> float:
        """Focal length in pixels (horizontal and vertical: square pixels)."""
        return focal_length_px(self.width_px, self.hfov_rad)

    @property
    def fy_px(self) -> float:
        return self.fx_px

    @property
    def cx_px(self) -> float:
        return self.width_px / 2.0

    @property
    def cy_px(self) -> float:
        return self.height_px / 2.0

    def intrinsics(self) -> Tensor:
        """3x3 intrinsic matrix K (float64) mapping (right, down, forward) to pixel coordinates."""
        return torch.tensor(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]], dtype=torch.float64
        )

    def _ray_unnormalised(self, device: torch.device | str, dtype: torch.dtype) -> Tensor:
        """[H, W, 3] ray through each pixel centre in frame C with unit forward component."""
        u = (torch.arange(self.width_px, device=device, dtype=torch.float64) + 0.5 - self.cx_px) / self.fx_px
        v = (torch.arange(self.height_px, device=device, dtype=torch.float64) + 0.5 - self.cy_px) / self.fy_px
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        return torch.stack([torch.ones_like(uu), -uu, -vv], dim=-1).to(dtype)

    def ray_directions(self, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> Tensor:
        """[H, W, 3] unit ray direction through each pixel centre, camera frame C (FLU-aligned)."""
        rays = self._ray_unnormalised(device, torch.float64)
        return (rays / torch.linalg.vector_norm(rays, dim=-1, keepdim=True)).to(dtype)

    def z_factor(self, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> Tensor:
        """[H, W] cosine of each ray's angle to the optical axis: z-depth = ray length x factor."""
        rays = self._ray_unnormalised(device, torch.float64)
        return (1.0 / torch.linalg.vector_norm(rays, dim=-1)).to(dtype)


@dataclass
class MountJitter:
    """Per-env error of the camera mount: offset_body_flu_m [B, 3] (m) added to the mount offset,
    quat_body_cam [B, 4] (w, x, y, z) rotating frame C into the body frame."""

    offset_body_flu_m: Tensor
    quat_body_cam: Tensor


def sample_mount_jitter(
    batch_size: int,
    generator: torch.Generator,
    max_offset_m: float = 0.05,
    max_angle_rad: float = math.radians(3.0),
    device: torch.device | str = "cpu",
) -> MountJitter:
    """Uniform mount jitter: each offset axis in [-max_offset_m, max_offset_m], roll/pitch/yaw each
    in [-max_angle_rad, max_angle_rad].  Drawn on the CPU from ``generator`` (a CPU generator), so
    the same generator state gives the same jitter on every device."""
    u = torch.rand((batch_size, 6), generator=generator, dtype=torch.float32) * 2.0 - 1.0
    offset = u[:, :3] * max_offset_m
    angles = u[:, 3:] * max_angle_rad
    quat = quat_from_euler(angles[:, 0], angles[:, 1], angles[:, 2])
    return MountJitter(offset_body_flu_m=offset.to(device), quat_body_cam=quat.to(device))


def camera_pose(
    pos_enu_m: Tensor, quat_enu_flu: Tensor, camera: CameraModel, jitter: MountJitter | None = None
) -> tuple[Tensor, Tensor]:
    """Camera pose from the body pose: (cam_pos_enu_m [B, 3], cam_quat_enu_cam [B, 4]).

    pos_enu_m [B, 3] and quat_enu_flu [B, 4] are the body's; the returned quaternion rotates
    camera frame C into world ENU (equal to the body's without jitter).
    """
    offset = torch.tensor(camera.mount_offset_body_flu_m, dtype=pos_enu_m.dtype, device=pos_enu_m.device)
    offset = offset.expand_as(pos_enu_m)
    quat = quat_enu_flu
    if jitter is not None:
        offset = offset + jitter.offset_body_flu_m
        quat = quat_multiply(quat_enu_flu, jitter.quat_body_cam)
    return pos_enu_m + quat_rotate(quat_enu_flu, offset), quat


# The camera never renders from inside a wall, the floor or the ceiling: closer than this to a
# face of the room it is held at this distance (a D455's glass sits ~1 cm behind its bezel).
CAMERA_ROOM_MARGIN_M = 0.02


def clamp_into_room(cam_pos_enu_m: Tensor, room_size_m: Tensor, margin_m: float = CAMERA_ROOM_MARGIN_M) -> Tensor:
    """Camera positions [B, 3] (world ENU, m) held inside rooms [B, 3] (L, W, H; the room spans
    [0, L] x [0, W] x [0, H]) by ``margin_m``.

    A vehicle whose pose comes from elsewhere (PX4 SIH knows no room; its estimate sits a few
    centimetres under the floor on the ground) can put the camera outside the room, where a ray
    cast from inside gives negative or infinite depth that no sensor reports.  A real camera
    pressed against a surface sees that surface at its minimum distance: holding it at the
    margin renders exactly that."""
    lo = torch.full_like(room_size_m, margin_m)
    hi = (room_size_m - margin_m).clamp_min(margin_m)
    return torch.minimum(torch.maximum(cam_pos_enu_m, lo), hi)
