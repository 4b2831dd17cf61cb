"""Table II's sensor and out-of-distribution conditions (stereo, stereo-projector-off,
patches-1-50px, patches-100px) in the batched env and in `evaluate_policy`, and its room sets
(validation for choosing, test for reporting), and the imitation gap to a teacher (`--teacher`), on a tiny
encoder and an untrained tiny policy."""

from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np
import pytest
import torch

from sim.preprocess_torch import preprocess_depth_batch
from training.checkpoint import checkpoint_fingerprint, save_weights
from training.cmwae.model import Cmwae, make_config
from training.policy.evaluate import CONDITIONS, ROOMS, PolicyEvalConfig, evaluate_policy, table2_env
from training.policy.network import POLICY_SIZES, ActorCritic

pytestmark = pytest.mark.timeout(300)
NEW_CONDITIONS = ("stereo", "stereo-projector-off", "patches-1-50px", "patches-100px")


@pytest.fixture(scope="module")
def encoder():
    torch.manual_seed(0)
    return Cmwae(make_config("tiny")).encoder.eval()


def _depth_and_clean(env):
    """The env's (preprocessed, conditioned) depth [N, 224, 224] and the clean depth of the same frames."""
    depth = env.render_inputs()[1][:, 0]
    return depth, preprocess_depth_batch(env.last_render.depth_m)


def _shortest_masked_run_px(invalid: torch.Tensor) -> int:
    """The shortest horizontal run of invalid pixels in a [224, 224] mask."""
    shortest = invalid.shape[-1]
    for row in invalid:
        padded = torch.cat([torch.tensor([False]), row, torch.tensor([False])]).int()
        edges = padded.diff()
        starts, ends = (edges == 1).nonzero().squeeze(1), (edges == -1).nonzero().squeeze(1)
        if len(starts):
            shortest = min(shortest, int((ends - starts).min()))
    return shortest


def test_stereo_conditions_give_matched_depth_that_agrees_with_the_clean_depth(encoder):
    invalid = {}
    for condition in ("stereo", "stereo-projector-off"):
        env = table2_env(encoder, level=3, condition=condition, num_envs=2, device="cpu", seed=ROOMS["validation"])
        env.reset()
        env.step(torch.zeros(2, 3))
        depth, clean = _depth_and_clean(env)
        valid = depth > 0
        # The D455's left band (no overlap with the right imager) at least, never everything.
        invalid[condition] = 1.0 - float(valid.float().mean())
        assert 0.08 < invalid[condition] < 0.9
        # Where it reports depth nearer than 4 m (normalised by 10 m), it is the scene's depth: with the
        # projector nearly all within 5 %; without it, passive matching on weak texture errs more often
        # (measured here 74 % within 5 %, 90 % within 10 %; CPUs differ in the last bits of the matching).
        relative = ((depth - clean).abs() / clean.clamp_min(1e-3))[valid & (clean < 0.4)]
        tolerance, share = {"stereo": (0.05, 0.9), "stereo-projector-off": (0.10, 0.75)}[condition]
        assert float((relative < tolerance).float().mean()) > share, condition
        assert not torch.equal(depth, clean)
        assert env.stage_seconds["stereo"] > 0.0
    assert invalid["stereo-projector-off"] > invalid["stereo"] + 0.03, invalid  # same rooms, same poses


@pytest.mark.parametrize(("condition", "sides_px"), [("patches-1-50px", (1, 50)), ("patches-100px", (100, 100))])
def test_out_of_distribution_patches_cover_half_the_image_and_stay_for_the_episode(encoder, condition, sides_px):
    env = table2_env(encoder, level=2, condition=condition, num_envs=3, device="cpu", seed=ROOMS["validation"])
    env.reset()
    first = env.render_inputs()[1][:, 0] == 0
    env.step(torch.zeros(3, 3))
    second = env.render_inputs()[1][:, 0] == 0
    assert torch.equal(first, second)  # fixed per episode
    for mask in first:
        assert 0.5 - 1e-6 <= float(mask.float().mean()) <= 0.5 + (sides_px[1] / 224) ** 2
    runs = [_shortest_masked_run_px(mask) for mask in first]
    if sides_px[0] == 100:
        assert min(runs) >= 100  # unions of 100 px squares inside the image
    else:
        assert min(runs) < 50


def test_room_sets_are_seed_0_and_1_and_differ(encoder):
    assert ROOMS == {"validation": 0, "test": 1}
    rooms = {}
    for name, seed in ROOMS.items():
        env = table2_env(encoder, level=2, condition="clean", num_envs=4, device="cpu", seed=seed)
        env.reset()
        rooms[name] = env.world.room_size_m.clone()
    assert not torch.equal(rooms["validation"], rooms["test"])
    assert PolicyEvalConfig("p", "e", rooms="test").room_seed == 1
    with pytest.raises(ValueError, match="seed 1, but seed=2"):
        PolicyEvalConfig("p", "e", rooms="test", seed=2).validate()
    with pytest.raises(ValueError, match="validation"):
        PolicyEvalConfig("p", "e", rooms="holdout").validate()


def test_evaluate_policy_runs_every_new_condition_on_test_rooms_and_records_fingerprints(tmp_path):
    torch.manual_seed(0)
    config = make_config("tiny")
    save_weights(tmp_path / "enc", Cmwae(config), "cmwae", asdict(config), 0, {"train": {"scheme": "s2"}})
    policy = ActorCritic(POLICY_SIZES["tiny"])
    save_weights(tmp_path / "policy", policy, "policy", POLICY_SIZES["tiny"].to_json(), 0,
                 {"encoder_fingerprint": checkpoint_fingerprint(tmp_path / "enc")})  # fmt: skip
    result = evaluate_policy(PolicyEvalConfig(str(tmp_path / "policy"), str(tmp_path / "enc"), levels=(1,),
                                              conditions=NEW_CONDITIONS, episodes=1, batch_envs=1, rooms="test",
                                              out_dir=str(tmp_path / "eval"), plots_per_cell=0, precision="fp32"))  # fmt: skip
    written = json.loads((tmp_path / "eval" / "table2.json").read_text())
    assert [c["condition"] for c in written["cells"]] == list(NEW_CONDITIONS)
    assert all(c["episodes"] == 1 for c in written["cells"])
    assert written["rooms"] == "test" and written["room_seed"] == 1
    assert written["policy_fingerprint"] == checkpoint_fingerprint(tmp_path / "policy")
    assert written["encoder_fingerprint"] == checkpoint_fingerprint(tmp_path / "enc")
    assert written["fast_path"]["encoder"] and written["fast_path"]["precision_requested"] == "fp32"
    assert set(written["stereo_sensor"]) == {"stereo", "stereo-projector-off"}
    assert written["stereo_sensor"]["stereo"]["projector_on"] and not written["stereo_sensor"]["stereo-projector-off"]["projector_on"]
    assert written["stereo_sensor"]["stereo"]["baseline_m"] == pytest.approx(0.095)
    assert result["out_dir"] == str(tmp_path / "eval") and written["complete"]
    assert "Incomplete" not in (tmp_path / "eval" / "table2.md").read_text()


def test_an_evaluation_stopped_early_keeps_the_cells_it_finished(tmp_path, monkeypatch):
    import training.policy.evaluate as evaluate

    torch.manual_seed(0)
    config = make_config("tiny")
    save_weights(tmp_path / "enc", Cmwae(config), "cmwae", asdict(config), 0, {"train": {"scheme": "s2"}})
    save_weights(tmp_path / "policy", ActorCritic(POLICY_SIZES["tiny"]), "policy", POLICY_SIZES["tiny"].to_json(), 0,
                 {"encoder_fingerprint": checkpoint_fingerprint(tmp_path / "enc")})  # fmt: skip
    fly, calls = evaluate.fly_episodes, []

    def stopped_at_the_second_cell(*args, **kwargs):
        calls.append(args[2:4])  # (level, condition)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return fly(*args, **kwargs)

    monkeypatch.setattr(evaluate, "fly_episodes", stopped_at_the_second_cell)
    with pytest.raises(KeyboardInterrupt):
        evaluate_policy(PolicyEvalConfig(str(tmp_path / "policy"), str(tmp_path / "enc"), levels=(0, 1), conditions=("clean",),
                                         episodes=1, batch_envs=1, out_dir=str(tmp_path / "eval"), plots_per_cell=0,
                                         precision="fp32"))  # fmt: skip
    written = json.loads((tmp_path / "eval" / "table2.json").read_text())
    assert calls == [(0, "clean"), (1, "clean")]
    assert [(c["condition"], c["level"], c["episodes"]) for c in written["cells"]] == [("clean", 0, 1)] and not written["complete"]
    table = (tmp_path / "eval" / "table2.md").read_text()
    assert "| clean | 0 | 1 |" in table and "Incomplete" in table


def test_every_condition_builds_a_valid_env_config():
    assert set(NEW_CONDITIONS) <= set(CONDITIONS)
    for overrides in CONDITIONS.values():
        assert set(overrides) <= {"corruption", "corruption_scheme"}


def _constant_policy(config, action):
    """A policy whose action is ``action`` whatever it observes."""
    policy = ActorCritic(config)
    torch.nn.init.zeros_(policy.action_head.weight)
    with torch.no_grad():
        policy.action_head.bias.copy_(torch.tensor(action))
    return policy


def test_the_imitation_gap_is_the_squared_distance_from_the_teachers_clamped_label(tmp_path):
    from dataclasses import replace

    from training.policy.env import NavEnvConfig
    from training.policy.network import TEACHER

    torch.manual_seed(0)
    config = make_config("tiny")
    save_weights(tmp_path / "enc", Cmwae(config), "cmwae", asdict(config), 0, {"train": {"scheme": "s2"}})
    student = _constant_policy(POLICY_SIZES["tiny"], [0.5, 0.0, 0.0])
    save_weights(tmp_path / "policy", student, "policy", POLICY_SIZES["tiny"].to_json(), 0,
                 {"encoder_fingerprint": checkpoint_fingerprint(tmp_path / "enc")})  # fmt: skip
    teacher_config = replace(POLICY_SIZES["tiny"], obs_dim=NavEnvConfig().privileged_obs_dim)
    teacher = _constant_policy(teacher_config, [0.5, -0.25, 3.0])  # its yaw label clamps to 1
    save_weights(tmp_path / "teacher", teacher, "policy", teacher_config.to_json(), 0, {"role": TEACHER})
    eval_config = PolicyEvalConfig(str(tmp_path / "policy"), str(tmp_path / "enc"), levels=(1,), conditions=("patches-100px",),
                                   episodes=2, batch_envs=2, out_dir=str(tmp_path / "eval"), plots_per_cell=0,
                                   precision="fp32", episode_duration_s=1.0, teacher_dir=str(tmp_path / "teacher"))  # fmt: skip
    result = evaluate_policy(eval_config)
    cell = result["cells"][0]
    assert cell["imitation_gap"] == pytest.approx(0.25**2 + 1.0**2, rel=1e-3)  # (0, 0.25, 1) off on every step
    assert result["teacher_fingerprint"] == checkpoint_fingerprint(tmp_path / "teacher")
    assert "imitation gap" in (tmp_path / "eval" / "table2.md").read_text()
    without = evaluate_policy(replace(eval_config, teacher_dir=None, out_dir=str(tmp_path / "eval-plain")))
    assert "imitation_gap" not in without["cells"][0] and "imitation gap" not in (tmp_path / "eval-plain" / "table2.md").read_text()
    with pytest.raises(ValueError, match="not a privileged teacher"):  # a student is not a teacher
        evaluate_policy(replace(eval_config, teacher_dir=str(tmp_path / "policy")))
    other_depth = replace(teacher_config, obs_dim=teacher_config.obs_dim + 1)  # trained on another privileged depth size
    save_weights(tmp_path / "teacher-other", ActorCritic(other_depth), "policy", other_depth.to_json(), 0, {"role": TEACHER})
    with pytest.raises(ValueError, match="observes .* values"):
        evaluate_policy(replace(eval_config, teacher_dir=str(tmp_path / "teacher-other")))


def test_the_imitation_gap_before_crashes_takes_each_crashs_last_second():
    from training.policy.env import CRASH, SUCCESS
    from training.policy.evaluate import imitation_gap

    crash = np.r_[np.zeros(30), np.ones(15)]  # apart only in its last second
    success = np.full(20, 0.5)
    gap = imitation_gap([crash, success], [CRASH, SUCCESS])
    assert gap["imitation_gap"] == pytest.approx((15 + 10) / 65)
    assert gap["imitation_gap_before_crash"] == pytest.approx(1.0)
    assert imitation_gap([success], [SUCCESS])["imitation_gap_before_crash"] is None
