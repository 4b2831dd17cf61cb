"""Stop signals: the first cancels the main task once; a second one while the safe stop runs is
ignored, and one after the event loop ended cannot kill the exiting process."""

import asyncio
import os
import signal
import subprocess
import sys

from runtime.service.signals import cancel_on_stop_signals


def test_first_signal_cancels_once_and_a_second_does_not_interrupt_the_safe_stop(caplog):
    async def main() -> tuple[str | None, bool]:
        signals = cancel_on_stop_signals()
        os.kill(os.getpid(), signal.SIGTERM)
        try:
            await asyncio.sleep(10.0)
        except asyncio.CancelledError:
            os.kill(os.getpid(), signal.SIGINT)
            await asyncio.sleep(0.2)  # the "safe stop": a second cancel would raise here
            return signals.received, signals.t_monotonic_ns > 0
        return None, False

    assert asyncio.run(main()) == ("SIGTERM", True)
    assert "SIGTERM received: stopping" in caplog.text
    assert "SIGINT received while stopping on SIGTERM: ignored" in caplog.text


def test_a_signal_after_the_loop_ended_does_not_kill_the_process():
    code = (
        "import asyncio, os, signal\n"
        "from runtime.service.signals import cancel_on_stop_signals, ignore_stop_signals\n"
        "async def main():\n"
        "    cancel_on_stop_signals()\n"
        "asyncio.run(main())\n"
        "ignore_stop_signals()\n"
        "os.kill(os.getpid(), signal.SIGINT)\n"
        "os.kill(os.getpid(), signal.SIGTERM)\n"
        "print('exited normally')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "exited normally" in proc.stdout, proc.stderr
