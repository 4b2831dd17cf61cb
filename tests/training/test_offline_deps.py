"""The GPU pipeline's stages run on a machine with only torch, onnx, onnxruntime and numpy: no
OpenCV, pytorch-msssim (used from vendor/), MCAP, Foxglove, MAVSDK, pymavlink, matplotlib, tqdm or
TensorBoard.  Subprocesses get an import blocker through sitecustomize.py, then import every module
of training, sim (less sim.sitl and sim.follower, which need pymavlink, sim.response, which flies
through MAVSDK, and sim.tracking, which reads flight logs), runtime.contract, export and cmnav, and run
`cmnav dataset`, `cmnav train cmwae` and `cmnav eval cmwae`."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from training.data import pngio, tartanair
from training.data.generate import DatasetSpec, generate_dataset
from training.data.tartanair import GrayDepthDataset, find_samples, read_depth_m, write_v2_depth_png

pytestmark = pytest.mark.timeout(300)

REPO = Path(__file__).resolve().parents[2]
BLOCKED = ("cv2", "pytorch_msssim", "mcap", "mcap_protobuf", "foxglove", "mavsdk", "pymavlink", "matplotlib", "tqdm", "tensorboard")

# The sys.path finder, less BLOCKED outside vendor/: those modules are simply absent (find_spec
# gives None, import raises ModuleNotFoundError), as on the offline machine, where the only copy of
# pytorch_msssim is the wheel in vendor/.
SITECUSTOMIZE = textwrap.dedent(
    f"""
    import importlib.machinery, sys

    BLOCKED = {set(BLOCKED)!r}
    VENDOR = {str(REPO / "vendor")!r}


    class OfflineGpuMachine(importlib.machinery.PathFinder):
        @classmethod
        def find_spec(cls, name, path=None, target=None):
            if name.partition(".")[0] in BLOCKED:
                path = [p for p in (sys.path if path is None else path) if str(p).startswith(VENDOR)]
                if not path:
                    return None
            return super().find_spec(name, path, target)


    sys.meta_path[:] = [OfflineGpuMachine if f is importlib.machinery.PathFinder else f for f in sys.meta_path]
    """
)

IMPORT_EVERYTHING = textwrap.dedent(
    """
    import importlib, pkgutil, sys

    for name in {blocked!r}:
        try:
            importlib.import_module(name)
        except ImportError:
            continue
        raise AssertionError(name + " should be blocked")
    import cmnav, export, runtime.contract, sim, training

    names = []
    for package in (training, sim, runtime.contract, export, cmnav):
        for module in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            # SITL only: MAVLink (sim.sitl, sim.follower, sim.response: flies through MAVSDK and
            # reads tracking errors the way flight logs do) and flight logs (sim.tracking)
            if module.name.split(".")[:2] in (["sim", "sitl"], ["sim", "follower"], ["sim", "tracking"], ["sim", "response"]) \
                    or module.name.endswith(".__main__"):
                continue
            importlib.import_module(module.name)
            names.append(module.name)
    import pytorch_msssim
    assert ".whl" in pytorch_msssim.__file__, pytorch_msssim.__file__
    print(len(names))
    """
).format(blocked=BLOCKED)


@pytest.fixture(scope="module")
def offline_env(tmp_path_factory):
    site = tmp_path_factory.mktemp("offline_site")
    (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(REPO)])}


def _run(env, *args):
    proc = subprocess.run([sys.executable, *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def test_every_module_imports_without_the_blocked_packages(offline_env):
    assert int(_run(offline_env, "-c", IMPORT_EVERYTHING).stdout.strip()) > 30


def test_dataset_train_eval_run_offline(offline_env, tmp_path):
    data, ckpt = tmp_path / "data", tmp_path / "ckpt"
    _run(offline_env, "-m", "cmnav", "dataset", "--out", str(data), "--count", "16", "--seed", "2", "--levels", "0", "3",
         "--frames-per-room", "4")  # fmt: skip
    _run(offline_env, "-m", "cmnav", "train", "cmwae", "--data", str(data), "--size", "tiny", "--steps", "2",
         "--batch-size", "4", "--workers", "0", "--out", str(ckpt))  # fmt: skip
    proc = _run(offline_env, "-m", "cmnav", "eval", "cmwae", "--checkpoint", str(ckpt), "--data", str(data),
                "--max-images", "4", "--json")  # fmt: skip
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert [r["corruption_pct"] for r in result["rows"]] == [0, 20, 30, 40, 50]
    assert all(r["images"] == 4 and -100 <= r["ssim_e2"] <= 100 for r in result["rows"])
    assert json.loads((ckpt / "eval" / "table1.json").read_text())["rows"] == result["rows"]
    assert result["plots"] == {} and not list((ckpt / "eval").glob("*.png"))
    assert proc.stderr.count("install opencv-python-headless and re-run `cmnav eval cmwae`") == 1

    # What was written without OpenCV is what OpenCV writes, and OpenCV reads it back the same.
    reference = tmp_path / "reference"
    generate_dataset(reference, DatasetSpec(count=16, seed=2, levels=(0, 3), frames_per_room=4))
    samples = find_samples(data)
    assert len(samples) == 16
    for sample in samples:
        ours = cv2.imread(str(sample.image_path), cv2.IMREAD_UNCHANGED)
        theirs = cv2.imread(str(reference / sample.image_path.relative_to(data)), cv2.IMREAD_UNCHANGED)
        assert ours.dtype == np.uint8 and ours.ndim == 2
        np.testing.assert_array_equal(ours, theirs)
        np.testing.assert_array_equal(np.load(sample.depth_path), np.load(reference / sample.depth_path.relative_to(data)))


def test_loader_without_opencv_matches_the_contract(tmp_path, monkeypatch):
    """Sim-size images: gray within one level, depth equal; colour images go to gray bit-exactly;
    V2 depth PNGs written without OpenCV read back through it."""
    generate_dataset(tmp_path, DatasetSpec(count=8, seed=1, levels=(0, 4), frames_per_room=2))
    rng = np.random.default_rng(0)
    for sample in find_samples(tmp_path):
        if sample.image_path.name.startswith("000000"):  # one colour frame per room, as TartanAir's RGB
            cv2.imwrite(str(sample.image_path), rng.integers(0, 256, (120, 212, 3), dtype=np.uint8))
    with_cv2 = GrayDepthDataset(tmp_path, "train")
    expected = [with_cv2[i] for i in range(len(with_cv2))]
    monkeypatch.setattr(pngio, "opencv", lambda: None)
    monkeypatch.setattr(tartanair, "opencv", lambda: None)
    without = GrayDepthDataset(tmp_path, "train")
    for i, (gray, depth) in enumerate(expected):
        gray_twin, depth_twin = without[i]
        assert gray_twin.shape == gray.shape == (1, 224, 224) and gray_twin.dtype == torch.float32
        assert float((gray_twin - gray).abs().max()) <= 1.0 / 255 + 1e-6
        torch.testing.assert_close(depth_twin, depth, rtol=0, atol=0)

    bgr = np.stack([*np.meshgrid(np.arange(256), np.arange(256), indexing="ij"), rng.integers(0, 256, (256, 256))], -1)
    bgr = np.concatenate([bgr, rng.integers(0, 256, (512, 256, 3))]).astype(np.uint8)
    np.testing.assert_array_equal(tartanair._gray_from_bgr(bgr), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))

    depth_m = rng.uniform(0.5, 12.0, (40, 56)).astype(np.float32)
    write_v2_depth_png(tmp_path / "v2_depth.png", depth_m)  # TartanAir V2's float-in-RGBA PNG, without OpenCV
    monkeypatch.undo()
    np.testing.assert_array_equal(read_depth_m(tmp_path / "v2_depth.png", "v2"), depth_m)  # read with OpenCV


def test_pipeline_runs_offline_in_several_calls(offline_env, tmp_path):
    """`cmnav pipeline` on tiny networks, each call cut short by --call-minutes (exit 3), the same
    command continuing until the run is complete (exit 0)."""
    out = tmp_path / "pipeline"
    command = [sys.executable, "-m", "cmnav", "pipeline", "--device", "cpu", "--minutes", "0.5", "--call-minutes", "0.2",
               "--out", str(out), "--dataset-count", "80", "--encoder-size", "tiny", "--encoder-batch-size", "4",
               "--policy-size", "tiny", "--envs", "4", "--teacher-envs", "8", "--eval-episodes", "1",
               "--eval-levels", "0"]  # fmt: skip
    codes = []
    for _ in range(8):
        proc = subprocess.run(command, cwd=REPO, env=offline_env, capture_output=True, text=True, timeout=280)
        codes.append(proc.returncode)
        assert proc.returncode in (0, 3), proc.stderr[-3000:]
        if proc.returncode == 0:
            break
    assert codes[0] == 3 and codes[-1] == 0, codes
    state = json.loads((out / "pipeline_state.json").read_text())
    assert state["done"] == ["dataset", "encoder", "table1", "teacher", "teacher_table2", "policy", "table2", "export"]
    assert state["spent_s"]["encoder"] >= 0.35 * 30 - 3 and state["spent_s"]["teacher"] >= 0.3 * 30 - 3
    assert state["spent_s"]["policy"] >= 0.25 * 30 - 3
    card = (out / "MODEL_CARD.md").read_text()
    assert "| 50% |" in card and "| projector-off | 0 | 1 |" in card and "The teacher (clean depth only" in card
    summary = json.loads((out / "pipeline.json").read_text())
    assert summary["export"]["parity"]["random (seed 0)"]["action"] <= 1e-4

    from runtime.model import PolicyModel

    PolicyModel(out / "model.onnx")  # the runtime flies what the pipeline exported
