"""Reading a flight log, replaying it and the pure parts of the loop need neither MAVSDK nor
foxglove: the data types live in ``runtime.state`` and the topic names in ``runtime.log.topics``."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

LIGHT_MODULES = (
    "runtime.state",
    "runtime.log.topics",
    "runtime.log.reader",
    "runtime.programs.replay",
    "runtime.policy_step",
    "runtime.watchdog",
)

SCRIPT = textwrap.dedent(
    """
    import importlib, sys
    for blocked in ("mavsdk", "foxglove"):
        sys.modules[blocked] = None  # any `import mavsdk` / `import foxglove` now raises ImportError
    importlib.import_module(sys.argv[1])
    """
)


@pytest.mark.parametrize("module", LIGHT_MODULES)
def test_module_imports_without_mavsdk_and_foxglove(module):
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, module],
        capture_output=True, text=True, timeout=60, cwd=Path(__file__).resolve().parents[2],
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]


def test_the_check_fails_on_a_module_that_needs_mavsdk():
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, "runtime.vehicle"],
        capture_output=True, text=True, timeout=60, cwd=Path(__file__).resolve().parents[2],
    )  # fmt: skip
    assert proc.returncode != 0 and "mavsdk" in proc.stderr
