"""A degraded MAVLink link: a UDP proxy on 127.0.0.1 between the vehicle and the companion.

The vehicle sends to ``proxy.port`` (the SITL vehicle's ``--mavlink-port``); the proxy forwards to
the runtime's port (MAVSDK ``udpin://127.0.0.1:PORT``) and sends the runtime's replies back to
wherever the vehicle last sent from, so a restarted vehicle is picked up at once.  Each datagram
meets the script's :class:`~sim.linkfault.script.Impairment` for its direction at that moment.

One thread does everything (select, then a heap of delayed datagrams); the proxy stops by itself
after ``lifetime_s`` (a test that forgets it cannot leave it running), or on :meth:`close`.
"""

from __future__ import annotations

import heapq
import logging
import random
import select
import socket
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Sequence

from .script import TO_RUNTIME, TO_VEHICLE, Impairment, ScriptClock

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
MAX_DATAGRAM_BYTES = 65535
POLL_S = 0.01


@dataclass
class LinkStats:
    """Per direction (``to_runtime`` / ``to_vehicle``): datagrams in, sent (copies included),
    lost (blackout or drop), held back to reorder, duplicated; and when datagrams were lost to a
    blackout (time.monotonic, s: the first and the last)."""

    received: Counter = field(default_factory=Counter)
    sent: Counter = field(default_factory=Counter)
    lost: Counter = field(default_factory=Counter)
    duplicated: Counter = field(default_factory=Counter)
    overtaken: Counter = field(default_factory=Counter)  # sent after a datagram that arrived later
    blackout_first_s: dict = field(default_factory=dict)
    blackout_last_s: dict = field(default_factory=dict)


class UdpLinkProxy:
    """vehicle <-> proxy <-> runtime over loopback UDP, degraded as ``impairments`` say."""

    def __init__(
        self,
        runtime_port: int,
        impairments: Sequence[Impairment] = (),
        seed: int = 0,
        lifetime_s: float = 120.0,
        start_when: Callable[[], bool] | None = None,
        ground_port: int | None = None,
    ) -> None:
        """``runtime_port``: where the companion listens (127.0.0.1).  The first impairment that
        applies to a datagram decides its fate; none = passed at once.  ``ground_port``: a ground
        station's (or scripted pilot's) port on 127.0.0.1, linked to the vehicle unimpaired, as
        mavlink-router links a second endpoint."""
        if not 0 < runtime_port < 65536:
            raise ValueError(f"runtime_port {runtime_port} is not a UDP port (1..65535)")
        self.impairments = tuple(impairments)
        self.clock = ScriptClock(start_when)
        self.stats = LinkStats()
        self._rng = random.Random(seed)
        self._runtime_dest = (LOOPBACK, runtime_port)
        self._vehicle_side = _bound_udp()
        self._runtime_side = _bound_udp()
        self._ground_side = _bound_udp() if ground_port is not None else None
        self._ground_dest = None if ground_port is None else (LOOPBACK, ground_port)
        self._vehicle_addr: tuple[str, int] | None = None
        self._queue: list[tuple[float, int, str, int, bytes]] = []  # (release_s, order, direction, arrival, data)
        self._order = 0
        self._last_sent_arrival = {TO_RUNTIME: -1, TO_VEHICLE: -1}
        self._deadline_s = time.monotonic() + lifetime_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="udp-link-proxy", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        """The vehicle sends here (its ``--mavlink-port``)."""
        return int(self._vehicle_side.getsockname()[1])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        for sock in (self._vehicle_side, self._runtime_side, self._ground_side):
            if sock is not None:
                sock.close()

    def __enter__(self) -> "UdpLinkProxy":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- the thread ------------------------------------------------------------------------

    def _run(self) -> None:
        sockets = [s for s in (self._vehicle_side, self._runtime_side, self._ground_side) if s is not None]
        arrival = 0
        while not self._stop.is_set() and time.monotonic() < self._deadline_s:
            now = time.monotonic()
            wait_s = POLL_S if not self._queue else min(POLL_S, max(0.0, self._queue[0][0] - now))
            readable, _, _ = select.select(sockets, [], [], wait_s)
            for sock in readable:
                try:
                    data, addr = sock.recvfrom(MAX_DATAGRAM_BYTES)
                except (BlockingIOError, ConnectionRefusedError):
                    continue  # ICMP from an earlier send to a port nobody listened on yet
                if sock is self._ground_side:
                    self._send_clean(self._vehicle_side, data, self._vehicle_addr)
                    continue
                if sock is self._vehicle_side:
                    self._vehicle_addr = addr
                    self._send_clean(self._ground_side, data, self._ground_dest)
                    direction = TO_RUNTIME
                else:
                    direction = TO_VEHICLE
                arrival += 1
                self._admit(direction, arrival, data)
            self._release_due(time.monotonic())
        if not self._stop.is_set():
            log.info("link proxy on %s:%d ended its lifetime", LOOPBACK, self.port)

    def _admit(self, direction: str, arrival: int, data: bytes) -> None:
        now = time.monotonic()
        self.stats.received[direction] += 1
        t_s = self.clock.now_s()
        impairment = None if t_s is None else next((i for i in self.impairments if i.applies(t_s, direction)), None)
        delays = [0.0] if impairment is None else impairment.fate(self._rng)
        if not delays:
            self.stats.lost[direction] += 1
            if impairment is not None and impairment.blackout:
                self.stats.blackout_first_s.setdefault(direction, now)
                self.stats.blackout_last_s[direction] = now
            return
        if len(delays) > 1:
            self.stats.duplicated[direction] += 1
        for delay_s in delays:
            self._order += 1
            heapq.heappush(self._queue, (now + delay_s, self._order, direction, arrival, data))

    def _release_due(self, now: float) -> None:
        while self._queue and self._queue[0][0] <= now:
            _, _, direction, arrival, data = heapq.heappop(self._queue)
            if arrival < self._last_sent_arrival[direction]:
                self.stats.overtaken[direction] += 1
            self._last_sent_arrival[direction] = max(arrival, self._last_sent_arrival[direction])
            try:
                if direction == TO_RUNTIME:
                    self._runtime_side.sendto(data, self._runtime_dest)
                elif self._vehicle_addr is not None:
                    self._vehicle_side.sendto(data, self._vehicle_addr)
                else:
                    continue
            except OSError:
                continue  # nobody listening yet: UDP loses such datagrams too
            self.stats.sent[direction] += 1

    @staticmethod
    def _send_clean(sock: socket.socket | None, data: bytes, dest: tuple[str, int] | None) -> None:
        if sock is None or dest is None:
            return
        try:
            sock.sendto(data, dest)
        except OSError:
            pass  # the ground station is not listening (yet): UDP loses it


def _bound_udp() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    sock.bind((LOOPBACK, 0))
    sock.setblocking(False)
    return sock
