"""Pure-Python dependencies kept as wheels in ``vendor/``, for the offline GPU machine.

That machine has torch, onnx, onnxruntime and numpy but no pytorch-msssim, and no internet to
install it.  A wheel of a pure-Python package is a zip archive that ``zipimport`` loads when the
wheel's path is on ``sys.path``, so the package imports straight from ``vendor/`` without
installing anything.  Where the package is installed (``pip install -e .[train]``) that copy wins.
Each wheel keeps its licence in its ``*.dist-info/LICENSE``; ``vendor/README.md`` lists them.
"""

from __future__ import annotations

import importlib
import logging
import sys
from pathlib import Path
from types import ModuleType

log = logging.getLogger(__name__)

VENDOR_DIR = Path(__file__).resolve().parents[1] / "vendor"

# module -> wheel in VENDOR_DIR; the version is the one pyproject's train extra resolves to here.
WHEELS = {"pytorch_msssim": "pytorch_msssim-1.0.0-py3-none-any.whl"}


def import_vendored(module: str) -> ModuleType:
    """``import module``, falling back to its wheel in ``vendor/`` when it is not installed."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        missing = err
    wheel = VENDOR_DIR / WHEELS[module]
    if not wheel.is_file():
        raise ImportError(
            f"{module} is not installed and its vendored wheel {wheel} is missing: "
            f"`pip install -e .[train]`, or restore vendor/ from the repository"
        ) from missing
    if str(wheel) not in sys.path:
        sys.path.append(str(wheel))  # appended, so it never shadows an installed package
    log.info("%s is not installed: importing it from %s", module, wheel)
    return importlib.import_module(module)
