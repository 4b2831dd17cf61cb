"""Pinning the runtime process to its CPUs (``runtime.cpu_affinity``; ``cmnav bench runtime``).

Linux applies ``sched_setaffinity`` to one thread; threads inherit their creator's affinity. A
process that pins itself after start therefore pins every thread it already has (numpy's BLAS
pool, a logging thread, ...) as well as the calling one, so that every thread created later
(ONNX Runtime's pool, MAVSDK's, the executor's) inherits the pinned set.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger(__name__)

_TASKS = Path("/proc/self/task")


def pin_process(cpus: Iterable[int]) -> tuple[int, ...]:
    """Pin every thread of this process to ``cpus`` (ids within ``os.sched_getaffinity``); returns
    the set now in force, sorted.  Raises ``ValueError`` naming the CPUs this process may use when
    one is not among them (validate with ``runtime.config.ProcessConfig`` first)."""
    wanted = set(cpus)
    allowed = os.sched_getaffinity(0)
    if not wanted or not wanted <= allowed:
        raise ValueError(f"cannot pin to CPUs {sorted(wanted)}: this process may run on {sorted(allowed)}")
    try:
        threads = [int(t.name) for t in _TASKS.iterdir()]
    except OSError:  # no /proc: pin the calling thread, which every later thread inherits from
        threads = [0]
    for tid in threads:
        try:
            os.sched_setaffinity(tid, wanted)
        except ProcessLookupError:  # the thread ended meanwhile
            continue
    pinned = tuple(sorted(os.sched_getaffinity(0)))
    log.info("process pinned to CPUs %s (%d threads)", list(pinned), len(threads))
    return pinned
