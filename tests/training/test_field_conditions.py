"""The field in the batched env (training.policy.field, issue 28): each effect measured on its own
and seeded (image-to-command latency, the autopilot's command delay, speed caps, state-estimate
noise/bias/delay, PX4's randomized response), then all together as Table II's ``field``."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, replace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.contract import action_to_velocity_flu
from runtime.contract.action import ActionLimits
from runtime.contract.constants import CONTROL_PERIOD_S, LATENT_DIM, MAX_INCLINATION_RAD, MAX_SPEED_M_S, STATE_DIM
from sim.delay import DelayLine, delay_steps
from sim.dynamics import (PER_ENV_PARAMS, PX4_SIH_V1_16, CommandDelay, DynamicsRandomization, QuadrotorDynamics, QuadState,
                          sample_dynamics)  # fmt: skip
from sim.estimate import PX4_EKF2_CORRECTED, StateEstimateConfig, StateEstimator
from sim.rotations import rotate_about_z
from training.checkpoint import checkpoint_fingerprint, save_weights
from training.cmwae.model import Cmwae, make_config
from training.policy.contract_torch import action_to_velocity_flu_batch
from training.policy.dagger import DaggerConfig
from training.policy.env import NavEnv, NavEnvConfig
from training.policy.evaluate import PolicyEvalConfig, condition_env_overrides, evaluate_policy, table2_env
from training.policy.field import FieldConfigError, field_action_limits, field_env_overrides, px4_vehicle_env_overrides
from training.policy.network import POLICY_SIZES, ActorCritic
from training.policy.train import PolicyTrainConfig

pytestmark = pytest.mark.timeout(300)
PX4 = replace(PX4_SIH_V1_16, ground_contact=False)
FORWARD = (1.0, 0.0, 0.0)  # full speed ahead, level
HOVER = (-1.0, 0.0, 0.0)  # speed 0


@pytest.fixture(scope="module")
def encoder():
    torch.manual_seed(0)
    return Cmwae(make_config("tiny")).encoder.eval()


def _env(encoder, num_envs: int = 2, level: int = 0, seed: int = 5, **overrides) -> NavEnv:
    config = NavEnvConfig(num_envs=num_envs, kick_probability=0.0, corruption="none", camera_jitter=False, **overrides)
    env = NavEnv(config, encoder, seed=seed, fixed_level=level, auto_reset=False)
    env.reset()
    return env


def _fly(env: NavEnv, actions: list[tuple[float, float, float]]) -> list[torch.Tensor]:
    positions = []
    for action in actions:
        env.step(torch.tensor([action] * env.num_envs))
        positions.append(env.state.pos_enu_m.clone())
    return positions


def test_image_to_command_latency_applies_the_action_whole_steps_late(encoder):
    """With a latency of exactly 2 control periods the vehicle flies, step for step, what the
    undelayed vehicle flies when given the same actions 2 steps later (hovering before)."""
    actions = [FORWARD] * 4 + [(0.0, 0.5, 1.0)] * 4 + [HOVER] * 2
    late = _fly(_env(encoder, latency_range_s=(2 * CONTROL_PERIOD_S, 2 * CONTROL_PERIOD_S)), actions)
    shifted = _fly(_env(encoder), [HOVER] * 2 + actions)
    undelayed = _fly(_env(encoder), actions)
    for k in range(len(actions)):
        torch.testing.assert_close(late[k], shifted[k], atol=1e-5, rtol=0)
    torch.testing.assert_close(late[1], late[0], atol=1e-6, rtol=0)  # 2 steps of hover first, then it flies
    assert float((late[-1] - late[1]).norm()) > 0.3
    assert float((late[3] - undelayed[3]).norm()) > 0.05  # not what the undelayed vehicle flies


def test_latency_is_drawn_per_episode_in_its_range_at_the_physics_rate(encoder):
    env = _env(encoder, num_envs=64, latency_range_s=(0.02, 0.08))
    assert float(env.latency_s.min()) >= 0.02 and float(env.latency_s.max()) <= 0.08
    assert float(env.latency_s.std()) > 0.01
    dt_s = env.config.physics_dt_s
    assert torch.equal(env.latency_steps, torch.ceil(env.latency_s.double() / dt_s - 1e-6).long())
    # A partial-period latency: the first step's command acts for only the tail of the period.
    partial, none = _env(encoder, latency_range_s=(0.04, 0.04)), _env(encoder)
    for env_ in (partial, none):
        env_.step(torch.tensor([FORWARD] * 2))
    speed_partial, speed_none = (float(e.state.vel_body_flu_m_s()[0, 0]) for e in (partial, none))
    assert 0.0 < speed_partial < speed_none


def test_autopilot_command_delay_equals_commanddelay_at_the_physics_rate(encoder):
    """PX4's identified per-axis delays hold the commands back as sim.dynamics.CommandDelay does."""
    env = _env(encoder, num_envs=1, dynamics=PX4)
    state = QuadState(*(None if v is None else v.clone() for v in (env.state.pos_enu_m, env.state.vel_enu_m_s,
                                                                   env.state.quat_enu_flu, env.state.angvel_body_flu_rad_s, None)))  # fmt: skip
    # Hover first: CommandDelay holds its first command until a command is due, the env (like the
    # runtime's hover setpoint before offboard) a hover.
    actions = [HOVER] + [FORWARD] * 5 + [(0.5, 0.8, -1.0)] * 5 + [HOVER] * 3
    dynamics, delay, dt_s = QuadrotorDynamics(PX4), CommandDelay(PX4), env.config.physics_dt_s
    i = 0
    for action in actions:
        env.step(torch.tensor([action]))
        cmd = action_to_velocity_flu_batch(torch.tensor([action]))
        for _ in range(env.config.physics_substeps):
            vel, yaw = delay.push(i * dt_s, rotate_about_z(cmd[:, :3], state.yaw_enu_rad()), cmd[:, 3])
            state = dynamics.step(state, vel, yaw, dt_s)
            i += 1
        torch.testing.assert_close(env.state.pos_enu_m, state.pos_enu_m, atol=1e-5, rtol=0)
        torch.testing.assert_close(env.state.quat_enu_flu, state.quat_enu_flu, atol=1e-5, rtol=0)
    assert env.command_delay_steps[0].tolist() == delay_steps(torch.tensor([PX4.command_delay_xy_s] * 2 + [
        PX4.command_delay_z_s, PX4.command_delay_yaw_s]), dt_s).tolist()  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(action=st.tuples(*[st.floats(-3, 3, allow_nan=False)] * 3), speed=st.floats(0.0, MAX_SPEED_M_S),
       incl=st.floats(0.0, MAX_INCLINATION_RAD))  # fmt: skip
def test_capped_action_twin_equals_the_runtime(action, speed, incl):
    limits = ActionLimits(max_speed_m_s=speed, max_inclination_rad=incl)
    ours = action_to_velocity_flu_batch(torch.tensor([action], dtype=torch.float64), limits)[0].numpy()
    np.testing.assert_allclose(ours, action_to_velocity_flu(np.array(action), limits), atol=1e-9)


def test_commanded_speed_and_climb_angle_never_exceed_the_field_caps(encoder):
    limits = field_action_limits()
    assert (limits.max_speed_m_s, limits.max_inclination_rad) == (1.0, 0.35)  # examples/cmnav.toml
    env = _env(encoder, num_envs=3, action_limits=limits)
    actions = torch.tensor([[1.0, 1.0, 0.0], [1.0, -1.0, 0.5], [0.6, 0.3, -0.2]])
    cmd = action_to_velocity_flu_batch(actions, limits)
    assert float(torch.linalg.vector_norm(cmd[:, :3], dim=-1).max()) <= limits.max_speed_m_s + 1e-6
    assert float(torch.atan2(cmd[:, 2].abs(), cmd[:, 0]).max()) <= limits.max_inclination_rad + 1e-6
    speeds = []
    for _ in range(30):  # 2 s: the ideal vehicle settles on its command
        env.step(actions)
        speeds.append(torch.linalg.vector_norm(env.state.vel_enu_m_s, dim=-1))
    settled = torch.stack(speeds[-5:])
    assert float(settled.max()) <= limits.max_speed_m_s * 1.03
    assert float(settled[:, 0].min()) >= 0.9 * limits.max_speed_m_s  # and the cap, not less, is flown


def test_field_config_limits_errors_name_the_key_and_the_fix(tmp_path):
    bad = tmp_path / "cmnav.toml"
    bad.write_text("[policy.limits]\nmax_speed_m_s = 3.0\n")
    with pytest.raises(FieldConfigError, match=r"\[policy.limits\] max_speed_m_s=3.0 must be in"):
        field_action_limits(bad)
    bad.write_text("[policy.limits]\nmax_speed = 1.0\n")
    with pytest.raises(FieldConfigError, match="unknown keys"):
        field_action_limits(bad)
    with pytest.raises(FieldConfigError, match="not found"):
        field_action_limits(tmp_path / "missing.toml")
    overrides = field_env_overrides(ActionLimits(max_speed_m_s=0.5))
    assert overrides["episode_duration_s"] == pytest.approx(40.0)  # 10 s at 2 m/s -> 40 s at 0.5 m/s


def test_state_estimate_is_the_truth_delayed_plus_bias_and_noise():
    dt_s = CONTROL_PERIOD_S / 7
    n = 256
    config = StateEstimateConfig(delay_range_s=(3 * dt_s, 3 * dt_s), position_drift_m=(0.0, 0.0), velocity_drift_m_s=(0.0, 0.0))
    estimator = StateEstimator(config, n, dt_s)
    gen = torch.Generator().manual_seed(0)
    pos = torch.zeros(n, 3)
    estimator.reset(torch.arange(n), QuadState.at_rest(pos), gen)
    assert estimator.delay_steps.unique().tolist() == [3]
    truths = []
    for i in range(1, 9):  # the vehicle moves 1 m along x per physics step
        state = QuadState.at_rest(pos + torch.tensor([float(i), 0.0, 0.0]))
        state.vel_enu_m_s[:, 0] = float(i)
        estimator.record(state, gen)
        truths.append(state)
    samples = torch.stack([estimator.estimate(gen).vel_enu_m_s for _ in range(40)])  # [40, n, 3]
    error = samples - torch.tensor([5.0, 0.0, 0.0])  # the truth 3 steps before the newest (8)
    # Per-episode bias: constant over an episode's samples, spread over episodes as configured.
    bias = error.mean(dim=0)
    torch.testing.assert_close(bias, estimator.velocity_bias_m_s, atol=4 * config.velocity_noise_m_s / math.sqrt(40), rtol=0)
    horizontal, vertical = config.velocity_bias_m_s
    assert float(estimator.velocity_bias_m_s[:, :2].std()) == pytest.approx(horizontal, rel=0.15)
    assert float(estimator.velocity_bias_m_s[:, 2].std()) == pytest.approx(vertical, rel=0.15)
    assert float((error - bias).std()) == pytest.approx(config.velocity_noise_m_s, rel=0.05)
    est = estimator.estimate(gen)
    assert float((est.pos_enu_m[:, 0] - 5.0).abs().max()) < 6 * (config.position_bias_m[0] + config.position_noise_m)
    # Attitude: a small rotation of the level truth, ~0.5 deg noise + ~0.5 deg bias per axis.
    roll_pitch = torch.stack([est.roll_pitch_rad() for est in (estimator.estimate(gen) for _ in range(20))])
    assert float(roll_pitch.std()) == pytest.approx(math.hypot(config.attitude_noise_rad, config.attitude_bias_rad), rel=0.15)


def test_state_estimate_drift_wanders_with_its_measured_size_and_correlation_times():
    """The drift is PX4 SIH's wandering error: stationary from the first step (drawn at reset), its
    spread per axis as configured, its autocorrelation exp(-lag / correlation time), position's and
    velocity's each their own (the runtime-corrected velocity's is short: 0.7 s against 2.5 s)."""
    dt_s = CONTROL_PERIOD_S / 7
    n = 2048
    config = PX4_EKF2_CORRECTED
    assert config.velocity_drift_correlation_s < config.drift_correlation_s
    estimator = StateEstimator(config, n, dt_s)
    gen = torch.Generator().manual_seed(1)
    state = QuadState.at_rest(torch.zeros(n, 3))
    estimator.reset(torch.arange(n), state, gen)
    start = estimator.drift.clone()
    lag_s = config.velocity_drift_correlation_s
    for _ in range(round(lag_s / dt_s)):
        estimator.record(state, gen)
    later = estimator.drift
    expected_sd = torch.tensor([*config.position_drift_m[:1] * 2, config.position_drift_m[1], *config.velocity_drift_m_s[:1] * 2, config.velocity_drift_m_s[1]])
    for drift in (start, later):
        torch.testing.assert_close(drift.std(dim=0), expected_sd, rtol=0.08, atol=0.0)
    correlation = (start * later).mean(dim=0) / (start.std(dim=0) * later.std(dim=0))
    expected = torch.tensor([math.exp(-lag_s / config.drift_correlation_s)] * 3 + [math.exp(-1.0)] * 3)
    assert float((correlation - expected).abs().max()) < 0.08, correlation
    # The estimate carries it: position error = bias + drift (+ noise); the bias stays, the drift moves.
    est = estimator.estimate(gen)
    error = est.pos_enu_m - estimator._line.read(estimator.delay_steps)[:, 0:3]
    residual = error - estimator.position_bias_m - later[:, 0:3]
    assert float(residual.std()) == pytest.approx(config.position_noise_m, rel=0.1)


def test_the_autopilot_holds_its_estimate_so_the_truth_slides_by_the_estimates_error(encoder):
    """PX4 controls its estimated velocity: told to hover, the vehicle whose estimate is 0.4 m/s
    off drifts at -0.4 m/s in truth while its estimate (what the policy sees) reads ~0."""
    config = StateEstimateConfig(velocity_bias_m_s=(0.4, 0.2), velocity_drift_m_s=(0.0, 0.0), velocity_noise_m_s=0.0,
                                 position_drift_m=(0.0, 0.0))  # fmt: skip
    env = _env(encoder, num_envs=64, state_estimate=config)
    for _ in range(30):  # 2 s: the velocity loop has settled
        obs = env.step(torch.tensor([HOVER] * 64)).obs
    bias = env.estimator.velocity_bias_m_s
    assert float(bias.abs().mean()) > 0.15
    torch.testing.assert_close(env.state.vel_enu_m_s, -bias, atol=0.08, rtol=0)
    assert float(obs[:, 6:9].abs().max()) < 0.1  # the estimated body velocity: at the setpoint


def test_the_env_observes_the_estimate_and_rewards_the_truth(encoder):
    config = StateEstimateConfig()
    env = _env(encoder, num_envs=64, state_estimate=config)
    obs = env.step(torch.tensor([HOVER] * 64)).obs
    true_obs = env._state_observation()
    vel_error = obs[:, 6:9] - true_obs[:, 6:9]  # body velocity (m/s): noise + bias + drift
    per_axis = [math.hypot(config.velocity_noise_m_s, b, d) for b, d in zip(config.velocity_bias_m_s, config.velocity_drift_m_s)]
    expected = math.sqrt((2 * per_axis[0] ** 2 + per_axis[1] ** 2) / 3)  # level: body x, y horizontal, z vertical
    assert float(vel_error.std()) == pytest.approx(expected, rel=0.2)
    assert torch.equal(obs[:, 12:15], true_obs[:, 12:15])  # the previous action is the policy's own


def test_randomized_dynamics_stay_in_range_and_equal_values_fly_the_scalar_path():
    gen = torch.Generator().manual_seed(0)
    r = DynamicsRandomization()
    drawn = sample_dynamics(PX4, r, 2000, gen)
    for name, values in drawn.items():
        nominal = getattr(PX4, name)
        ratio = values / nominal
        assert float(ratio.min()) >= 1 - r.fraction(name) - 1e-6 and float(ratio.max()) <= 1 + r.fraction(name) + 1e-6
        assert float(ratio.max() - ratio.min()) > 1.8 * r.fraction(name), name  # the range is used
    assert torch.equal(drawn["velocity_gain_1_s"], sample_dynamics(PX4, r, 2000, torch.Generator().manual_seed(0))["velocity_gain_1_s"])
    # Per-env values equal to the scalars: the same flight as the scalar path.
    b = 4
    state = QuadState.at_rest(torch.zeros(b, 3) + 2.0, torch.linspace(-1, 1, b))
    per_env = {name: torch.full((b,), float(getattr(PX4, name))) for name in PER_ENV_PARAMS}
    dyn = QuadrotorDynamics(PX4)
    a = b_ = state
    cmd, yaw = torch.tensor([[1.5, -0.5, 0.3]] * b), torch.tensor([0.7] * b)
    for _ in range(60):
        a = dyn.step(a, cmd, yaw, 0.01)
        b_ = dyn.step(b_, cmd, yaw, 0.01, per_env=per_env)
    for name in ("pos_enu_m", "vel_enu_m_s", "quat_enu_flu", "angvel_body_flu_rad_s", "vel_error_integral_m"):
        # float32: the scalar path's math.exp is double, the per-env path's torch.exp single precision
        torch.testing.assert_close(getattr(b_, name), getattr(a, name), atol=5e-4, rtol=0)
    with pytest.raises(ValueError, match="not supported"):
        dyn.step(state, cmd, yaw, 0.01, per_env={"mass_kg": torch.ones(b)})


def test_randomized_vehicles_answer_the_same_command_differently(encoder):
    env = _env(encoder, num_envs=16, dynamics=PX4, dynamics_randomization=DynamicsRandomization())
    for _ in range(15):
        env.step(torch.tensor([FORWARD] * 16))
    speed = env.state.vel_body_flu_m_s()[:, 0]
    assert float(speed.std()) > 0.03 and float(speed.max()) < 2.0
    delays = env.command_delay_s[:, 0] / PX4.command_delay_xy_s
    assert float(delays.min()) >= 0.7 - 1e-6 and float(delays.max()) <= 1.3 + 1e-6 and float(delays.std()) > 0.05
    # A new episode draws its own vehicle; the same seed draws the same ones.
    again = _env(encoder, num_envs=16, dynamics=PX4, dynamics_randomization=DynamicsRandomization())
    torch.testing.assert_close(again.dynamics_per_env["velocity_gain_1_s"], env.dynamics_per_env["velocity_gain_1_s"])
    env._reset_envs(torch.tensor([0]))
    assert float(env.dynamics_per_env["velocity_gain_1_s"][0]) != float(again.dynamics_per_env["velocity_gain_1_s"][0])


def test_delay_line_refuses_a_delay_it_cannot_hold():
    line = DelayLine(DelayLine.capacity_for(0.05, 0.01), 2, 1)
    line.push(torch.ones(2, 1))
    assert line.read(torch.tensor([0, 5])).flatten().tolist() == [1.0, 0.0]
    with pytest.raises(ValueError, match="capacity_for"):
        line.read(torch.tensor([6, 0]))


def test_field_condition_and_dagger_field_config_set_every_effect_together(encoder):
    env = table2_env(encoder, level=2, condition="field", num_envs=2, device="cpu", seed=1)
    cfg = env.config
    assert cfg.corruption == "stereo" and env.stereo_sensor.config.projector_on
    assert cfg.gray_camera is not None and cfg.state_estimate is not None and cfg.dynamics_randomization is not None
    assert cfg.latency_range_s[1] > 0 and cfg.action_limits == field_action_limits()
    assert cfg.dynamics.command_delay_xy_s == PX4_SIH_V1_16.command_delay_xy_s
    assert cfg.max_steps == 300  # 20 s: the paper's 10 s at half the top speed
    env.reset()
    env.step(torch.zeros(2, 3))
    assert env.stage_seconds["stereo"] > 0 and env.stage_seconds["gray"] > 0
    assert env.last_gray is not None and not torch.equal(env.last_gray.gray_u8, env.last_render.gray_u8)
    student = DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", num_envs=2, field_conditions=True)
    student.validate()
    env_config = student.env_config()
    for key, value in field_env_overrides().items():
        assert getattr(env_config, key) == value, key
    assert env_config.corruption == "stereo" and env_config.level_sampling == "uniform"
    assert DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o").env_config().gray_camera is None


def test_evaluate_policy_runs_the_field_condition_and_records_its_settings(tmp_path):
    torch.manual_seed(0)
    config = make_config("tiny")
    save_weights(tmp_path / "enc", Cmwae(config), "cmwae", asdict(config), 0, {"train": {"scheme": "s2"}})
    save_weights(tmp_path / "policy", ActorCritic(POLICY_SIZES["tiny"]), "policy", POLICY_SIZES["tiny"].to_json(), 0,
                 {"encoder_fingerprint": checkpoint_fingerprint(tmp_path / "enc")})  # fmt: skip
    evaluate_policy(PolicyEvalConfig(str(tmp_path / "policy"), str(tmp_path / "enc"), levels=(1,), conditions=("field",),
                                     episodes=2, batch_envs=2, rooms="test", out_dir=str(tmp_path / "eval"),
                                     plots_per_cell=0, precision="fp32", episode_duration_s=0.4))  # fmt: skip
    written = json.loads((tmp_path / "eval" / "table2.json").read_text())
    (cell,) = written["cells"]
    assert cell["condition"] == "field" and cell["episodes"] == 2
    assert cell["success_pct"] + cell["timeout_pct"] + cell["crash_pct"] == pytest.approx(100.0)
    field = written["field"]["field"]
    assert field["action_limits"] == {"max_speed_m_s": 1.0, "max_inclination_rad": 0.35}
    assert field["state_estimate"]["position_drift_m"] == list(StateEstimateConfig().position_drift_m) and field["latency_range_s"] == [0.02, 0.08]
    assert written["stereo_sensor"]["field"]["projector_on"]
    assert written["config"]["episode_duration_s"] == 0.4


def test_px4_condition_and_dagger_px4_vehicle_fly_pxs_response_with_the_trained_camera(encoder):
    env = table2_env(encoder, level=2, condition="px4", num_envs=2, device="cpu", seed=1)
    cfg = env.config
    assert cfg.corruption == "none" and cfg.gray_camera is None and cfg.action_limits is None
    assert cfg.dynamics == PX4 and cfg.dynamics_randomization is not None and cfg.state_estimate is not None
    assert cfg.latency_range_s[1] > 0 and cfg.max_steps == NavEnvConfig().max_steps  # the contract's speeds, its 10 s
    student = DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", num_envs=2, vehicle="px4")
    student.validate()
    env_config = student.env_config()
    assert env_config.dynamics == PX4 and env_config.corruption == "train" and env_config.gray_camera is None
    for wrong, match in (({"vehicle": "px5"}, "vehicle"), ({"vehicle": "px4", "field_conditions": True}, "one of them"),
                         ({"vehicle": "field", "field_conditions": True}, "one of them")):
        with pytest.raises(ValueError, match=match):
            DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", **wrong).validate()


def test_the_field_vehicle_is_the_fields_less_its_camera():
    """``--vehicle field`` (a teacher for a field student) flies Table II's ``field`` vehicle, caps
    and episode length, on clean depth and without the field's gray camera."""
    teacher = PolicyTrainConfig(encoder_dir=None, out_dir="o", num_envs=4, vehicle="field")
    teacher.validate()
    flown, field = teacher.env_config(), condition_env_overrides("field")
    for key in ("dynamics", "dynamics_randomization", "state_estimate", "latency_range_s", "action_limits", "episode_duration_s"):
        assert getattr(flown, key) == field[key], key
    assert flown.action_limits.max_speed_m_s == 1.0 and flown.max_steps == 2 * NavEnvConfig().max_steps
    assert flown.corruption == "train" and flown.gray_camera is None


def test_ended_table2_episodes_are_not_matched_nor_encoded(encoder, monkeypatch):
    """Table II's episodes do not reset: once one ends, its frames are never flown on, so the
    stereo matching and the encoder skip it (they are most of a field cell's time); the live
    episodes keep their own frames."""
    env = table2_env(encoder, level=2, condition="stereo", num_envs=3, device="cpu", seed=1)
    env.reset()
    measured, depths = [], []
    measure, render_inputs = env.stereo_sensor.measure, env.render_inputs
    monkeypatch.setattr(env.stereo_sensor, "measure", lambda world, pos, quat, gen: measured.append(len(pos)) or measure(world, pos, quat, gen))
    monkeypatch.setattr(env, "render_inputs", lambda: depths.append(render_inputs()[1][:, 0]) or (torch.zeros(3, 1, 224, 224), depths[-1].unsqueeze(1)))
    full = env._observe()
    env.active[1] = False
    part = env._observe()
    assert measured == [3, 2]
    assert torch.equal(part[1, STATE_DIM:], torch.zeros(LATENT_DIM)) and torch.equal(part[:, :STATE_DIM], full[:, :STATE_DIM])
    # Each live env keeps its own frames: only the matching's noise is drawn anew.
    change = (depths[1] - depths[0]).abs().mean(dim=(1, 2))
    between_envs = (depths[0][0] - depths[0][2]).abs().mean()
    assert change[0] < 0.2 * between_envs and change[2] < 0.2 * between_envs
    env.active[:] = False
    assert torch.equal(env._observe()[:, STATE_DIM:], torch.zeros(3, LATENT_DIM)) and measured == [3, 2]


def test_field_training_on_the_parametric_stereo_uses_it_and_costs_less(encoder):
    student = DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", num_envs=2, field_conditions=True, field_depth="approx")
    student.validate()
    env = NavEnv(replace(student.env_config(), num_envs=4), encoder, seed=3)
    assert env.config.corruption == "stereo-approx" and env.stereo_sensor is None and env.stereo_approx.projector_on
    env.reset()
    for _ in range(3):
        env.step(torch.zeros(4, 3))
    assert env.stage_seconds["stereo"] > 0.0  # the stand-in ran, timed where the stereo path is
    with pytest.raises(ValueError, match="field_depth"):
        DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", field_depth="lidar").validate()


def test_the_px4_vehicle_flies_the_estimate_as_the_shipped_runtime_corrects_it():
    """The runtime's contract wins: it corrects PX4's velocity estimate by default, so training's
    PX4 (Table II's ``px4``/``field``, ``--vehicle px4``) flies the corrected estimate's error."""
    from runtime.config import VehicleConfig

    assert VehicleConfig().velocity_bias_correction
    assert px4_vehicle_env_overrides()["state_estimate"] == PX4_EKF2_CORRECTED
