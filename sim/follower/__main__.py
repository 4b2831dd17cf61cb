"""``python -m sim.follower``: follow one autopilot until SIGTERM / SIGINT (see sim/follower/__init__)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from runtime.faults.catalogue import CAMERA_FAULTS, FaultSite, parse_injection
from sim.sitl.camera_server import CameraPortError
from sim.sitl.camera_feed import DEPTH_MODES
from sim.sitl.vehicle import start_world_process

from .follower import FollowerConfig, FollowerNotReadyError, WorldFollower
from .pose_link import AutopilotLinkError
from .url import AutopilotUrlError, parse_autopilot_url

log = logging.getLogger("sim.follower")


def parse_args(argv: list[str] | None = None) -> FollowerConfig:
    parser = argparse.ArgumentParser(
        prog="python -m sim.follower",
        description="The SITL camera world following an external autopilot's pose over MAVLink: camera frames over "
        "TCP 127.0.0.1:CAMERA_PORT. Writes the episode JSON once the autopilot is armable and the trace JSON on "
        "SIGTERM/SIGINT.",
    )
    parser.add_argument("--autopilot", required=True, metavar="URL",
                        help="udp://HOST:PORT where the autopilot's MAVLink arrives (PX4 SITL: udp://127.0.0.1:14550)")  # fmt: skip
    parser.add_argument("--allow-remote", action="store_true", help="accept an --autopilot host other than 127.0.0.1")
    parser.add_argument("--camera-port", type=int, required=True, help="TCP port to serve camera frames on (127.0.0.1)")
    parser.add_argument("--level", type=int, required=True, help="curriculum level = number of obstacles")
    parser.add_argument("--seed", type=int, required=True, help="world seed")
    parser.add_argument("--episode-json", type=Path, required=True, help="where to write the episode description")
    parser.add_argument("--trace", type=Path, required=True, help="where to write the ground-truth trace at exit")
    parser.add_argument("--status-json", type=Path, help="keep the autopilot's mode log here, rewritten at every change")
    parser.add_argument("--camera-hz", type=float, default=FollowerConfig.camera_hz,
                        help=f"camera frame rate (default {FollowerConfig.camera_hz:g})")
    parser.add_argument("--degrade", default=FollowerConfig.degrade, choices=DEPTH_MODES,
                        help="depth degradation of the served frames")
    parser.add_argument("--timeout-s", type=float, default=FollowerConfig.timeout_s,
                        help=f"offboard time limit the judge applies (s, default {FollowerConfig.timeout_s:g})")
    parser.add_argument("--ready-timeout-s", type=float, default=FollowerConfig.ready_timeout_s,
                        help=f"how long to wait for the autopilot (s, default {FollowerConfig.ready_timeout_s:g})")
    parser.add_argument("--inject", action="append", default=[], metavar="KIND@SECONDS",
                        help="inject a camera fault on the served frames SECONDS after the autopilot's first OFFBOARD "
                        f"(seen in its HEARTBEAT; repeatable; kinds: {', '.join(sorted(k.value for k in CAMERA_FAULTS))})")  # fmt: skip
    args = parser.parse_args(argv)
    try:
        host, port = parse_autopilot_url(args.autopilot, args.allow_remote)
        injections = tuple(parse_injection(text, [FaultSite.VEHICLE]) for text in args.inject)
        config = FollowerConfig(host, port, args.camera_port, args.level, args.seed, args.episode_json, args.trace,
                                args.status_json, args.camera_hz, args.degrade, args.timeout_s, args.ready_timeout_s,
                                injections)  # fmt: skip
        config.validate()
    except (AutopilotUrlError, ValueError) as err:  # InjectionError is a ValueError
        parser.error(str(err))
    return config


def main(argv: list[str] | None = None) -> int:
    config = parse_args(argv)
    stop = start_world_process()
    try:
        follower = WorldFollower(config)
    except (CameraPortError, AutopilotLinkError) as err:
        log.error("%s", err)
        return 2
    try:
        follower.run(stop)
    except FollowerNotReadyError as err:
        log.error("%s", err)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
