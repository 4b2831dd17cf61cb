"""`cmnav bench sim`: the real command as a subprocess, in its quick mode.  Checks the JSON shape,
the markdown table and that every cell's fast frames matched the reference; never timings."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import fields

import pytest
import torch

from bench.sim import QUICK, SimBenchCell, format_sim_bench
from sim.render import MAX_MISMATCH_FRACTION


def test_bench_sim_quick_json() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "cmnav", "bench", "sim", "--json", "--quick"],
        capture_output=True, text=True, check=True, timeout=240,
    )  # fmt: skip
    result = json.loads(proc.stdout)
    assert result["camera_px"] == [212, 120]
    assert result["reference_device"] == "cpu" and result["threads"] >= 1
    assert result["tolerance"] == {"depth_rel": 1e-4, "gray_levels": 1}
    devices = ["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"]
    assert [d.split()[0] for d in result["devices"]] == devices

    cells = result["cells"]
    expected = {(d, n, k) for d in devices for n in QUICK.batch_sizes for k in QUICK.box_counts}
    assert {(c["device"], c["batch_size"], c["boxes"]) for c in cells} == expected
    assert len(cells) == len(expected)
    for cell in cells:
        assert set(cell) == {f.name for f in fields(SimBenchCell)}
        assert cell["fast_fps"] > 0 and cell["reference_fps"] > 0
        assert cell["fast_fps_best"] >= cell["fast_fps"] and cell["reference_fps_best"] >= cell["reference_fps"]
        assert cell["ratio"] == pytest.approx(cell["fast_fps"] / cell["reference_fps"])
        assert cell["ratio_best"] == pytest.approx(cell["fast_fps_best"] / cell["reference_fps_best"])
        assert cell["reference_envs"] == 1
        assert cell["depth_mismatch_fraction"] <= MAX_MISMATCH_FRACTION
        assert cell["gray_mismatch_fraction"] <= MAX_MISMATCH_FRACTION

    table = format_sim_bench(result).splitlines()
    assert table[2].startswith("| device | N | boxes | fast frames/s, median (best) | reference frames/s")
    assert len(table) == 4 + len(cells)
    assert all(row.startswith("| cpu | ") or row.startswith("| cuda | ") for row in table[4:])
