"""A RealSense recording made the way librealsense makes one, from frames the sim renders: a
software device (``rs.software_device``) with a depth sensor (z16, its depth units as a recorded
option) and a gray image sensor (color rgb8 as realsense-viewer records it, or infrared y8),
wrapped by ``rs.recorder``; frames are handed over at the recording rate with D455-style global
(host wall clock) timestamps, so the file plays back in real time at that rate.

librealsense up to 2.57 writes ROS 1 ``.bag`` files, 2.58 on ROS 2 ``.db3`` (its recorder refuses
another extension): :func:`recording_suffix` asks the installed one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.contract.camera import focal_length_px
from runtime.contract.constants import CAMERA_RATE_HZ

WIDTH_PX, HEIGHT_PX = 424, 240  # a D455 mode of the contract's 848:480 aspect
DEPTH_UNITS_M = 0.001  # the D455's default: 1 mm per z16 step


@dataclass(frozen=True)
class RenderedFrames:
    """Frames as the sim renders them: depth float32 metres (0 = invalid), gray uint8, [N, H, W]."""

    depth_m: np.ndarray
    gray_u8: np.ndarray

    def __len__(self) -> int:
        return len(self.depth_m)


def render_walk(n_frames: int, level: int = 3, seed: int = 5) -> RenderedFrames:
    """``n_frames`` frames of a camera walking down a sim room (level = obstacles), 424x240."""
    import torch

    from sim.camera import CameraModel, camera_pose, clamp_into_room
    from sim.render import render
    from sim.rotations import quat_from_yaw
    from sim.world import make_worlds

    world = make_worlds(level, seed)
    camera = CameraModel(width_px=WIDTH_PX, height_px=HEIGHT_PX)
    start, goal = world.start_m[0], world.goal_m[0]
    fraction = torch.linspace(0.0, 0.6, n_frames, dtype=torch.float32)[:, None]
    pos = start + fraction * (goal - start)
    yaw = torch.atan2(goal[1] - start[1], goal[0] - start[0]).expand(n_frames)
    cam_pos, cam_quat = camera_pose(pos, quat_from_yaw(yaw), camera)
    cam_pos = clamp_into_room(cam_pos, world.room_size_m.expand(n_frames, 3))
    depth, gray = [], []
    with torch.no_grad():
        for i in range(n_frames):  # one world, one pose at a time
            out = render(world, cam_pos[i : i + 1], cam_quat[i : i + 1], camera)
            depth.append(out.depth_m[0].numpy())
            gray.append(out.gray_u8[0].numpy())
    return RenderedFrames(np.stack(depth).astype(np.float32), np.stack(gray).astype(np.uint8))


def recording_suffix(rs) -> str:
    """The file type the installed librealsense records: ".db3" (ROS 2 bag) or ".bag" (ROS 1)."""
    version = tuple(int(v) for v in rs.__version__.split(".")[:2])
    return ".db3" if version >= (2, 58) else ".bag"


def depth_z16(depth_m: np.ndarray, units_m: float) -> np.ndarray:
    """Metres -> z16 steps of ``units_m`` as a D455 reports them (0 = invalid, beyond range clipped)."""
    steps = np.where(np.isfinite(depth_m) & (depth_m > 0.0), np.rint(depth_m / units_m), 0.0)
    return np.clip(steps, 0, 65535).astype(np.uint16)


def write_recording(path: Path, frames: RenderedFrames, depth_units_m: float = DEPTH_UNITS_M, gray_stream: str = "color",
                    fps: int = int(CAMERA_RATE_HZ), emitter_enabled: bool = True) -> Path:  # fmt: skip
    """Record ``frames`` to ``path`` with librealsense's recorder; takes ``len(frames) / fps`` s
    (the recorder stamps each frame with its arrival time, and playback keeps those gaps)."""
    import pyrealsense2 as rs

    h, w = frames.depth_m.shape[1:]
    fx = focal_length_px(w)  # the contract's pinhole, the sim's
    intrinsics = rs.intrinsics()
    intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy = w, h, fx, fx
    intrinsics.ppx, intrinsics.ppy, intrinsics.model, intrinsics.coeffs = w / 2.0, h / 2.0, rs.distortion.none, [0.0] * 5

    def stream(kind, index, uid, fmt, bpp):
        s = rs.video_stream()
        s.type, s.index, s.uid, s.width, s.height, s.fps, s.bpp, s.fmt, s.intrinsics = kind, index, uid, w, h, fps, bpp, fmt, intrinsics
        return s

    device = rs.software_device()
    depth_sensor = device.add_sensor("Stereo Module")
    depth_profile = depth_sensor.add_video_stream(stream(rs.stream.depth, 0, 0, rs.format.z16, 2))
    depth_sensor.add_read_only_option(rs.option.depth_units, depth_units_m)
    depth_sensor.add_read_only_option(rs.option.emitter_enabled, 1.0 if emitter_enabled else 0.0)
    if gray_stream == "color":
        gray_sensor = device.add_sensor("RGB Camera")
        gray_profile = gray_sensor.add_video_stream(stream(rs.stream.color, 0, 1, rs.format.rgb8, 3))
        gray_images = np.repeat(frames.gray_u8[..., None], 3, axis=-1)  # R = G = B: the luma is the gray value
        gray_bpp = 3
    else:  # the left imager's infrared: the same sensor as depth on a D455
        gray_sensor = depth_sensor
        gray_profile = depth_sensor.add_video_stream(stream(rs.stream.infrared, 1, 1, rs.format.y8, 1))
        gray_images, gray_bpp = frames.gray_u8, 1
    identity = rs.extrinsics()
    identity.rotation, identity.translation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0]
    depth_profile.register_extrinsics_to(gray_profile, identity)  # the sim renders both from one pinhole

    recorder = rs.recorder(str(path), device, True)
    sensors = [depth_sensor] if gray_sensor is depth_sensor else [depth_sensor, gray_sensor]
    if gray_sensor is depth_sensor:
        depth_sensor.open([depth_profile, gray_profile])
    else:
        depth_sensor.open(depth_profile)
        gray_sensor.open(gray_profile)
    for sensor in sensors:
        sensor.start(lambda frame: None)
    period_s = 1.0 / fps
    t0_s, t0_wall_ms = time.monotonic(), time.time() * 1e3
    try:
        for i in range(len(frames)):
            time.sleep(max(0.0, t0_s + i * period_s - time.monotonic()))
            stamp_ms = t0_wall_ms + i * 1e3 * period_s
            for sensor, profile, data, bpp in ((depth_sensor, depth_profile, depth_z16(frames.depth_m[i], depth_units_m), 2),
                                               (gray_sensor, gray_profile, gray_images[i], gray_bpp)):  # fmt: skip
                frame = rs.software_video_frame()
                frame.pixels, frame.stride, frame.bpp = np.ascontiguousarray(data), w * bpp, bpp
                frame.timestamp, frame.domain, frame.frame_number = stamp_ms, rs.timestamp_domain.global_time, i
                frame.profile = profile.as_video_stream_profile()
                sensor.on_video_frame(frame)
    finally:
        for sensor in sensors:
            sensor.stop()
            sensor.close()
        del recorder  # closes the file
    return path
