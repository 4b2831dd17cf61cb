"""The ``replay`` camera source: a flight log's camera frames, at the pace they were recorded.

For bench runs without a camera (the runtime against the SITL vehicle or a real autopilot on the
bench, fed the images of an earlier flight).  Frames keep their recorded spacing: each is due at
(start of playback + its recorded offset) on this host's CLOCK_MONOTONIC and carries that time as
``t_capture_ns``; a frame whose slot has passed by more than one control period when the
consumer asks is skipped, never queued.  The log is read front to back in a worker thread, so a
log cut short by a killed process plays up to its last complete chunk.  At the end of the log the
frames stop (the flight loop's watchdog then sees stale frames).
"""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path
from typing import AsyncIterator, Iterator

from ..contract import CONTROL_PERIOD_S
from ..log.reader import FlightLogReader, LoggedFrame, LoggedStep, ReplayError
from ..log.topics import FRAME_TOPICS
from .frame import Frame

log = logging.getLogger(__name__)

_LATE_NS = int(CONTROL_PERIOD_S * 1e9)


class ReplayCameraSource:
    """A :class:`runtime.camera.CameraSource` playing back a flight log's frames."""

    def __init__(self, path: str | Path) -> None:
        """``path``: an MCAP flight log written by cmnav; :class:`runtime.log.reader.ReplayError`
        if it is not one (raised here for a non-MCAP file, by :meth:`start` for the rest)."""
        self._reader = FlightLogReader(path)
        self._records: Iterator[LoggedFrame | LoggedStep] | None = None
        self._first: LoggedFrame | None = None
        self._reading: asyncio.Future | None = None
        self.frames_played = 0
        self.frames_skipped = 0

    async def start(self) -> None:
        """Open the log and read up to its first frame; :class:`ReplayError` if it has none."""
        self._records = self._reader.records(FRAME_TOPICS)
        self._first = await self._next()
        if self._first is None:
            self._reader.check_topics(FRAME_TOPICS, "the replay camera needs the recorded frames")
            raise ReplayError(f"{self._reader.path} holds no complete camera frame to replay")
        log.info("replaying camera frames of %s", self._reader.path)

    async def frames(self) -> AsyncIterator[Frame]:
        """The log's frames at their recorded pace, late ones skipped, until the log ends."""
        if self._first is None:
            raise RuntimeError("ReplayCameraSource.frames() before start()")
        t0_recorded_ns = self._first.t_capture_ns
        t0_ns = time.monotonic_ns()
        logged: LoggedFrame | None = self._first
        while logged is not None:
            due_ns = t0_ns + (logged.t_capture_ns - t0_recorded_ns)
            now_ns = time.monotonic_ns()
            if now_ns - due_ns > _LATE_NS:
                self.frames_skipped += 1
            else:
                if due_ns > now_ns:
                    await asyncio.sleep((due_ns - now_ns) / 1e9)
                self.frames_played += 1
                yield Frame(
                    t_capture_ns=due_ns, depth_m=logged.depth_m, gray_u8=logged.gray_u8, seq=self.frames_played,
                    meta={"replay_log": str(self._reader.path), "recorded_t_capture_ns": logged.t_capture_ns},
                )  # fmt: skip
            logged = await self._next()
        log.info("end of the replayed log %s: %d frames played, %d skipped as late", self._reader.path,
                 self.frames_played, self.frames_skipped)  # fmt: skip

    async def close(self) -> None:
        """Stop reading and close the log file."""
        records, self._records = self._records, None
        if self._reading is not None:
            await asyncio.wait([self._reading])  # a generator cannot be closed while a thread runs it
        if records is not None:
            records.close()

    async def _next(self) -> LoggedFrame | None:
        """The next frame from the log (read in a worker thread), or None at its end."""
        records = self._records
        if records is None:
            return None

        def read() -> LoggedFrame | None:
            for item in records:
                if isinstance(item, LoggedFrame):
                    return item
            return None

        self._reading = asyncio.get_running_loop().run_in_executor(None, read)
        try:
            return await asyncio.shield(self._reading)
        finally:
            if self._reading.done():
                self._reading = None
