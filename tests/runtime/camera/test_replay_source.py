"""The `replay` camera source: a flight log's frames through the CameraSource protocol."""

import asyncio
import time

import numpy as np
import pytest

from runtime.camera import CameraSource, Frame
from runtime.camera.replay_source import ReplayCameraSource
from runtime.config import RecorderConfig
from runtime.log.reader import ReplayError
from runtime.log.recorder import Recorder

PERIOD_NS = 66_666_667


def _frame(seq: int, t_ns: int) -> Frame:
    depth = np.full((120, 212), 0.1 * seq, np.float32)
    depth[0, 0] = np.nan  # invalid pixels survive
    return Frame(t_ns, depth, np.full((120, 212), seq, np.uint8), seq)


@pytest.fixture
def log_with_frames(tmp_path):
    path = tmp_path / "frames.mcap"
    recorder = Recorder(path, RecorderConfig(flush_period_s=0.2))
    t0 = time.monotonic_ns() - 10 * PERIOD_NS
    for seq in range(1, 9):
        recorder.log_frame(_frame(seq, t0 + seq * PERIOD_NS))
    recorder.close()
    return path


async def _collect(source: ReplayCameraSource, n: int | None = None, pause_after_first_s: float = 0.0) -> list[Frame]:
    await source.start()
    frames = []
    try:
        async for frame in source.frames():
            frames.append(frame)
            if len(frames) == 1 and pause_after_first_s:
                await asyncio.sleep(pause_after_first_s)  # a consumer that falls behind
            if n is not None and len(frames) == n:
                break
    finally:
        await source.close()
    return frames


def test_plays_every_frame_in_order_with_the_recorded_spacing(log_with_frames):
    source = ReplayCameraSource(log_with_frames)
    assert isinstance(source, CameraSource)
    frames = asyncio.run(_collect(source))
    assert [f.seq for f in frames] == list(range(1, 9)) and source.frames_skipped == 0
    for k, frame in enumerate(frames, start=1):
        expected = _frame(k, 0)
        np.testing.assert_array_equal(frame.depth_m, expected.depth_m)
        np.testing.assert_array_equal(frame.gray_u8, expected.gray_u8)
    # Capture times keep the recorded spacing, on this host's monotonic clock.
    assert np.diff([f.t_capture_ns for f in frames]).tolist() == [PERIOD_NS] * 7
    assert np.diff([f.meta["recorded_t_capture_ns"] for f in frames]).tolist() == [PERIOD_NS] * 7


def test_a_late_consumer_skips_frames_instead_of_queueing(log_with_frames):
    source = ReplayCameraSource(log_with_frames)
    frames = asyncio.run(_collect(source, pause_after_first_s=0.4))
    assert source.frames_skipped >= 3
    assert len(frames) + source.frames_skipped == 8


def test_a_log_without_frames_is_refused_at_start(tmp_path):
    path = tmp_path / "empty.mcap"
    recorder = Recorder(path, RecorderConfig(flush_period_s=0.2))
    recorder.log_watchdog(time.monotonic_ns(), {"event": "start"})
    recorder.close()
    with pytest.raises(ReplayError, match="lacks the channel.*/camera/depth, /camera/gray"):
        asyncio.run(ReplayCameraSource(path).start())


def test_not_a_log_is_refused_at_once(tmp_path):
    path = tmp_path / "x.mcap"
    path.write_text("hello")
    with pytest.raises(ReplayError, match="not an MCAP file"):
        ReplayCameraSource(path)
