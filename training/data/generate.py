"""`cmnav dataset`: gray/depth pairs rendered from random collision-free poses in random rooms
across curriculum levels, written in the TartanAir V1 layout (one room = one trajectory).

With ``depth="stereo"`` each frame also carries the simulated D455's depth of the same view
(``sim.sensor``: matched from rendered IR images, the projector off in a share
``stereo_projector_off_fraction`` of the frames), in ``depth_stereo/`` beside the clean depth:
the degraded input of `cmnav train cmwae --scheme stereo`, whose target is the clean depth."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from sim.camera import CameraModel, camera_pose, sample_mount_jitter
from sim.collision import min_clearance_m
from sim.render import render
from sim.rotations import quat_from_euler
from sim.sensor import D455, StereoDepthSensor
from sim.world import WorldBatch, make_worlds

from ..progress import Progress
from .pngio import write_png
from .tartanair import STEREO_DEPTH_DIR, STEREO_DEPTH_SUFFIX, v1_paths

DIFFICULTY = "Easy"
DEPTH_KINDS = ("rendered", "stereo")


@dataclass(frozen=True)
class DatasetSpec:
    count: int
    seed: int
    levels: tuple[int, ...] = (0, 2, 5, 10, 15, 20)
    frames_per_room: int = 16
    min_clearance_m: float = 0.4
    # Views mostly look down the room (+x, toward the goal), as in flight; some look anywhere.
    forward_yaw_rad: float = math.radians(60.0)
    any_yaw_fraction: float = 0.3
    max_tilt_rad: float = math.radians(10.0)
    render_chunk: int = 32
    depth: str = "rendered"  # or "stereo": also the simulated D455's depth of every frame
    stereo_projector_off_fraction: float = 0.5

    def validate(self) -> None:
        if self.depth not in DEPTH_KINDS:
            raise ValueError(f"depth={self.depth!r} must be one of {DEPTH_KINDS}")
        if not 0.0 <= self.stereo_projector_off_fraction <= 1.0:
            raise ValueError(f"stereo_projector_off_fraction={self.stereo_projector_off_fraction} must lie in [0, 1]")
        if self.count < 1 or self.frames_per_room < 1:
            raise ValueError(f"count={self.count} and frames_per_room={self.frames_per_room} must be >= 1")
        if not self.levels or min(self.levels) < 0:
            raise ValueError(f"levels={self.levels} must be non-empty and >= 0")


def env_name(level: int, room: int) -> str:
    return f"sim_L{level:02d}_R{room:05d}"


def sample_poses(world: WorldBatch, per_env: int, spec: DatasetSpec, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(pos_enu_m [B*per_env, 3], quat_enu_flu [B*per_env, 4]) collision-free, env-major order."""
    batch = world.batch_size
    room = world.room_size_m.repeat_interleave(per_env, dim=0)
    env_index = torch.arange(batch).repeat_interleave(per_env)
    n = batch * per_env
    pos = torch.empty(n, 3)
    todo = torch.ones(n, dtype=torch.bool)
    margin = spec.min_clearance_m + 0.1
    for _ in range(200):
        idx = todo.nonzero().squeeze(1)
        if idx.numel() == 0:
            break
        u = torch.rand(idx.numel(), 3, generator=generator)
        pos[idx] = margin + u * (room[idx] - 2 * margin)
        clear = min_clearance_m(world.select(env_index[idx]), pos[idx]) >= spec.min_clearance_m
        todo[idx[clear]] = False
    if bool(todo.any()):
        raise RuntimeError(f"{int(todo.sum())} poses found no free space after 200 draws: lower min_clearance_m")
    any_yaw = torch.rand(n, generator=generator) < spec.any_yaw_fraction
    yaw = torch.where(
        any_yaw,
        (torch.rand(n, generator=generator) * 2 - 1) * math.pi,
        (torch.rand(n, generator=generator) * 2 - 1) * spec.forward_yaw_rad,
    )
    tilt = (torch.rand(n, 2, generator=generator) * 2 - 1) * spec.max_tilt_rad
    return pos, quat_from_euler(tilt[:, 0], tilt[:, 1], yaw)


def write_pair(out: Path, trajectory: str, index: int, gray_u8: torch.Tensor, depth_m: torch.Tensor) -> float:
    """Write frame ``index`` of ``trajectory`` (``ENV`` of ENV/Easy/P000) in the TartanAir V1 layout:
    the gray PNG and the depth in metres (.npy); returns the share of invalid depth pixels."""
    image_path, depth_path = v1_paths(out, trajectory, DIFFICULTY, 0, index)
    image_path.parent.mkdir(parents=True, exist_ok=True)
    depth_path.parent.mkdir(parents=True, exist_ok=True)
    depth = depth_m.numpy().astype(np.float32)
    write_png(image_path, gray_u8.numpy())
    np.save(depth_path, depth)
    return float(np.mean(~np.isfinite(depth) | (depth <= 0)))


def write_stereo_depth(out: Path, trajectory: str, index: int, depth_m: torch.Tensor) -> float:
    """Write the stereo depth (m, 0 = invalid) of frame ``index`` beside its clean depth; returns
    its share of invalid pixels."""
    image_path, _ = v1_paths(out, trajectory, DIFFICULTY, 0, index)
    path = image_path.parent.parent / STEREO_DEPTH_DIR / f"{index:06d}{STEREO_DEPTH_SUFFIX}"
    path.parent.mkdir(parents=True, exist_ok=True)
    depth = depth_m.numpy().astype(np.float32)
    np.save(path, depth)
    return float(np.mean(depth <= 0))


def _stereo_depth(world: WorldBatch, cam_pos: torch.Tensor, cam_quat: torch.Tensor, projector_on: torch.Tensor,
                  generator: torch.Generator) -> torch.Tensor:  # fmt: skip
    """[B, H, W] the simulated D455's depth (its matching resolution) of each view, projector per view."""
    depth = None
    for on in (True, False):
        idx = (projector_on == on).nonzero().squeeze(1)
        if len(idx) == 0:
            continue
        sensor = StereoDepthSensor(replace(D455, projector_on=on))
        frame = sensor.measure(world.select(idx), cam_pos[idx], cam_quat[idx], generator)
        if depth is None:
            depth = torch.zeros(cam_pos.shape[0], *frame.depth_m.shape[1:])
        depth[idx] = frame.depth_m
    return depth


def generate_dataset(out_dir: str | Path, spec: DatasetSpec, camera: CameraModel = CameraModel()) -> dict:
    """Render ``spec.count`` pairs under ``out_dir``; returns (and writes) a manifest."""
    spec.validate()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rooms = math.ceil(spec.count / spec.frames_per_room)
    levels = [spec.levels[r % len(spec.levels)] for r in range(rooms)]
    all_rooms = make_worlds(levels, seed=spec.seed)
    generator = torch.Generator().manual_seed(spec.seed)
    progress = Progress(spec.count, f"dataset {out}", unit="frames")
    written = 0
    invalid_fracs, stereo_invalid = [], []
    stereo_projector: dict[str, list[bool]] = {}
    for first_room in range(0, rooms, max(1, spec.render_chunk // spec.frames_per_room)):
        room_ids = list(range(first_room, min(rooms, first_room + max(1, spec.render_chunk // spec.frames_per_room))))
        world = all_rooms.select(room_ids)
        pos, quat = sample_poses(world, spec.frames_per_room, spec, generator)
        jitter = sample_mount_jitter(pos.shape[0], generator)
        cam_pos, cam_quat = camera_pose(pos, quat, camera, jitter)
        views = world.select(torch.arange(len(room_ids)).repeat_interleave(spec.frames_per_room))
        frames = render(views, cam_pos, cam_quat, camera)
        stereo = None
        if spec.depth == "stereo":
            projector_on = torch.rand(pos.shape[0], generator=generator) >= spec.stereo_projector_off_fraction
            stereo = _stereo_depth(views, cam_pos, cam_quat, projector_on, generator)
        for k in range(pos.shape[0]):
            if written >= spec.count:
                break
            room = room_ids[k // spec.frames_per_room]
            trajectory = env_name(levels[room], room)
            invalid_fracs.append(write_pair(out, trajectory, k % spec.frames_per_room, frames.gray_u8[k], frames.depth_m[k]))
            if stereo is not None:
                stereo_invalid.append(write_stereo_depth(out, trajectory, k % spec.frames_per_room, stereo[k]))
                stereo_projector.setdefault(trajectory, []).append(bool(projector_on[k]))
            written += 1
            progress.update(1)
    progress.close()
    manifest = {"spec": asdict(spec), "rooms": rooms, "frames": written, "camera": asdict(camera),
                "layout": "tartanair-v1", "invalid_depth_frac_mean": float(np.mean(invalid_fracs))}  # fmt: skip
    if spec.depth == "stereo":
        manifest["stereo"] = {"sensor": asdict(D455), "invalid_depth_frac_mean": float(np.mean(stereo_invalid)),
                              "projector_on": stereo_projector}  # fmt: skip
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return manifest
