"""Is a camera frame fit to fly on?  The flight loop asks before a frame may refresh the
camera's freshness or reach the policy: a broken driver, a corrupted buffer or a bad clock
must make the watchdog see "no valid frame" (and trip), never crash the loop or steer it.

A frame is refused when:
- depth is not a 2-D float image in metres, or gray not uint8 of the same (H, W), or a side < 2 px;
- its (H, W) differs from the stream's, fixed by the first frame accepted;
- its depth holds values no depth sensor reports: negative or infinite (the contract's
  vocabulary is metres > 0, and 0 or NaN for invalid — those pass, as degraded depth);
- its capture time is not after the previous accepted frame's, or more than
  FUTURE_TOLERANCE_NS ahead of now (CLOCK_MONOTONIC; such a stamp would look fresh for ever).
"""

from __future__ import annotations

import numpy as np

from .frame import Frame

# Sources map their device clock onto CLOCK_MONOTONIC; allow that mapping this much jitter (ns).
FUTURE_TOLERANCE_NS = 50_000_000


class FrameValidator:
    """Checks frames of one stream; remembers its (H, W) and the newest accepted capture time."""

    def __init__(self) -> None:
        self.shape: tuple[int, int] | None = None
        self._t_last_ns = 0

    def problem(self, frame: Frame, now_ns: int) -> str | None:
        """Why ``frame`` is unfit at ``now_ns`` (ns, CLOCK_MONOTONIC), or None: then it is accepted."""
        depth, gray = frame.depth_m, frame.gray_u8
        if not isinstance(depth, np.ndarray) or depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
            return f"depth is not a float (H, W) image in metres ({getattr(depth, 'dtype', type(depth))} {np.shape(depth)})"
        if not isinstance(gray, np.ndarray) or gray.dtype != np.uint8 or gray.shape != depth.shape:
            return f"gray is not uint8 of depth's shape {depth.shape} ({getattr(gray, 'dtype', type(gray))} {np.shape(gray)})"
        if min(depth.shape) < 2:
            return f"frame of {depth.shape[1]}x{depth.shape[0]} px is too small"
        if self.shape is not None and depth.shape != self.shape:
            return f"frame of {depth.shape[1]}x{depth.shape[0]} px in a {self.shape[1]}x{self.shape[0]} stream"
        bad_values = int(np.count_nonzero((depth < 0.0) | np.isinf(depth)))
        if bad_values:
            return f"{bad_values} depth pixels are negative or infinite (a depth sensor reports metres > 0, 0 or NaN)"
        if frame.t_capture_ns <= self._t_last_ns:
            return f"capture time {(frame.t_capture_ns - self._t_last_ns) / 1e6:.1f} ms after the previous frame's"
        if frame.t_capture_ns > now_ns + FUTURE_TOLERANCE_NS:
            return f"capture time {(frame.t_capture_ns - now_ns) / 1e9:.3f} s in the future"
        self.shape = depth.shape
        self._t_last_ns = frame.t_capture_ns
        return None
