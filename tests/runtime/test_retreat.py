"""The dry run's retreat before its landing (issue 27): after the goal, brake, fly back along the
path flown for ``mission.land_retreat_m``, brake again, then Hold — on PX4 the Hold and Land drift
up to ~1.1 m, and goals lie 0.5-1 m from a wall.  The path geometry, then the flight loop on a
vehicle that lags like PX4."""

import asyncio
import math

import numpy as np
import pytest

from runtime.config import MissionConfig, ConfigError, RecorderConfig, RuntimeConfig, WatchdogConfig
from runtime.flight import FlightLoop
from runtime.model import PolicyModel
from runtime.watchdog import RETREAT_LOOKAHEAD_M, RETREAT_SPEED_M_S, retreat_path, retreat_velocity_enu
from tests.runtime.test_brake import LaggingVehicle, goal_seeker  # noqa: F401 (the fixture)
from tests.runtime.test_flight_loop import START, FakeCamera


def test_the_path_is_walked_back_from_its_end_for_the_distance_asked():
    flown = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [2.0, 0.0, 2.0], [2.0, 1.0, 2.0], [2.0, 2.0, 2.5]])
    path = retreat_path(flown, 2.5)  # 1 m north back to (2, 1), 1 m to (2, 0), then 0.5 m west
    np.testing.assert_allclose(path, [[2.0, 2.0, 2.5], [2.0, 1.0, 2.0], [2.0, 0.0, 2.0], [1.5, 0.0, 2.0]])
    np.testing.assert_allclose(retreat_path(flown, 10.0), flown[::-1])  # shorter than asked: all of it
    np.testing.assert_allclose(retreat_path(flown[:1], 2.0), flown[:1])  # nothing flown: nowhere to go
    # Points where the vehicle hovered (no horizontal step) do not count as length.
    still = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 2.1], [3.0, 0.0, 2.0], [3.0, 0.0, 2.0]])
    np.testing.assert_allclose(retreat_path(still, 1.0)[-1], [2.0, 0.0, 2.0 + 0.1 / 3.0])


def test_the_pursuit_follows_the_path_slows_at_its_end_and_never_goes_back():
    path = np.array([[4.0, 0.0, 2.0], [0.0, 0.0, 2.0]])  # back west along the x axis
    vel, progress = retreat_velocity_enu(np.array([4.0, 0.3, 1.8]), path, 0.0)
    assert vel[0] < 0.0 and vel[1] < 0.0  # west, and back onto the line
    assert np.linalg.norm(vel[:2]) == pytest.approx(RETREAT_SPEED_M_S) and vel[2] == pytest.approx(0.2)
    assert progress == pytest.approx(0.0, abs=1e-9)
    vel, progress = retreat_velocity_enu(np.array([0.2, 0.0, 2.0]), path, progress)
    assert np.linalg.norm(vel[:2]) == pytest.approx(0.4) and vel[0] < 0.0  # 0.2 m left: 0.4 m/s
    assert progress == pytest.approx(3.8)
    # Progress kept: a vehicle blown back past where it was still pursues the point ahead of its progress.
    vel, again = retreat_velocity_enu(np.array([3.0, 0.0, 2.0]), path, 3.0)
    assert again == pytest.approx(3.0) and vel[0] < 0.0
    target_x = 4.0 - (3.0 + RETREAT_LOOKAHEAD_M)
    assert math.atan2(vel[1], vel[0]) == pytest.approx(math.atan2(0.0, target_x - 3.0))


def test_the_retreat_is_a_mission_key_with_bounds():
    assert MissionConfig().land_retreat_m == 1.5
    with pytest.raises(ConfigError, match="mission.land_retreat_m"):
        MissionConfig(land_retreat_m=-1.0)


async def _fly_and_retreat(model_path, vehicle, goal, retreat_m, camera=None):
    config = RuntimeConfig(watchdog=WatchdogConfig(hold_grace_s=0.3, brake_timeout_s=4.0), recorder=RecorderConfig(log_dir=None))
    await vehicle.start()
    loop = FlightLoop(config, PolicyModel(model_path), vehicle, camera or FakeCamera(), None)
    await loop.start()
    try:
        await loop.wait_first_frame(2.0)
        result = await loop.fly(goal, 20.0, retreat_m)
        return result, vehicle.pos.copy()
    finally:
        await loop.close()
        vehicle._task.cancel()


def test_a_goal_reached_is_followed_by_the_retreat_then_hold(goal_seeker):  # noqa: F811
    vehicle = LaggingVehicle()
    goal = START + np.array([4.0, 0.0, 0.0])
    result, at_hold = asyncio.run(_fly_and_retreat(goal_seeker, vehicle, goal, 1.5))
    assert result.outcome == "success", result
    retreat = result.brake["retreat"]
    assert retreat["ended"] == "arrived" and retreat["retreated_m"] > 1.2, result.brake
    # Back along the way it came (it flew +x from START), at the height it flew, stopped before Hold.
    assert at_hold[0] < goal[0] - 1.0 - 1.2 + 0.5 and abs(at_hold[1] - START[1]) < 0.2 and abs(at_hold[2] - START[2]) < 0.2
    assert vehicle.holds == 1 and vehicle.speed_at_hold < 0.2 and result.brake["speed_at_hold_m_s"] < 0.2


def test_a_timeout_or_a_trip_lands_where_it_stopped(goal_seeker):  # noqa: F811
    vehicle = LaggingVehicle()
    result, _ = asyncio.run(_fly_and_retreat(goal_seeker, vehicle, START + np.array([15.0, 0.0, 0.0]), 1.5,
                                             camera=FakeCamera(stop_after_s=1.0)))  # fmt: skip
    assert result.outcome == "aborted" and "retreat" not in result.brake


def test_a_stale_estimate_ends_the_retreat_into_the_brake_and_hold(goal_seeker):  # noqa: F811
    class EstimateDiesAfterTheBrake(LaggingVehicle):
        def state(self):
            s = super().state()
            if self.t_hold_ns is None and self.t_hover_ns is not None and any(self.cmd_flu[:2]):
                return type(s)(**{**s.__dict__, "t_posvel_ns": self.t_hover_ns - 1})  # retreating: no fresh estimate
            return s

    vehicle = EstimateDiesAfterTheBrake()
    result, _ = asyncio.run(_fly_and_retreat(goal_seeker, vehicle, START + np.array([4.0, 0.0, 0.0]), 1.5))
    assert result.outcome == "success" and result.brake["retreat"]["ended"] == "stale_telemetry", result.brake
    assert vehicle.holds == 1
