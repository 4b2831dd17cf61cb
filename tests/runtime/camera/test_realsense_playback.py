"""RealSense recordings through the live camera's code path: files written by librealsense's own
recorder from sim-rendered frames (``realsense_recording``), played back by librealsense's
playback device through :class:`RealSenseSource`, and the frames that come out checked against
the frames that went in."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from runtime.camera.realsense import RealSenseSource, RecordingError
from tests.runtime.camera.realsense_recording import DEPTH_UNITS_M, RenderedFrames, depth_z16, recording_suffix, render_walk, write_recording

rs = pytest.importorskip(
    "pyrealsense2",
    reason="pyrealsense2 cannot be imported here: it needs `pip install 'cmnav[realsense]'` and the libusb-1.0 system "
    "library (apt-get install libusb-1.0-0)",
    exc_type=ImportError,  # not installed, or installed without the libusb-1.0 it loads at import
)

N_FRAMES = 30  # 2 s at 15 Hz
FINE_UNITS_M = 0.0005  # not the D455's default: the units must come from the file


@pytest.fixture(scope="module")
def rendered() -> RenderedFrames:
    return render_walk(N_FRAMES)


@pytest.fixture(scope="module")
def recordings(rendered, tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("recordings")
    suffix = recording_suffix(rs)
    return {
        "infrared": write_recording(tmp / f"infrared{suffix}", rendered, depth_units_m=FINE_UNITS_M, gray_stream="infrared",
                                    emitter_enabled=False),  # fmt: skip
        "color": write_recording(tmp / f"color{suffix}", rendered, gray_stream="color"),
    }


def _play(path: Path, real_time: bool) -> tuple[RealSenseSource, list]:
    source = RealSenseSource(recording=path, real_time=real_time)

    async def run():
        await source.start()
        frames = [frame async for frame in source.frames()]  # ends with the recording
        await source.close()
        return frames

    return source, asyncio.run(run())


def test_every_recorded_frame_comes_out_as_it_went_in(recordings, rendered):
    """Infrared: depth is in the left imager's frame, no alignment; read as fast as played."""
    source, frames = _play(recordings["infrared"], real_time=False)
    assert source.ended and source.depth_scale_m == pytest.approx(FINE_UNITS_M, rel=1e-6)
    assert [f.seq for f in frames] == list(range(N_FRAMES))
    for frame in frames:
        expected_m = depth_z16(rendered.depth_m[frame.seq], FINE_UNITS_M) * np.float32(source.depth_scale_m)
        np.testing.assert_array_equal(frame.depth_m, expected_m)  # the z16 steps, in the recorded units
        valid = rendered.depth_m[frame.seq] > 0
        assert np.abs(frame.depth_m - rendered.depth_m[frame.seq])[valid].max() <= FINE_UNITS_M / 2 + 1e-6
        np.testing.assert_array_equal(frame.gray_u8, rendered.gray_u8[frame.seq])
        assert frame.meta["emitter_enabled"] is False and frame.meta["recording"] == str(recordings["infrared"])
    assert all(b.t_capture_ns > a.t_capture_ns for a, b in zip(frames, frames[1:]))


def test_a_color_recording_plays_in_real_time_with_depth_aligned_to_it(recordings, rendered):
    """Color rgb8 as realsense-viewer records it: gray by the contract's luma weights, depth aligned
    to color by librealsense, capture times at the recording's 15 Hz spacing."""
    source, frames = _play(recordings["color"], real_time=True)
    seqs = [f.seq for f in frames]
    assert source.ended and 0 < len(frames) <= N_FRAMES and seqs == sorted(set(seqs)), seqs
    assert source.depth_scale_m == pytest.approx(DEPTH_UNITS_M, rel=1e-6)
    for frame in frames:
        np.testing.assert_array_equal(frame.gray_u8, rendered.gray_u8[frame.seq])
        truth_m = rendered.depth_m[frame.seq]
        aligned = (frame.depth_m > 0) & (truth_m > 0)
        # align leaves holes (0) where pixel footprints round apart, and at depth edges a pixel
        # takes its neighbour's depth: each aligned pixel is within the units' precision of the
        # truth at itself or at one of its 8 neighbours, most at itself.
        assert aligned.mean() > 0.95
        error_m = np.abs(frame.depth_m - truth_m)
        padded = np.pad(truth_m, 1, mode="edge")
        h, w = truth_m.shape
        nearest_m = np.min([np.abs(frame.depth_m - padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w])
                            for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)  # fmt: skip
        precision_m = DEPTH_UNITS_M / 2 + 1e-6
        assert nearest_m[aligned].max() <= precision_m
        assert np.mean(error_m[aligned] <= precision_m) > 0.98
    device_ms = np.array([f.meta["device_timestamp_ms"] for f in frames])
    capture_ms = np.array([f.t_capture_ns for f in frames]) / 1e6
    np.testing.assert_allclose(np.diff(device_ms) / (1e3 / 15), np.diff(seqs), atol=0.01)  # recorded 15 Hz stamps
    assert np.all(np.diff(capture_ms) > 0)


def test_recordings_the_policy_cannot_fly_on_are_refused_with_the_fix(rendered, tmp_path):
    fast = write_recording(tmp_path / f"fast{recording_suffix(rs)}", RenderedFrames(rendered.depth_m[:3], rendered.gray_u8[:3]), fps=30)
    with pytest.raises(RecordingError, match=r"recorded at depth 30 / color 30 fps .*the camera rate, 15 Hz; record"):
        asyncio.run(RealSenseSource(recording=fast).start())
    junk = tmp_path / "junk.bag"
    junk.write_text("not a recording")
    with pytest.raises(RecordingError, match="librealsense cannot play .*junk.bag"):
        asyncio.run(RealSenseSource(recording=junk).start())
    with pytest.raises(RecordingError, match="no such file"):
        asyncio.run(RealSenseSource(recording=tmp_path / "missing.db3").start())
