"""Latest-value holders: how the runtime's asyncio tasks hand data to each other.

A slot keeps only the newest value with the time it was put (``time.monotonic_ns``) and a
sequence number.  A slow reader skips values, it never makes anything queue up.  Slots belong to
one event loop; put and read them from that loop's thread.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from typing import Callable, Generic, TypeVar

from .service.shutdown import wait_within

T = TypeVar("T")


@dataclass(frozen=True)
class Stamped(Generic[T]):
    """A value with the time it was put (ns, CLOCK_MONOTONIC) and its sequence number (1, 2, ...)."""

    value: T
    t_ns: int
    seq: int


class LatestSlot(Generic[T]):
    """Holds the latest value only; readers wait for one newer than the last they saw."""

    def __init__(self, name: str, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self.name = name
        self._clock_ns = clock_ns
        self._latest: Stamped[T] | None = None
        self._changed = asyncio.Event()

    def put(self, value: T, t_ns: int | None = None) -> Stamped[T]:
        """Replace the value; ``t_ns`` defaults to now.  Wakes every waiting reader."""
        seq = 1 if self._latest is None else self._latest.seq + 1
        self._latest = Stamped(value, self._clock_ns() if t_ns is None else t_ns, seq)
        self._changed.set()
        self._changed = asyncio.Event()
        return self._latest

    def latest(self) -> Stamped[T] | None:
        """The newest value, or None if nothing was put yet."""
        return self._latest

    def age_ns(self, now_ns: int | None = None) -> int | None:
        """Nanoseconds since the newest value was put, or None if nothing was put yet."""
        if self._latest is None:
            return None
        return (self._clock_ns() if now_ns is None else now_ns) - self._latest.t_ns

    async def wait_newer(self, after_seq: int, timeout_s: float | None = None) -> Stamped[T]:
        """The newest value whose seq is greater than ``after_seq``, waiting for it if needed.

        Raises ``asyncio.TimeoutError`` when none comes within ``timeout_s`` seconds.
        """
        await wait_within(self._wait_newer(after_seq), timeout_s)
        assert self._latest is not None
        return self._latest

    async def _wait_newer(self, after_seq: int) -> None:
        while self._latest is None or self._latest.seq <= after_seq:
            await self._changed.wait()
