"""Readiness as PX4 v1.16 reports it (issue 27), held to a recording of the real thing.

``fixtures/px4_v1_16_startup.json`` is what PX4 v1.16.0 SITL (SIH, airframe 10040) sent on its
GCS link from start-up (``scripts/px4-record-startup.py``): HEARTBEAT system_status UNINIT, then
STANDBY at 4.25 s; SYS_STATUS's pre-arm bit healthy from 5.27 s and never present nor enabled.
The follower must find it ready exactly then, and our SITL vehicle must send the same pattern, so
a stand-in test would have caught a readiness rule that waits for ever on PX4."""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from sim.follower.pose_link import PoseLink, prearm_passed

FIXTURE = Path(__file__).parent / "fixtures" / "px4_v1_16_startup.json"
PREARM = mavlink.MAV_SYS_STATUS_PREARM_CHECK
LOOPBACK = "127.0.0.1"

pytestmark = pytest.mark.timeout(120)


def _recorded() -> list[dict]:
    return json.loads(FIXTURE.read_text())["messages"]


def _message(record: dict):
    kind = record["type"]
    if kind == "HEARTBEAT":
        return mavlink.MAVLink_heartbeat_message(record["type_"], record["autopilot"], record["base_mode"],
                                                 record["custom_mode"], record["system_status"], 3)  # fmt: skip
    if kind == "SYS_STATUS":
        return mavlink.MAVLink_sys_status_message(record["present"], record["enabled"], record["health"],
                                                  0, 16200, -1, 100, 0, 0, 0, 0, 0, 0, 0, 0, 0)  # fmt: skip
    return None


def _pattern(records: list[dict]) -> list[tuple]:
    """The distinct readiness states in order: (system_status, pre-arm present, enabled, healthy),
    carried forward from the latest HEARTBEAT and SYS_STATUS."""
    status, bits, states = None, None, []
    for r in records:
        if r["type"] == "HEARTBEAT" and r["src"][1] == mavlink.MAV_COMP_ID_AUTOPILOT1:
            status = r["system_status"]
        elif r["type"] == "SYS_STATUS":
            bits = tuple(bool(r[k] & PREARM) for k in ("present", "enabled", "health"))
        if status is not None and bits is not None and (not states or states[-1] != (status, *bits)):
            states.append((status, *bits))
    return states


def test_the_recording_is_px4s_start_up():
    states = _pattern(_recorded())
    assert states == [
        (mavlink.MAV_STATE_UNINIT, False, False, False),
        (mavlink.MAV_STATE_STANDBY, False, False, False),
        (mavlink.MAV_STATE_STANDBY, False, False, True),
    ]


def test_the_follower_is_ready_when_px4_is():
    """The recorded messages through the follower's link: not ready before the pre-arm health bit,
    ready from the SYS_STATUS that carries it."""
    link = PoseLink(LOOPBACK, 0)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((LOOPBACK, 0))
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    ready_at_s = None
    try:
        for record in _recorded():
            msg = _message(record)
            if msg is None or record["src"][1] != mavlink.MAV_COMP_ID_AUTOPILOT1:
                continue
            sock.sendto(msg.pack(mav), (LOOPBACK, link.local_port))
            deadline = time.monotonic() + 2.0
            seen = link.view.system_status if record["type"] == "HEARTBEAT" else None
            while time.monotonic() < deadline:
                link.poll(time.monotonic())
                if record["type"] == "HEARTBEAT" and link.view.system_id is not None and link.view.system_status == record["system_status"]:
                    break
                if record["type"] == "SYS_STATUS" and link.view.prearm_ok == prearm_passed(record["health"]):
                    break
                time.sleep(0.002)
            del seen
            if link.view.armable and ready_at_s is None:
                ready_at_s = record["t_s"]
    finally:
        sock.close()
        link.close()
    first_healthy = min(r["t_s"] for r in _recorded() if r["type"] == "SYS_STATUS" and r["health"] & PREARM)
    assert ready_at_s == first_healthy == pytest.approx(5.27, abs=0.2)
