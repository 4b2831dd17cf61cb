"""Intel RealSense D455 camera source (pyrealsense2, imported lazily: optional extra).

Depth z16 and color BGR8 at 848x480, 15 Hz; depth aligned to color; depth scale read from the
device; IR emitter switchable (emitter off = the paper's degraded-depth condition).  Frames
carry the device timestamp mapped onto this host's CLOCK_MONOTONIC.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any, AsyncIterator

import numpy as np

from ..config import RealSenseConfig
from ..contract.images import gray_from_bgr
from ..service.shutdown import in_daemon_thread
from .frame import Frame

log = logging.getLogger(__name__)


class RealSenseUnavailableError(RuntimeError):
    """pyrealsense2 or the camera cannot be used; the message says what to install or plug in."""


def import_pyrealsense2() -> Any:
    """Import pyrealsense2, turning the two usual failures into instructions."""
    try:
        import pyrealsense2 as rs
    except ImportError as err:
        if "libusb" in str(err):
            raise RealSenseUnavailableError(
                f"pyrealsense2 is installed but cannot load libusb ({err}): install it, "
                "e.g. `sudo apt-get install libusb-1.0-0`"
            ) from err
        raise RealSenseUnavailableError(
            f"pyrealsense2 is not installed ({err}): `pip install 'cmnav[realsense]'` "
            "(wheels exist for x86_64, and for aarch64 on Python 3.10 and 3.12 only)"
        ) from err
    return rs


class DeviceClock:
    """Maps device timestamps (ms) onto time.monotonic_ns().

    Global/system time domains are host wall-clock milliseconds: shift by the current
    wall-to-monotonic offset.  A hardware clock has an unknown offset: use the smallest observed
    (arrival - device time), i.e. assume the fastest frame seen so far arrived with no delay.
    """

    def __init__(self) -> None:
        self._hw_offset_ns: int | None = None

    def to_monotonic_ns(self, device_ms: float, wall_clock_domain: bool, arrival_monotonic_ns: int) -> int:
        device_ns = int(device_ms * 1e6)
        if wall_clock_domain:
            return device_ns - time.time_ns() + time.monotonic_ns()
        offset = arrival_monotonic_ns - device_ns
        if self._hw_offset_ns is None or offset < self._hw_offset_ns:
            self._hw_offset_ns = offset
        return device_ns + self._hw_offset_ns


class RealSenseSource:
    """``CameraSource`` for a D455.  ``rs`` may be given (tests pass a recorded-frames double)."""

    def __init__(self, config: RealSenseConfig = RealSenseConfig(), rs: Any = None) -> None:
        self.config = config
        self._rs = rs
        self._pipeline: Any = None
        self._align: Any = None
        self._depth_scale_m: float = 0.0
        self._clock = DeviceClock()
        self.frames_dropped = 0

    @property
    def depth_scale_m(self) -> float:
        return self._depth_scale_m

    async def start(self) -> None:
        await asyncio.get_running_loop().run_in_executor(None, self._start_blocking)

    def _start_blocking(self) -> None:
        rs = self._rs if self._rs is not None else import_pyrealsense2()
        self._rs = rs
        ctx = rs.context()
        devices = ctx.query_devices()
        if len(devices) == 0:
            raise RealSenseUnavailableError(
                "no RealSense device found: is the D455 plugged in (USB 3 port and cable) and does this "
                "user have access to it (udev rules from librealsense, group plugdev)?"
            )
        cfg = rs.config()
        if self.config.serial:
            cfg.enable_device(self.config.serial)
        w, h, fps = self.config.width_px, self.config.height_px, self.config.fps
        cfg.enable_stream(rs.stream.depth, w, h, rs.format.z16, fps)
        cfg.enable_stream(rs.stream.color, w, h, rs.format.bgr8, fps)
        pipeline = rs.pipeline(ctx)
        try:
            profile = pipeline.start(cfg)
        except RuntimeError as err:
            raise RealSenseUnavailableError(
                f"the RealSense pipeline did not start ({err}): check that no other process uses the "
                f"camera and that it supports depth z16 + color bgr8 at {w}x{h}@{fps}"
            ) from err
        depth_sensor = profile.get_device().first_depth_sensor()
        self._depth_scale_m = float(depth_sensor.get_depth_scale())
        if depth_sensor.supports(rs.option.emitter_enabled):
            depth_sensor.set_option(rs.option.emitter_enabled, 1.0 if self.config.emitter_enabled else 0.0)
        elif not self.config.emitter_enabled:
            log.warning("this RealSense has no emitter option; the IR projector stays as it is")
        self._align = rs.align(rs.stream.color)
        self._pipeline = pipeline
        log.info("RealSense started: %dx%d@%d, depth scale %.6f m, emitter %s",
                 w, h, fps, self._depth_scale_m, "on" if self.config.emitter_enabled else "off")  # fmt: skip

    def _next_blocking(self) -> Frame | None:
        rs = self._rs
        ok, frames = self._pipeline.try_wait_for_frames(self.config.frame_timeout_ms)
        arrival_ns = time.monotonic_ns()
        if not ok:
            return None
        aligned = self._align.process(frames)
        depth_frame, color_frame = aligned.get_depth_frame(), aligned.get_color_frame()
        if not depth_frame or not color_frame:
            self.frames_dropped += 1
            return None
        depth_m = np.asanyarray(depth_frame.get_data()).astype(np.float32) * np.float32(self._depth_scale_m)
        gray_u8 = gray_from_bgr(np.asanyarray(color_frame.get_data()))
        domain = depth_frame.get_frame_timestamp_domain()
        wall_clock = domain in (rs.timestamp_domain.global_time, rs.timestamp_domain.system_time)
        device_ms = float(depth_frame.get_timestamp())
        return Frame(
            t_capture_ns=self._clock.to_monotonic_ns(device_ms, wall_clock, arrival_ns),
            depth_m=depth_m,
            gray_u8=gray_u8,
            seq=int(depth_frame.get_frame_number()),
            meta={"device_timestamp_ms": device_ms, "timestamp_domain": str(domain),
                  "emitter_enabled": self.config.emitter_enabled},
            t_received_ns=time.monotonic_ns(),  # aligned and converted: the runtime has it now
        )  # fmt: skip

    async def frames(self) -> AsyncIterator[Frame]:
        """Frames as they arrive; a timed-out wait yields nothing (the watchdog sees the gap)."""
        if self._pipeline is None:
            raise RuntimeError("RealSenseSource.frames() before start()")
        loop = asyncio.get_running_loop()
        while True:
            frame = await loop.run_in_executor(None, self._next_blocking)
            if frame is not None:
                yield frame

    async def close(self) -> None:
        if self._pipeline is not None:
            pipeline, self._pipeline = self._pipeline, None
            await in_daemon_thread("realsense-stop", pipeline.stop)  # a wedged USB stop must not block exit
