"""Fault injection syntax (runtime.faults.catalogue) and the runtime's own injected faults (runtime.faults.injection)."""

import asyncio
import time

import numpy as np
import pytest

from runtime.faults import injection as fault_injection
from runtime.command_gate import CommandGate
from runtime.config import WatchdogConfig
from runtime.faults.injection import FaultyPolicy, shrink_geofence, shrink_geofence_at
from runtime.faults.catalogue import FAULT_SITE, FaultKind, FaultSite, Injection, InjectionError, parse_injection
from runtime.model import ModelOutput
from runtime.state import VehicleState
from runtime.watchdog import Watchdog

S = 1_000_000_000


def test_parse_every_kind():
    for kind in FaultKind:
        at = "0" if kind == FaultKind.OFFBOARD_REFUSED else "2.5"
        injection = parse_injection(f"{kind.value}@{at}")
        assert injection == Injection(kind, float(at)) and str(injection) == f"{kind.value}@{at}"
    assert set(FAULT_SITE) == set(FaultKind)


@pytest.mark.parametrize(
    "text, why",
    [
        ("camera-stall", "expected KIND@SECONDS"),
        ("camera-stal@2", "unknown fault kind 'camera-stal'"),
        ("camera-stall@-1", "SECONDS must be a number >= 0"),
        ("camera-stall@nan", "SECONDS must be a number >= 0"),
        ("camera-stall@soon", "SECONDS must be a number >= 0"),
        ("offboard-refused@2", "write offboard-refused@0"),
        ("runtime-kill@0", "needs a time after offboard start"),
    ],
)
def test_bad_injections_are_named(text, why):
    with pytest.raises(InjectionError, match=why):
        parse_injection(text)


def test_each_process_accepts_only_its_own_kinds():
    assert parse_injection("nan-action@1", [FaultSite.RUNTIME]).site == FaultSite.RUNTIME
    with pytest.raises(InjectionError, match="expected one of geofence, inference-overrun, nan-action"):
        parse_injection("camera-stall@1", [FaultSite.RUNTIME])


class ConstantModel:
    def initial_hidden(self):
        return np.zeros(4, np.float32)

    def step(self, gray, depth, state, hidden):
        return ModelOutput(np.array([0.5, 0.0, 0.1], np.float32), hidden + 1, np.zeros(64, np.float32))


def _step(policy):
    return policy.step(None, None, None, np.zeros(4, np.float32))


def test_nan_action_from_its_time_on():
    clock = [0]
    policy = FaultyPolicy(ConstantModel(), [Injection(FaultKind.NAN_ACTION, 2.0)], clock_ns=lambda: clock[0])
    assert np.all(np.isfinite(_step(policy).action))  # not started: nothing injected
    policy.start(10 * S)
    clock[0] = 11 * S
    assert np.all(np.isfinite(_step(policy).action)) and policy.injected == {}
    clock[0] = 12 * S
    out = _step(policy)
    assert np.all(np.isnan(out.action)) and out.hidden_next[0] == 1.0
    assert policy.injected == {FaultKind.NAN_ACTION: 12.0}
    np.testing.assert_array_equal(policy.initial_hidden(), np.zeros(4))


def test_inference_overrun_blocks_the_step(monkeypatch):
    slept = []
    monkeypatch.setattr(fault_injection.time, "sleep", slept.append)
    clock = [0]
    policy = FaultyPolicy(ConstantModel(), [Injection(FaultKind.INFERENCE_OVERRUN, 1.0)], clock_ns=lambda: clock[0])
    policy.start(0)
    _step(policy)
    clock[0] = S
    assert np.all(np.isfinite(_step(policy).action))  # late, not wrong
    assert slept == [fault_injection.INFERENCE_OVERRUN_S] and FaultKind.INFERENCE_OVERRUN in policy.injected


class NoVehicle:
    async def set_velocity_body(self, cmd):
        pass

    async def stop_offboard(self):
        pass


def _supervising_watchdog(start_xy=(1.0, 2.0)) -> Watchdog:
    watchdog = Watchdog(WatchdogConfig(), CommandGate(NoVehicle()))
    now = time.monotonic_ns()
    state = VehicleState(pos_enu_m=np.array([*start_xy, 1.5]), t_posvel_ns=now, t_att_ns=now, home_enu_m=np.zeros(3))
    watchdog.start(now, state)
    return watchdog


def test_shrink_geofence_excludes_the_point():
    watchdog = _supervising_watchdog()
    radius = shrink_geofence(watchdog, np.array([1.0, 2.0]), np.array([7.0, 10.0, 1.0]))  # 10 m away
    assert radius == pytest.approx(5.0) and watchdog.config.geofence_radius_m == pytest.approx(5.0)
    assert shrink_geofence(watchdog, np.array([1.0, 2.0]), np.array([1.0, 2.0, 1.0])) == fault_injection.GEOFENCE_MIN_RADIUS_M


def test_shrink_geofence_at_its_time_around_the_vehicle():
    watchdog = _supervising_watchdog()
    state = VehicleState(pos_enu_m=np.array([4.0, 6.0, 1.5]))  # 5 m from the start
    t0_ns = time.monotonic_ns()
    t_injected = asyncio.run(shrink_geofence_at(watchdog, 0.05, t0_ns, lambda: state))
    assert t_injected >= t0_ns / S + 0.05
    assert watchdog.config.geofence_radius_m == pytest.approx(2.5)
