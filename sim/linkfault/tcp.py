"""A degraded camera link: a TCP proxy on 127.0.0.1 between the SITL camera server and the
runtime's ``sim`` camera source, frame-aware (``runtime.camera.sim_wire``).

The runtime connects to ``proxy.port``; for each connection the proxy connects to the camera
server (``upstream_port``, settable while running: a restarted vehicle serves on a new port) and
forwards whole frames, applying the script's :class:`~sim.linkfault.script.StreamFault` s, each
once, at the first frame at or after its time.  Its upstream receive buffer is about one frame,
as a USB camera's is, so a stall makes the server skip frames instead of queueing them.

The proxy stops by itself after ``lifetime_s``, or on :meth:`close`.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

from runtime.camera.sim_wire import HEADER, FrameDecodeError, decode_header, payload_size

from .script import DROP_FRAMES, PARTIAL_FRAME, RECONNECT, STALL, ScriptClock, StreamFault

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
POLL_S = 0.1
UPSTREAM_RCVBUF_BYTES = 64 * 1024


class _LinkClosed(Exception):
    """The proxy is stopping, or one side of the connection went away."""


@dataclass
class StreamStats:
    """Connections accepted, frames forwarded / dropped, and each fault as applied:
    ``(kind, time.monotonic s)``."""

    connections: int = 0
    frames_forwarded: int = 0
    frames_dropped: int = 0
    applied: list[tuple[str, float]] = field(default_factory=list)


class TcpLinkProxy:
    """runtime -> proxy -> camera server, with scripted partial frames, lost frames, stalls and
    reconnects."""

    def __init__(
        self,
        upstream_port: int,
        faults: Sequence[StreamFault] = (),
        lifetime_s: float = 120.0,
        start_when: Callable[[], bool] | None = None,
    ) -> None:
        self.upstream_port = upstream_port
        self.clock = ScriptClock(start_when)
        self.stats = StreamStats()
        self._pending = sorted(faults, key=lambda f: f.at_s)
        self._drop_left = 0
        self._deadline_s = time.monotonic() + lifetime_s
        self._stop = threading.Event()
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind((LOOPBACK, 0))
        self._listener.listen(4)
        self._listener.settimeout(POLL_S)
        self._thread = threading.Thread(target=self._accept_loop, name="tcp-link-proxy", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        """The runtime's camera port (``camera.sim.port``)."""
        return int(self._listener.getsockname()[1])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._listener.close()

    def __enter__(self) -> "TcpLinkProxy":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _running(self) -> bool:
        return not self._stop.is_set() and time.monotonic() < self._deadline_s

    # ---- threads ---------------------------------------------------------------------------

    def _accept_loop(self) -> None:
        # One connection at a time, served in this thread: the camera server itself serves one.
        while self._running():
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self.stats.connections += 1
            try:
                upstream = socket.create_connection((LOOPBACK, self.upstream_port), timeout=2.0)
            except OSError as err:
                log.info("camera server on port %d not up (%s): closing the client", self.upstream_port, err)
                client.close()
                continue
            upstream.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UPSTREAM_RCVBUF_BYTES)
            upstream.settimeout(POLL_S)
            client.settimeout(2.0)
            try:
                self._pump(upstream, client)
            except (_LinkClosed, OSError, FrameDecodeError) as err:
                log.info("camera link proxy: connection ended (%s)", err)
            finally:
                upstream.close()
                client.close()

    def _pump(self, upstream: socket.socket, client: socket.socket) -> None:
        while True:
            header = self._read(upstream, HEADER.size)
            _, _, width, height, meta_len = decode_header(header)
            frame = header + self._read(upstream, payload_size(width, height, meta_len))
            fault = self._due()
            if fault is not None:
                self.stats.applied.append((fault.kind, time.monotonic()))
                if fault.kind == DROP_FRAMES:
                    self._drop_left = fault.count
                elif fault.kind == STALL:
                    self._sleep(fault.duration_s)
                    continue  # the frame read before the stall is as old as the stall: gone with it
                elif fault.kind == PARTIAL_FRAME:
                    client.sendall(frame[: len(frame) // 2])
                    continue
                elif fault.kind == RECONNECT:
                    return
            if self._drop_left > 0:
                self._drop_left -= 1
                self.stats.frames_dropped += 1
                continue
            client.sendall(frame)
            self.stats.frames_forwarded += 1

    def _due(self) -> StreamFault | None:
        t_s = self.clock.now_s()
        if t_s is None or not self._pending or self._pending[0].at_s > t_s:
            return None
        return self._pending.pop(0)

    def _read(self, sock: socket.socket, n: int) -> bytes:
        chunks, got = [], 0
        while got < n:
            if not self._running():
                raise _LinkClosed("proxy stopped")
            try:
                chunk = sock.recv(min(n - got, 1 << 16))
            except TimeoutError:
                continue
            if not chunk:
                raise _LinkClosed("camera server closed the connection")
            chunks.append(chunk)
            got += len(chunk)
        return b"".join(chunks)

    def _sleep(self, duration_s: float) -> None:
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            if not self._running():
                raise _LinkClosed("proxy stopped")
            time.sleep(min(0.02, max(0.0, end - time.monotonic())))
