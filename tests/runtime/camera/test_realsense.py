"""RealSense source: through the CameraSource contract with a recorded-frames double of
pyrealsense2, and with the real pyrealsense2 and no device attached."""

import asyncio
import builtins
import time
from enum import Enum
from types import SimpleNamespace

import numpy as np
import pytest

from runtime.camera import CameraSource
from runtime.camera.realsense import RealSenseSource, RealSenseUnavailableError, import_pyrealsense2
from runtime.config import RealSenseConfig
from runtime.contract import preprocess_depth, preprocess_gray

DEPTH_SCALE_M = 0.001


class _Enum(Enum):
    depth = "depth"
    color = "color"
    z16 = "z16"
    bgr8 = "bgr8"
    emitter_enabled = "emitter_enabled"
    global_time = "global_time"
    system_time = "system_time"
    hardware_clock = "hardware_clock"


class _Frame:
    def __init__(self, data, number, timestamp_ms, domain):
        self._data, self._number, self._ts, self._domain = data, number, timestamp_ms, domain

    def __bool__(self):
        return True

    def get_data(self):
        return self._data

    def get_frame_number(self):
        return self._number

    def get_timestamp(self):
        return self._ts

    def get_frame_timestamp_domain(self):
        return self._domain


class FakeRealSense:
    """Just the pyrealsense2 surface RealSenseSource uses, replaying recorded frames."""

    stream = SimpleNamespace(depth=_Enum.depth, color=_Enum.color)
    format = SimpleNamespace(z16=_Enum.z16, bgr8=_Enum.bgr8)
    option = SimpleNamespace(emitter_enabled=_Enum.emitter_enabled)
    timestamp_domain = SimpleNamespace(
        global_time=_Enum.global_time, system_time=_Enum.system_time, hardware_clock=_Enum.hardware_clock
    )

    def __init__(self, recorded, devices=1, domain=_Enum.global_time):
        self.recorded = list(recorded)  # (depth_u16, bgr_u8)
        self.devices = devices
        self.domain = domain
        self.streams = []
        self.options = {}
        self.align_target = None
        self.stopped = False
        fake = self

        class context:
            def query_devices(self):
                return [object()] * fake.devices

        class config:
            def enable_stream(self, stream, w, h, fmt, fps):
                fake.streams.append((stream, w, h, fmt, fps))

            def enable_device(self, serial):
                fake.serial = serial

        class _Sensor:
            def get_depth_scale(self):
                return DEPTH_SCALE_M

            def supports(self, option):
                return option is _Enum.emitter_enabled

            def set_option(self, option, value):
                fake.options[option] = value

        class pipeline:
            def __init__(self, ctx):
                self.n = 0

            def start(self, cfg):
                return SimpleNamespace(get_device=lambda: SimpleNamespace(first_depth_sensor=_Sensor))

            def try_wait_for_frames(self, timeout_ms):
                if self.n >= len(fake.recorded):
                    time.sleep(timeout_ms / 1e3)
                    return False, None
                depth, bgr = fake.recorded[self.n]
                self.n += 1
                ts = time.time() * 1e3 - 30.0  # captured 30 ms ago, host wall clock in ms
                return True, SimpleNamespace(
                    depth=_Frame(depth, self.n, ts, fake.domain), color=_Frame(bgr, self.n, ts, fake.domain)
                )

            def stop(self):
                fake.stopped = True

        class align:
            def __init__(self, target):
                fake.align_target = target

            def process(self, frames):
                return SimpleNamespace(get_depth_frame=lambda: frames.depth, get_color_frame=lambda: frames.color)

        self.context, self.config, self.pipeline, self.align = context, config, pipeline, align


def _recording(n=3):
    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        depth = rng.integers(0, 12000, size=(480, 848), dtype=np.uint16)
        depth[:100] = 0
        out.append((depth, rng.integers(0, 256, size=(480, 848, 3), dtype=np.uint8)))
    return out


async def _take(source, n):
    await source.start()
    frames = []
    async for frame in source.frames():
        frames.append(frame)
        if len(frames) == n:
            break
    await source.close()
    return frames


def test_recorded_frames_through_the_camera_contract():
    recorded = _recording()
    fake = FakeRealSense(recorded)
    source = RealSenseSource(RealSenseConfig(emitter_enabled=False), rs=fake)
    assert isinstance(source, CameraSource)
    t0 = time.monotonic_ns()
    frames = asyncio.run(_take(source, 3))
    assert (_Enum.depth, 848, 480, _Enum.z16, 15) in fake.streams
    assert (_Enum.color, 848, 480, _Enum.bgr8, 15) in fake.streams
    assert fake.align_target is _Enum.color  # depth aligned to color
    assert fake.options[_Enum.emitter_enabled] == 0.0  # projector off
    assert fake.stopped and source.depth_scale_m == DEPTH_SCALE_M
    for frame, (depth_u16, bgr) in zip(frames, recorded):
        assert frame.depth_m.dtype == np.float32 and frame.gray_u8.dtype == np.uint8
        np.testing.assert_allclose(frame.depth_m, depth_u16 * DEPTH_SCALE_M, rtol=1e-6)
        assert np.all(frame.depth_m[:100] == 0.0)  # z16 zero = invalid stays 0
        assert frame.gray_u8.shape == (480, 848)
        # device time (30 ms before the call) mapped onto the monotonic clock
        assert t0 - 200_000_000 < frame.t_capture_ns < time.monotonic_ns()
        assert preprocess_depth(frame.depth_m).shape == preprocess_gray(frame.gray_u8).shape == (224, 224)


def test_hardware_clock_offset_is_the_smallest_seen():
    fake = FakeRealSense(_recording(2), domain=_Enum.hardware_clock)
    frames = asyncio.run(_take(RealSenseSource(rs=fake), 2))
    assert frames[1].t_capture_ns >= frames[0].t_capture_ns
    assert frames[0].meta["timestamp_domain"].endswith("hardware_clock")


def test_no_device_says_what_to_plug_in():
    with pytest.raises(RealSenseUnavailableError, match="no RealSense device found: is the D455 plugged in"):
        asyncio.run(RealSenseSource(rs=FakeRealSense([], devices=0)).start())


def test_real_pyrealsense2_without_a_device():
    try:
        import pyrealsense2  # noqa: F401
    except ImportError as err:  # not installed, or installed without the libusb-1.0 it loads at import
        pytest.skip(f"pyrealsense2 cannot be imported here ({err}): it needs `pip install 'cmnav[realsense]'` and the "
                    "libusb-1.0 system library (apt-get install libusb-1.0-0), through which it talks to the D455 over USB")  # fmt: skip
    with pytest.raises(RealSenseUnavailableError, match="no RealSense device found"):
        asyncio.run(RealSenseSource().start())


@pytest.mark.parametrize(
    "message, advice",
    [("libusb-1.0.so.0: cannot open shared object file", "apt-get install libusb-1.0-0"),
     ("No module named 'pyrealsense2'", "pip install 'cmnav\\[realsense\\]'")],
)  # fmt: skip
def test_import_failures_say_what_to_install(monkeypatch, message, advice):
    real_import = builtins.__import__

    def failing_import(name, *args, **kwargs):
        if name == "pyrealsense2":
            raise ImportError(message)
        return real_import(name, *args, **kwargs)

    monkeypatch.delitem(__import__("sys").modules, "pyrealsense2", raising=False)
    monkeypatch.setattr(builtins, "__import__", failing_import)
    with pytest.raises(RealSenseUnavailableError, match=advice):
        import_pyrealsense2()
