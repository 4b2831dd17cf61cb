#!/usr/bin/env python3
"""Record PX4's ODOMETRY beside its LOCAL_POSITION_NED on the GCS link (udp 127.0.0.1:14550),
while something else flies it (e.g. scripts/px4-identify.sh, whose sequence yaws the vehicle
round): the fixture that shows in which frame PX4 v1.16 sends ODOMETRY's velocity.

    python scripts/px4-record-odometry.py --seconds 80 --every 10 -o tests/runtime/fixtures/px4_v1_16_odometry.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from pymavlink import mavutil

RATE_HZ = 10.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=80.0)
    parser.add_argument("--every", type=int, default=10, help="keep one pair in N")
    parser.add_argument("-o", "--out", type=Path, required=True)
    args = parser.parse_args()
    link = mavutil.mavlink_connection("udpin:127.0.0.1:14550", source_system=255)
    if link.wait_heartbeat(timeout=30) is None:
        print("error: no PX4 heartbeat on udp 14550 in 30 s: is PX4 SITL running?", file=sys.stderr)
        return 2
    for msg_id in (mavutil.mavlink.MAVLINK_MSG_ID_ODOMETRY, mavutil.mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED):
        link.mav.command_long_send(link.target_system, link.target_component, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                                   0, msg_id, 1e6 / RATE_HZ, 0, 0, 0, 0, 0)  # fmt: skip
    pairs, latest_local, t0, n = [], None, time.monotonic(), 0
    while time.monotonic() - t0 < args.seconds:
        msg = link.recv_match(type=["ODOMETRY", "LOCAL_POSITION_NED"], blocking=True, timeout=0.5)
        if msg is None:
            continue
        if msg.get_type() == "LOCAL_POSITION_NED":
            latest_local = msg
            continue
        if latest_local is None or abs(latest_local.time_boot_ms * 1000 - msg.time_usec) > 30_000:
            continue
        n += 1
        if n % args.every:
            continue
        pairs.append({
            "odometry": {"time_usec": msg.time_usec, "frame_id": msg.frame_id, "child_frame_id": msg.child_frame_id,
                         "x": msg.x, "y": msg.y, "z": msg.z, "q": list(msg.q), "vx": msg.vx, "vy": msg.vy, "vz": msg.vz},
            "local_position_ned": {"time_boot_ms": latest_local.time_boot_ms, "vx": latest_local.vx, "vy": latest_local.vy,
                                   "vz": latest_local.vz},
        })  # fmt: skip
    link.close()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"px4": "v1.16.0 SITL, SIH quadrotor (airframe 10040)", "pairs": pairs}, indent=0) + "\n")
    print(f"{len(pairs)} ODOMETRY / LOCAL_POSITION_NED pairs written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
