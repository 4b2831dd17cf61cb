"""The brake before leaving offboard (issue 27): every end of an episode holds a zero-velocity
setpoint until the measured speed is below ``brake_speed_m_s`` (``brake_timeout_s`` at most),
then Hold.  A vehicle that answers like PX4 (a lagging velocity) is still moving when a fixed
one-second hover ends; Hold must wait for it."""

import asyncio
import time

import numpy as np
import pytest

from runtime.config import RecorderConfig, RuntimeConfig, WatchdogConfig
from runtime.flight import FlightLoop
from runtime.model import PolicyModel
from runtime.state import VehicleState
from runtime.contract import HOVER, mavsdk_to_velocity_flu
from runtime.watchdog import brake_ended, brake_setpoint
from tests.runtime.test_flight_loop import START, FakeCamera, KinematicVehicle

BRAKE_TAU_S = 0.8  # slower than PX4's, so a 0.3 s hover alone would end well above 0.2 m/s


class LaggingVehicle(KinematicVehicle):
    """The velocity follows the command with a first-order lag; ``speed_at_hold`` is what it was
    doing when Hold came.  ``telemetry_dies_at_hover``: no position/velocity after the hover."""

    def __init__(self, telemetry_dies_at_hover: bool = False):
        super().__init__()
        self.vel_enu = np.zeros(3)
        self.speed_at_hold: float | None = None
        self.t_hover_ns: int | None = None
        self.t_hold_ns: int | None = None
        self._dies = telemetry_dies_at_hover

    async def _integrate(self):
        dt = 0.01
        while True:
            if self.mode == "OFFBOARD":
                super_state = super().state()
                target = super_state.vel_enu_m_s
                self.vel_enu = self.vel_enu + (target - self.vel_enu) * (1.0 - np.exp(-dt / BRAKE_TAU_S))
                self.pos = self.pos + self.vel_enu * dt
                self.yaw += self.cmd_flu[3] * dt
            await asyncio.sleep(dt)

    def state(self) -> VehicleState:
        s = super().state()
        t_posvel = s.t_posvel_ns
        if self._dies and self.t_hover_ns is not None:
            t_posvel = self.t_hover_ns - 1
        return VehicleState(**{**s.__dict__, "vel_enu_m_s": self.vel_enu.copy(), "t_posvel_ns": t_posvel})

    async def set_velocity_body(self, cmd) -> None:
        await super().set_velocity_body(cmd)
        if not np.any(self.cmd_flu) and self.t_hover_ns is None:
            self.t_hover_ns = time.monotonic_ns()

    async def stop_offboard(self) -> None:
        self.speed_at_hold = float(np.linalg.norm(self.vel_enu))
        self.t_hold_ns = time.monotonic_ns()
        await super().stop_offboard()


async def _fly(model_path, vehicle, goal, timeout_s=20.0, brake_timeout_s=4.0, camera=None, brake_gain=1.0):
    config = RuntimeConfig(watchdog=WatchdogConfig(hold_grace_s=0.3, brake_timeout_s=brake_timeout_s, brake_gain=brake_gain),
                           recorder=RecorderConfig(log_dir=None))  # fmt: skip
    await vehicle.start()
    loop = FlightLoop(config, PolicyModel(model_path), vehicle, camera or FakeCamera(), None)
    await loop.start()
    try:
        await loop.wait_first_frame(2.0)
        return await loop.fly(goal, timeout_s)
    finally:
        await loop.close()
        vehicle._task.cancel()


def test_success_holds_only_once_the_vehicle_has_stopped(goal_seeker):
    vehicle = LaggingVehicle()  # a zero-velocity brake: the lag alone sets how long it takes
    result = asyncio.run(_fly(goal_seeker, vehicle, START + np.array([4.0, 0.0, 0.0]), brake_gain=0.0))
    assert result.outcome == "success", result
    assert vehicle.holds == 1 and vehicle.speed_at_hold < 0.2
    assert result.brake["ended"] == "stopped" and result.brake["speed_at_hold_m_s"] <= 0.2  # 3 decimals: 0.19999 reads 0.2
    # It arrived at cruise speed and a first-order lag of 0.8 s needs over a second to shed it.
    assert result.brake["duration_s"] > 0.3 + BRAKE_TAU_S


def test_a_trip_brakes_the_same_way(goal_seeker):
    vehicle = LaggingVehicle()
    goal = START + np.array([15.0, 0.0, 0.0])  # far: the camera dies while it cruises
    result = asyncio.run(_fly(goal_seeker, vehicle, goal, camera=FakeCamera(stop_after_s=1.5), brake_gain=0.0))
    assert result.outcome == "aborted" and result.abort_reason == "stale_frame", result
    assert vehicle.holds == 1 and vehicle.speed_at_hold < 0.2
    assert result.brake["ended"] == "stopped" and result.watchdog_trips[0]["hold_t_s"] - result.watchdog_trips[0]["t_s"] > 1.0


def test_without_telemetry_the_brake_times_out_into_hold(goal_seeker):
    vehicle = LaggingVehicle(telemetry_dies_at_hover=True)
    result = asyncio.run(_fly(goal_seeker, vehicle, START + np.array([4.0, 0.0, 0.0]), brake_timeout_s=1.5))
    assert vehicle.holds == 1
    assert result.brake["ended"] == "brake_timeout"
    assert (vehicle.t_hold_ns - vehicle.t_hover_ns) / 1e9 == pytest.approx(1.5, abs=0.3)


def _state(speed_m_s: float, t_posvel_ns: int) -> VehicleState:
    return VehicleState(vel_enu_m_s=np.array([speed_m_s, 0.0, 0.0]), t_posvel_ns=t_posvel_ns)


@pytest.mark.parametrize(
    "braked_s, speed, age_ms, expected",
    [
        (0.5, 0.0, 10, None),  # stopped, but not braked hold_grace_s yet
        (1.2, 0.1, 10, "stopped"),
        (1.2, 0.3, 10, None),  # still moving
        (1.2, 0.1, 900, None),  # stopped, says telemetry older than telemetry_stale_ms
        (1.2, float("nan"), 10, None),
        (4.0, 1.5, 10, "brake_timeout"),
    ],
)
def test_brake_rule(braked_s, speed, age_ms, expected):
    config = WatchdogConfig(hold_grace_s=1.0, brake_speed_m_s=0.2, brake_timeout_s=4.0, telemetry_stale_ms=500.0)
    t_brake = 1_000_000_000
    now = t_brake + int(braked_s * 1e9)
    assert brake_ended(_state(speed, now - int(age_ms * 1e6)), t_brake, now, config) == expected


def test_a_brake_shorter_than_the_hover_is_refused():
    with pytest.raises(ValueError, match=r"watchdog\.brake_timeout_s"):
        WatchdogConfig(hold_grace_s=2.0, brake_timeout_s=1.0)


def _moving(vel_enu, yaw_rad: float, t_posvel_ns: int) -> VehicleState:
    from runtime.contract.frames import quat_from_euler

    return VehicleState(vel_enu_m_s=np.asarray(vel_enu, dtype=float), t_posvel_ns=t_posvel_ns,
                        quat_enu_flu=quat_from_euler(0.0, 0.0, yaw_rad))  # fmt: skip


def test_the_brake_setpoint_opposes_the_measured_velocity_in_the_body_frame():
    config = WatchdogConfig(brake_gain=1.0, brake_setpoint_max_m_s=1.5)
    now = 10_000_000_000
    # Facing north (ENU yaw 90 deg), moving north at 1.2 m/s: forward 1.2 -> command backwards 1.2.
    sp = brake_setpoint(_moving([0.0, 1.2, 0.0], np.pi / 2, now - 20_000_000), now, config)
    assert mavsdk_to_velocity_flu(sp) == pytest.approx([-1.2, 0.0, 0.0, 0.0], abs=1e-9)
    # Fast: the setpoint's norm is capped; climbing: it asks to descend.
    sp = brake_setpoint(_moving([3.0, 0.0, 1.0], 0.0, now - 20_000_000), now, config)
    flu = mavsdk_to_velocity_flu(sp)
    assert np.linalg.norm(flu[:3]) == pytest.approx(1.5) and flu[0] < 0 and flu[2] < 0


@pytest.mark.parametrize("why", ["stale", "never", "gain 0"])
def test_without_a_fresh_velocity_the_brake_asks_for_zero(why):
    config = WatchdogConfig(brake_gain=0.0 if why == "gain 0" else 1.0)
    now = 10_000_000_000
    t_posvel = {"stale": now - 900_000_000, "never": 0, "gain 0": now}[why]
    assert brake_setpoint(_moving([1.0, 0.0, 0.0], 0.0, t_posvel), now, config) == HOVER


def test_an_active_brake_stops_sooner_than_a_zero_setpoint(goal_seeker):
    """Against the lagging vehicle, commanding against the velocity halves the time to stop."""
    zero, active = LaggingVehicle(), LaggingVehicle()
    goal = START + np.array([4.0, 0.0, 0.0])
    result_zero = asyncio.run(_fly(goal_seeker, zero, goal, brake_gain=0.0))
    result_active = asyncio.run(_fly(goal_seeker, active, goal, brake_gain=1.0))
    assert result_zero.brake["ended"] == result_active.brake["ended"] == "stopped"
    assert result_active.brake["duration_s"] < 0.75 * result_zero.brake["duration_s"]
    assert any(mavsdk_to_velocity_flu(sp)[0] < -0.1 for sp in active.setpoints)  # it commanded backwards
