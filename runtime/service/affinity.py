"""Pinning the runtime process to its CPUs (``runtime.cpu_affinity``; ``cmnav bench runtime``),
and keeping the control path first on them: a short GIL switch interval.

No thread of the process is demoted (SCHED_IDLE, nice): the background threads (the flight log's
writer, the report's drawing) hold the GIL while they work, and a demoted holder that loses its
core to another process keeps the GIL until the scheduler runs it again, so the control path
waits behind it (priority inversion).  Measured on this 2-core machine with a 2-thread training
run on both cores: a 10 ms sleep loop with a pure-Python thread beside it woke up late by
p99 1398 ms with that thread at SCHED_IDLE (798 ms with both pinned to one core), p50 30 ms at
nice 10, p99 6.9 ms at normal priority (5.5 ms pinned) — the SITL flights' stale-frame trips.

Linux applies ``sched_setaffinity`` to one thread; threads inherit their creator's affinity. A
process that pins itself after start therefore pins every thread it already has (numpy's BLAS
pool, a logging thread, ...) as well as the calling one, so that every thread created later
(ONNX Runtime's pool, MAVSDK's, the executor's) inherits the pinned set.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger(__name__)

_TASKS = Path("/proc/self/task")

# A thread that wants the GIL (the event loop, woken by a finished ONNX step) waits up to this long
# for a thread holding it (the flight log's writer, encoding a frame) to let go.  CPython's
# default, 5 ms, alone exceeds the 3 ms overhead budget around the step; measured with the
# default, the hops to and from the step's worker thread had p99s near 1.1 ms at p50s of 0.15 ms.
GIL_SWITCH_INTERVAL_S = 0.0005


def prepare_control_process(cpus: Iterable[int] | None) -> tuple[int, ...] | None:
    """Set up the runtime process for the control loop: pin it to ``cpus`` (:func:`pin_process`,
    skipped when None or empty) and shorten the GIL switch interval.  Call it before ONNX
    Runtime's and MAVSDK's threads exist.  Returns the pinned CPUs, or None when not pinned."""
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    return pin_process(cpus) if cpus else None


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
