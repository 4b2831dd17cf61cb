"""Renders what the vehicle's camera sees, at the camera rate, from whatever pose it is given.

The feed takes a pose source (a callable returning the latest body pose), not the dynamics, so
the same world and camera can follow our own dynamics or a real PX4 SIH's pose.  Only physical
frames go out: the camera is held inside the room (``sim.camera.clamp_into_room``: a pose from an
autopilot that knows no room can sit under the floor), and a frame whose depth is still negative,
infinite or NaN is withheld and the reason logged, never served.

Its depth (``DEPTH_MODES``): the rendered depth map ("none"), the same with a D455's losses
without its projector drawn on it ("projector-off", ``sim.degradation``), or the simulated D455's
own stereo depth ("stereo", "stereo-projector-off": ``sim.sensor``, matched from rendered IR images
at 424 x 240 and brought to the camera's grid by the RealSense decimation filter's median, as the
runtime needs depth and gray on one grid).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable

import numpy as np
import torch

from runtime.camera.frame import Frame
from runtime.contract.images import invalid_depth_fraction
from sim.camera import CameraModel, camera_pose, clamp_into_room
from sim.degradation import ProjectorOffModel
from sim.render import render
from sim.sensor import D455, StereoDepthSensor, decimate_depth
from sim.world import WorldBatch

from .kinematics import Kinematics

log = logging.getLogger(__name__)

# The served frames' depth, by name (--degrade of sim.sitl, the follower and cmnav sitl).
DEPTH_MODES = ("none", "projector-off", "stereo", "stereo-projector-off")


class CameraFeed:
    """A thread that renders one frame per period (deadline-scheduled, no drift) and hands it to
    ``publish``.  A render that overruns its period skips the missed deadlines."""

    def __init__(
        self,
        world: WorldBatch,
        camera: CameraModel,
        pose_source: Callable[[], Kinematics],
        publish: Callable[[Frame], None],
        rate_hz: float,
        depth_mode: str = "none",
        seed: int = 0,
    ) -> None:
        """``depth_mode``: one of ``DEPTH_MODES``; its noise and losses are drawn from a generator
        seeded with ``seed`` so a seed replays the same frames."""
        if depth_mode not in DEPTH_MODES:
            raise ValueError(f"depth mode {depth_mode!r} must be one of {', '.join(DEPTH_MODES)}")
        if world.batch_size != 1:
            raise ValueError(f"the camera feed renders one world, got a batch of {world.batch_size}")
        if not rate_hz > 0.0:
            raise ValueError(f"camera rate {rate_hz} Hz must be > 0")
        self._world = world
        self._camera = camera
        self._pose_source = pose_source
        self._publish = publish
        self._period_s = 1.0 / rate_hz
        self._seq = 0
        self._projector_off = ProjectorOffModel() if depth_mode == "projector-off" else None
        self._stereo = None
        if depth_mode.startswith("stereo"):
            self._stereo = StereoDepthSensor(dataclasses.replace(D455, projector_on=depth_mode == "stereo"), threads=1)
            self._decimation = self._stereo.camera.width_px // camera.width_px
            if self._decimation * camera.width_px != self._stereo.camera.width_px or \
                    self._decimation * camera.height_px != self._stereo.camera.height_px:
                raise ValueError(f"stereo depth {self._stereo.camera.width_px}x{self._stereo.camera.height_px} px is not a "
                                 f"whole multiple of the camera's {camera.width_px}x{camera.height_px} px")  # fmt: skip
        self._generator = torch.Generator().manual_seed(seed)
        self.skipped_deadlines = 0
        self.withheld_unphysical = 0  # frames never served: depth no sensor reports
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="camera-render", daemon=True)

    def render_frame(self, kin: Kinematics) -> Frame:
        """Render the view from body pose ``kin``; t_capture_ns = time.monotonic_ns() now."""
        t_capture_ns = time.monotonic_ns()
        pos = torch.as_tensor(kin.pos_enu_m, dtype=torch.float32).reshape(1, 3)
        quat = torch.as_tensor(kin.quat_enu_flu, dtype=torch.float32).reshape(1, 4)
        cam_pos, cam_quat = camera_pose(pos, quat, self._camera)
        cam_pos = clamp_into_room(cam_pos, self._world.room_size_m)
        with torch.no_grad():
            out = render(self._world, cam_pos, cam_quat, self._camera)
        depth = out.depth_m
        if self._projector_off is not None:
            depth, _ = self._projector_off.apply(depth, out.gray_u8, self._camera.fx_px, self._generator)
        elif self._stereo is not None:
            with torch.no_grad():
                matched = self._stereo.measure(self._world, cam_pos, cam_quat, self._generator).depth_m
            depth = decimate_depth(matched, self._decimation)
        depth_m = np.ascontiguousarray(depth[0].numpy(), dtype=np.float32)
        gray_u8 = np.ascontiguousarray(out.gray_u8[0].numpy(), dtype=np.uint8)
        frame = Frame(
            t_capture_ns=t_capture_ns,
            depth_m=depth_m,
            gray_u8=gray_u8,
            seq=self._seq,
            meta={"invalid_depth_frac": invalid_depth_fraction(depth_m)},
        )
        self._seq += 1
        return frame

    def start(self) -> None:
        """Render and publish the first frame now (so a client never waits for one), then run."""
        self._render_and_publish()
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        next_s = time.monotonic() + self._period_s
        while not self._stop.wait(max(0.0, next_s - time.monotonic())):
            self._render_and_publish()
            next_s += self._period_s
            now = time.monotonic()
            if now > next_s:
                missed = int((now - next_s) / self._period_s) + 1
                self.skipped_deadlines += missed
                next_s += missed * self._period_s

    def _render_and_publish(self) -> None:
        frame = self.render_frame(self._pose_source())
        problem = unphysical_depth(frame.depth_m)
        if problem is None:
            self._publish(frame)
            return
        self.withheld_unphysical += 1
        if self.withheld_unphysical == 1 or self.withheld_unphysical % 100 == 0:
            log.error("camera frame %d withheld: %s (%d withheld so far)", frame.seq, problem, self.withheld_unphysical)


def unphysical_depth(depth_m: np.ndarray) -> str | None:
    """Why ``depth_m`` (metres, 0 = invalid) is not something a depth sensor reports (negative,
    infinite or NaN values), or None when every pixel is a distance or the invalid 0."""
    bad = ~np.isfinite(depth_m) | (depth_m < 0.0)
    count = int(np.count_nonzero(bad))
    if count == 0:
        return None
    return f"{count} depth pixels are negative, infinite or NaN (a camera outside the room?)"
