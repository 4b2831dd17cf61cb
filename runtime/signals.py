"""Process signals for the runtime's entry points."""

from __future__ import annotations

import asyncio
import signal


def cancel_on_stop_signals() -> None:
    """Make SIGTERM and SIGINT cancel the calling task (an entry point's main coroutine), so its
    ``except CancelledError`` / ``finally`` blocks leave offboard safely instead of dying mid-flight."""
    task = asyncio.current_task()
    if task is None:
        raise RuntimeError("cancel_on_stop_signals() must be called from inside a task")
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, task.cancel)
