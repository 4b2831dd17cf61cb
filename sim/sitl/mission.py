"""The vehicle's mission store and the MAVLink mission protocol, as PX4 serves it to a ground
station (QGroundControl) and to MAVSDK's mission_raw plugin.

- Upload (ground station -> vehicle): MISSION_COUNT, then the vehicle asks for each item with
  MISSION_REQUEST_INT (seq 0..n-1, re-asked after ``RETRY_S`` without an answer, given up after
  ``MAX_RETRIES``), MISSION_ITEM_INT answers, MISSION_ACK (ACCEPTED) closes it; the new mission
  replaces the old one only when complete.  An item out of order is answered by asking again for
  the one expected; count 0 (or MISSION_CLEAR_ALL) clears the mission.
- Download (vehicle -> ground station): MISSION_REQUEST_LIST -> MISSION_COUNT; MISSION_REQUEST_INT
  (or the old MISSION_REQUEST) seq -> MISSION_ITEM_INT; the requester's MISSION_ACK ends it.
- Current item: MISSION_SET_CURRENT or MAV_CMD_DO_SET_MISSION_CURRENT (224) sets it;
  MISSION_CURRENT (seq, total) is sent at once and then at ``CURRENT_RATE_HZ``, so every ground
  station on the link shows the progress.
- Mission types other than MISSION (geofence, rally points) are stored empty: a download of one
  answers count 0, an upload of one is acknowledged with MAV_MISSION_UNSUPPORTED.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

from pymavlink.dialects.v20 import common as mavlink

log = logging.getLogger(__name__)

RETRY_S = 0.25
MAX_RETRIES = 8
CURRENT_RATE_HZ = 2.0
MAX_ITEMS = 500

Send = Callable[[mavlink.MAVLink_message], None]


@dataclass(frozen=True)
class MissionItem:
    """One stored item, field for field as MISSION_ITEM_INT carries it (x, y: degE7 in global
    frames; z: metres)."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float


@dataclass
class _Upload:
    count: int
    partner: tuple[int, int]
    items: list[MissionItem]
    t_asked_s: float
    retries: int = 0


class MissionServer:
    """The mission side of the autopilot, on one MAVLink link (``send``)."""

    def __init__(self, send: Send, system_id: int, component_id: int) -> None:
        self._send = send
        self._ids = (system_id, component_id)
        self.items: list[MissionItem] = []
        self.current_seq = 0
        self._upload: _Upload | None = None
        self._next_current_s = 0.0

    def handle(self, msg: mavlink.MAVLink_message, t_s: float) -> bool:
        """Act on a mission message (True), or leave it to the autopilot (False)."""
        kind = msg.get_type()
        if kind == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_DO_SET_MISSION_CURRENT:
            if self._for_us(msg):
                ok = self._set_current(int(msg.param1), t_s)
                self._send(mavlink.MAVLink_command_ack_message(
                    msg.command, mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_DENIED, 0, 0,
                    msg.get_srcSystem(), msg.get_srcComponent()))  # fmt: skip
            return True
        handler = {
            "MISSION_COUNT": self._on_count, "MISSION_ITEM_INT": self._on_item, "MISSION_REQUEST_LIST": self._on_request_list,
            "MISSION_REQUEST_INT": self._on_request, "MISSION_REQUEST": self._on_request, "MISSION_SET_CURRENT": self._on_set_current,
            "MISSION_CLEAR_ALL": self._on_clear, "MISSION_ACK": self._on_ack,
        }.get(kind)  # fmt: skip
        if handler is None:
            return False
        if self._for_us(msg):
            handler(msg, t_s)
        return True

    def update(self, t_s: float) -> None:
        """Re-ask for an unanswered upload item; send MISSION_CURRENT at its rate."""
        upload = self._upload
        if upload is not None and t_s - upload.t_asked_s >= RETRY_S:
            if upload.retries >= MAX_RETRIES:
                log.warning("mission upload abandoned: item %d never came", len(upload.items))
                self._ack(upload.partner, mavlink.MAV_MISSION_OPERATION_CANCELLED)
                self._upload = None
            else:
                upload.retries += 1
                self._request_item(upload, t_s)
        if t_s >= self._next_current_s:
            self._send_current(t_s)

    # ------------------------------------------------------------------ upload

    def _on_count(self, msg: mavlink.MAVLink_message, t_s: float) -> None:
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        if getattr(msg, "mission_type", 0) != mavlink.MAV_MISSION_TYPE_MISSION:
            self._ack(partner, mavlink.MAV_MISSION_UNSUPPORTED, msg.mission_type)
            return
        if msg.count > MAX_ITEMS:
            self._ack(partner, mavlink.MAV_MISSION_NO_SPACE)
            return
        if msg.count == 0:
            self._replace([], partner, t_s)
            return
        self._upload = _Upload(count=msg.count, partner=partner, items=[], t_asked_s=t_s)
        self._request_item(self._upload, t_s)

    def _on_item(self, msg: mavlink.MAVLink_message, t_s: float) -> None:
        upload = self._upload
        if upload is None or getattr(msg, "mission_type", 0) != mavlink.MAV_MISSION_TYPE_MISSION:
            return
        if msg.seq != len(upload.items):
            self._request_item(upload, t_s)  # out of order or a repeat: ask again for the one expected
            return
        upload.items.append(MissionItem(
            seq=msg.seq, frame=msg.frame, command=msg.command, current=msg.current, autocontinue=msg.autocontinue,
            param1=msg.param1, param2=msg.param2, param3=msg.param3, param4=msg.param4, x=msg.x, y=msg.y, z=msg.z,
        ))  # fmt: skip
        upload.retries = 0
        if len(upload.items) == upload.count:
            self._upload = None
            self._replace(upload.items, upload.partner, t_s)
        else:
            self._request_item(upload, t_s)

    def _request_item(self, upload: _Upload, t_s: float) -> None:
        upload.t_asked_s = t_s
        self._send(mavlink.MAVLink_mission_request_int_message(*upload.partner, len(upload.items), mavlink.MAV_MISSION_TYPE_MISSION))

    def _replace(self, items: list[MissionItem], partner: tuple[int, int], t_s: float) -> None:
        self.items = list(items)
        self.current_seq = 0
        self._ack(partner, mavlink.MAV_MISSION_ACCEPTED)
        log.info("mission stored: %d item(s)", len(self.items))
        self._send_current(t_s)

    def _on_clear(self, msg: mavlink.MAVLink_message, t_s: float) -> None:
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        if getattr(msg, "mission_type", 0) != mavlink.MAV_MISSION_TYPE_MISSION:
            self._ack(partner, mavlink.MAV_MISSION_ACCEPTED, msg.mission_type)  # nothing stored of that type
            return
        self._replace([], partner, t_s)

    # ------------------------------------------------------------------ download

    def _on_request_list(self, msg: mavlink.MAVLink_message, t_s: float) -> None:
        mission_type = getattr(msg, "mission_type", 0)
        count = len(self.items) if mission_type == mavlink.MAV_MISSION_TYPE_MISSION else 0
        self._send(mavlink.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(), count, mission_type))

    def _on_request(self, msg: mavlink.MAVLink_message, t_s: float) -> None:
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        if getattr(msg, "mission_type", 0) != mavlink.MAV_MISSION_TYPE_MISSION or not 0 <= msg.seq < len(self.items):
            self._ack(partner, mavlink.MAV_MISSION_INVALID_SEQUENCE)
            return
        item = self.items[msg.seq]
        self._send(mavlink.MAVLink_mission_item_int_message(
            *partner, item.seq, item.frame, item.command, int(item.seq == self.current_seq), item.autocontinue,
            item.param1, item.param2, item.param3, item.param4, item.x, item.y, item.z, mavlink.MAV_MISSION_TYPE_MISSION,
        ))  # fmt: skip

    def _on_ack(self, msg: mavlink.MAVLink_message, t_s: float) -> None:
        """The end of a download, or a ground station cancelling our upload."""
        upload = self._upload
        if upload is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == upload.partner and msg.type != mavlink.MAV_MISSION_ACCEPTED:
            log.info("mission upload cancelled by the ground station (MISSION_ACK type %d)", msg.type)
            self._upload = None

    # ------------------------------------------------------------------ current item

    def _on_set_current(self, msg: mavlink.MAVLink_message, t_s: float) -> None:
        self._set_current(int(msg.seq), t_s)

    def _set_current(self, seq: int, t_s: float) -> bool:
        if not 0 <= seq < len(self.items):
            log.warning("set current mission item %d refused: the mission has %d item(s)", seq, len(self.items))
            return False
        self.current_seq = seq
        log.info("current mission item: %d of %d", seq, len(self.items))
        self._send_current(t_s)
        return True

    def _send_current(self, t_s: float) -> None:
        self._next_current_s = t_s + 1.0 / CURRENT_RATE_HZ
        state = mavlink.MISSION_STATE_NO_MISSION if not self.items else mavlink.MISSION_STATE_ACTIVE
        self._send(mavlink.MAVLink_mission_current_message(self.current_seq, len(self.items), state, 0))

    # ------------------------------------------------------------------ helpers

    def _for_us(self, msg: mavlink.MAVLink_message) -> bool:
        system, component = self._ids
        return getattr(msg, "target_system", 0) in (0, system) and getattr(msg, "target_component", 0) in (0, component)

    def _ack(self, partner: tuple[int, int], result: int, mission_type: int = mavlink.MAV_MISSION_TYPE_MISSION) -> None:
        self._send(mavlink.MAVLink_mission_ack_message(*partner, result, mission_type))
