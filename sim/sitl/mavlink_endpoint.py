"""The vehicle's MAVLink link: one UDP socket on 127.0.0.1 that sends to the companion
computer's port (as PX4 does to 14540) and receives its replies, MAVLink 2, as system 1
component 1 (the autopilot).

Untrusted bytes never raise: every datagram is parsed on its own (a garbage datagram cannot
desynchronise the next one), and what is not a valid message is counted and dropped.
"""

from __future__ import annotations

import logging
import socket

from pymavlink.dialects.v20 import common as mavlink

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
SYSTEM_ID = 1
COMPONENT_ID = mavlink.MAV_COMP_ID_AUTOPILOT1
MAX_DATAGRAM_BYTES = 65535
MAX_DATAGRAMS_PER_POLL = 256
# Room for bursts (a parameter download, a flood of junk) between two polls of the loop.
RECEIVE_BUFFER_BYTES = 1 << 20


class MavlinkEndpoint:
    """UDP MAVLink 2 endpoint: ``send`` to 127.0.0.1:gcs_port, ``receive`` what arrives."""

    def __init__(self, gcs_port: int) -> None:
        if not 0 < gcs_port < 65536:
            raise ValueError(f"MAVLink port {gcs_port} is not a valid UDP port (1..65535)")
        self._dest = (LOOPBACK, gcs_port)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
        self._sock.bind((LOOPBACK, 0))
        self._sock.setblocking(False)
        # Packs with our ids and sequence numbers; we send the bytes ourselves (no pymavlink file).
        self._mav = mavlink.MAVLink(None, srcSystem=SYSTEM_ID, srcComponent=COMPONENT_ID)
        self.bad_datagrams = 0
        self.send_errors = 0
        # A dead transmit line (fault injection): send() drops everything, receive() still works.
        self.tx_silent = False
        self.dropped_silent = 0
        log.info("MAVLink endpoint on udp %s:%d -> %s:%d", LOOPBACK, self.local_port, *self._dest)

    @property
    def local_port(self) -> int:
        return int(self._sock.getsockname()[1])

    def fileno(self) -> int:
        return self._sock.fileno()

    def send(self, msg: mavlink.MAVLink_message) -> None:
        """Pack with our system/component id and sequence number and send it (dropped while
        ``tx_silent``)."""
        data = msg.pack(self._mav)
        self._mav.seq = (self._mav.seq + 1) % 256
        if self.tx_silent:
            self.dropped_silent += 1
            return
        try:
            self._sock.sendto(data, self._dest)
        except OSError as err:
            # Nobody listening yet (or the client went away): PX4 keeps sending regardless.
            self.send_errors += 1
            if self.send_errors in (1, 10, 100) or self.send_errors % 1000 == 0:
                log.warning("MAVLink send to %s:%d failed (%s); %d failures so far", *self._dest, err, self.send_errors)

    def receive(self) -> list[mavlink.MAVLink_message]:
        """All valid messages waiting on the socket (never blocks)."""
        messages: list[mavlink.MAVLink_message] = []
        for _ in range(MAX_DATAGRAMS_PER_POLL):
            try:
                data, _addr = self._sock.recvfrom(MAX_DATAGRAM_BYTES)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:
                # ICMP port-unreachable from an earlier send (the client is not up yet).
                continue
            messages.extend(self._parse(data))
        return messages

    def _parse(self, data: bytes) -> list[mavlink.MAVLink_message]:
        good, problems = parse_datagram(data)
        for problem in problems:
            self._count_bad(problem)
        return good

    def _count_bad(self, what: str) -> None:
        self.bad_datagrams += 1
        if self.bad_datagrams in (1, 10, 100) or self.bad_datagrams % 1000 == 0:
            log.warning("MAVLink: %s; %d bad so far, ignored", what, self.bad_datagrams)

    def close(self) -> None:
        self._sock.close()


def parse_datagram(data: bytes) -> tuple[list[mavlink.MAVLink_message], list[str]]:
    """The valid MAVLink messages in one datagram (parsed on its own, so garbage cannot
    desynchronise the next), and a description of each bad part.  Never raises."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    try:
        parsed = parser.parse_buffer(data) or []
    except mavlink.MAVError as err:
        return [], [f"unparseable datagram of {len(data)} bytes ({err})"]
    good, problems = [], []
    for msg in parsed:
        if isinstance(msg, mavlink.MAVLink_bad_data):
            problems.append(f"bad data in a {len(data)}-byte datagram ({msg.reason})")
        elif isinstance(msg, mavlink.MAVLink_unknown):
            log.debug("ignoring message id %d not in the common dialect", msg.get_msgId())
        else:
            good.append(msg)
    return good, problems
