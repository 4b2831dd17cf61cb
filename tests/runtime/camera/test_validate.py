"""Which camera frames the flight loop may fly on (runtime.camera.validate)."""

import numpy as np
import pytest

from runtime.camera import Frame
from runtime.camera.validate import FUTURE_TOLERANCE_NS, FrameValidator

MS = 1_000_000
NOW = 50_000 * MS
H, W = 120, 212


def _frame(t_ns=NOW, depth=None, gray=None) -> Frame:
    depth = np.full((H, W), 2.5, np.float32) if depth is None else depth
    gray = np.full(depth.shape, 100, np.uint8) if gray is None else gray
    return Frame(t_ns, depth, gray)


def test_good_frames_pass_including_degraded_depth():
    validator = FrameValidator()
    depth = np.full((H, W), 2.5, np.float32)
    depth[:10] = 0.0
    depth[10:20] = np.nan  # the contract's two ways of saying "invalid"
    assert validator.problem(_frame(NOW - 10 * MS, depth), NOW) is None
    assert validator.problem(_frame(NOW, np.zeros((H, W), np.float32)), NOW) is None  # blackout is degraded, not garbage
    assert validator.shape == (H, W)


@pytest.mark.parametrize(
    "depth, gray, why",
    [
        (np.full((H, W), -1.0, np.float32), None, "negative or infinite"),
        (np.full((H, W), np.inf, np.float32), None, "negative or infinite"),
        (np.full((H, W), 2, np.uint16), None, "not a float"),
        (np.full((H, W, 1), 2.0, np.float32), None, "not a float"),
        (None, np.full((H, W), 0.5, np.float32), "gray is not uint8"),
        (None, np.full((H, W - 1), 9, np.uint8), "gray is not uint8"),
        (np.full((1, W), 2.0, np.float32), None, "too small"),
    ],
)
def test_garbage_is_named(depth, gray, why):
    assert why in FrameValidator().problem(_frame(depth=depth, gray=gray), NOW)


def test_stream_shape_is_fixed_by_the_first_good_frame():
    validator = FrameValidator()
    assert validator.problem(_frame(NOW - 20 * MS), NOW) is None
    problem = validator.problem(_frame(NOW, np.full((60, 70), 2.0, np.float32)), NOW)
    assert problem == f"frame of 70x60 px in a {W}x{H} stream"


def test_capture_times_must_be_new_and_not_from_the_future():
    validator = FrameValidator()
    assert validator.problem(_frame(NOW), NOW) is None
    assert "after the previous frame's" in validator.problem(_frame(NOW), NOW + 66 * MS)
    assert validator.problem(_frame(NOW + 66 * MS + FUTURE_TOLERANCE_NS), NOW + 66 * MS) is None  # clock jitter
    assert "s in the future" in validator.problem(_frame(NOW + 10_000 * MS), NOW + 100 * MS)
    assert validator.problem(_frame(NOW + 133 * MS), NOW + 133 * MS) is None  # the rejected one changed nothing
