"""The SITL camera link: a TCP server on 127.0.0.1 that pushes the newest frame to one client.

Wire format: ``runtime.camera.sim_wire``.  One client at a time: a new connection replaces the
old one (a runtime that reconnects after a hiccup must not be locked out by its own stale
socket).  Newest frame only: while a send is in progress, newer frames replace the waiting one,
and the socket's send buffer is kept to about one frame, so a slow client gets fresh frames at a
lower rate instead of a growing backlog.
"""

from __future__ import annotations

import logging
import socket
import threading
from dataclasses import dataclass

from runtime.camera.frame import Frame
from runtime.camera.sim_wire import encode_frame

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
POLL_S = 0.2


class CameraPortError(OSError):
    """The camera port could not be opened."""


@dataclass(frozen=True)
class ServedFrame:
    """Record of one frame delivered to a client: its capture time (time.monotonic_ns) and
    the fraction of invalid depth pixels it carried."""

    t_capture_ns: int
    invalid_depth_frac: float


class FrameServer:
    """Accepts clients on 127.0.0.1:port and streams :class:`Frame` s to the current one."""

    def __init__(self, port: int) -> None:
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind((LOOPBACK, port))
        except OSError as err:
            self._listener.close()
            raise CameraPortError(
                f"cannot listen on camera port {LOOPBACK}:{port} ({err}); pick a free port with --camera-port"
            ) from err
        self._listener.listen(1)
        self._listener.settimeout(POLL_S)
        self._cond = threading.Condition()
        self._latest: tuple[int, bytes, Frame] | None = None
        self._client: socket.socket | None = None
        self._closed = False
        self._served: list[ServedFrame] = []
        self._threads: list[threading.Thread] = []
        self._accept_thread = threading.Thread(target=self._accept_loop, name="camera-accept", daemon=True)

    @property
    def port(self) -> int:
        return int(self._listener.getsockname()[1])

    def start(self) -> None:
        self._accept_thread.start()
        log.info("camera server listening on tcp %s:%d", LOOPBACK, self.port)

    def publish(self, frame: Frame) -> None:
        """Make ``frame`` the newest; the client's sender picks it up (older unsent ones are dropped)."""
        data = encode_frame(frame)
        with self._cond:
            self._latest = (frame.seq, data, frame)
            self._cond.notify_all()

    def served(self) -> list[ServedFrame]:
        """Frames delivered so far, in order."""
        with self._cond:
            return list(self._served)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            client, self._client = self._client, None
            self._cond.notify_all()
        if client is not None:
            _shutdown(client)
        for thread in [self._accept_thread, *self._threads]:
            if thread.is_alive():
                thread.join(timeout=2.0)
        self._listener.close()

    # ---- threads --------------------------------------------------------------------------

    def _accept_loop(self) -> None:
        while True:
            with self._cond:
                if self._closed:
                    return
            try:
                conn, addr = self._listener.accept()
            except TimeoutError:
                continue
            except OSError as err:
                if not self._closed:
                    log.error("camera server stopped accepting: %s", err)
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._cond:
                frame_bytes = len(self._latest[1]) if self._latest else 0
                old, self._client = self._client, conn
            if frame_bytes:
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, frame_bytes)
            if old is not None:
                log.info("camera client %s:%d replaces the previous one", *addr)
                _shutdown(old)
            else:
                log.info("camera client %s:%d connected", *addr)
            sender = threading.Thread(target=self._send_loop, args=(conn,), name="camera-send", daemon=True)
            self._threads = [t for t in self._threads if t.is_alive()] + [sender]
            sender.start()

    def _send_loop(self, conn: socket.socket) -> None:
        last_seq = -1
        while True:
            with self._cond:
                while not self._closed and self._client is conn and (self._latest is None or self._latest[0] == last_seq):
                    self._cond.wait(POLL_S)
                if self._closed or self._client is not conn:
                    break
                seq, data, frame = self._latest
            try:
                conn.sendall(data)
            except OSError as err:
                log.info("camera client gone (%s)", err)
                break
            last_seq = seq
            with self._cond:
                self._served.append(ServedFrame(frame.t_capture_ns, float(frame.meta.get("invalid_depth_frac", 0.0))))
        with self._cond:
            if self._client is conn:
                self._client = None
        conn.close()


def _shutdown(conn: socket.socket) -> None:
    """Unblock a sender stuck in sendall; it closes the socket itself."""
    try:
        conn.shutdown(socket.SHUT_RDWR)
    except OSError as err:
        log.debug("camera client already disconnected (%s)", err)

