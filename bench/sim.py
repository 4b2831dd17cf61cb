"""`cmnav bench sim`: frames/s of the fast renderer (:func:`sim.render.render`) and of the plain
reference (:func:`sim.render.render_reference`, always on the CPU) at the raw camera size, for
batch sizes x obstacle counts, on the CPU and on CUDA when present, with their ratio measured in
the same run, and how far the fast frames are from the reference's.

A cell's frames/s is its batch size over the median wall-clock time of one call (and, as
``*_best``, over the fastest call: other work on the machine skews the median), timed after a
warm-up call (which also compiles or loads the CPU kernel).  The reference is slow and renders
each env on its own, so it is timed on the first ``reference_max_envs`` envs of the batch only;
the mismatch columns compare the fast renderer's frames of those envs with the reference's.
torch, and so the CPU kernel, uses every core this process may run on.
"""

from __future__ import annotations

import logging
import math
import os
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from sim.camera import CameraModel
from sim.render import DEPTH_REL_TOLERANCE, GRAY_TOLERANCE_LEVELS, RenderOutput, render, render_reference
from sim.rotations import quat_from_euler
from sim.world import WorldBatch, make_worlds

from .device import device_name, synchronize

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimBenchConfig:
    """What `cmnav bench sim` measures, and for how long (seconds of timed calls per cell)."""

    batch_sizes: tuple[int, ...] = (1, 16, 64)
    box_counts: tuple[int, ...] = (0, 10, 26)
    fast_time_s: float = 2.0
    reference_time_s: float = 1.0
    min_calls: int = 5
    reference_max_envs: int = 4
    # Camera poses: anywhere in the room this far from the walls, tilted up to this much in roll
    # and pitch, any yaw.
    wall_margin_m: float = 0.2
    max_tilt_rad: float = 0.3
    seed: int = 0


# `--quick`: a smoke run of the whole path (seconds), not a measurement.
QUICK = SimBenchConfig(
    batch_sizes=(1, 2), box_counts=(0, 3), fast_time_s=0.0, reference_time_s=0.0, min_calls=1, reference_max_envs=1
)


@dataclass
class SimBenchCell:
    """One (device, batch size, obstacle count) measurement.  *_fps: from the median call time,
    *_fps_best: from the fastest call (what the code does when nothing else runs); ratio, ratio_best:
    fast / reference of each.  reference_envs: frames per reference call; depth_mismatch_fraction / gray_mismatch_fraction: fraction of those frames' pixels off by
    more than DEPTH_REL_TOLERANCE (relative) / GRAY_TOLERANCE_LEVELS."""

    device: str
    batch_size: int
    boxes: int
    fast_fps: float
    fast_fps_best: float
    reference_fps: float
    reference_fps_best: float
    ratio: float
    ratio_best: float
    reference_envs: int
    depth_rel_err_max: float
    depth_mismatch_fraction: float
    gray_diff_max: int
    gray_mismatch_fraction: float


def bench_scene(
    batch_size: int, boxes: int, config: SimBenchConfig
) -> tuple[WorldBatch, Tensor, Tensor]:
    """Worlds with ``boxes`` obstacles each and camera poses (cam_pos_enu_m [B, 3],
    cam_quat_enu_flu [B, 4]) drawn from ``config.seed``, on the CPU."""
    world = make_worlds(boxes, seed=config.seed, batch_size=batch_size)
    gen = torch.Generator().manual_seed(config.seed)
    margin = config.wall_margin_m
    pos = margin + torch.rand(batch_size, 3, generator=gen) * (world.room_size_m - 2.0 * margin)
    limits = torch.tensor([config.max_tilt_rad, config.max_tilt_rad, math.pi])
    angles = (torch.rand(batch_size, 3, generator=gen) * 2.0 - 1.0) * limits
    return world, pos, quat_from_euler(*angles.unbind(-1))


def run_sim_bench(config: SimBenchConfig = SimBenchConfig()) -> dict:
    """Measure every cell; returns a JSON-able dict (see :func:`format_sim_bench`)."""
    threads = len(os.sched_getaffinity(0))
    torch.set_num_threads(threads)
    load_average = os.getloadavg()[0]  # other work on the machine skews every number
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    camera = CameraModel()
    cells = []
    for batch_size in config.batch_sizes:
        for boxes in config.box_counts:
            world, pos, quat = bench_scene(batch_size, boxes, config)
            envs = min(batch_size, config.reference_max_envs)
            ref_args = (world.select(slice(0, envs)), pos[:envs], quat[:envs], camera)
            ref_median_s, ref_best_s, reference = _time_calls(
                lambda: render_reference(*ref_args), "cpu", config.reference_time_s, config.min_calls
            )
            for device in devices:
                args = (world.to(device), pos.to(device), quat.to(device), camera)
                median_s, best_s, fast = _time_calls(lambda: render(*args), device, config.fast_time_s, config.min_calls)
                fast_frames = RenderOutput(depth_m=fast.depth_m[:envs].cpu(), gray_u8=fast.gray_u8[:envs].cpu())
                cell = SimBenchCell(
                    device=device,
                    batch_size=batch_size,
                    boxes=boxes,
                    fast_fps=batch_size / median_s,
                    fast_fps_best=batch_size / best_s,
                    reference_fps=envs / ref_median_s,
                    reference_fps_best=envs / ref_best_s,
                    ratio=(batch_size / median_s) / (envs / ref_median_s),
                    ratio_best=(batch_size / best_s) / (envs / ref_best_s),
                    reference_envs=envs,
                    **_mismatch(reference, fast_frames),
                )
                log.info(
                    "%s N=%d boxes=%d: %.0f frames/s, %.1fx the reference",
                    device, batch_size, boxes, cell.fast_fps, cell.ratio,
                )  # fmt: skip
                cells.append(cell)
    return {
        "camera_px": [camera.width_px, camera.height_px],
        "threads": threads,
        "load_average_1min": load_average,
        "devices": [device_name(d) for d in devices],
        "reference_device": "cpu",
        "tolerance": {"depth_rel": DEPTH_REL_TOLERANCE, "gray_levels": GRAY_TOLERANCE_LEVELS},
        "cells": [asdict(cell) for cell in cells],
    }


def format_sim_bench(result: dict) -> str:
    """The result of :func:`run_sim_bench` as a markdown table with a one-line header."""
    width, height = result["camera_px"]
    tol = result["tolerance"]
    lines = [
        f"Renderer at {width}x{height}, {result['threads']} CPU threads (load average {result['load_average_1min']:.1f} "
        f"at the start); devices: {', '.join(result['devices'])}; reference on the CPU.  Mismatch: pixels off "
        f"by > {tol['depth_rel']:g} relative depth / > {tol['gray_levels']} gray level.",
        "",
        "| device | N | boxes | fast frames/s, median (best) | reference frames/s, median (best) "
        "| fast / reference | max depth rel err | depth mismatch | max gray diff | gray mismatch |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for c in result["cells"]:
        lines.append(
            f"| {c['device']} | {c['batch_size']} | {c['boxes']} | {c['fast_fps']:.0f} ({c['fast_fps_best']:.0f}) "
            f"| {c['reference_fps']:.1f} ({c['reference_fps_best']:.1f}) "
            f"| {c['ratio']:.0f}x ({c['ratio_best']:.0f}x) | {c['depth_rel_err_max']:.1e} | {c['depth_mismatch_fraction']:.1e} "
            f"| {c['gray_diff_max']} | {c['gray_mismatch_fraction']:.1e} |"
        )
    return "\n".join(lines)


def _time_calls(
    call: Callable[[], RenderOutput], device: str, min_time_s: float, min_calls: int
) -> tuple[float, float, RenderOutput]:
    """Median and fastest seconds per call over at least ``min_calls`` calls and ``min_time_s``
    seconds, after one warm-up call; and the last call's output."""
    out = call()
    synchronize(device)
    times = []
    start = time.perf_counter()
    while len(times) < min_calls or time.perf_counter() - start < min_time_s:
        t0 = time.perf_counter()
        out = call()
        synchronize(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), min(times), out


def _mismatch(reference: RenderOutput, fast: RenderOutput) -> dict[str, float | int]:
    rel = ((fast.depth_m.double() - reference.depth_m.double()).abs() / reference.depth_m.double()).flatten()
    gray_diff = (fast.gray_u8.int() - reference.gray_u8.int()).abs().flatten()
    return {
        "depth_rel_err_max": float(rel.max()),
        "depth_mismatch_fraction": float((rel > DEPTH_REL_TOLERANCE).double().mean()),
        "gray_diff_max": int(gray_diff.max()),
        "gray_mismatch_fraction": float((gray_diff > GRAY_TOLERANCE_LEVELS).double().mean()),
    }
