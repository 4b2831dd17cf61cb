"""systemd notification protocol (sd_notify) without libsystemd: READY, WATCHDOG, STATUS, STOPPING.

Under ``Type=notify`` with ``WatchdogSec=``, systemd sets ``NOTIFY_SOCKET`` and ``WATCHDOG_USEC``;
the flight loop calls :meth:`SystemdNotifier.loop_alive` from its control step, so a stalled loop
stops the pings and systemd restarts the service.  Outside systemd every call is a no-op.
"""

from __future__ import annotations

import logging
import os
import socket
import time

log = logging.getLogger(__name__)


class SystemdNotifier:
    def __init__(self, environ: dict[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self._address = env.get("NOTIFY_SOCKET") or None
        if self._address and self._address.startswith("@"):
            self._address = "\0" + self._address[1:]  # abstract namespace socket
        watchdog_usec = int(env.get("WATCHDOG_USEC", "0") or 0)
        # Ping at half the watchdog period, as sd_watchdog_enabled(3) advises.
        self.ping_interval_s = watchdog_usec / 2e6 if watchdog_usec > 0 else None
        self._last_ping_s = float("-inf")
        self._socket: socket.socket | None = None
        if self._address:
            self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self._socket is not None

    def _send(self, message: str) -> None:
        if self._socket is None:
            return
        try:
            self._socket.sendto(message.encode(), self._address)
        except OSError as err:
            log.warning("sd_notify(%r) failed: %s", message, err)

    def ready(self, status: str = "") -> None:
        self._send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> None:
        self._send(f"STATUS={text}")

    def loop_alive(self, now_s: float | None = None) -> None:
        """Called by the flight loop on every healthy iteration; pings at most every half period."""
        if self.ping_interval_s is None:
            return
        now_s = time.monotonic() if now_s is None else now_s
        if now_s - self._last_ping_s >= self.ping_interval_s:
            self._last_ping_s = now_s
            self._send("WATCHDOG=1")

    def stopping(self) -> None:
        self._send("STOPPING=1")

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None
