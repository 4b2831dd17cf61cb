"""Intel RealSense D455 camera source (pyrealsense2, imported lazily: optional extra).

Depth z16 and color BGR8 at 848x480, 15 Hz; depth aligned to color; depth scale read from the
device; IR emitter switchable (emitter off = the paper's degraded-depth condition).  Frames
carry the device timestamp mapped onto this host's CLOCK_MONOTONIC.

A recording (``recording=``: a ``.bag`` / ``.db3`` from realsense-viewer or ``rs.recorder``) goes
through the same path, with librealsense's playback device in place of the camera: the
recorded streams are checked (depth z16; color rgb8/bgr8/y8, or infrared y8; 15 fps; a D455 size
of the contract's aspect), depth units are the recorded depth sensor's, depth is aligned to the
gray image's stream, and the playback runs in real time (the recording's own 15 Hz pacing).
Recorded timestamps are mapped onto this host's clock by their offset (the recording's wall clock
is of another day).  The end of the file is a lost camera: :meth:`RealSenseSource.frames` ends,
and the watchdog's stale-frame rule ends the episode.
"""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path
from typing import Any, AsyncIterator

import numpy as np

from ..config import D455_MODES, RealSenseConfig
from ..contract.constants import CAMERA_RATE_HZ
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


class RecordingError(RealSenseUnavailableError):
    """A recording that cannot be flown on (not a RealSense recording, or streams the policy cannot
    use); a restart does not help.  The message names the file, the cause and how to re-record."""


# Gray image sources in a recording, in order of preference, and the formats each may have.
_GRAY_FORMATS = {"color": ("rgb8", "bgr8", "y8"), "infrared": ("y8",)}
# A D4xx computes depth in its left imager's frame (infrared 1): depth needs no alignment to it
# (librealsense's align would only add holes where its pixel footprints round apart).
_LEFT_IMAGER = 1


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
    """``CameraSource`` for a D455, or for a recording of one (``recording``: played in real time
    unless ``real_time`` is false, when each frame waits for the reader: tests that count frames).
    ``rs`` may be given (tests pass a recorded-frames double)."""

    def __init__(
        self, config: RealSenseConfig = RealSenseConfig(), rs: Any = None, recording: Path | None = None, real_time: bool = True
    ) -> None:
        self.config = config
        self._rs = rs
        self.recording = None if recording is None else Path(recording)
        self._real_time = real_time
        self._pipeline: Any = None
        self._playback: Any = None
        self._align: Any = None
        self._depth_scale_m: float = 0.0
        self._gray_stream = "color"  # which aligned frame holds the gray image: "color" or "infrared"
        self._gray_format = "bgr8"
        self._emitter_enabled: bool | None = config.emitter_enabled
        self._last_depth_number: int | None = None
        self._clock = DeviceClock()
        self.frames_dropped = 0
        self.frames_repeated = 0  # framesets whose depth frame was already yielded (a recording's syncer re-sends it)
        self.ended = False  # the recording played to its end

    @property
    def depth_scale_m(self) -> float:
        return self._depth_scale_m

    async def start(self) -> None:
        await asyncio.get_running_loop().run_in_executor(None, self._start_blocking)

    def _start_blocking(self) -> None:
        rs = self._rs if self._rs is not None else import_pyrealsense2()
        self._rs = rs
        if self.recording is not None:
            self._start_recording(rs)
            return
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

    def _start_recording(self, rs: Any) -> None:
        """The playback device on ``self.recording``, its streams checked, in real time."""
        path = self.recording
        assert path is not None
        if not path.is_file():
            raise RecordingError(f"RealSense recording {path}: no such file")
        cfg = rs.config()
        pipeline = rs.pipeline()
        try:
            cfg.enable_device_from_file(str(path), repeat_playback=False)
            # The pace is set on the resolved device before the pipeline starts it (start() keeps the
            # resolved one): a change after start comes once frames already flow.
            cfg.resolve(pipeline).get_device().as_playback().set_real_time(self._real_time)
            profile = pipeline.start(cfg)  # every recorded stream
        except RuntimeError as err:
            raise RecordingError(f"librealsense cannot play {path} ({err}): is it a RealSense recording "
                                 "(.bag / .db3 from realsense-viewer or rs.recorder) and complete?") from err  # fmt: skip
        try:
            self._playback = profile.get_device().as_playback()
            if self._playback.is_real_time() != self._real_time:  # not the resolved device after all
                self._playback.set_real_time(self._real_time)
            gray_stream, gray_index = self._check_recorded_streams(rs, profile, path)
            self._depth_scale_m = self._recorded_depth_units(rs, profile, path)
        except BaseException:
            pipeline.stop()
            raise
        self._gray_stream = gray_stream
        self._align = None if gray_stream == "infrared" else rs.align(getattr(rs.stream, gray_stream))
        self._pipeline = pipeline
        log.info("RealSense recording %s: gray from %s %d (%s, depth %s), depth units %.6f m, emitter %s, %s",
                 path, gray_stream, gray_index, self._gray_format,
                 "in its frame" if self._align is None else "aligned to it", self._depth_scale_m,
                 {True: "on", False: "off", None: "not recorded"}[self._emitter_enabled],
                 "real time" if self._real_time else "as fast as read")  # fmt: skip

    def _check_recorded_streams(self, rs: Any, profile: Any, path: Path) -> tuple[str, int]:
        """Which recorded stream gives the gray image; :class:`RecordingError` for streams the
        policy cannot fly on.  Sets the gray image's format."""
        streams = {}
        for stream in profile.get_streams():
            if not stream.is_video_stream_profile():
                continue  # the IMU's accel / gyro: recorded beside the images, not flown on
            kind = str(stream.stream_type()).rsplit(".", 1)[-1]
            video = stream.as_video_stream_profile()
            streams.setdefault(kind, []).append(
                (stream.stream_index(), str(stream.format()).rsplit(".", 1)[-1], int(stream.fps()), video.width(), video.height())
            )
        recorded = "; ".join(f"{k} {f} {w}x{h}@{fps}" for k, v in streams.items() for _, f, fps, w, h in v) or "no streams"
        fix = ("record depth z16 and color (rgb8) or infrared (y8) at 15 fps and a D455 size of aspect 848:480 "
               "(848x480, 640x360, 424x240, ...)")  # fmt: skip
        depth = [s for s in streams.get("depth", []) if s[1] == "z16"]
        if not depth:
            raise RecordingError(f"{path} has no depth z16 stream ({recorded}): {fix}")
        gray = [(kind, s) for kind, formats in _GRAY_FORMATS.items() for s in streams.get(kind, []) if s[1] in formats
                and (kind == "color" or s[0] == _LEFT_IMAGER)]  # fmt: skip
        if not gray:
            raise RecordingError(f"{path} has no gray image stream (color rgb8/bgr8/y8 or the left infrared 1, y8) ({recorded}): {fix}")
        kind, (index, fmt, fps, width, height) = gray[0]
        rate = int(CAMERA_RATE_HZ)
        if fps != rate or depth[0][2] != rate:
            raise RecordingError(f"{path} was recorded at depth {depth[0][2]} / {kind} {fps} fps ({recorded}): the policy "
                                 f"runs at the camera rate, {rate} Hz; {fix}")  # fmt: skip
        if (width, height) not in D455_MODES:
            raise RecordingError(f"{path}: {kind} {width}x{height} is not a D455 size of the contract's aspect ({recorded}): {fix}")
        self._gray_format = fmt
        return kind, index

    def _recorded_depth_units(self, rs: Any, profile: Any, path: Path) -> float:
        """Metres per z16 step, as the recorded depth sensor said; and its emitter state, if recorded."""
        try:
            sensor = profile.get_device().first_depth_sensor()
            scale_m = float(sensor.get_depth_scale())
        except RuntimeError as err:
            raise RecordingError(f"{path} does not record its depth units ({err}): record with realsense-viewer or "
                                 "rs.recorder, which save the depth sensor's options") from err  # fmt: skip
        if not 0.0 < scale_m < 1.0:
            raise RecordingError(f"{path} records depth units of {scale_m} m: a RealSense reports (0, 1) m per step")
        self._emitter_enabled = None
        if sensor.supports(rs.option.emitter_enabled):
            self._emitter_enabled = bool(sensor.get_option(rs.option.emitter_enabled))
        return scale_m

    def _gray_u8(self, data: np.ndarray) -> np.ndarray:
        """The gray image from the gray stream's frame data (the contract's luma weights for color)."""
        if self._gray_format == "bgr8":
            return gray_from_bgr(data)
        if self._gray_format == "rgb8":
            return gray_from_bgr(np.ascontiguousarray(data[..., ::-1]))
        return np.array(data, dtype=np.uint8)  # y8: gray already (a copy: the driver reuses its buffer)

    def _next_blocking(self) -> Frame | None:
        rs = self._rs
        ok, frames = self._pipeline.try_wait_for_frames(self.config.frame_timeout_ms)
        arrival_ns = time.monotonic_ns()
        if not ok:
            if self._playback is not None and self._playback.current_status() == rs.playback_status.stopped:
                self.ended = True
            return None
        aligned = frames if self._align is None else self._align.process(frames)
        depth_frame = aligned.get_depth_frame()
        gray_frame = aligned.get_color_frame() if self._gray_stream == "color" else aligned.get_infrared_frame(_LEFT_IMAGER)
        if not depth_frame or not gray_frame:
            self.frames_dropped += 1
            return None
        number = int(depth_frame.get_frame_number())
        if self._playback is not None:
            # The playback's syncer may hand a depth frame out twice (paired with the old and then
            # the new gray frame): a frame is new only with a new depth frame.
            if self._last_depth_number is not None and number <= self._last_depth_number:
                self.frames_repeated += 1
                return None
            self._last_depth_number = number
        depth_m = np.asanyarray(depth_frame.get_data()).astype(np.float32) * np.float32(self._depth_scale_m)
        gray_u8 = self._gray_u8(np.asanyarray(gray_frame.get_data()))
        domain = depth_frame.get_frame_timestamp_domain()
        # A recording's wall-clock stamps are of the day it was made: mapped by their offset.
        wall_clock = self._playback is None and domain in (rs.timestamp_domain.global_time, rs.timestamp_domain.system_time)
        device_ms = float(depth_frame.get_timestamp())
        meta = {"device_timestamp_ms": device_ms, "timestamp_domain": str(domain), "emitter_enabled": self._emitter_enabled}
        if self.recording is not None:
            meta["recording"] = str(self.recording)
        return Frame(
            t_capture_ns=self._clock.to_monotonic_ns(device_ms, wall_clock, arrival_ns),
            depth_m=depth_m,
            gray_u8=gray_u8,
            seq=number,
            meta=meta,
            t_received_ns=time.monotonic_ns(),  # aligned and converted: the runtime has it now
        )

    async def frames(self) -> AsyncIterator[Frame]:
        """Frames as they arrive; a timed-out wait yields nothing (the watchdog sees the gap).
        A recording's end ends the iteration: the camera is lost, the watchdog trips on stale frames."""
        if self._pipeline is None:
            raise RuntimeError("RealSenseSource.frames() before start()")
        loop = asyncio.get_running_loop()
        yielded = 0
        while True:
            frame = await loop.run_in_executor(None, self._next_blocking)
            if frame is not None:
                yielded += 1
                yield frame
            elif self.ended:
                log.warning("end of the RealSense recording %s after %d frames (%d repeated, %d incomplete): the camera "
                            "is lost from here (the watchdog's stale_frame trip, frame_stale_ms, ends a flight)",
                            self.recording, yielded, self.frames_repeated, self.frames_dropped)  # fmt: skip
                return

    async def close(self) -> None:
        if self._pipeline is not None:
            pipeline, self._pipeline = self._pipeline, None
            await in_daemon_thread("realsense-stop", pipeline.stop)  # a wedged USB stop must not block exit
