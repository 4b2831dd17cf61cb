"""Bounded waits and teardown: a stop must reach every task at once, and once the vehicle is down
the process must exit even if a driver's teardown (MAVSDK's C destroy, a camera pipeline) hangs.

:func:`wait_within` is the runtime's ``asyncio.wait_for``: on Python 3.10 and 3.11 (the Jetson's
and ours) ``wait_for`` loses a cancellation that arrives while the awaited thing has just finished
(CPython gh-86296, fixed in 3.12): the task goes on as if never stopped.  CI saw it: SIGTERM
reached the runtime as a camera frame came in, the policy task's wait for the frame swallowed its
cancellation and flew the policy on for 9.8 s until the goal, and the stop began only then.

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
from typing import Awaitable, Callable, TypeVar

log = logging.getLogger(__name__)

CLOSE_STEP_TIMEOUT_S = 5.0  # x 2 steps in `cmnav fly`: within systemd's TimeoutStopSec=15s
STUCK_LOOP_GRACE_S = 2.0
LEFTOVER_TIMEOUT_S = 2.0  # after the program's end, for the tasks still pending (see run_bounded)

T = TypeVar("T")


async def wait_within(awaitable: Awaitable[T], timeout_s: float | None) -> T:
    """``awaitable``'s result, ``asyncio.TimeoutError`` after ``timeout_s`` (None: no limit).  A
    cancellation of the caller always propagates; the awaitable is then cancelled and not waited
    for (it may be slow to honour it; ``run_bounded`` collects what is left at exit)."""
    task = asyncio.ensure_future(awaitable)
    try:
        done, _ = await asyncio.wait({task}, timeout=timeout_s)
    except asyncio.CancelledError:
        task.cancel()
        raise
    if not done:
        task.cancel()
        raise asyncio.TimeoutError
    return task.result()


async def close_step(name: str, close: Callable[[], Awaitable[None]], timeout_s: float = CLOSE_STEP_TIMEOUT_S) -> bool:
    """Run one teardown step within ``timeout_s``; True if it finished, False if abandoned.

    An overrunning step is cancelled and left behind, not awaited: ``asyncio.wait_for`` would wait
    for the cancelled step to finish, and a step slow to honour its cancellation (a driver's
    teardown awaiting its own I/O) then held the process past the timeout."""
    # Fires only if the event-loop thread itself is stuck (then the wait below cannot return).
    faulthandler.dump_traceback_later(timeout_s + STUCK_LOOP_GRACE_S, exit=False, file=sys.stderr)
    task = asyncio.ensure_future(close())
    try:
        done, _ = await asyncio.wait({task}, timeout=timeout_s)
        if not done:
            task.cancel()
            log.error("closing %s took over %.1f s: abandoned so that the process can exit (thread stacks follow)",
                      name, timeout_s)  # fmt: skip
            faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
            return False
        task.result()
        return True
    except asyncio.CancelledError:
        task.cancel()
        raise
    except Exception:  # a failed teardown step must not stop the next ones (nor hide the flight's result)
        log.exception("closing %s failed", name)
        return False
    finally:
        faulthandler.cancel_dump_traceback_later()


def run_bounded(main: Awaitable[T], leftover_timeout_s: float = LEFTOVER_TIMEOUT_S) -> T:
    """``asyncio.run`` whose exit cannot hang on a task left behind: when ``main`` is done, the
    tasks still pending (e.g. a step :func:`close_step` abandoned) are cancelled and given
    ``leftover_timeout_s`` to finish; those that do not are named in the log and dropped."""
    loop = asyncio.new_event_loop()
    try:
        asyncio.set_event_loop(loop)
        return loop.run_until_complete(main)
    finally:
        try:
            leftover = asyncio.all_tasks(loop)
            for task in leftover:
                task.cancel()
            if leftover:
                _, stuck = loop.run_until_complete(asyncio.wait(leftover, timeout=leftover_timeout_s))
                for task in stuck:
                    log.error("task %s did not end %.1f s after its cancellation: left behind at exit", task.get_name(), leftover_timeout_s)
            loop.run_until_complete(asyncio.wait_for(loop.shutdown_asyncgens(), leftover_timeout_s))
            loop.run_until_complete(asyncio.wait_for(loop.shutdown_default_executor(), leftover_timeout_s))
        except (asyncio.TimeoutError, RuntimeError) as err:
            log.error("event loop shutdown abandoned: %r", err)
        finally:
            asyncio.set_event_loop(None)
            loop.close()


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
