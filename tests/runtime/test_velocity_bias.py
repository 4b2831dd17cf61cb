"""runtime.tracking.VelocityBias: the autopilot's velocity error measured against the rate of its own
position estimate, on PX4 v1.16 SIH's recorded estimates and on constructed ones; the adapter
corrects the state and every setpoint it sends by it."""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from runtime.config import ConfigError, VehicleConfig
from runtime.contract import VelocityBodyYawspeed
from runtime.tracking import VelocityBias, setpoint_with_bias
from runtime.vehicle import Vehicle

FIXTURE = Path(__file__).parent / "fixtures" / "px4_v1_16_velocity_bias.json"


def _rms(a: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(a * a, axis=0))


def test_on_px4_sih_the_corrected_velocity_is_nearer_the_truth():
    """PX4 SIH's EKF2 reports a velocity 0.2-0.4 m/s off the truth for seconds while its position
    moves with the truth; less the measured bias, the velocity is within ~half that."""
    record = json.loads(FIXTURE.read_text())
    raw_err, corrected_err = [], []
    for flight in record["flights"]:
        t = np.array(flight["t_s"])
        pos, vel, truth = (np.array(flight[k]) for k in ("pos_enu_m", "vel_enu_m_s", "truth_vel_enu_m_s"))
        bias_of = VelocityBias()
        bias = np.stack([bias_of.update(t[i], pos[i], vel[i]).copy() for i in range(len(t))])
        settled = t - t[0] >= 1.0  # the window filled long ago
        raw_err.append((vel - truth)[settled])
        corrected_err.append((vel - bias - truth)[settled])
    raw, corrected = _rms(np.concatenate(raw_err)), _rms(np.concatenate(corrected_err))
    raw_h, corrected_h = math.hypot(raw[0], raw[1]), math.hypot(corrected[0], corrected[1])
    assert raw_h > 0.25, f"the recording no longer shows PX4's velocity error: {raw.round(3)}"
    assert corrected_h < 0.6 * raw_h, f"horizontal RMS error {raw_h:.3f} -> {corrected_h:.3f} m/s"
    assert corrected[2] < raw[2], f"vertical RMS error {raw[2]:.3f} -> {corrected[2]:.3f} m/s"


def _accelerating(bias_enu: np.ndarray, n: int = 40, dt: float = 0.1, accel: float = 2.5):
    for i in range(n):
        t = i * dt
        pos = np.array([0.5 * accel * t * t, -0.4 * t, 2.0])
        vel = np.array([accel * t, -0.4, 0.0]) + bias_enu
        yield t, pos, vel


def test_acceleration_is_not_taken_for_bias_and_a_steady_bias_is_found():
    bias_of = VelocityBias(window_s=0.3)
    true_bias = np.array([0.1, 0.3, -0.1])
    found = [bias_of.update(t, p, v).copy() for t, p, v in _accelerating(true_bias)]
    assert np.allclose(found[0], 0.0) and np.allclose(found[2], 0.0)  # window not full yet: no bias
    assert np.allclose(found[-1], true_bias, atol=1e-9)
    assert np.allclose(VelocityBias().update(0.0, np.zeros(3), np.ones(3)), 0.0)


def test_bias_is_bounded():
    bias_of = VelocityBias(max_m_s=0.5)
    found = [bias_of.update(t, p, v).copy() for t, p, v in _accelerating(np.array([2.0, 0.0, 0.0]))]
    assert math.isclose(float(np.linalg.norm(found[-1])), 0.5)


@pytest.mark.parametrize("how", ["gap", "jump", "clock_back", "nan"])
def test_gaps_resets_and_garbage_restart_the_window(how):
    bias_of = VelocityBias(window_s=0.3, max_gap_s=0.5)
    true_bias = np.array([0.0, 0.3, 0.0])
    for t, p, v in _accelerating(true_bias, n=10):
        bias_of.update(t, p, v)
    assert np.allclose(bias_of.bias_enu_m_s, true_bias)
    t, p, v = 0.9, np.array([1.0, -0.36, 2.0]), np.array([2.25, -0.1, 0.0])
    if how == "gap":
        t = 2.0
    elif how == "jump":
        p = p + np.array([1.5, 0.0, 0.0])  # an EKF reset: 1.5 m in 0.1 s
        t = 1.0
    elif how == "clock_back":
        t = -5.0  # a rebooted autopilot
    else:
        v = np.array([np.nan, 0.0, 0.0])
    assert np.allclose(bias_of.update(t, p, v), 0.0)
    assert bias_of.resets == 1


def test_an_estimate_not_newer_changes_nothing():
    bias_of = VelocityBias()
    for t, p, v in _accelerating(np.array([0.0, 0.2, 0.0]), n=10):
        bias_of.update(t, p, v)
    before = bias_of.bias_enu_m_s.copy()
    assert np.allclose(bias_of.update(0.9, np.zeros(3), np.zeros(3)), before)  # same time as the last
    assert bias_of.resets == 0


@pytest.mark.parametrize("yaw_deg", [0.0, 90.0, -135.0])
def test_the_autopilot_holding_its_estimate_at_the_corrected_setpoint_flies_the_command(yaw_deg):
    """PX4 holds its estimate (truth + bias) at the setpoint: with the bias added, the truth is the
    command, in every heading."""
    yaw = math.radians(yaw_deg)
    bias = np.array([0.2, -0.3, 0.1])
    cmd_fwd, cmd_right, cmd_down = 1.5, 0.0, -0.2
    fwd, right, down = setpoint_with_bias(cmd_fwd, cmd_right, cmd_down, bias, yaw)

    def body_frd_to_enu(f, r, d):
        left = -r
        return np.array([f * math.cos(yaw) - left * math.sin(yaw), f * math.sin(yaw) + left * math.cos(yaw), -d])

    truth = body_frd_to_enu(fwd, right, down) - bias
    assert np.allclose(truth, body_frd_to_enu(cmd_fwd, cmd_right, cmd_down))


def _odometry(t_us: int, north_m: float, north_m_s: float) -> SimpleNamespace:
    return SimpleNamespace(
        time_usec=t_us,
        position_body=SimpleNamespace(x_m=north_m, y_m=0.0, z_m=-2.0),
        velocity_body=SimpleNamespace(x_m_s=north_m_s, y_m_s=0.0, z_m_s=0.0),
        q=SimpleNamespace(w=1.0, x=0.0, y=0.0, z=0.0),  # facing north
        angular_velocity_body=SimpleNamespace(roll_rad_s=0.0, pitch_rad_s=0.0, yaw_rad_s=0.0),
    )


class _Offboard:
    def __init__(self) -> None:
        self.sent: list = []
        self._plugin = SimpleNamespace(set_velocity_body=self.sent.append)


def _feed(vehicle: Vehicle) -> None:
    """Standing still (the position does not move) while the estimate says 0.3 m/s north."""
    for i in range(10):
        vehicle._fields.update(vehicle._estimate_fields(_odometry(1_000_000 + i * 100_000, 5.0, 0.3)))


def test_the_adapter_reports_the_corrected_velocity_and_sends_the_corrected_setpoint():
    vehicle = Vehicle(VehicleConfig())
    vehicle._offboard = _Offboard()
    _feed(vehicle)
    state = vehicle.state()
    assert np.allclose(state.vel_bias_enu_m_s, [0.0, 0.3, 0.0])  # ENU: north is y
    assert np.allclose(state.vel_enu_m_s, 0.0)
    asyncio.run(vehicle.set_velocity_body(VelocityBodyYawspeed(1.0, 0.0, 0.0, 0.0)))
    sent = vehicle._offboard.sent[-1]
    assert math.isclose(sent.forward_m_s, 1.3) and abs(sent.right_m_s) < 1e-12 and sent.down_m_s == 0.0


def test_correction_off_keeps_the_autopilots_velocity_and_setpoints():
    vehicle = Vehicle(VehicleConfig(velocity_bias_correction=False))
    vehicle._offboard = _Offboard()
    _feed(vehicle)
    state = vehicle.state()
    assert np.allclose(state.vel_enu_m_s, [0.0, 0.3, 0.0]) and np.allclose(state.vel_bias_enu_m_s, 0.0)
    asyncio.run(vehicle.set_velocity_body(VelocityBodyYawspeed(1.0, 0.0, 0.0, 0.0)))
    assert vehicle._offboard.sent[-1].forward_m_s == 1.0


def test_the_window_is_validated():
    with pytest.raises(ConfigError, match="vehicle.velocity_bias_window_s"):
        VehicleConfig(velocity_bias_window_s=5.0)
