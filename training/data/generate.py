"""`cmnav dataset`: gray/depth pairs rendered from random collision-free poses in random rooms
across curriculum levels, written in the TartanAir V1 layout (one room = one trajectory)."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from sim.camera import CameraModel, camera_pose, sample_mount_jitter
from sim.collision import min_clearance_m
from sim.render import render
from sim.rotations import quat_from_euler
from sim.world import WorldBatch, make_worlds

from ..progress import Progress
from .pngio import write_png
from .tartanair import v1_paths

DIFFICULTY = "Easy"


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

    def validate(self) -> None:
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
    invalid_fracs = []
    for first_room in range(0, rooms, max(1, spec.render_chunk // spec.frames_per_room)):
        room_ids = list(range(first_room, min(rooms, first_room + max(1, spec.render_chunk // spec.frames_per_room))))
        world = all_rooms.select(room_ids)
        pos, quat = sample_poses(world, spec.frames_per_room, spec, generator)
        jitter = sample_mount_jitter(pos.shape[0], generator)
        cam_pos, cam_quat = camera_pose(pos, quat, camera, jitter)
        frames = render(world.select(torch.arange(len(room_ids)).repeat_interleave(spec.frames_per_room)), cam_pos, cam_quat, camera)
        for k in range(pos.shape[0]):
            if written >= spec.count:
                break
            room = room_ids[k // spec.frames_per_room]
            trajectory = env_name(levels[room], room)
            invalid_fracs.append(write_pair(out, trajectory, k % spec.frames_per_room, frames.gray_u8[k], frames.depth_m[k]))
            written += 1
            progress.update(1)
    progress.close()
    manifest = {"spec": asdict(spec), "rooms": rooms, "frames": written, "camera": asdict(camera),
                "layout": "tartanair-v1", "invalid_depth_frac_mean": float(np.mean(invalid_fracs))}  # fmt: skip
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return manifest
