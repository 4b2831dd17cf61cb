"""Flight reports drawn one after another on one long-lived daemon thread (at normal priority: a
demoted thread holding the GIL stalls the control path, see ``runtime.service.affinity``).

One thread for the program's life, not one per report: matplotlib caches its fonts per thread
(``font_manager`` keeps an open-file cache keyed on the thread id), so a new thread per episode
kept three more font files open every episode of a long field run (the soak caught it)."""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
from collections.abc import Callable
from pathlib import Path

from .render import report_paths, write_report_quietly

log = logging.getLogger(__name__)


class ReportWorker:
    """``submit(log_path, record)`` queues a report; ``pending()`` the ones not drawn yet."""

    def __init__(self) -> None:
        self._jobs: queue.SimpleQueue[tuple[Callable[[], None], asyncio.Future] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._futures: list[asyncio.Future] = []

    def submit(self, log_path: Path, record: dict) -> asyncio.Future:
        """Draw the report of ``log_path`` beside it; ``record["report"]`` names the page once drawn."""
        html_path, _ = report_paths(log_path)

        def draw() -> None:
            if write_report_quietly(log_path, record) is not None:
                record["report"] = str(html_path)

        loop = asyncio.get_running_loop()
        future = loop.create_future()
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, args=(loop,), name="flight-report", daemon=True)
            self._thread.start()
        self._jobs.put((draw, future))
        self._futures = [f for f in self._futures if not f.done()] + [future]
        return future

    def pending(self) -> list[asyncio.Future]:
        self._futures = [f for f in self._futures if not f.done()]
        return list(self._futures)

    def _run(self, loop: asyncio.AbstractEventLoop) -> None:
        while (job := self._jobs.get()) is not None:
            draw, future = job
            try:
                draw()
            except Exception as err:  # write_report_quietly already turns every known failure into a warning
                log.warning("flight report failed: %r", err)
            if not loop.is_closed():
                loop.call_soon_threadsafe(lambda f=future: f.done() or f.set_result(None))
