"""What a degraded link does, and when: the script a link proxy plays (``sim.linkfault``).

Times are seconds on the script's clock, which starts when ``start_when()`` first returns true
(polled by the proxy, e.g. "the vehicle reports OFFBOARD"), or at once without it.  Everything
random comes from one seeded generator per proxy, so a scripted test sees the same losses on
every run that offers the same traffic.
"""

from __future__ import annotations

import math
import random
import threading
import time
from dataclasses import dataclass
from typing import Callable

TO_RUNTIME = "to_runtime"  # vehicle -> companion: telemetry, ACKs, camera frames
TO_VEHICLE = "to_vehicle"  # companion -> vehicle: setpoints, commands
BOTH = "both"
DIRECTIONS = (TO_RUNTIME, TO_VEHICLE, BOTH)


class LinkScriptError(ValueError):
    """A link script value out of range; the message names the field and the allowed range."""


def _check(ok: bool, what: str, value: object, allowed: str) -> None:
    if not ok:
        raise LinkScriptError(f"{what}={value!r} is invalid: must be {allowed}")


@dataclass(frozen=True)
class Impairment:
    """A datagram link's behaviour from ``start_s`` to ``end_s`` (script clock, s) in ``direction``.

    Each datagram is, in this order: lost in a ``blackout``; dropped with probability
    ``drop_frac``; delayed by ``delay_ms`` ± ``jitter_ms`` (uniform; jitter alone reorders
    datagrams closer together than itself); held back a further ``reorder_ms`` with probability
    ``reorder_frac`` (later datagrams overtake it); sent a second time, ``duplicate_lag_ms`` after
    the first copy, with probability ``duplicate_frac``.
    """

    start_s: float = 0.0
    end_s: float = math.inf
    direction: str = BOTH
    blackout: bool = False
    drop_frac: float = 0.0
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    reorder_frac: float = 0.0
    reorder_ms: float = 40.0
    duplicate_frac: float = 0.0
    duplicate_lag_ms: float = 30.0

    def __post_init__(self) -> None:
        _check(0.0 <= self.start_s < self.end_s, "start_s/end_s", (self.start_s, self.end_s), "0 <= start_s < end_s")
        _check(self.direction in DIRECTIONS, "direction", self.direction, f"one of {DIRECTIONS}")
        for name in ("drop_frac", "reorder_frac", "duplicate_frac"):
            _check(0.0 <= getattr(self, name) <= 1.0, name, getattr(self, name), "a fraction in [0, 1]")
        for name in ("delay_ms", "jitter_ms", "reorder_ms", "duplicate_lag_ms"):
            _check(0.0 <= getattr(self, name) <= 10_000.0, name, getattr(self, name), "in [0, 10000] ms")

    def applies(self, t_s: float, direction: str) -> bool:
        return self.start_s <= t_s < self.end_s and self.direction in (BOTH, direction)

    def fate(self, rng: random.Random) -> list[float]:
        """Send delays (s) for one datagram: [] = lost, two = duplicated."""
        if self.blackout or rng.random() < self.drop_frac:
            return []
        delay_ms = max(0.0, self.delay_ms + rng.uniform(-self.jitter_ms, self.jitter_ms))
        if rng.random() < self.reorder_frac:
            delay_ms += self.reorder_ms
        delays = [delay_ms / 1000.0]
        if rng.random() < self.duplicate_frac:
            delays.append((delay_ms + self.duplicate_lag_ms) / 1000.0)
        return delays


# What a byte-stream (camera) fault does at its time; see StreamFault.
PARTIAL_FRAME = "partial_frame"
DROP_FRAMES = "drop_frames"
STALL = "stall"
RECONNECT = "reconnect"
STREAM_FAULTS = (PARTIAL_FRAME, DROP_FRAMES, STALL, RECONNECT)


@dataclass(frozen=True)
class StreamFault:
    """One camera-link fault at ``at_s`` (script clock, s), acting on the next whole frame:

    - ``partial_frame``: only the first half of the frame is sent, the stream goes on with the
      next frame (the reader loses the framing: what it reads next is not a frame);
    - ``drop_frames``: ``count`` frames are not sent (a USB camera that lost them);
    - ``stall``: nothing is sent for ``duration_s`` (the proxy stops reading, so the sender's
      socket fills and it skips frames, as a stalled USB transfer does), then the link goes on;
    - ``reconnect``: the connection is closed (the reader reconnects; the proxy accepts it again).
    """

    at_s: float
    kind: str
    count: int = 1
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        _check(self.at_s >= 0.0, "at_s", self.at_s, ">= 0 s")
        _check(self.kind in STREAM_FAULTS, "kind", self.kind, f"one of {STREAM_FAULTS}")
        _check(1 <= self.count <= 1000, "count", self.count, "in [1, 1000] frames")
        _check(0.0 <= self.duration_s <= 60.0, "duration_s", self.duration_s, "in [0, 60] s")


class ScriptClock:
    """The script's time: None until ``start_when()`` is first true (or from creation without
    it); ``poll()`` checks the predicate at most every ``poll_period_s``."""

    def __init__(self, start_when: Callable[[], bool] | None = None, poll_period_s: float = 0.05) -> None:
        self._start_when = start_when
        self._poll_period_s = poll_period_s
        self._lock = threading.Lock()
        self._t0_s: float | None = None if start_when is not None else time.monotonic()
        self._next_poll_s = 0.0

    @property
    def t0_s(self) -> float | None:
        """When the script started (time.monotonic, s), None before."""
        return self._t0_s

    def now_s(self) -> float | None:
        """Seconds since the script started, None before."""
        self.poll()
        t0 = self._t0_s
        return None if t0 is None else time.monotonic() - t0

    def poll(self) -> None:
        if self._t0_s is not None or self._start_when is None:
            return
        now = time.monotonic()
        with self._lock:
            if self._t0_s is not None or now < self._next_poll_s:
                return
            self._next_poll_s = now + self._poll_period_s
            if self._start_when():
                self._t0_s = time.monotonic()
