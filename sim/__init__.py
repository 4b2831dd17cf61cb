"""The simulated world: rooms with obstacles, camera rendering, quadrotor dynamics, collisions.

The public names below are re-exported lazily, so importing a light submodule (the SITL session
launcher, the plots) does not load torch.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "WorldBatch": "world",
    "WorldConfig": "world",
    "make_worlds": "world",
    "CameraModel": "camera",
    "MountJitter": "camera",
    "camera_pose": "camera",
    "sample_mount_jitter": "camera",
    "RenderOutput": "render",
    "render": "render",
    "render_reference": "render",
    "DynamicsParams": "dynamics",
    "QuadState": "dynamics",
    "QuadrotorDynamics": "dynamics",
    "collides": "collision",
    "min_clearance_m": "collision",
    "preprocess_depth_batch": "preprocess_torch",
    "preprocess_gray_batch": "preprocess_torch",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> object:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
