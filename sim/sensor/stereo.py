"""The simulated D455's depth: render the IR pair, match it, report metres in the left imager's
frame (the gray camera's), invalid = 0 as the sensor reports.

:class:`StereoDepthSensor` is the batched entry point the datasets, the batched env, the SITL
camera feed and the follower share.  Depth comes at the matching resolution (424 x 240, the
gray camera's pinhole with twice its pixels: the contract's preprocessing resizes either to
224 x 224 onto the same rays); :func:`decimate_depth` brings it to a coarser camera's grid the
way the RealSense decimation filter does (median of the valid pixels of each block).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from runtime.contract.constants import DEPTH_INVALID_VALUE

from ..camera import CameraModel
from ..world import WorldBatch
from .config import StereoConfig
from .ir import IrPair, render_ir_pair
from .matching import match_depth


@dataclass
class StereoFrame:
    """depth_m [B, H, W] float32 z-depth (m) in the left imager's frame at the matching resolution,
    0 where the matcher found none; ir: the IR pair it was matched from; invalid_fraction [B]."""

    depth_m: Tensor
    ir: IrPair
    invalid_fraction: Tensor


class StereoDepthSensor:
    """A D455 whose depth is matched from rendered IR images (see :mod:`sim.sensor`).  ``threads``:
    matching threads (default: torch's thread count).  Noise is drawn from the generator passed
    to :meth:`measure`, so a seed replays the same frames."""

    def __init__(self, config: StereoConfig = StereoConfig(), threads: int | None = None) -> None:
        config.validate()
        self.config = config
        self.threads = threads

    @property
    def camera(self) -> CameraModel:
        """The left imager at the matching resolution (the frame and grid of the depth)."""
        return self.config.camera

    def measure(self, world: WorldBatch, cam_pos_enu_m: Tensor, cam_quat_enu_flu: Tensor,
                generator: torch.Generator) -> StereoFrame:  # fmt: skip
        """Depth for left-imager poses cam_pos_enu_m [B, 3] (m, world ENU) and cam_quat_enu_flu [B, 4]
        (camera frame C -> ENU): the gray camera's pose (sim.camera.camera_pose).  Computed on the
        CPU; returned on the world's device."""
        pair = render_ir_pair(world, cam_pos_enu_m, cam_quat_enu_flu, self.config, generator)
        depth_m = match_depth(pair.left_u8, pair.right_u8, self.config, self.threads)
        invalid = (depth_m <= 0.0).float().mean(dim=(1, 2))
        return StereoFrame(depth_m=depth_m.to(world.device), ir=pair, invalid_fraction=invalid)


def decimate_depth(depth_m: Tensor, factor: int) -> Tensor:
    """[B, H / factor, W / factor] depth from [B, H, W]: the median of the valid pixels of each
    factor x factor block (the lower median for an even count), invalid where none is valid, as
    the RealSense decimation filter reports it."""
    batch, height, width = depth_m.shape
    if factor < 1 or height % factor or width % factor:
        raise ValueError(f"decimate_depth: factor {factor} must divide the image size {height}x{width}")
    if factor == 1:
        return depth_m
    blocks = depth_m.reshape(batch, height // factor, factor, width // factor, factor).permute(0, 1, 3, 2, 4)
    blocks = blocks.reshape(batch, height // factor, width // factor, factor * factor)
    valid = blocks > 0.0
    count = valid.sum(dim=-1)
    # Invalid pixels sort last; the lower median of the k valid ones is at index (k - 1) // 2.
    ordered = torch.where(valid, blocks, torch.full_like(blocks, float("inf"))).sort(dim=-1).values
    median = ordered.gather(-1, ((count - 1).clamp_min(0) // 2).unsqueeze(-1)).squeeze(-1)
    return torch.where(count > 0, median, torch.full_like(median, DEPTH_INVALID_VALUE))
