"""Bounded teardown: a hung close is abandoned with its name and the thread stacks in the log, the
next steps still run, and the process exits."""

import asyncio
import logging
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from runtime.config import VehicleConfig
from runtime.service.shutdown import close_step, in_daemon_thread, wait_within
from runtime.vehicle import Vehicle


class _HungDestroy:
    """A MAVSDK handle whose destroy() never returns (the hang seen once after landing)."""

    def __init__(self) -> None:
        self.called = threading.Event()
        self._never = threading.Event()

    def destroy(self) -> None:
        self.called.set()
        self._never.wait()


def test_hung_and_failing_steps_are_abandoned_and_named(caplog):
    caplog.set_level(logging.ERROR, logger="runtime.service.shutdown")
    ran = []

    async def hang() -> None:
        await asyncio.Event().wait()

    async def fail() -> None:
        raise OSError("device gone")

    async def ok() -> None:
        ran.append("ok")

    async def teardown() -> list[bool]:
        return [await close_step("the camera", hang, 0.2), await close_step("the log", fail, 0.2), await close_step("MAVSDK", ok, 0.2)]

    t0 = time.monotonic()
    assert asyncio.run(teardown()) == [False, False, True]
    assert time.monotonic() - t0 < 5.0
    assert ran == ["ok"]
    assert "closing the camera took over 0.2 s: abandoned" in caplog.text
    assert "closing the log failed" in caplog.text and "device gone" in caplog.text


def test_vehicle_close_does_not_wait_for_a_hung_mavsdk_destroy():
    vehicle = Vehicle(VehicleConfig())
    hung = _HungDestroy()
    vehicle._mavsdk = hung  # as after connect(); no plugins, no subscriptions

    async def teardown() -> bool:
        return await close_step("MAVSDK", vehicle.close, 0.3)

    assert asyncio.run(teardown()) is False
    assert hung.called.is_set()


def test_in_daemon_thread_returns_results_and_raises_errors():
    def boom() -> None:
        raise ValueError("bad handle")

    async def run() -> None:
        box = []
        await in_daemon_thread("fill", lambda: box.append(1))
        assert box == [1]
        with pytest.raises(ValueError, match="bad handle"):
            await in_daemon_thread("boom", boom)

    asyncio.run(run())


def test_process_exits_despite_a_teardown_that_never_returns():
    """asyncio.run's default-executor shutdown and the interpreter's exit both wait for executor
    threads; the daemon-thread teardown must leave neither waiting."""
    script = textwrap.dedent(
        """
        import asyncio, threading
        from runtime.service.shutdown import close_step, in_daemon_thread, wait_within
        never = threading.Event()
        async def main():
            done = await close_step("MAVSDK", lambda: in_daemon_thread("mavsdk-destroy", never.wait), 0.5)
            print("closed", done, flush=True)
        asyncio.run(main())
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "closed False" in proc.stdout
    assert "closing MAVSDK took over 0.5 s" in proc.stderr
    assert 'Thread' in proc.stderr and "in wait" in proc.stderr  # faulthandler's stacks name the hung thread's frame


def test_a_step_slow_to_honour_its_cancellation_is_left_behind_and_the_process_exits():
    """A teardown step that answers its cancellation by awaiting more (a driver closing its own
    I/O) once held `cmnav fly` past the timeout: asyncio.wait_for waits for the cancelled step.
    close_step leaves it behind at its timeout, and run_bounded (the programs' asyncio.run) gives
    such leftovers a bounded time at exit."""
    script = textwrap.dedent(
        """
        import asyncio, time
        from runtime.service.shutdown import close_step, run_bounded

        async def deaf():
            while True:
                try:
                    await asyncio.sleep(3600)
                except asyncio.CancelledError:
                    continue  # ignores every cancellation

        async def main():
            t0 = time.monotonic()
            done = await close_step("the camera", deaf, 0.3)
            print("closed", done, round(time.monotonic() - t0, 1), flush=True)
            return 3

        print("code", run_bounded(main(), leftover_timeout_s=0.5), flush=True)
        """
    )
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "closed False 0.3" in proc.stdout and "code 3" in proc.stdout
    assert "closing the camera took over 0.3 s: abandoned" in proc.stderr
    assert "did not end 0.5 s after its cancellation: left behind at exit" in proc.stderr
    assert time.monotonic() - t0 < 30.0


async def _cancel_as_it_finishes(wait) -> str:
    """Cancel a task just as the thing it waits for finishes (a frame arriving as SIGTERM does):
    the inner future completes in one loop iteration and the cancel comes before its waiter runs."""
    event = asyncio.Event()

    async def inner() -> str:
        await event.wait()
        return "frame"

    async def waiter() -> str:
        return await wait(inner(), 5.0)

    task = asyncio.create_task(waiter())
    await asyncio.sleep(0)  # the waiter waits
    event.set()
    await asyncio.sleep(0)  # inner finishes; the waiter's wake-up is queued behind us
    task.cancel()
    try:
        return await task
    except asyncio.CancelledError:
        return "cancelled"


def test_wait_within_never_loses_a_cancellation_that_wait_for_loses():
    if sys.version_info < (3, 12):  # the race this guards against, as the interpreter has it
        assert asyncio.run(_cancel_as_it_finishes(asyncio.wait_for)) == "frame"
    assert asyncio.run(_cancel_as_it_finishes(wait_within)) == "cancelled"


def test_wait_within_returns_raises_and_times_out():
    async def main() -> None:
        async def value() -> int:
            await asyncio.sleep(0.01)
            return 7

        async def fail() -> None:
            raise OSError("link down")

        never = asyncio.Event()
        assert await wait_within(value(), 1.0) == 7
        assert await wait_within(value(), None) == 7
        with pytest.raises(OSError, match="link down"):
            await wait_within(fail(), 1.0)
        t0 = time.monotonic()
        with pytest.raises(asyncio.TimeoutError):
            await wait_within(never.wait(), 0.05)
        assert time.monotonic() - t0 < 1.0
        await asyncio.sleep(0)
        pending = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        assert pending == [], pending  # what timed out was cancelled, not left waiting

    asyncio.run(main())
