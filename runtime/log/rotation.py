"""Flight-log files of ``cmnav fly``: one per offboard episode, named by UTC start time, rotated.

Only files this module names (``cmnav-YYYYmmddTHHMMSSZ-epNNN.mcap``) and their flight reports
(the same name with ``.html`` / ``.png``) are ever deleted; anything else in the log directory is
left alone.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

log = logging.getLogger(__name__)

LOG_GLOB = "cmnav-*-ep*.mcap"
REPORT_SUFFIXES = (".html", ".png")  # a log's report beside it, deleted with it
BYTES_PER_GB = 1_000_000_000


def new_log_path(log_dir: Path, episode: int, t_unix_s: float | None = None) -> Path:
    """``log_dir/cmnav-<UTC time>-ep<episode>.mcap`` (names sort in time order)."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(time.time() if t_unix_s is None else t_unix_s))
    return log_dir / f"cmnav-{stamp}-ep{episode:03d}.mcap"


def rotate_logs(log_dir: Path, max_logs: int, max_total_gb: float) -> list[Path]:
    """Before a new log starts: delete the oldest logs so that at most ``max_logs - 1`` remain and
    they take at most ``max_total_gb`` (10^9 bytes).  Returns the deleted paths."""
    logs = sorted(log_dir.glob(LOG_GLOB))
    sizes = {p: p.stat().st_size for p in logs}
    total = sum(sizes.values())
    deleted: list[Path] = []
    while logs and (len(logs) > max_logs - 1 or total > max_total_gb * BYTES_PER_GB):
        oldest = logs.pop(0)
        oldest.unlink(missing_ok=True)
        for companion in REPORT_SUFFIXES:  # its flight report (runtime.report), if one was drawn
            oldest.with_suffix(companion).unlink(missing_ok=True)
        total -= sizes[oldest]
        deleted.append(oldest)
    if deleted:
        log.info("log rotation: deleted %d old flight log(s) from %s (keeping at most %d, %.1f GB)",
                 len(deleted), log_dir, max_logs, max_total_gb)  # fmt: skip
    return deleted
