"""Our SITL vehicle with PX4's estimate (`--estimate px4`): the autopilot knows and reports the
estimate and holds it at the setpoint, so the airframe (the truth the camera sees) slides by the
estimate's velocity error."""

import numpy as np
import pytest

from sim.estimate import StateEstimateConfig
from sim.sitl.airframe import Airframe
from sim.sitl.estimate import SitlEstimate
from sim.sitl.flight_tasks import VelocityCommand
from sim.world import make_worlds

DT_S = 0.01
# A fixed error, large enough to see in 2 s of hover: no drift, no white noise.
FIXED = StateEstimateConfig(position_bias_m=(0.3, 0.3), position_drift_m=(0.0, 0.0), position_noise_m=0.0,
                            velocity_bias_m_s=(0.3, 0.2), velocity_drift_m_s=(0.0, 0.0), velocity_noise_m_s=0.0)  # fmt: skip


def _airborne() -> Airframe:
    world = make_worlds(0, 11, 1)
    airframe = Airframe(world, world.start_m[0, :2].double().numpy())
    for _ in range(150):  # climb off the gear to ~1.6 m
        airframe.step(VelocityCommand(np.array([0.0, 0.0, 1.0]), 0.0), DT_S)
    for _ in range(200):
        airframe.step(VelocityCommand(np.zeros(3), 0.0), DT_S)
    return airframe


def test_the_autopilot_holds_its_estimate_and_the_airframe_slides_by_its_error():
    airframe = _airborne()
    estimate = SitlEstimate(airframe.kinematics(), DT_S, seed=3, config=FIXED)
    error = estimate.velocity_error_m_s()
    assert np.abs(error).max() > 0.1  # the draw is a real error, not zero
    hover = VelocityCommand(np.zeros(3), 0.0)
    for _ in range(300):  # 3 s of "hold still", as the autopilot sees it
        airframe.step(estimate.flown(hover), DT_S)
        known = estimate.update(airframe.kinematics())
    truth = airframe.kinematics()
    np.testing.assert_allclose(truth.vel_enu_m_s, -error, atol=0.05)  # the truth slides
    np.testing.assert_allclose(known.vel_enu_m_s, np.zeros(3), atol=0.05)  # the autopilot sees itself still
    offset = known.pos_enu_m - truth.pos_enu_m  # position: bias only here
    assert np.linalg.norm(offset) > 0.05 and np.linalg.norm(offset) < 6 * 0.3 * np.sqrt(3)
    assert known.on_ground == truth.on_ground


def test_the_measured_estimate_drifts_and_a_seed_replays_it():
    airframe = _airborne()
    runs = []
    for seed in (5, 5, 6):
        estimate = SitlEstimate(airframe.kinematics(), DT_S, seed=seed)
        runs.append(np.array([estimate.update(airframe.kinematics()).pos_enu_m for _ in range(300)]))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])
    error = runs[0] - airframe.kinematics().pos_enu_m
    assert float(np.abs(error[-1] - error[0]).max()) > 0.005  # the drift moves it over 3 s


@pytest.mark.parametrize("value", ["exact", "px4"])
def test_the_vehicle_config_takes_the_estimates(value, tmp_path):
    from sim.sitl.vehicle import SitlConfig

    SitlConfig(1, 2, 0, 0, tmp_path / "e.json", tmp_path / "t.json", estimate=value).validate()
    with pytest.raises(ValueError, match="--estimate 'ekf' must be one of exact, px4"):
        SitlConfig(1, 2, 0, 0, tmp_path / "e.json", tmp_path / "t.json", estimate="ekf").validate()
