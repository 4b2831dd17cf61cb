"""The navigation environment follows the runtime's contract: observations and actions equal the
runtime's numpy functions on the same states, images equal the runtime's preprocessing, and
episodes end as the task defines (success within 1 m, crash on contact, 10 s timeout)."""

import math

import numpy as np
import pytest
import torch
from torch import Tensor
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.contract import action_to_velocity_flu, observation_state, preprocess_depth, preprocess_gray
from runtime.contract.constants import CONTROL_PERIOD_S, EPISODE_DURATION_S, STATE_DIM
from sim.camera import camera_pose
from sim.degradation import RL_TRAINING
from sim.render import render
from sim.rotations import quat_from_euler
from training.cmwae.model import Cmwae, make_config
from training.policy.contract_torch import action_to_velocity_flu_batch, observation_state_batch
from training.policy.env import CRASH, SUCCESS, TIMEOUT, Curriculum, CurriculumConfig, NavEnv, NavEnvConfig

pytestmark = pytest.mark.timeout(300)

finite = st.floats(-20.0, 20.0, allow_nan=False, width=32)
angle = st.floats(-math.pi, math.pi, allow_nan=False)
small_angle = st.floats(-1.2, 1.2, allow_nan=False)
vec3 = st.tuples(finite, finite, finite)


@pytest.fixture(scope="module")
def encoder():
    torch.manual_seed(0)
    return Cmwae(make_config("tiny")).encoder.eval()


def _env(encoder, level: int = 2, **overrides) -> NavEnv:
    config = NavEnvConfig(num_envs=3, kick_probability=0.0, **({"corruption": "none"} | overrides))
    return NavEnv(config, encoder, seed=3, fixed_level=level)


@settings(max_examples=60, deadline=None)
@given(pos=vec3, goal=vec3, roll=small_angle, pitch=small_angle, yaw=angle, vel=vec3, angvel=vec3,
       prev=st.tuples(*[st.floats(-1, 1)] * 3))  # fmt: skip
def test_observation_state_twin_equals_the_runtime(pos, goal, roll, pitch, yaw, vel, angvel, prev):
    quat = quat_from_euler(torch.tensor(roll), torch.tensor(pitch), torch.tensor(yaw)).double()
    vel_enu = torch.tensor(vel, dtype=torch.float64)
    ours = observation_state_batch(torch.tensor([pos], dtype=torch.float64), torch.tensor([goal], dtype=torch.float64),
                                   quat[None], vel_enu[None], torch.tensor([angvel], dtype=torch.float64),
                                   torch.tensor([prev], dtype=torch.float64))[0].numpy()  # fmt: skip
    from sim.rotations import quat_rotate_inverse

    vel_body = quat_rotate_inverse(quat, vel_enu).numpy()
    theirs = observation_state(np.array(pos), np.array(goal), quat.numpy(), vel_body, np.array(angvel), np.array(prev))
    assert ours.shape == theirs.shape == (STATE_DIM,)
    np.testing.assert_allclose(ours, theirs, atol=2e-5)


@settings(max_examples=60, deadline=None)
@given(action=st.tuples(*[st.floats(-3, 3, allow_nan=False)] * 3))
def test_action_twin_equals_the_runtime(action):
    ours = action_to_velocity_flu_batch(torch.tensor([action], dtype=torch.float64))[0].numpy()
    np.testing.assert_allclose(ours, action_to_velocity_flu(np.array(action)), atol=1e-9)


def test_env_observation_is_the_runtime_observation_of_its_state(encoder):
    env = _env(encoder)
    env.reset()
    action = torch.tensor([[0.5, 0.2, -0.3], [-1.0, 0.0, 1.0], [2.0, -2.0, 0.0]])  # the last is clipped
    obs = env.step(action).obs
    s = env.state
    for i in range(env.num_envs):
        expected = observation_state(
            s.pos_enu_m[i].double().numpy(), env.world.goal_m[i].double().numpy(), s.quat_enu_flu[i].double().numpy(),
            s.vel_body_flu_m_s()[i].double().numpy(), s.angvel_body_flu_rad_s[i].double().numpy(),
            np.clip(action[i].numpy(), -1, 1),
        )  # fmt: skip
        np.testing.assert_allclose(obs[i, :STATE_DIM].numpy(), expected, atol=1e-5)
    # The latent is the encoder's output on the env's own (runtime-equal) images.
    gray, depth = env.render_inputs()
    with torch.no_grad():
        np.testing.assert_allclose(obs[:, STATE_DIM:].numpy(), encoder(gray, depth).numpy(), atol=1e-5)


def test_env_images_equal_the_runtime_preprocessing(encoder):
    env = _env(encoder)
    env.reset()
    gray, depth = env.render_inputs()
    cam_pos, cam_quat = camera_pose(env.state.pos_enu_m, env.state.quat_enu_flu, env.camera, env.jitter)
    raw = render(env.world, cam_pos, cam_quat, env.camera)
    for i in range(env.num_envs):
        np.testing.assert_array_equal(depth[i, 0].numpy(), preprocess_depth(raw.depth_m[i].numpy()))
        assert np.abs(gray[i, 0].numpy() - preprocess_gray(raw.gray_u8[i].numpy())).max() <= 1.0 / 255 + 1e-6


def test_training_corruption_hits_a_subset_and_episode_masks_stay_fixed(encoder):
    env = _env(encoder, corruption="train", corrupted_env_fraction=0.5)
    env.reset()
    invalid = torch.stack([env.render_inputs()[1].eq(0).float().mean(dim=(1, 2, 3)) for _ in range(12)])
    corrupted = invalid > 0.3
    assert corrupted.any() and (~corrupted).any()  # some envs corrupted, some clean, each step
    assert float(invalid[corrupted].min()) >= RL_TRAINING.min_coverage - 1e-6

    env = _env(encoder, corruption="episode")
    env.reset()
    first = env.render_inputs()[1].eq(0)
    env.step(torch.zeros(3, 3))
    second = env.render_inputs()[1].eq(0)
    assert float(first.float().mean()) >= 0.5 - 1e-6
    assert bool((first & ~second).sum() == 0)  # the patches did not move


def test_forward_action_flies_at_the_contract_speed(encoder):
    env = _env(encoder, level=0)
    env.auto_reset = False
    env.reset()
    for _ in range(20):  # 1.3 s at full speed, level
        env.step(torch.tensor([[1.0, 0.0, 0.0]] * 3))
    assert env.active.any()  # the ones that did not reach a wall yet
    speed_forward = env.state.vel_body_flu_m_s()[env.active, 0]
    assert torch.allclose(speed_forward, torch.full_like(speed_forward, 2.0), atol=0.1)


def _hover_near_goal(env: NavEnv) -> Tensor:
    """Env 0's goal put 0.5 m from it, env 1 climbing into the ceiling, env 2 far from its goal; all
    three hover (action: speed 0) but env 1."""
    env.reset()
    env.auto_reset = False
    env.world.goal_m[0] = env.state.pos_enu_m[0] + torch.tensor([0.5, 0.0, 0.0])
    env.prev_dist_m[0] = 0.5
    return torch.tensor([[-1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


def test_episodes_end_in_success_crash_and_timeout(encoder):
    """A crash ends an episode at once; otherwise it lasts 10 s and ends in success if the vehicle
    is then within 1 m of the goal (reaching the goal earlier does not end it), else timeout."""
    env = _env(encoder, level=0)
    action = _hover_near_goal(env)
    outcomes = {}
    for step in range(env.config.max_steps):
        out = env.step(action)
        for i in out.done.nonzero().flatten().tolist():
            outcomes[i] = (int(out.outcome[i]), step + 1, float(out.reward[i]))
    assert outcomes[0][0] == SUCCESS and outcomes[0][1] * CONTROL_PERIOD_S == pytest.approx(EPISODE_DURATION_S)
    assert outcomes[1][0] == CRASH and outcomes[1][1] < 40 and outcomes[1][2] == -env.config.reward.crash_penalty
    assert outcomes[2][0] == TIMEOUT and outcomes[2][1] * CONTROL_PERIOD_S == pytest.approx(EPISODE_DURATION_S)
    assert not env.active.any()


def test_end_at_goal_ends_in_success_at_the_first_step_there_paid_at_least_staying(encoder):
    """--end-at-goal: the runtime's rule (success at the first step within 1 m); the arrival pays
    the hover reward on the goal for every step left, which is at least what hovering there for the
    rest of the paper's 10 s episode earns."""
    stay = _env(encoder, level=0)
    action = _hover_near_goal(stay)
    stayed_reward = 0.0
    for _ in range(stay.config.max_steps):
        stayed_reward += float(stay.step(action).reward[0])
    assert int(stay.step_count[0]) == stay.config.max_steps

    end = _env(encoder, level=0, end_at_goal=True)
    action = _hover_near_goal(end)
    out = end.step(action)
    assert out.outcome.tolist()[0] == SUCCESS and out.done.tolist() == [True, False, False]
    assert float(out.reward[0]) >= stayed_reward
    expected_arrival = (end.config.max_steps - 1) * end.goal_hover_reward()
    assert out.reward_terms["arrival"] == pytest.approx(expected_arrival / 3, rel=1e-5)
    assert float(out.reward[2]) < 20.0  # no arrival far from the goal
    outcomes = {}
    for step in range(1, end.config.max_steps):
        out = end.step(action)
        for i in out.done.nonzero().flatten().tolist():
            outcomes[i] = int(out.outcome[i])
    assert outcomes == {1: CRASH, 2: TIMEOUT}


def test_curriculum_moves_by_the_window_success_rate():
    c = Curriculum(CurriculumConfig(start_level=2, max_level=3, window_episodes=4))
    c.record([True, True, True, False])  # 75 % > 70 %: up
    assert c.level == 3
    c.record([True] * 4)  # capped
    assert c.level == 3
    c.record([True, False, False, False])  # 25 % < 30 %: down
    assert c.level == 2
    c.record([True, True, False, False])  # 50 %: stay
    assert (c.level, c.changes) == (2, 2)


def test_auto_reset_starts_new_rooms_at_the_curriculum_level(encoder):
    config = NavEnvConfig(num_envs=2, kick_probability=0.0, corruption="none",
                          curriculum=CurriculumConfig(start_level=3, max_level=5, window_episodes=1))  # fmt: skip
    env = NavEnv(config, encoder, seed=1)
    env.reset()
    assert env.world.obstacle_count().tolist() == [3, 3]
    first_rooms = env.world.room_size_m.clone()
    for _ in range(env.config.max_steps):
        out = env.step(torch.tensor([[1.0, 1.0, 0.0]] * 2))  # straight up into the ceiling
        if out.done.any():
            break
    ended = out.done
    assert (out.outcome[ended] == CRASH).all()
    # Each crash was a failed window of one episode: the level went down by one per crash, and
    # the rooms that replaced the crashed envs' have the new level.
    assert env.curriculum.level == 3 - int(ended.sum())
    assert env.world.obstacle_count()[ended].tolist() == [env.curriculum.level] * int(ended.sum())
    assert not torch.equal(env.world.room_size_m[ended], first_rooms[ended])
    assert env.step_count[ended].tolist() == [0] * int(ended.sum())
