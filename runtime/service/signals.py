"""Process signals for the runtime's entry points."""

from __future__ import annotations

import asyncio
import logging
import signal
import time

log = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class StopSignals:
    """SIGTERM and SIGINT cancel the entry point's main task once, so that its ``except
    CancelledError`` / ``finally`` blocks leave offboard safely instead of dying mid-flight.

    ``received`` is the first signal's name (None until one came) and ``t_monotonic_ns`` /
    ``t_unix_s`` its arrival.  A second signal is logged and otherwise ignored: cancelling again
    would interrupt the safe stop the first one started (systemd's TimeoutStopSec and SIGKILL
    remain the bound on a stop that hangs)."""

    def __init__(self, task: asyncio.Task) -> None:
        self._task = task
        self.received: str | None = None
        self.t_monotonic_ns = 0
        self.t_unix_s = 0.0

    def _on_signal(self, signum: signal.Signals) -> None:
        name = signal.Signals(signum).name
        if self.received is not None:
            log.warning("%s received while stopping on %s: ignored, the safe stop goes on", name, self.received)
            return
        self.received, self.t_monotonic_ns, self.t_unix_s = name, time.monotonic_ns(), time.time()
        log.warning("%s received: stopping", name)
        self._task.cancel(f"stopped by {name}")


def cancel_on_stop_signals() -> StopSignals:
    """Make the first SIGTERM or SIGINT cancel the calling task (an entry point's main coroutine)."""
    task = asyncio.current_task()
    if task is None:
        raise RuntimeError("cancel_on_stop_signals() must be called from inside a task")
    signals = StopSignals(task)
    loop = asyncio.get_running_loop()
    for signum in STOP_SIGNALS:
        loop.add_signal_handler(signum, signals._on_signal, signum)
    return signals


def ignore_stop_signals() -> None:
    """After the main task ended (the event loop, and its handlers, are gone): a late SIGTERM or
    SIGINT — a second one, or one sent while the program prints its summary — must not turn an
    orderly exit into a KeyboardInterrupt or a death by signal; the exit code is decided.  SIG_IGN,
    not a Python handler: the interpreter resets its own handlers to the default while it finalises."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
