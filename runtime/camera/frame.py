"""What every camera source yields, and the protocol it implements (DESIGN §3)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import AsyncIterator, Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Frame:
    """One aligned depth + gray capture.

    ``t_capture_ns`` is the capture time on this host's CLOCK_MONOTONIC (``time.monotonic_ns``);
    sources whose device has its own clock map it onto that one.  ``t_received_ns`` (same clock)
    is when the source handed the frame to the runtime: received off the SITL link, or out of the
    RealSense driver with depth aligned and gray converted; the capture-to-receipt time is the
    camera's and link's latency, not the runtime's.  None where a source does not stamp it (a
    replayed log): the capture time stands in.  ``depth_m`` is float32 metres with 0 / NaN =
    invalid; ``gray_u8`` is uint8 of the same (H, W).
    """

    t_capture_ns: int
    depth_m: np.ndarray
    gray_u8: np.ndarray
    seq: int = 0
    meta: dict = field(default_factory=dict)
    t_received_ns: int | None = None

    @property
    def t_grab_ns(self) -> int:
        """When the runtime got the frame: ``t_received_ns``, else the capture time."""
        return self.t_capture_ns if self.t_received_ns is None else self.t_received_ns


@runtime_checkable
class CameraSource(Protocol):
    """An async source of frames.  A late or dropped frame is skipped, never queued."""

    async def start(self) -> None: ...

    def frames(self) -> AsyncIterator[Frame]: ...

    async def close(self) -> None: ...
