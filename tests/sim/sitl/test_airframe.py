"""The airframe in its room: sitting on its gear, lifting off, touch-down versus crash, walls."""

import numpy as np
import pytest

from sim.sitl.airframe import LANDING_GEAR_HEIGHT_M, Airframe
from sim.sitl.flight_tasks import VelocityCommand
from sim.world import make_worlds

DT_S = 0.01


@pytest.fixture
def airframe() -> Airframe:
    world = make_worlds(0, 11, 1)
    return Airframe(world, world.start_m[0, :2].double().numpy())


def _fly(airframe: Airframe, vel_enu_m_s, seconds: float, yaw_rate: float = 0.0) -> str | None:
    command = VelocityCommand(np.asarray(vel_enu_m_s, dtype=float), yaw_rate)
    for _ in range(round(seconds / DT_S)):
        hit = airframe.step(command, DT_S)
        if hit is not None:
            return hit
    return None


def test_spawns_landed_at_home(airframe):
    kin = airframe.kinematics()
    assert kin.on_ground and kin.pos_enu_m[2] == pytest.approx(LANDING_GEAR_HEIGHT_M)
    np.testing.assert_allclose(kin.pos_enu_m, airframe.home_enu_m, atol=1e-6)
    assert kin.yaw_enu_rad == pytest.approx(0.0)


def test_sits_still_unless_told_to_climb(airframe):
    start = airframe.kinematics().pos_enu_m
    assert _fly(airframe, [1.0, 0.0, -0.5], 1.0) is None  # sideways or down: stays on its gear
    np.testing.assert_allclose(airframe.kinematics().pos_enu_m, start, atol=1e-6)
    assert airframe.step(None, DT_S) is None and airframe.kinematics().on_ground


def test_lifts_off_and_lands_softly(airframe):
    assert _fly(airframe, [0.0, 0.0, 1.0], 1.5) is None
    kin = airframe.kinematics()
    assert not kin.on_ground and kin.pos_enu_m[2] > 1.0
    assert _fly(airframe, [0.0, 0.0, -0.7], 4.0) is None  # PX4's land speed
    kin = airframe.kinematics()
    assert kin.on_ground and kin.pos_enu_m[2] == pytest.approx(LANDING_GEAR_HEIGHT_M)
    np.testing.assert_allclose(kin.vel_enu_m_s, 0.0)
    assert not airframe.crashed


def test_hard_floor_contact_is_a_crash(airframe):
    _fly(airframe, [0.0, 0.0, 2.0], 1.5)
    hit = _fly(airframe, [0.0, 0.0, -2.0], 3.0)
    assert hit is not None and hit.startswith("floor at") and airframe.crashed


def test_motors_off_in_the_air_falls(airframe):
    _fly(airframe, [0.0, 0.0, 1.0], 1.0)
    z0 = airframe.kinematics().pos_enu_m[2]
    for _ in range(30):  # 0.3 s: climbing at 1 m/s when the motors stop, then falling
        airframe.step(None, DT_S)
    assert airframe.kinematics().pos_enu_m[2] < z0 and airframe.kinematics().vel_enu_m_s[2] < -0.5


def test_wall_collision_freezes_the_vehicle(airframe):
    _fly(airframe, [0.0, 0.0, 1.0], 1.0)
    hit = _fly(airframe, [-2.0, 0.0, 0.0], 5.0)  # backwards into the wall behind the start
    assert hit == "wall x=0" and airframe.crashed
    kin = airframe.kinematics()
    assert kin.pos_enu_m[0] == pytest.approx(0.2, abs=0.03)  # the vehicle's radius from the wall
    np.testing.assert_allclose(kin.vel_enu_m_s, 0.0)
    assert airframe.step(VelocityCommand(np.zeros(3), 0.0), DT_S) is None
    np.testing.assert_allclose(airframe.kinematics().pos_enu_m, kin.pos_enu_m)


def test_obstacle_collision_is_named():
    world = make_worlds(1, 4, 1)
    airframe = Airframe(world, world.start_m[0, :2].double().numpy())
    box = world.box_center_m[0, 0].double().numpy()
    _fly(airframe, [0.0, 0.0, 1.0], box[2] / 1.0)
    _fly(airframe, [0.0, 0.0, 0.0], 0.5)
    to_box = box[:2] - airframe.kinematics().pos_enu_m[:2]
    hit = _fly(airframe, [*(1.5 * to_box / np.linalg.norm(to_box)), 0.0], 15.0)
    assert hit == "obstacle 0"
