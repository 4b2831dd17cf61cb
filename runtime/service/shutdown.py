"""Bounded teardown: once the vehicle is down, the process must exit even if a driver's teardown
(MAVSDK's C destroy, a camera pipeline) hangs.

Each step gets ``timeout_s``.  A step that overruns is abandoned with an error naming it, and the
stacks of every thread go to stderr, so the log shows where it hung.  A step stuck in a C call on
the event-loop thread cannot be interrupted from asyncio; ``faulthandler``'s watchdog thread still
dumps the stacks then, so even that hang leaves its trace in the log.
"""

from __future__ import annotations

import asyncio
import faulthandler
import logging
import sys
import threading
from typing import Awaitable, Callable

log = logging.getLogger(__name__)

CLOSE_STEP_TIMEOUT_S = 5.0  # x 2 steps in `cmnav fly`: within systemd's TimeoutStopSec=15s
STUCK_LOOP_GRACE_S = 2.0


async def close_step(name: str, close: Callable[[], Awaitable[None]], timeout_s: float = CLOSE_STEP_TIMEOUT_S) -> bool:
    """Run one teardown step within ``timeout_s``; True if it finished, False if abandoned."""
    # Fires only if the event-loop thread itself is stuck (then wait_for below cannot).
    faulthandler.dump_traceback_later(timeout_s + STUCK_LOOP_GRACE_S, exit=False, file=sys.stderr)
    try:
        await asyncio.wait_for(close(), timeout_s)
        return True
    except asyncio.TimeoutError:
        log.error("closing %s took over %.1f s: abandoned so that the process can exit (thread stacks follow)",
                  name, timeout_s)  # fmt: skip
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        return False
    except Exception:  # a failed teardown step must not stop the next ones (nor hide the flight's result)
        log.exception("closing %s failed", name)
        return False
    finally:
        faulthandler.cancel_dump_traceback_later()


async def in_daemon_thread(name: str, blocking: Callable[[], None]) -> None:
    """Run a blocking call in a daemon thread and wait for it.  Unlike the default executor, a call
    that never returns does not hold up ``asyncio.run``'s shutdown or the interpreter's exit."""
    loop = asyncio.get_running_loop()
    done = loop.create_future()

    def run() -> None:
        error: BaseException | None = None
        try:
            blocking()
        except BaseException as err:  # noqa: BLE001 - handed to the awaiting task
            error = err
        loop.call_soon_threadsafe(_settle, done, error)

    threading.Thread(target=run, name=name, daemon=True).start()
    await done


def _settle(future: asyncio.Future, error: BaseException | None) -> None:
    if future.done():  # the waiter was cancelled (close_step's timeout)
        return
    if error is None:
        future.set_result(None)
    else:
        future.set_exception(error)
