#!/usr/bin/env python3
"""Record what a PX4 SITL sends on its GCS link from start-up until it is ready to fly.

Starts PX4 (SIH quadrotor, airframe 10040) in an empty working folder, listens on udp
127.0.0.1:14550 (PX4's GCS link) with pymavlink and writes, for every HEARTBEAT, SYS_STATUS,
EXTENDED_SYS_STATE, HOME_POSITION, LOCAL_POSITION_NED and STATUSTEXT received, its time since
PX4 was started and the fields that tell readiness.  PX4 is stopped by its PID.  The JSON is the
fixture ``tests/sim/follower/fixtures/px4_v1_16_startup.json`` that the follower's readiness and
our SITL vehicle's start-up pattern are tested against.

    python scripts/px4-record-startup.py --px4-build /path/to/PX4-Autopilot/build/px4_sitl_default \
        --seconds 9 -o tests/sim/follower/fixtures/px4_v1_16_startup.json
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pymavlink import mavutil

KEPT = ("HEARTBEAT", "SYS_STATUS", "EXTENDED_SYS_STATE", "HOME_POSITION", "LOCAL_POSITION_NED", "STATUSTEXT")


def _record(msg, t_s: float) -> dict:
    kind = msg.get_type()
    record = {"t_s": round(t_s, 3), "type": kind, "src": [msg.get_srcSystem(), msg.get_srcComponent()]}
    if kind == "HEARTBEAT":
        record.update(type_=msg.type, autopilot=msg.autopilot, base_mode=msg.base_mode, custom_mode=msg.custom_mode,
                      system_status=msg.system_status)  # fmt: skip
    elif kind == "SYS_STATUS":
        record.update(present=msg.onboard_control_sensors_present, enabled=msg.onboard_control_sensors_enabled,
                      health=msg.onboard_control_sensors_health)  # fmt: skip
    elif kind == "EXTENDED_SYS_STATE":
        record.update(landed_state=msg.landed_state)
    elif kind == "HOME_POSITION":
        record.update(x=msg.x, y=msg.y, z=msg.z)
    elif kind == "LOCAL_POSITION_NED":
        record.update(x=round(msg.x, 4), y=round(msg.y, 4), z=round(msg.z, 4))
    elif kind == "STATUSTEXT":
        record.update(severity=msg.severity, text=msg.text.rstrip("\x00") if isinstance(msg.text, str) else str(msg.text))
    return record


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--px4-build", type=Path, required=True, help="PX4's build/px4_sitl_default folder")
    parser.add_argument("--seconds", type=float, default=9.0, help="how long to record after start (s)")
    parser.add_argument("--every-pose", type=int, default=25, help="keep one LOCAL_POSITION_NED in N (all other kinds are kept)")
    parser.add_argument("-o", "--out", type=Path, required=True)
    args = parser.parse_args()
    px4 = args.px4_build / "bin" / "px4"
    if not px4.is_file():
        print(f"error: no PX4 binary at {px4}: build PX4 as docs/px4-sitl.md says", file=sys.stderr)
        return 2
    link = mavutil.mavlink_connection("udpin:127.0.0.1:14550", source_system=255)
    with tempfile.TemporaryDirectory(prefix="px4-startup-") as rootfs:
        env = {**os.environ, "PX4_SYS_AUTOSTART": "10040", "PX4_SIM_MODEL": "sihsim_quadx"}
        with open(Path(rootfs) / "px4.log", "w") as px4_log:
            proc = subprocess.Popen([str(px4), "-d", str(args.px4_build / "etc")], cwd=rootfs, env=env,
                                    stdout=px4_log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)  # fmt: skip
            t0 = time.monotonic()
            records, poses = [], 0
            try:
                while (t_s := time.monotonic() - t0) < args.seconds:
                    msg = link.recv_match(blocking=True, timeout=0.1)
                    if msg is None or msg.get_type() not in KEPT:
                        continue
                    if msg.get_type() == "LOCAL_POSITION_NED":
                        poses += 1
                        if poses % args.every_pose != 1:
                            continue
                    records.append(_record(msg, t_s))
            finally:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
    link.close()
    version = "v1.16.0 SITL, SIH quadrotor (airframe 10040)"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"px4": version, "link": "GCS udp 14550", "messages": records}, indent=0) + "\n")
    print(f"{len(records)} messages in {args.seconds:.0f} s written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
