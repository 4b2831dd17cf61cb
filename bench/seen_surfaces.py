"""How much of the runtime's map of the surfaces its depth frames showed
(:class:`runtime.camera.surfaces.SeenSurfaces`: where a dry run lands, how fast it approaches its
last goal) lies where nothing is, built along a policy's own flights from the SITL camera's depth.

    python -m bench.seen_surfaces --policy models/student-field --encoder models/cmwae-pooled \\
        [--levels 10,15] [--episodes 12] [--rooms validation] [--depth stereo] [--json]

The policy flies Table II's episodes of the batched sim (``clean``, ``--rooms``' seed); along each
flight that reached the goal the SITL camera's frame (:class:`sim.sitl.camera_feed.CameraFeed`:
the simulated D455 matched at 424 x 240 and decimated to the served grid, or the rendered depth)
is added at every control step, once with the exact body pose and once through an EKF2-like
estimate (:data:`DRIFT`: a position offset random walk of ~0.2 m stationary sigma and ~1.4 deg of
attitude error, the drift a map is built through on PX4).  Per pose, over the flights: the share of
the map's cells at the flight height (+-0.3 m) farther than :data:`PHANTOM_M` from every true
surface at that height (the estimate's offset at the end taken out), the 90th percentile of the
cells' distance to the truth, the cells per map, and the time of ``add_frame`` and of the approach cap's query after it
(``free_ahead_m`` as :func:`runtime.watchdog.cap_approach` asks it, every step near the goal)."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch

from runtime.camera.surfaces import SeenSurfaces
from runtime.contract.frames import quat_from_euler
from runtime.watchdog import APPROACH_HALF_WIDTH_M, APPROACH_LOOKAHEAD_M, LANDING_WAY_HEIGHT_MARGIN_M
from sim.camera import CameraModel
from sim.collision import box_signed_distance_m
from sim.sitl.camera_feed import CameraFeed
from sim.sitl.kinematics import Kinematics
from sim.world import WorldBatch

PHANTOM_M = 0.3  # a cell farther than this from every true surface shows what is not there
BAND_M = 0.3  # the cells counted: within this of the flight height (the landing's way and the approach's band)
POSES = ("exact", "drift")
TIMED = ("add_frame_ms", "free_ahead_ms")  # the calls timed per frame, in the result's keys


@dataclass(frozen=True)
class Drift:
    """An EKF2-like pose error per control step: the position offset walks (sigma per step, per
    axis ENU) and decays (stationary sigma = step / sqrt(1 - decay^2)); roll and pitch errors
    likewise; the yaw error is white."""

    pos_step_m: tuple[float, float, float] = (0.02, 0.02, 0.01)
    pos_decay: float = 0.995  # stationary sigma 0.2 m horizontally
    tilt_step_rad: float = 0.006
    tilt_decay: float = 0.97  # stationary sigma 0.025 rad (1.4 deg)
    yaw_sigma_rad: float = 0.01


DRIFT = Drift()


def true_distance_m(world: WorldBatch, xy_m: np.ndarray, z_m: float) -> np.ndarray:
    """[N] distance (m) from the points (x, y) at height z_m to the nearest wall (horizontally) or
    box surface of the one room in ``world``."""
    points = torch.tensor(np.c_[xy_m, np.full(len(xy_m), z_m)], dtype=torch.float32)
    room = world.room_size_m[0]
    walls = torch.minimum(points[:, :2], room[:2] - points[:, :2]).amin(dim=1)
    if world.num_slots:
        boxes = box_signed_distance_m(world.select([0] * len(points)), points).amin(dim=1)
        walls = torch.minimum(walls, boxes)
    return walls.numpy()


def heading_yaw_rad(path_m: np.ndarray, t: int) -> float:
    """The yaw the flight had at step t: along its motion over the last 3 steps (0 when hovering)."""
    d = path_m[t] - path_m[max(0, t - 3)]
    return math.atan2(d[1], d[0]) if math.hypot(d[0], d[1]) > 0.05 else 0.0


def map_flight(world: WorldBatch, path_m: np.ndarray, depth: str, seed: int) -> dict:
    """Build the map along one flight with each pose of :data:`POSES`; per pose the phantom share,
    the 90th percentile distance and the cells; and the times (ms) of add_frame and of the
    approach cap's free_ahead_m after it (along the flight's heading)."""
    feed = CameraFeed(world, CameraModel(), lambda: None, lambda frame: None, 15.0, depth_mode=depth, seed=seed)
    rng = np.random.default_rng(seed)
    maps = {pose: SeenSurfaces() for pose in POSES}
    offset_m, tilt_rad, add_ms, ahead_ms = np.zeros(3), np.zeros(2), [], []
    for t in range(1, len(path_m)):
        yaw = heading_yaw_rad(path_m, t)
        quat = quat_from_euler(0.0, 0.0, yaw)
        frame = feed.render_frame(Kinematics(t_ns=0, pos_enu_m=path_m[t], vel_enu_m_s=np.zeros(3), quat_enu_flu=quat,
                                             angvel_body_flu_rad_s=np.zeros(3), on_ground=False))  # fmt: skip
        offset_m = DRIFT.pos_decay * offset_m + rng.normal(0.0, DRIFT.pos_step_m)
        tilt_rad = DRIFT.tilt_decay * tilt_rad + rng.normal(0.0, DRIFT.tilt_step_rad, 2)
        poses = {"exact": (path_m[t], quat),
                 "drift": (path_m[t] + offset_m, quat_from_euler(tilt_rad[0], tilt_rad[1], yaw + rng.normal(0.0, DRIFT.yaw_sigma_rad)))}  # fmt: skip
        for pose, (pos, q) in poses.items():
            t0 = time.perf_counter()
            maps[pose].add_frame(frame.depth_m, pos, q, 0.0)
            t1 = time.perf_counter()
            maps[pose].free_ahead_m(pos[:2], yaw, APPROACH_HALF_WIDTH_M, pos[2] + LANDING_WAY_HEIGHT_MARGIN_M,
                                    pos[2] - LANDING_WAY_HEIGHT_MARGIN_M, APPROACH_LOOKAHEAD_M)  # fmt: skip
            t2 = time.perf_counter()
            add_ms.append(1e3 * (t1 - t0))
            ahead_ms.append(1e3 * (t2 - t1))
    z_m = float(path_m[-1, 2])
    result = dict(zip(TIMED, (add_ms, ahead_ms)))
    for pose, seen in maps.items():
        shift = offset_m[:2] if pose == "drift" else np.zeros(2)
        cells = seen.cells_xy_m(z_m + BAND_M, z_m - BAND_M) - shift
        dist = true_distance_m(world, cells, z_m) if len(cells) else np.zeros(0)
        result[pose] = {"cells": len(cells), "phantom_share": float(np.mean(dist > PHANTOM_M)) if len(cells) else None,
                        "p90_distance_m": float(np.percentile(dist, 90)) if len(cells) else None}  # fmt: skip
    return result


def run(policy_dir: str, encoder_dir: str, levels: list[int], episodes: int, rooms: str, depth: str) -> dict:
    from training.cmwae.train import load_cmwae
    from training.policy.env import SUCCESS, env_encoder
    from training.policy.evaluate import ROOMS, fly_episodes
    from training.policy.network import check_trained_on, load_policy

    device = torch.device("cpu")
    policy, card = load_policy(policy_dir, device)
    check_trained_on(card, policy_dir, encoder_dir)
    cmwae, _ = load_cmwae(encoder_dir, device)
    encoder = env_encoder(cmwae.encoder, "fp32", device, seed=0)
    flights, times_ms = [], {name: [] for name in TIMED}
    for level in levels:
        for k, (outcome, path, described, _) in enumerate(fly_episodes(policy, encoder, level, "clean", episodes, episodes, device,
                                                                    seed=ROOMS[rooms])):  # fmt: skip
            if outcome != SUCCESS:
                continue
            one = map_flight(WorldBatch.from_descriptions([described]), path, depth, seed=1000 * level + k)
            for name, values in times_ms.items():
                values += one.pop(name)
            flights.append({"level": level, "episode": k, **one})
    summary = {}
    for pose in POSES:
        shares = [f[pose]["phantom_share"] for f in flights if f[pose]["phantom_share"] is not None]
        p90 = [f[pose]["p90_distance_m"] for f in flights if f[pose]["p90_distance_m"] is not None]
        summary[pose] = {"flights": len(shares), "phantom_share_median": _stat(np.median, shares),
                         "phantom_share_mean": _stat(np.mean, shares), "phantom_share_max": _stat(np.max, shares),
                         "p90_distance_m_median": _stat(np.median, p90),
                         "cells_median": _stat(np.median, [f[pose]["cells"] for f in flights])}  # fmt: skip
    return {"policy": policy_dir, "encoder": encoder_dir, "rooms": rooms, "levels": levels, "episodes": episodes, "depth": depth,
            "flights": flights, "summary": summary,
            **{name: {"median": _stat(np.median, ms), "p99": _stat(lambda v: np.percentile(v, 99), ms)} for name, ms in times_ms.items()}}  # fmt: skip


def _stat(fn, values: list) -> float | None:
    return float(fn(values)) if len(values) else None


def report(result: dict) -> str:
    lines = [f"SeenSurfaces along {result['policy']}'s flights ({result['rooms']} rooms, levels "
             f"{','.join(map(str, result['levels']))}, {result['episodes']} a level; depth: {result['depth']}):",
             f"| pose | flights | phantom cells (> {PHANTOM_M} m) median / mean / max | p90 distance m (median) | cells (median) |",
             "|---|---|---|---|---|"]  # fmt: skip
    for pose, s in result["summary"].items():
        if not s["flights"]:
            lines.append(f"| {pose} | 0 | - | - | - |")
            continue
        lines.append(f"| {pose} | {s['flights']} | {100 * s['phantom_share_median']:.1f} / {100 * s['phantom_share_mean']:.1f} / "
                     f"{100 * s['phantom_share_max']:.1f} % | {s['p90_distance_m_median']:.2f} | {s['cells_median']:.0f} |")  # fmt: skip
    for name in TIMED:
        ms = result[name]
        if ms["median"] is not None:
            lines.append(f"{name.removesuffix('_ms')}: {ms['median']:.2f} ms median, {ms['p99']:.2f} ms p99")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.seen_surfaces", description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", required=True, help="policy checkpoint that flies")
    parser.add_argument("--encoder", required=True, help="the encoder it was trained on")
    parser.add_argument("--levels", default="10,15", help="comma-separated levels (default 10,15)")
    parser.add_argument("--episodes", type=int, default=12, help="episodes a level (default 12)")
    parser.add_argument("--rooms", choices=["validation", "test"], default="validation", help="Table II's rooms (default validation)")
    parser.add_argument("--depth", choices=["stereo", "none"], default="stereo",
                        help="the SITL camera's depth: the simulated D455's (stereo) or the rendered depth (none)")  # fmt: skip
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object instead")
    args = parser.parse_args(argv)
    try:
        levels = [int(v) for v in args.levels.split(",")]
    except ValueError:
        parser.error(f"--levels {args.levels!r}: expected comma-separated integers")
    if args.episodes < 1:
        parser.error(f"--episodes {args.episodes}: expected at least 1")
    torch.set_num_threads(1)
    try:
        result = run(args.policy, args.encoder, levels, args.episodes, args.rooms, args.depth)
    except (OSError, ValueError) as err:  # a missing checkpoint, a policy trained on another encoder
        print(f"bench.seen_surfaces: {err}", file=sys.stderr)
        return 2
    print(json.dumps(result) if args.json else report(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
