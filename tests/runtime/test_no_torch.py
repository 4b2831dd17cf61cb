"""The runtime never imports torch: every module imports and a full step runs with torch blocked."""

import subprocess
import sys
import textwrap
from pathlib import Path

from tests.runtime.onnx_models import save, step_model

SCRIPT = textwrap.dedent(
    """
    import importlib, pkgutil, sys
    sys.modules["torch"] = None  # any `import torch` now raises ImportError
    import numpy as np
    import runtime

    names = [m.name for m in pkgutil.walk_packages(runtime.__path__, "runtime.")]
    for name in names:
        importlib.import_module(name)

    from runtime.contract import observation_state, preprocess_depth, preprocess_gray
    from runtime.model import PolicyModel

    rng = np.random.default_rng(0)
    gray = preprocess_gray(rng.integers(0, 256, (120, 212), dtype=np.uint8))
    depth_m = rng.uniform(0.2, 12.0, (120, 212)).astype(np.float32)
    depth_m[:10] = 0.0
    depth = preprocess_depth(depth_m)
    state = observation_state(np.zeros(3), np.array([5.0, 1.0, 0.5]), np.array([1.0, 0, 0, 0]),
                              np.zeros(3), np.zeros(3), np.zeros(3))
    model = PolicyModel(sys.argv[1])
    out = model.step(gray, depth, state, model.initial_hidden())
    assert out.action.shape == (3,) and np.all(np.isfinite(out.action))
    assert out.latent.shape == (64,)
    print("modules", len(names), "torch" in sys.modules and sys.modules["torch"] is not None)
    """
)


def test_runtime_imports_and_steps_without_torch(tmp_path):
    model = save(step_model(), tmp_path / "m.onnx")
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(model)],
        capture_output=True, text=True, timeout=60, cwd=Path(__file__).resolve().parents[2],
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    count, torch_loaded = proc.stdout.split()[1:]
    assert int(count) >= 15 and torch_loaded == "False"
