"""Can this process write where it was told to?  Checked before any work starts (``--check``,
``cmnav sitl --out``, ``cmnav export -o``), so a bad path is one clear line, not a traceback later."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def directory_problem(path: str | Path) -> str | None:
    """Why ``path`` cannot be used (created if missing) as a writable directory, or None."""
    target = Path(path)
    if target.exists():
        if not target.is_dir():
            return f"{target} is a file, not a directory"
        return _probe(target) if os.access(target, os.W_OK | os.X_OK) else f"{target} is not writable by this user"
    return _ancestor_problem(target)


def _probe(directory: Path) -> str | None:
    """Create (and remove) a directory in ``directory``: permissions alone miss read-only mounts,
    /proc and /sys, and root's bypass of them."""
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".cmnav-write-check-", dir=directory))
    except OSError as err:
        return f"cannot create anything in {directory} ({err.strerror or err})"
    return None


def output_file_problem(path: str | Path) -> str | None:
    """Why a file cannot be written at ``path`` (its parents created if missing), or None."""
    target = Path(path)
    if target.is_dir():
        return f"{target} is a directory: give a file name, e.g. {target / 'model.onnx'}"
    if target.exists() and not os.access(target, os.W_OK):
        return f"{target} exists and is not writable by this user"
    return _ancestor_problem(target)


def _ancestor_problem(target: Path) -> str | None:
    ancestor = target.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        return f"cannot create {target}: {ancestor} is a file, not a directory"
    if not os.access(ancestor, os.W_OK | os.X_OK):
        return f"cannot create {target}: {ancestor} is not writable by this user"
    return _probe(ancestor)
