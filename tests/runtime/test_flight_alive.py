"""The flight loop's ``on_alive`` (what feeds systemd's watchdog): called by healthy iterations
only, so a stalled step stops it; the watchdog's trip response keeps it going."""

import asyncio
import threading

import numpy as np

from runtime.config import RuntimeConfig, WatchdogConfig
from runtime.flight import FlightLoop
from runtime.model import PolicyModel
from tests.runtime.onnx_models import save, step_model
from tests.runtime.test_flight_loop import START, FakeCamera, KinematicVehicle

STALL_AFTER_STEPS = 5


class StallingModel:
    """Delegates to a model; its 6th step blocks (in the step thread) until released."""

    def __init__(self, model: PolicyModel) -> None:
        self._model = model
        self.steps = 0
        self.stalled = threading.Event()
        self.release = threading.Event()

    def initial_hidden(self):
        return self._model.initial_hidden()

    def step(self, *args):
        self.steps += 1
        if self.steps == STALL_AFTER_STEPS + 1:
            self.stalled.set()
            self.release.wait(5.0)
            self.stalled.clear()
        return self._model.step(*args)


async def _fly(model, during, config: RuntimeConfig, timeout_s: float, stalled: threading.Event | None = None):
    vehicle = KinematicVehicle()
    await vehicle.start()
    alive: list[bool] = []  # at each on_alive call: was the step stalled?
    loop = FlightLoop(config, model, vehicle, FakeCamera(), on_alive=lambda: alive.append(stalled is not None and stalled.is_set()))
    await loop.start()
    try:
        await loop.wait_first_frame(2.0)
        fly = asyncio.create_task(loop.fly(START + np.array([15.0, 0.0, 0.0]), timeout_s))
        if during is not None:
            await during(model, alive)
        result = await fly
    finally:
        await loop.close()
        vehicle._task.cancel()
    return result, alive


def test_a_stalled_step_stops_the_pings(tmp_path):
    model = StallingModel(PolicyModel(save(step_model(), tmp_path / "m.onnx")))
    config = RuntimeConfig(watchdog=WatchdogConfig(step_trip_ms=1000.0, hold_grace_s=0.2))  # the longest allowed

    async def stall_then_release(model, alive):
        while not model.stalled.is_set():
            await asyncio.sleep(0.01)
        calls_when_stalled = len(alive)
        await asyncio.sleep(0.5)  # the loop is stuck in its step: nothing may report it alive
        assert len(alive) == calls_when_stalled
        model.release.set()

    result, alive = asyncio.run(_fly(model, stall_then_release, config, timeout_s=1.5, stalled=model.stalled))
    assert result.watchdog_trips == []  # the step limit was not reached: only the pings tell
    assert alive.count(False) > STALL_AFTER_STEPS and not any(alive)
    assert result.steps > STALL_AFTER_STEPS + 1  # it stepped (and pinged) again once released


def test_the_trip_response_keeps_reporting_alive(tmp_path):
    nan_model = PolicyModel(save(step_model(action_offset=float("nan")), tmp_path / "nan.onnx"))
    config = RuntimeConfig(watchdog=WatchdogConfig(hold_grace_s=0.3))
    result, alive = asyncio.run(_fly(nan_model, None, config, timeout_s=5.0))
    assert result.steps == 0 and result.watchdog_trips[0]["cause"] == "bad_action"
    assert len(alive) > 0  # no step ever completed, yet hovering then Hold counted as alive
