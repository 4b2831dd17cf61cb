"""The ``sim`` camera source: frames from the SITL vehicle over TCP on 127.0.0.1.

The SITL vehicle listens on a TCP port and pushes every rendered frame in the
``runtime.camera.sim_wire`` format.  This source connects, reads continuously and keeps only the
latest frame (a slow consumer skips frames, nothing queues).  It reconnects whenever the link
drops or falls silent; bytes that are not a frame are logged and counted, and the link is re-opened (a stream
that lost its framing cannot be trusted) — the source itself never dies of them.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass
from typing import AsyncIterator

from ..service.shutdown import wait_within
from ..slots import LatestSlot
from .frame import Frame
from .sim_wire import HEADER, FrameDecodeError, decode_header, decode_payload, payload_size

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"


@dataclass
class SimCameraStats:
    """Counters of the camera link since start."""

    frames: int = 0
    decode_errors: int = 0
    connects: int = 0
    disconnects: int = 0
    last_error: str = ""


class SimCameraSource:
    """A :class:`runtime.camera.CameraSource` reading the SITL vehicle's camera link."""

    def __init__(
        self, port: int, reconnect_delay_s: float = 0.2, connect_timeout_s: float = 2.0, read_timeout_s: float = 2.0
    ) -> None:
        """``port``: the SITL vehicle's camera TCP port on 127.0.0.1.  A link silent for
        ``read_timeout_s`` is taken for dead and re-opened (times in seconds)."""
        self.port = port
        self.reconnect_delay_s = reconnect_delay_s
        self.connect_timeout_s = connect_timeout_s
        self.read_timeout_s = read_timeout_s
        self.stats = SimCameraStats()
        self.latest: LatestSlot[Frame] = LatestSlot("sim_camera")
        self._reader_task: asyncio.Task | None = None

    async def start(self) -> None:
        """Start reading in the background (connecting and reconnecting as needed)."""
        if self._reader_task is None:
            self._reader_task = asyncio.create_task(self._read_forever(), name="sim_camera_reader")

    async def frames(self) -> AsyncIterator[Frame]:
        """Each newest frame once, skipping those that arrived while the consumer was busy."""
        seq = 0
        while True:
            stamped = await self.latest.wait_newer(seq)
            seq = stamped.seq
            yield stamped.value

    async def close(self) -> None:
        """Stop reading and close the link."""
        if self._reader_task is not None:
            self._reader_task.cancel()
            try:
                await self._reader_task
            except asyncio.CancelledError:
                if not self._reader_task.cancelled():
                    raise
            self._reader_task = None

    async def _read_forever(self) -> None:
        while True:
            try:
                reader, writer = await wait_within(
                    asyncio.open_connection(LOOPBACK, self.port), self.connect_timeout_s
                )
            except (OSError, asyncio.TimeoutError) as err:
                log.debug("camera link %s:%d not up (%s); retrying", LOOPBACK, self.port, err)
                await asyncio.sleep(self.reconnect_delay_s)
                continue
            self.stats.connects += 1
            frames_before = self.stats.frames
            log.info("camera link connected to %s:%d", LOOPBACK, self.port)
            try:
                await self._read_frames(reader)
            except FrameDecodeError as err:
                self.stats.decode_errors += 1
                self.stats.last_error = str(err)
                log.error("camera link: %s; reconnecting (decode errors so far: %d)", err, self.stats.decode_errors)
            except (asyncio.IncompleteReadError, ConnectionError) as err:
                self.stats.last_error = f"link dropped: {err!r}"
                log.warning("camera link to %s:%d dropped (%r); reconnecting", LOOPBACK, self.port, err)
            except asyncio.TimeoutError:
                self.stats.last_error = f"link silent for {self.read_timeout_s} s"
                log.warning("camera link to %s:%d silent for %.1f s; reconnecting", LOOPBACK, self.port, self.read_timeout_s)
            finally:
                self.stats.disconnects += 1
                writer.close()
            # A link that was delivering frames is re-opened at once: a torn frame or a dropped
            # connection then costs about one frame period, not reconnect_delay_s on top of it
            # (which alone would come close to the watchdog's stale-frame limit).  A peer that
            # fails before its first frame is retried after the delay, so it cannot spin us.
            if self.stats.frames == frames_before:
                await asyncio.sleep(self.reconnect_delay_s)

    async def _read_frames(self, reader: asyncio.StreamReader) -> None:
        while True:
            header = await wait_within(reader.readexactly(HEADER.size), self.read_timeout_s)
            seq, t_ns, width, height, meta_len = decode_header(header)
            payload = await wait_within(reader.readexactly(payload_size(width, height, meta_len)), self.read_timeout_s)
            self.latest.put(decode_payload(seq, t_ns, width, height, payload, t_received_ns=time.monotonic_ns()))
            self.stats.frames += 1
