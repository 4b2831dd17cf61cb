"""Quadrotor dynamics: velocity tracking, limits, yaw sign, hover, kicks, batching."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from runtime.contract import frames
from sim.dynamics import DynamicsParams, QuadrotorDynamics, QuadState, vel_body_flu

DT_S = 0.01  # the SITL vehicle's 100 Hz physics step
PARAMS = DynamicsParams()


def fly(
    state: QuadState,
    vel_cmd: torch.Tensor,
    yaw_rate_cmd: torch.Tensor,
    duration_s: float,
    dynamics: QuadrotorDynamics = QuadrotorDynamics(),
) -> QuadState:
    for _ in range(round(duration_s / DT_S)):
        state = dynamics.step(state, vel_cmd, yaw_rate_cmd, DT_S)
    return state


def rest(batch: int = 1, z_m: float = 2.0, yaw_rad: float = 0.0) -> QuadState:
    pos = torch.tensor([[3.0, 3.0, z_m]]).repeat(batch, 1)
    return QuadState.at_rest(pos, yaw_rad)


def test_hover_holds_altitude_and_attitude() -> None:
    start = rest(z_m=2.5)
    end = fly(start, torch.zeros(1, 3), torch.zeros(1), 3.0)
    assert torch.allclose(end.pos_enu_m, start.pos_enu_m, atol=1e-5)
    assert torch.allclose(end.vel_enu_m_s, torch.zeros(1, 3), atol=1e-5)
    assert float(end.tilt_rad()) < 1e-5


def test_tracks_commanded_velocity_within_10_percent_in_2_s() -> None:
    gen = torch.Generator().manual_seed(0)
    batch = 64
    speed = torch.rand(batch, generator=gen) * 1.9 + 0.1  # the contract's speed range, (0, 2] m/s
    incl = (torch.rand(batch, generator=gen) * 2 - 1) * math.pi / 4
    heading = (torch.rand(batch, generator=gen) * 2 - 1) * math.pi
    cmd = torch.stack([speed * incl.cos() * heading.cos(), speed * incl.cos() * heading.sin(), speed * incl.sin()], -1)
    end = fly(rest(batch, z_m=10.0), cmd, torch.zeros(batch), 2.0)  # high enough not to land
    error = torch.linalg.vector_norm(end.vel_enu_m_s - cmd, dim=-1)
    assert torch.all(error <= 0.1 * speed), error.max()


def test_tilt_never_exceeds_limit_under_aggressive_commands_and_kicks() -> None:
    gen = torch.Generator().manual_seed(1)
    dynamics = QuadrotorDynamics()
    batch = 32
    state = rest(batch)
    max_tilt = torch.zeros(batch)
    for step in range(400):
        if step % 20 == 0:
            cmd = (torch.rand(batch, 3, generator=gen) * 2 - 1) * 8.0
            yaw_rate = (torch.rand(batch, generator=gen) * 2 - 1) * 2.0
        kick = (torch.rand(batch, 3, generator=gen) * 2 - 1) * 20.0 * (torch.rand(batch, 1, generator=gen) < 0.05)
        state = dynamics.step(state, cmd, yaw_rate, DT_S, kick_force_n=kick)
        max_tilt = torch.maximum(max_tilt, state.tilt_rad())
        assert torch.allclose(torch.linalg.vector_norm(state.quat_enu_flu, dim=-1), torch.ones(batch), atol=1e-5)
    assert torch.all(max_tilt <= PARAMS.max_tilt_rad + 1e-4)
    assert float(max_tilt.max()) > PARAMS.max_tilt_rad - 0.05, "the limit is reached, so the test bites"


def test_positive_yaw_rate_turns_left() -> None:
    end = fly(rest(yaw_rad=0.3), torch.zeros(1, 3), torch.tensor([0.5]), 2.0)
    # 0.5 rad/s for 2 s, less the lag of the first-order yaw-rate response (0.5 * tau).
    expected = 0.3 + 0.5 * (2.0 - PARAMS.yaw_rate_tau_s)
    assert float(end.yaw_enu_rad()) == pytest.approx(expected, abs=0.01)
    assert float(end.angvel_body_flu_rad_s[0, 2]) == pytest.approx(0.5, abs=1e-3)
    backwards = fly(rest(yaw_rad=0.3), torch.zeros(1, 3), torch.tensor([-0.5]), 1.0)
    assert float(backwards.yaw_enu_rad()) < 0.3


def test_forward_acceleration_pitches_nose_down_and_body_velocity_is_forward() -> None:
    # Heading north (yaw +90 deg), commanded north: body-forward motion.
    state = fly(rest(yaw_rad=math.pi / 2), torch.tensor([[0.0, 1.5, 0.0]]), torch.zeros(1), 0.3)
    roll, pitch = state.roll_pitch_rad()[0].tolist()
    assert pitch > 0.1 and abs(roll) < 1e-3, "contract convention: positive pitch = nose down"
    vel_body = state.vel_body_flu_m_s()[0]
    assert float(vel_body[0]) > 0.3 and abs(float(vel_body[1])) < 1e-3


def test_kick_perturbs_then_controller_recovers() -> None:
    dynamics = QuadrotorDynamics()
    state = rest()
    kick = torch.tensor([[0.0, 10.0, 0.0]])  # 10 N sideways on a 1 kg vehicle for 0.05 s
    for _ in range(5):
        state = dynamics.step(state, torch.zeros(1, 3), torch.zeros(1), DT_S, kick_force_n=kick)
    assert float(state.vel_enu_m_s[0, 1]) > 0.3
    state = fly(state, torch.zeros(1, 3), torch.zeros(1), 3.0, dynamics)
    assert float(torch.linalg.vector_norm(state.vel_enu_m_s)) < 0.02


def test_vertical_acceleration_is_limited() -> None:
    dynamics = QuadrotorDynamics()
    state = dynamics.step(rest(), torch.tensor([[0.0, 0.0, 10.0]]), torch.zeros(1), DT_S)
    assert float(state.vel_enu_m_s[0, 2]) == pytest.approx(PARAMS.max_accel_up_m_s2 * DT_S, rel=1e-3)


def test_ground_contact_keeps_vehicle_on_the_floor() -> None:
    end = fly(rest(z_m=0.3), torch.tensor([[0.0, 0.0, -1.0]]), torch.zeros(1), 2.0)
    assert float(end.pos_enu_m[0, 2]) == 0.0
    assert float(end.vel_enu_m_s[0, 2]) >= 0.0


def test_batched_step_equals_per_env_steps() -> None:
    gen = torch.Generator().manual_seed(2)
    batch = 5
    cmd = torch.randn(batch, 3, generator=gen)
    yaw_rate = torch.randn(batch, generator=gen)
    kick = torch.randn(batch, 3, generator=gen)
    initial = QuadState.at_rest(torch.rand(batch, 3, generator=gen) * 3 + 1, torch.randn(batch, generator=gen))
    dynamics = QuadrotorDynamics()
    together = initial
    for _ in range(30):
        together = dynamics.step(together, cmd, yaw_rate, DT_S, kick_force_n=kick)
    for i in range(batch):
        alone = initial.select(i)
        for _ in range(30):
            alone = dynamics.step(alone, cmd[i : i + 1], yaw_rate[i : i + 1], DT_S, kick_force_n=kick[i : i + 1])
        for name in ("pos_enu_m", "vel_enu_m_s", "quat_enu_flu", "angvel_body_flu_rad_s"):
            assert torch.allclose(getattr(alone, name), getattr(together.select(i), name), atol=1e-6), name


def test_state_helpers_match_the_contract_frames() -> None:
    gen = torch.Generator().manual_seed(3)
    quat = torch.randn(16, 4, generator=gen, dtype=torch.float64)
    quat = quat / quat.norm(dim=-1, keepdim=True)
    vel = torch.randn(16, 3, generator=gen, dtype=torch.float64)
    state = QuadState(torch.zeros(16, 3, dtype=torch.float64), vel, quat, torch.zeros(16, 3, dtype=torch.float64))
    expected_body = frames.quat_rotate(frames.quat_conjugate(quat.numpy()), vel.numpy())
    np.testing.assert_allclose(state.vel_body_flu_m_s().numpy(), expected_body, atol=1e-12)
    np.testing.assert_allclose(vel_body_flu(quat, vel).numpy(), expected_body, atol=1e-12)
    euler = frames.euler_from_quat(quat.numpy())
    np.testing.assert_allclose(state.roll_pitch_rad().numpy(), euler[:, :2], atol=1e-12)
    np.testing.assert_allclose(state.yaw_enu_rad().numpy(), euler[:, 2], atol=1e-12)


def test_bad_params_are_named() -> None:
    with pytest.raises(ValueError, match="max_tilt_rad"):
        QuadrotorDynamics(DynamicsParams(max_tilt_rad=2.0))
    with pytest.raises(ValueError, match="max_accel_down_m_s2"):
        QuadrotorDynamics(DynamicsParams(max_accel_down_m_s2=12.0))
