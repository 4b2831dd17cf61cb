"""Ray-cast depth and textured gray images of the worlds in a :class:`~sim.world.WorldBatch`.

Every pixel's ray (see :mod:`sim.camera`) is intersected with the room's six faces (from inside)
and each valid box (slab test in the box's own frame); the nearest hit gives the depth (z-depth,
metres, float32) and the gray value: the surface's procedural albedo (:mod:`sim.texture`) times
Lambertian shading from a fixed light direction plus ambient, rounded to uint8.

- :func:`render` (here): the one entry point, the fast path on the world's device;
- :mod:`sim.render.reference`: ``render_reference``, the plain ray caster every fast path is
  tested equal to, the shared shading, and ``render_torch`` (batched torch ops, the CUDA path);
- :mod:`sim.render.cpu`: ``render_cpu``, the numba kernel of the CPU path.

The package imports one way: ``cpu`` and this module import ``reference``, nothing imports back.
"""

from __future__ import annotations

from torch import Tensor

from ..camera import CameraModel
from ..world import WorldBatch
from .reference import (
    AMBIENT_FRACTION,
    DEPTH_REL_TOLERANCE,
    GRAY_TOLERANCE_LEVELS,
    LIGHT_DIR_ENU,
    MAX_MISMATCH_FRACTION,
    RenderOutput,
    render_reference,
    render_torch,
)

__all__ = [
    "AMBIENT_FRACTION",
    "DEPTH_REL_TOLERANCE",
    "GRAY_TOLERANCE_LEVELS",
    "LIGHT_DIR_ENU",
    "MAX_MISMATCH_FRACTION",
    "RenderOutput",
    "render",
    "render_reference",
    "render_torch",
]


def render(
    world: WorldBatch, cam_pos_enu_m: Tensor, cam_quat_enu_flu: Tensor, camera: CameraModel
) -> RenderOutput:
    """Render depth and gray for camera poses cam_pos_enu_m [B, 3] (m), cam_quat_enu_flu [B, 4]
    (camera frame C -> world ENU) on the world's device; equal to :func:`render_reference` within
    DEPTH_REL_TOLERANCE / GRAY_TOLERANCE_LEVELS.  On the CPU the numba kernel of
    :mod:`sim.render.cpu` (boxes culled to their screen rectangles, as many threads as torch
    uses), elsewhere :func:`render_torch`."""
    if world.device.type == "cpu":
        # Imported here: numba, which the torch path does not need, loads with it.
        from .cpu import render_cpu

        return render_cpu(world, cam_pos_enu_m, cam_quat_enu_flu, camera)
    return render_torch(world, cam_pos_enu_m, cam_quat_enu_flu, camera)
