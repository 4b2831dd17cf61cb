"""`python -m bench.seen_surfaces`: the map of what the frames showed, against the room's truth."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from bench.seen_surfaces import map_flight, true_distance_m
from sim.world import WorldBatch

# A 10 x 5 x 3 m room with one 1 m cube centred at (6, 2.5, 1.5), the flight height.
ROOM = {"room_size_m": [10.0, 5.0, 3.0], "boxes": [{"center_m": [6.0, 2.5, 1.5], "half_extent_m": [0.5, 0.5, 0.5], "yaw_rad": 0.0}],
        "start_m": [1.0, 2.5, 1.5], "goal_m": [4.5, 1.0, 1.5], "texture_seed": 3}  # fmt: skip


def test_the_truth_is_the_nearest_wall_or_box_at_the_flight_height():
    world = WorldBatch.from_descriptions([ROOM])
    xy = np.array([[5.0, 2.5], [6.0, 1.2], [2.0, 0.4], [6.0, 2.5]])
    np.testing.assert_allclose(true_distance_m(world, xy, 1.5), [0.5, 0.8, 0.4, -0.5], atol=1e-6)
    # above the cube's top (z 2 m) the box is as far as its edge
    np.testing.assert_allclose(true_distance_m(world, xy[:1], 2.5), [0.7071], atol=1e-4)


def test_a_map_from_the_rendered_depth_with_the_exact_pose_shows_no_phantoms_and_a_drifting_one_shows_more():
    world = WorldBatch.from_descriptions([ROOM])
    path = np.array([[1.0 + 0.08 * t, 2.5 - 0.02 * t, 1.5] for t in range(45)])  # toward the cube and past its side
    result = map_flight(world, path, "none", seed=0)
    exact, drift = result["exact"], result["drift"]
    assert exact["cells"] > 50 and drift["cells"] > 50
    assert exact["phantom_share"] < 0.02 and exact["p90_distance_m"] < 0.15, exact
    assert drift["p90_distance_m"] > exact["p90_distance_m"], (exact, drift)
    assert len(result["add_frame_ms"]) == len(result["free_ahead_ms"]) == 2 * (len(path) - 1)


@pytest.mark.timeout(300)
def test_the_bench_flies_a_policy_and_reports_per_pose():
    proc = subprocess.run([sys.executable, "-m", "bench.seen_surfaces", "--policy", "models/student-field", "--encoder",
                           "models/cmwae-pooled", "--levels", "0", "--episodes", "1", "--depth", "none", "--json"],
                          capture_output=True, text=True, timeout=280)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout)
    assert set(result["summary"]) == {"exact", "drift"} and result["summary"]["exact"]["flights"] == 1
    assert result["summary"]["exact"]["phantom_share_median"] < 0.05
    assert result["flights"][0]["level"] == 0 and result["add_frame_ms"]["median"] > 0.0 and result["free_ahead_ms"]["median"] > 0.0
    wrong = subprocess.run([sys.executable, "-m", "bench.seen_surfaces", "--policy", "models/student-field", "--encoder",
                            "models/cmwae-depth", "--levels", "0", "--episodes", "1"], capture_output=True, text=True, timeout=280)  # fmt: skip
    assert wrong.returncode == 2 and wrong.stderr.startswith("bench.seen_surfaces: the policy models/student-field was trained on encoder")
