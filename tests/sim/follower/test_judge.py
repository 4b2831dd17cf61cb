"""The follower's judge: contact, floor touch-down versus crash, goal, time limit, geofence."""

import numpy as np
import pytest

from runtime.config import WatchdogConfig
from sim.follower.judge import Judge
from sim.sitl.kinematics import Kinematics
from sim.world import make_worlds


@pytest.fixture(scope="module")
def world():
    return make_worlds(0, 4, 1)  # an empty room


def _kin(pos, vel=(0.0, 0.0, 0.0)):
    return Kinematics(0, np.asarray(pos, float), np.asarray(vel, float), np.array([1.0, 0, 0, 0]), np.zeros(3), False)


def _judge(world, timeout_s=5.0, fence=WatchdogConfig()):
    size = world.room_size_m[0].numpy()
    goal = np.array([size[0] - 1.0, size[1] / 2, 1.5])
    return Judge(world, goal, np.array([1.0, size[1] / 2, 0.15]), timeout_s, fence), goal, size


def test_goal_then_nothing_else(world):
    judge, goal, size = _judge(world)
    judge.observe(0.5, _kin([1.0, size[1] / 2, 0.15]))
    assert judge.verdict.goal_reached_t_s is None  # before offboard nothing counts but contact
    judge.offboard_entered(1.0, _kin([1.0, size[1] / 2, 1.5]))
    judge.observe(2.0, _kin(goal + [0.5, 0.0, 0.0]))
    judge.observe(20.0, _kin(goal))
    v = judge.verdict
    assert v.goal_reached_t_s == 2.0 and v.timeout_t_s is None and v.contact is None and v.geofence is None


def test_time_limit_counts_from_offboard(world):
    judge, _, size = _judge(world, timeout_s=5.0)
    judge.offboard_entered(10.0, _kin([1.0, size[1] / 2, 1.5]))
    judge.observe(14.9, _kin([2.0, size[1] / 2, 1.5]))
    assert judge.verdict.timeout_t_s is None
    judge.observe(15.1, _kin([2.0, size[1] / 2, 1.5]))
    assert judge.verdict.timeout_t_s == 15.1


def test_wall_contact_is_reported_once(world):
    judge, _, size = _judge(world)
    assert judge.observe(1.0, _kin([size[0] - 0.05, size[1] / 2, 1.5]))["what"].startswith("wall x=")
    assert judge.observe(1.1, _kin([size[0] - 0.01, size[1] / 2, 1.5])) is None  # latched: the first one counts
    assert judge.verdict.contact["t_s"] == 1.0


def test_floor_touch_down_is_not_a_crash_but_a_fast_one_is(world):
    judge, _, size = _judge(world)
    assert judge.observe(1.0, _kin([2.0, size[1] / 2, 0.15], vel=(0.0, 0.0, -0.5))) is None
    assert judge.observe(2.0, _kin([2.0, size[1] / 2, 0.1], vel=(0.0, 0.0, -3.0)))["what"] == "floor at 3.0 m/s"


def test_geofence_from_the_offboard_start(world):
    judge, _, size = _judge(world, fence=WatchdogConfig(geofence_radius_m=2.0))
    judge.offboard_entered(1.0, _kin([1.0, size[1] / 2, 1.5]))
    judge.observe(2.0, _kin([2.5, size[1] / 2, 1.5]))
    assert judge.verdict.geofence is None
    judge.observe(3.0, _kin([3.5, size[1] / 2, 1.5]))
    assert "> 2.0 m" in judge.verdict.geofence["what"]
