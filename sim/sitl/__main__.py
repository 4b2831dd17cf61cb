"""``python -m sim.sitl``: run one SITL vehicle until SIGTERM / SIGINT (see sim/sitl/__init__)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from runtime.faults.catalogue import FaultSite, parse_injection

from .camera_server import CameraPortError
from .camera_feed import DEPTH_MODES
from .estimate import ESTIMATES
from .vehicle import DYNAMICS, SitlConfig, SitlVehicle, start_world_process

log = logging.getLogger("sim.sitl")


def parse_args(argv: list[str] | None = None) -> SitlConfig:
    parser = argparse.ArgumentParser(
        prog="python -m sim.sitl",
        description="A PX4-like quadrotor in a simulated room: MAVLink 2 over UDP to 127.0.0.1:MAVLINK_PORT "
        "(MAVSDK: udpin://127.0.0.1:MAVLINK_PORT), camera frames over TCP 127.0.0.1:CAMERA_PORT. "
        "Writes the episode JSON once ready and the trace JSON on SIGTERM/SIGINT.",
    )
    parser.add_argument("--mavlink-port", type=int, required=True, help="UDP port the MAVLink client listens on")
    parser.add_argument("--camera-port", type=int, help="TCP port to serve camera frames on (needed unless --stand-in)")
    parser.add_argument("--level", type=int, required=True, help="curriculum level = number of obstacles")
    parser.add_argument("--seed", type=int, required=True, help="world seed")
    parser.add_argument("--episode-json", type=Path, required=True, help="where to write the episode description")
    parser.add_argument("--trace", type=Path, required=True, help="where to write the ground-truth trace at exit")
    parser.add_argument("--physics-hz", type=float, default=100.0, help="physics and MAVLink loop rate (default 100)")
    parser.add_argument("--camera-hz", type=float, default=15.0, help="camera frame rate (default 15)")
    parser.add_argument("--inject", action="append", default=[], metavar="KIND@SECONDS",
                        help="inject a fault SECONDS after this vehicle first enters OFFBOARD (repeatable; kinds: "
                        "camera-stall, camera-garbage, camera-blackout, telemetry-loss, pilot-takeover, offboard-refused@0, "
                        "vehicle-stuck)")  # fmt: skip
    parser.add_argument("--degrade", default="none", choices=DEPTH_MODES,
                        help="depth of the served frames: rendered (none), with a D455's losses without its projector "
                        "(projector-off), or the simulated D455's stereo depth, projector on or off (sim.sensor)")  # fmt: skip
    parser.add_argument("--status-json", type=Path, help="keep the mode log here, rewritten at every mode change")
    parser.add_argument("--stand-in", action="store_true",
                        help="stand in for an external autopilot (PX4 SIH) in tests of the world follower: no camera "
                        "server, no room to hit (only the floor)")  # fmt: skip
    parser.add_argument("--pose-port", type=int,
                        help="a second MAVLink link to 127.0.0.1:POSE_PORT with its own streams (as PX4's GCS link to "
                        "14550), for the world follower (python -m sim.follower)")  # fmt: skip
    parser.add_argument("--heading-deg", type=float, default=SitlConfig.heading_deg,
                        help="heading at spawn, degrees counter-clockwise from the room's +x (default 0: facing the goal "
                        "side; 90 = north, where PX4 SIH starts)")  # fmt: skip
    parser.add_argument("--boot-time-scale", type=float, default=SitlConfig.boot_time_scale,
                        help="replay PX4 v1.16's recorded start-up (STANDBY at 4.25 s, pre-arm checks passed at 5.27 s) "
                        f"at this fraction of its times: 1 as PX4, 0 ready at once (default {SitlConfig.boot_time_scale})")
    parser.add_argument("--dynamics", choices=sorted(DYNAMICS), default=SitlConfig.dynamics,
                        help="the velocity response: px4 (PX4 v1.16 SIH as identified: delays, ~0.8 of a commanded "
                        "speed, creep after a stop) or ideal (the batched training sim's vehicle) (default px4)")
    parser.add_argument("--estimate", choices=ESTIMATES, default=SitlConfig.estimate,
                        help="what the autopilot knows of its state: exact (the truth) or px4 (PX4 SIH's EKF2 as measured: "
                        "biased, drifting; reported over MAVLink and flown, so the vehicle slides by its velocity error; "
                        "the camera sees the truth) (default exact)")  # fmt: skip
    args = parser.parse_args(argv)
    try:
        injections = tuple(parse_injection(text, [FaultSite.VEHICLE]) for text in args.inject)
        config = SitlConfig(
            args.mavlink_port, args.camera_port, args.level, args.seed, args.episode_json, args.trace,
            args.physics_hz, args.camera_hz, injections, args.status_json, args.degrade, args.stand_in, args.pose_port,
            args.heading_deg, args.boot_time_scale, args.dynamics, args.estimate,
        )  # fmt: skip
        config.validate()
    except ValueError as err:  # InjectionError is one
        parser.error(str(err))
    return config


def main(argv: list[str] | None = None) -> int:
    config = parse_args(argv)
    stop = start_world_process()
    try:
        vehicle = SitlVehicle(config)
    except CameraPortError as err:
        log.error("%s", err)
        return 2
    vehicle.run(stop)
    return 0


if __name__ == "__main__":
    sys.exit(main())
