"""The privileged teacher (low-resolution env, PPO) and the DAgger student: labels come from the
teacher on the student's own states, corruption reaches the student's input and never the
teacher's, and the student exports to a model the runtime loads."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn
from torch.nn import functional as F

from export.policy_onnx import PARITY_TOLERANCE, ExportError, export_policy, load_networks, random_inputs, torch_outputs
from runtime.contract import constants as c
from runtime.contract.constants import STATE_DIM
from runtime.model import PolicyModel
from training.checkpoint import checkpoint_fingerprint, load_train_state, save_weights
from training.cmwae.model import Cmwae, make_config
from training.data.tartanair import GrayDepthDataset, find_samples
from training.policy.dagger import DaggerConfig, Sequences, collect, distill, load_teacher, near_surface_states
from training.policy.env import CurriculumConfig, NavEnv, NavEnvConfig
from training.policy.network import ActorCritic, PolicyConfig, load_policy

pytestmark = pytest.mark.timeout(300)
GAP_SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "student-gap.py"
BOUND_SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "squares-bound.py"
TEACHER = ["train", "teacher", "--size", "tiny", "--envs", "16", "--rollout", "8", "--minibatches", "2",
           "--checkpoint-every", "2", "--curriculum-window", "4", "--max-level", "3"]  # fmt: skip


def _cmnav(*args):
    proc = subprocess.run([sys.executable, "-m", "cmnav", *args], capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout, proc.stderr


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny teacher trained by PPO on the low-resolution env, and a tiny encoder."""
    root = tmp_path_factory.mktemp("dagger")
    _cmnav(*TEACHER, "--out", str(root / "teacher"), "--steps", "512")
    torch.manual_seed(0)
    save_weights(root / "enc", Cmwae(make_config("tiny")), "cmwae", asdict(make_config("tiny")), 0, {"train": {"scheme": "s2"}})
    return root


def test_a_tiny_teacher_trains_on_the_low_resolution_env_and_is_evaluated_alone(trained, tmp_path):
    card = json.loads((trained / "teacher" / "model.json").read_text())
    assert card["meta"]["role"] == "teacher" and card["meta"]["encoder"] is None
    assert card["config"]["obs_dim"] == NavEnvConfig().privileged_obs_dim == STATE_DIM + 32 * 18
    assert card["step"] == 512
    stdout, _ = _cmnav("eval", "policy", "--policy", str(trained / "teacher"), "--episodes", "2", "--levels", "0",
                       "--batch-envs", "2", "--conditions", "clean,corrupted,px4,field", "--out", str(tmp_path), "--json")  # fmt: skip
    result = json.loads(stdout.strip().splitlines()[-1])
    # It sees clean depth and the true state only: the rows whose depth is clean (px4 changes the
    # vehicle alone) and the field, whose vehicle, latency and speed caps it still flies.
    assert result["role"] == "teacher" and [c["condition"] for c in result["cells"]] == ["clean", "px4", "field"]
    assert result["field"]["field"]["action_limits"]["max_speed_m_s"] == 1.0
    with pytest.raises(ExportError, match="privileged teacher"):
        export_policy(trained / "enc", trained / "teacher", tmp_path / "t.onnx", random_samples=1)


def test_a_teacher_trains_on_px4s_response_and_resumes_only_on_it(tmp_path):
    out = tmp_path / "teacher-px4"
    _cmnav(*TEACHER, "--out", str(out), "--steps", "256", "--vehicle", "px4", "--end-at-goal", "--keep-checkpoints")
    card = json.loads((out / "model.json").read_text())
    assert [p.name for p in sorted((out / "checkpoints").iterdir())] == ["step-0000000256"]  # PPO keeps its checkpoints too
    assert checkpoint_fingerprint(out / "checkpoints" / "step-0000000256") == checkpoint_fingerprint(out)
    assert card["meta"]["train"]["vehicle"] == "px4" and load_train_state(out)["vehicle"] == "px4"
    assert card["meta"]["train"]["end_at_goal"] is True and load_train_state(out)["end_at_goal"] is True
    for given, refusal in (((), "trained on the px4 vehicle, but --vehicle ideal"),
                           (("--vehicle", "px4"), "trained with episodes ending at the goal, but --end-at-goal was not given")):
        proc = subprocess.run([sys.executable, "-m", "cmnav", *TEACHER, "--out", str(out), "--steps", "512", "--resume", *given],
                              capture_output=True, text=True, timeout=280)  # fmt: skip
        assert proc.returncode != 0 and refusal in proc.stderr, proc.stderr[-2000:]
        assert "Traceback" not in proc.stderr
    _cmnav(*TEACHER, "--out", str(out), "--steps", "512", "--resume", "--vehicle", "px4", "--end-at-goal")
    assert json.loads((out / "model.json").read_text())["step"] == 512


class ScriptedTeacher(nn.Module):
    """Steer by the privileged observation alone: yaw toward the goal (obs[1] is the goal
    direction's left component), speed from the nearest depth; records what it was shown."""

    def __init__(self, obs_dim: int) -> None:
        super().__init__()
        self.config = PolicyConfig(obs_dim=obs_dim, mlp_sizes=(4,), gru_size=2)
        self.seen: list[torch.Tensor] = []

    def initial_hidden(self, batch, device="cpu"):
        return torch.zeros(batch, 2, device=device)

    def step(self, obs, hidden):
        self.seen.append(obs.clone())
        nearest = obs[:, STATE_DIM:].min(dim=1).values
        action = torch.stack([nearest * 4.0 - 1.0, torch.zeros_like(nearest), obs[:, 1] * 2.0], dim=1)
        return action, torch.zeros(obs.shape[0]), hidden


def _env(encoder, corruption="train", n=6, seed=3):
    config = NavEnvConfig(num_envs=n, corruption=corruption, level_sampling="uniform", kick_probability=0.0,
                          curriculum=CurriculumConfig(start_level=0, min_level=0, max_level=4))  # fmt: skip
    return NavEnv(config, encoder, "cpu", seed=seed, teacher_obs=True)


def _carry(env, student, teacher):
    n = env.num_envs
    return {"obs": env.reset(), "teacher_obs": env.teacher_observation(), "starts": torch.ones(n, dtype=torch.bool),
            "h_student": student.initial_hidden(n), "h_teacher": teacher.initial_hidden(n)}  # fmt: skip


@pytest.mark.parametrize("beta", [0.0, 1.0])
def test_labels_come_from_the_teacher_on_the_states_the_mixture_visits(beta):
    torch.manual_seed(1)
    encoder = Cmwae(make_config("tiny")).encoder
    env = _env(encoder)
    teacher = ScriptedTeacher(env.config.privileged_obs_dim)
    # A frozen normaliser, so that re-running the student afterwards gives the actions it took.
    student = ActorCritic(PolicyConfig(mlp_sizes=(16,), gru_size=8, obs_norm_max_count=0))
    steps = 20
    seq, _ = collect(student, teacher, env, _carry(env, student, teacher), steps, beta, torch.Generator().manual_seed(0))
    shown = torch.stack(teacher.seen)  # [T, N, P] what the teacher saw at each step
    # The teacher saw the very states the student saw (the same 15 state values, previous action
    # included), and its labels are its actions on them, clipped.
    torch.testing.assert_close(shown[:, :, :STATE_DIM], seq.obs[:, :, :STATE_DIM])
    expected = torch.stack([ScriptedTeacher(1).step(o, None)[0] for o in shown]).clamp(-1, 1)
    torch.testing.assert_close(seq.labels, expected)
    # Who flew: the previous action in the next observation is the executed one.
    with torch.no_grad():
        student_actions, _ = student.unroll(seq.obs, seq.hidden0, seq.starts)
    executed = (seq.labels if beta == 1.0 else student_actions).clamp(-1, 1)
    continuing = ~seq.starts[1:]
    torch.testing.assert_close(seq.obs[1:, :, 12:15][continuing], executed[:-1][continuing])
    assert not torch.allclose(seq.labels, student_actions.clamp(-1, 1))  # the two policies differ


def test_corruption_reaches_the_student_and_never_the_teacher():
    encoder = Cmwae(make_config("tiny")).encoder
    env = _env(encoder, corruption="episode", n=4)
    env.reset()
    _, depth = env.render_inputs()
    invalid = (depth == 0.0).flatten(1).float().mean(dim=1)
    assert bool((invalid >= 0.45).all())  # the paper's 1-30 px patches to 50 %
    teacher_depth = env.teacher_observation()[:, STATE_DIM:]
    assert bool((teacher_depth > 0.0).all())  # clean: nothing invalid
    step = env.step(torch.zeros(4, 3))
    assert bool((step.teacher_obs[:, STATE_DIM:] > 0.0).all())
    # projector-off episodes also reach only the student
    off = NavEnv(NavEnvConfig(num_envs=4, corruption="none", projector_off_episode_fraction=1.0), encoder, "cpu", seed=5,
                 teacher_obs=True)  # fmt: skip
    off.reset()
    assert bool((off.render_inputs()[1] == 0.0).flatten(1).any(dim=1).all())
    assert bool((off.teacher_observation()[:, STATE_DIM:] > 0.0).all())


def test_distillation_fits_the_labels():
    torch.manual_seed(2)
    encoder = Cmwae(make_config("tiny")).encoder
    env = _env(encoder, n=8)
    teacher = ScriptedTeacher(env.config.privileged_obs_dim)
    student = ActorCritic(PolicyConfig(mlp_sizes=(32,), gru_size=16))
    seq, _ = collect(student, teacher, env, _carry(env, student, teacher), 16, 1.0, torch.Generator().manual_seed(0))
    optimizer = torch.optim.Adam(student.parameters(), lr=3e-3)
    first = distill(student, optimizer, [seq], 1, 2, 1.0, torch.Generator().manual_seed(0))
    for _ in range(40):
        last = distill(student, optimizer, [seq], 1, 2, 1.0, torch.Generator().manual_seed(0))
    assert last < 0.5 * first


def test_near_surface_states_are_those_whose_teacher_sees_a_surface_nearer_than_near_m():
    pixels = NavEnvConfig().privileged_obs_dim - STATE_DIM
    obs = torch.zeros(3, STATE_DIM + pixels)
    obs[:, STATE_DIM:] = 3.0 / c.DEPTH_MAX_M  # everything 3 m away
    obs[1, STATE_DIM + 7] = 1.2 / c.DEPTH_MAX_M  # one pixel at 1.2 m
    obs[2, STATE_DIM + 7] = 1.6 / c.DEPTH_MAX_M
    obs[:, :STATE_DIM] = 0.01  # the state values are not depth
    assert near_surface_states(obs, 1.5).tolist() == [False, True, False]
    assert near_surface_states(obs, 2.0).tolist() == [False, True, True]
    with pytest.raises(ValueError, match="near_m=12.0 must lie in"):  # the encoder's check, shared
        DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", near_m=12.0).validate()
    with pytest.raises(ValueError, match="near_weight=-1.0 must lie in"):
        DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", near_weight=-1.0).validate()


def test_collect_weights_each_step_by_what_its_teacher_saw():
    torch.manual_seed(4)
    env = _env(Cmwae(make_config("tiny")).encoder, n=8)
    teacher = ScriptedTeacher(env.config.privileged_obs_dim)
    student = ActorCritic(PolicyConfig(mlp_sizes=(16,), gru_size=8))
    seq, stats = collect(student, teacher, env, _carry(env, student, teacher), 24, 0.0, torch.Generator().manual_seed(0),
                         near_weight=4.0, near_m=2.5)  # fmt: skip
    near = torch.stack([near_surface_states(o, 2.5) for o in teacher.seen])  # [T, N] at the labelled step
    assert 0 < int(near.sum()) < near.numel()  # both kinds of state occur
    torch.testing.assert_close(seq.weights, 1.0 + 4.0 * near.float())
    assert stats["near_share"] == pytest.approx(float(near.float().mean()))


def test_weighted_distillation_fits_the_heavy_steps_closer():
    """A student too small for its random labels: weighting half of the sequences 20x fits those closer
    than the same run unweighted, and the others less close."""
    torch.manual_seed(5)
    steps, n = 8, 32
    obs, labels = torch.randn(steps, n, 79), torch.rand(steps, n, 3) * 2 - 1
    heavy = torch.zeros(steps, n, dtype=torch.bool)
    heavy[:, : n // 2] = True
    errors = {}
    for weight in (1.0, 20.0):
        torch.manual_seed(6)
        student = ActorCritic(PolicyConfig(mlp_sizes=(8,), gru_size=4, obs_norm_max_count=0))
        seq = Sequences(obs, torch.zeros(steps, n, dtype=torch.bool), labels, torch.zeros(n, 4), 1.0 + (weight - 1.0) * heavy.float())
        optimizer = torch.optim.Adam(student.parameters(), lr=1e-2)
        for _ in range(60):
            distill(student, optimizer, [seq], 1, 1, 1.0, torch.Generator().manual_seed(0))
        with torch.no_grad():
            error = (student.unroll(obs, seq.hidden0, seq.starts)[0] - labels).pow(2).mean(dim=-1)
        errors[weight] = (float(error[heavy].mean()), float(error[~heavy].mean()))
    assert errors[20.0][0] < 0.8 * errors[1.0][0]
    assert errors[20.0][1] > errors[1.0][1]


def test_the_distilled_student_exports_and_the_runtime_loads_it(trained, tmp_path):
    out = tmp_path / "student"
    _cmnav("train", "policy", "--teacher", str(trained / "teacher"), "--encoder", str(trained / "enc"), "--out", str(out),
           "--size", "tiny", "--envs", "4", "--rollout", "8", "--minibatches", "2", "--steps", "64", "--precision", "fp32",
           "--beta-decay-env-steps", "32")  # fmt: skip
    assert load_train_state(out)["optimizer"]["param_groups"][0]["lr"] == pytest.approx(DaggerConfig.lr)
    # resumed with another --lr: the student's optimizer takes it
    _cmnav("train", "policy", "--teacher", str(trained / "teacher"), "--encoder", str(trained / "enc"), "--out", str(out),
           "--size", "tiny", "--envs", "4", "--rollout", "8", "--minibatches", "2", "--steps", "96", "--precision", "fp32",
           "--beta-decay-env-steps", "32", "--resume", "--lr", "1e-4", "--min-level", "2", "--near-weight", "3")  # fmt: skip
    assert load_train_state(out)["optimizer"]["param_groups"][0]["lr"] == pytest.approx(1e-4)
    assert load_train_state(out)["vehicle"] == "ideal"
    proc = subprocess.run([sys.executable, "-m", "cmnav", "train", "policy", "--teacher", str(trained / "teacher"), "--encoder",
                           str(trained / "enc"), "--out", str(out), "--size", "tiny", "--envs", "4", "--steps", "128",
                           "--resume", "--vehicle", "px4"], capture_output=True, text=True, timeout=280)  # fmt: skip
    assert proc.returncode != 0 and "trained on the ideal vehicle, but --vehicle px4" in proc.stderr
    card = json.loads((out / "model.json").read_text())
    assert card["meta"]["train"]["min_level"] == 2 and card["meta"]["train"]["near_weight"] == 3.0
    assert card["meta"]["role"] == "policy" and card["meta"]["algorithm"] == "dagger"
    assert card["meta"]["teacher_fingerprint"] and card["config"]["obs_dim"] == 79
    export_policy(trained / "enc", out, tmp_path / "student.onnx", random_samples=2)  # parity-checked inside
    model = PolicyModel(tmp_path / "student.onnx")  # the runtime's loader: contract and shapes checked
    nets = load_networks(trained / "enc", out)
    inputs = random_inputs(1, model.hidden_size, seed=3)
    reference = torch_outputs(nets.step, inputs)
    step = model.step(inputs.gray[0, 0], inputs.depth[0, 0], inputs.state[0], inputs.hidden[0])
    np.testing.assert_allclose(step.action, reference[c.ONNX_OUTPUT_ACTION][0], atol=PARITY_TOLERANCE)

    # a student distilled before starts a new DAgger run on another encoder: its weights, the latent
    # statistics re-estimated on the new encoder; with --beta-start 0 the student flies from the first step
    torch.manual_seed(1)
    save_weights(trained / "enc2", Cmwae(make_config("tiny")), "cmwae", asdict(make_config("tiny")), 0, {"train": {"scheme": "s2"}})
    again = tmp_path / "again"
    _cmnav("train", "policy", "--teacher", str(trained / "teacher"), "--encoder", str(trained / "enc2"), "--out", str(again),
           "--size", "tiny", "--envs", "4", "--rollout", "8", "--minibatches", "2", "--steps", "32", "--precision", "fp32",
           "--init-from", str(out), "--beta-start", "0")  # fmt: skip
    again_card = json.loads((again / "model.json").read_text())
    assert again_card["meta"]["init_from"]["dir"] == str(out) and again_card["meta"]["init_from"]["latent_stats_reestimated"]
    assert again_card["meta"]["train"]["beta_start"] == 0.0 and load_train_state(again)["init_from"]["dir"] == str(out)
    source, tuned = load_policy(out)[0].state_dict(), load_policy(again)[0].state_dict()
    assert not torch.equal(source["obs_norm.mean"][STATE_DIM:], tuned["obs_norm.mean"][STATE_DIM:])
    assert torch.nn.functional.cosine_similarity(  # 32 steps of imitation moved the weights a little, from the source's
        source["gru.weight_hh"].flatten(), tuned["gru.weight_hh"].flatten(), dim=0) > 0.9

    # scripts/student-gap.py: the student flies, the teacher labels its states, the decoder reconstructs
    proc = subprocess.run([sys.executable, str(GAP_SCRIPT), "--student", str(out), "--encoder", str(trained / "enc"),
                           "--teacher", str(trained / "teacher"), "--levels", "3", "--episodes", "3"],
                          capture_output=True, text=True, timeout=280)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    gap = json.loads(proc.stdout.strip().splitlines()[-1])["3"]
    assert gap["episodes"] == 3 and gap["crashes"] + gap["successes"] <= 3
    phases = [p for p in ("successful episodes", "last 1 s before a crash") if p in gap]
    assert len(phases) == bool(gap["successes"]) + bool(gap["crashes"])
    for phase in phases:
        m = gap[phase]
        assert m["steps"] >= 1 and 0.0 <= m["near_share"] <= 1.0
        assert all(np.isfinite(m[k]) and m[k] >= 0.0 for k in ("action_mse", "recon_mse", "recon_mse_near", "recon_mse_teacher_view"))
        assert m["action_mse"] <= 4.0  # both actions lie in [-1, 1]


def test_keep_checkpoints_keeps_each_checkpoint_s_weights_as_a_policy_of_its_own(trained, tmp_path):
    out = tmp_path / "student"
    args = ["train", "policy", "--teacher", str(trained / "teacher"), "--encoder", str(trained / "enc"), "--out", str(out),
            "--size", "tiny", "--envs", "4", "--rollout", "8", "--minibatches", "2", "--precision", "fp32", "--checkpoint-every", "1"]  # fmt: skip
    _cmnav(*args, "--steps", "64", "--keep-checkpoints")
    _cmnav(*args, "--steps", "96", "--resume", "--keep-checkpoints")
    kept = sorted((out / "checkpoints").iterdir())
    assert [p.name for p in kept] == ["step-0000000032", "step-0000000064", "step-0000000096"]
    weights = []
    for path, step in zip(kept, (32, 64, 96)):
        policy, card = load_policy(path)
        assert card["step"] == step and card["meta"]["algorithm"] == "dagger" and not (path / "train_state.pt").exists()
        weights.append(torch.cat([p.flatten() for p in policy.parameters()]))
    assert not torch.equal(weights[0], weights[1]) and not torch.equal(weights[1], weights[2])
    assert checkpoint_fingerprint(kept[-1]) == checkpoint_fingerprint(out)  # the last kept is the run's own
    _cmnav(*args, "--steps", "128", "--resume")  # without the option, nothing more is kept
    assert len(list((out / "checkpoints").iterdir())) == 3


def test_a_student_trains_in_the_field_and_outside_it_each_with_its_teacher(trained, tmp_path):
    """``--field-env-fraction``: a share of the envs flies the field (the stand-in's stereo depth,
    PX4's response under the caps), the others the training patches on the ideal vehicle, each
    labelled by its teacher; a resume must split them alike."""
    outside = tmp_path / "outside-teacher"
    _cmnav(*TEACHER, "--out", str(outside), "--steps", "256", "--seed", "3")
    out = tmp_path / "split"
    args = ["train", "policy", "--teacher", str(trained / "teacher"), "--encoder", str(trained / "enc"), "--out", str(out),
            "--size", "tiny", "--envs", "4", "--rollout", "8", "--minibatches", "2", "--precision", "fp32", "--beta-start", "0",
            "--field", "--field-depth", "approx", "--field-env-fraction", "0.5", "--outside-teacher", str(outside)]  # fmt: skip
    _, err = _cmnav(*args, "--steps", "32")
    assert "success_field" in err and "success_outside" in err
    card = json.loads((out / "model.json").read_text())
    assert card["meta"]["train"]["field_env_fraction"] == 0.5 and card["meta"]["outside_teacher_fingerprint"]
    assert len(load_train_state(out)["env_rngs"]) == 2
    config = DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", num_envs=4, field_conditions=True, field_env_fraction=0.5,
                          field_depth="approx")
    (in_field, n_field), (outside_field, n_outside) = config.env_parts()
    assert (in_field, n_field, outside_field, n_outside) == (True, 2, False, 2)
    assert config.env_config(True, 2).action_limits.max_speed_m_s == 1.0 and config.env_config(False, 2).action_limits is None
    assert config.env_config(False, 2).corruption == "train" and config.env_config(True, 2).corruption == "stereo-approx"
    ends = replace(config, end_at_goal=True)  # the runtime's rule in the field, the paper's outside it
    assert ends.env_config(True, 2).end_at_goal and not ends.env_config(False, 2).end_at_goal
    assert replace(ends, field_conditions=False, field_env_fraction=1.0).env_config().end_at_goal
    _cmnav(*args, "--steps", "64", "--resume")
    assert json.loads((out / "model.json").read_text())["step"] == 64
    proc = subprocess.run([sys.executable, "-m", "cmnav", *args[:-4], "--steps", "96", "--resume"],
                          capture_output=True, text=True, timeout=280)  # fmt: skip
    assert proc.returncode != 0 and "resume with the same --field and --field-env-fraction" in proc.stderr, proc.stderr[-2000:]
    with pytest.raises(ValueError, match="need field_conditions"):
        DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", field_env_fraction=0.5).validate()


def test_flight_frames_are_recorded_clean_along_a_policy_s_flights_with_crash_windows_whole(trained, tmp_path):
    """`cmnav dataset --policy`: a tiny student flies (it crashes often); with --every-steps
    larger than any flight, a flight keeps its first frame, plus its last second when it crashed."""
    policy_dir, out = tmp_path / "student", tmp_path / "frames"
    torch.manual_seed(0)
    config = PolicyConfig(mlp_sizes=(4,), gru_size=2)
    save_weights(policy_dir, ActorCritic(config), "policy", config.to_json(), 0,
                 {"role": "policy", "encoder_fingerprint": checkpoint_fingerprint(trained / "enc")})  # fmt: skip
    stdout, _ = _cmnav("dataset", "--policy", str(policy_dir), "--encoder", str(trained / "enc"), "--out", str(out),
                       "--count", "40", "--envs", "4", "--every-steps", "1000", "--levels", "4", "6")  # fmt: skip
    assert "wrote 40 gray/depth pairs" in stdout
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["frames"] == 40 and manifest["flight_outcomes"]["crash"] >= 1
    samples = find_samples(out)
    per_flight = Counter(s.trajectory for s in samples)
    assert len(samples) == 40 and len(per_flight) == manifest["flights_with_frames"]
    assert {t.split("/")[0][:10] for t in per_flight} <= {"flight_L04", "flight_L05", "flight_L06"}
    # 1 frame per flight, plus up to the 15-step window of each crash
    assert max(per_flight.values()) <= 1 + 15 and manifest["frames_added_from_crash_windows"] == 40 - len(per_flight)
    assert manifest["frames_added_from_crash_windows"] >= 1
    ended = manifest["outcome_by_trajectory"]  # a flight with more than its first frame ended in a crash
    assert set(ended) <= {t.split("/")[0] for t in per_flight} and "crash" in ended.values()
    assert all(ended.get(t.split("/")[0]) == "crash" for t, n in per_flight.items() if n > 1)
    for sample in samples[:10]:  # the kept depth is the clean render: no patch holes
        assert np.isfinite(np.load(sample.depth_path)).all() and (np.load(sample.depth_path) > 0).all()
    gray, depth = GrayDepthDataset(out, "train")[0]  # a dataset `cmnav train cmwae --data` reads
    assert gray.shape == depth.shape == (1, 224, 224)

    teacher = subprocess.run([sys.executable, "-m", "cmnav", "dataset", "--policy", str(trained / "teacher"), "--encoder",
                              str(trained / "enc"), "--out", str(tmp_path / "t"), "--count", "2"],
                             capture_output=True, text=True, timeout=120)  # fmt: skip
    assert teacher.returncode != 0 and "is a privileged teacher" in teacher.stderr
    alone = subprocess.run([sys.executable, "-m", "cmnav", "dataset", "--policy", str(policy_dir), "--out", str(tmp_path / "a"),
                            "--count", "2"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert alone.returncode == 2 and "--policy and --encoder go together" in alone.stderr


def test_a_policy_is_not_taken_for_a_teacher(tmp_path):
    save_weights(tmp_path / "p", ActorCritic(PolicyConfig(mlp_sizes=(4,), gru_size=2)), "policy",
                 PolicyConfig(mlp_sizes=(4,), gru_size=2).to_json(), 0, {"role": "policy"})  # fmt: skip
    with pytest.raises(ValueError, match="is not a privileged teacher"):
        load_teacher(tmp_path / "p", torch.device("cpu"))
    with pytest.raises(ValueError, match="'train' or 'none'"):
        DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", corruption="episode").validate()


def test_squares_episodes_keep_one_large_mask_for_their_whole_episode():
    encoder = Cmwae(make_config("tiny")).encoder
    env = NavEnv(NavEnvConfig(num_envs=4, corruption="train", corrupted_env_fraction=0.0, squares_episode_fraction=1.0), encoder, "cpu",
                 seed=5, teacher_obs=True)  # fmt: skip
    env.reset()
    first = env.render_inputs()[1] == 0.0
    covered = first.flatten(1).float().mean(dim=1)
    assert bool(((covered >= 0.19) & (covered <= 0.55)).all()), covered  # EPISODE_SQUARES: 20-50 %
    env.step(torch.zeros(4, 3))
    assert bool(((env.render_inputs()[1] == 0.0) >= first).all())  # the same squares a step later (and any invalid pixel of the frame)
    assert bool((env.teacher_observation()[:, STATE_DIM:] > 0.0).all())  # the teacher's depth stays clean
    # None of them without it: the per-step patches alone (none with corrupted_env_fraction = 0).
    plain = NavEnv(NavEnvConfig(num_envs=4, corruption="train", corrupted_env_fraction=0.0), encoder, "cpu", seed=5)
    plain.reset()
    assert float((plain.render_inputs()[1] == 0.0).float().mean()) < 0.05
    with pytest.raises(ValueError, match="squares_episode_fraction=0.5 needs corruption='train'"):
        NavEnvConfig(corruption="none", squares_episode_fraction=0.5).validate()
    with pytest.raises(ValueError, match="squares_episode_fraction=0.5 needs corruption='train'"):
        DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", corruption="none", squares_episode_fraction=0.5).validate()
    # With every env in the field there is none for the squares: refused, not ignored.
    with pytest.raises(ValueError, match="squares_episode_fraction=0.5 applies to the envs outside the field"):
        DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", field_conditions=True, squares_episode_fraction=0.5).validate()
    # In the field's envs the field's depth replaces them; outside it they apply.
    config = DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", field_conditions=True, field_env_fraction=0.5,
                          squares_episode_fraction=0.3)  # fmt: skip
    assert config.env_config(in_field=True).squares_episode_fraction == 0.0 and config.env_config(in_field=False).squares_episode_fraction == 0.3


def test_the_teacher_sees_the_encoders_reconstruction_under_the_squares_when_asked():
    """squares_privileged="reconstructed": under a squares episode's mask (the render pixels it
    covers for at least half their area) the teacher's depth is the decoder's reconstruction from
    the student's latent; elsewhere, and in the episodes without squares, the clean depth."""
    torch.manual_seed(0)
    cmwae = Cmwae(make_config("tiny"))
    config = NavEnvConfig(num_envs=6, corruption="train", corrupted_env_fraction=0.0, squares_episode_fraction=0.5)
    recon_env, clean_env = (NavEnv(replace(config, squares_privileged=view), cmwae.encoder, "cpu", seed=0, teacher_obs=True,
                                   decoder=cmwae.decoder) for view in ("reconstructed", "clean"))  # fmt: skip
    recon_env.reset(), clean_env.reset()
    shown, clean = recon_env.teacher_observation()[:, STATE_DIM:], clean_env.teacher_observation()[:, STATE_DIM:]
    squares = recon_env.squares_episode
    assert 0 < int(squares.sum()) < 6 and torch.equal(squares, clean_env.squares_episode)
    assert torch.equal(shown[~squares], clean[~squares]) and not torch.equal(shown[squares], clean[squares])
    # Where the mask covers whole cells, the cell is the nearest reconstructed pixel.
    width, height = config.privileged_render_px
    env = int(squares.nonzero()[0])
    masked = F.interpolate(recon_env.episode_masks[env][None, None].float(), size=(height, width), mode="area")[0, 0] >= 0.5
    recon_m = F.interpolate(cmwae.decoder(recon_env.last_latent[env : env + 1]), size=(height, width), mode="area")[0, 0] * c.DEPTH_MAX_M
    whole = masked.view(height // 2, 2, width // 2, 2).all(dim=3).all(dim=1).flatten()
    nearest = -F.max_pool2d(-recon_m[None, None], 2).flatten()
    torch.testing.assert_close(shown[env][whole], (nearest[whole] / c.DEPTH_MAX_M).clamp(0, 1))
    with pytest.raises(ValueError, match="needs the encoder and its decoder"):
        NavEnv(replace(config, squares_privileged="reconstructed"), cmwae.encoder, "cpu")
    with pytest.raises(ValueError, match="give a squares_episode_fraction above 0"):
        DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", squares_teacher_view="reconstructed").validate()
    assert DaggerConfig(teacher_dir="t", encoder_dir="e", out_dir="o", field_conditions=True, field_env_fraction=0.5, squares_episode_fraction=0.3,
                        squares_teacher_view="reconstructed").env_config(in_field=False).squares_privileged == "reconstructed"  # fmt: skip


def test_the_squares_bound_script_flies_the_teacher_on_each_view(trained):
    proc = subprocess.run([sys.executable, str(BOUND_SCRIPT), "--teacher", str(trained / "teacher"), "--encoder", str(trained / "enc"),
                           "--levels", "0", "--episodes", "2"], capture_output=True, text=True, timeout=280)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert [line.split()[2] for line in lines] == ["clean", "reconstructed"] and all("success" in line for line in lines)
    bad = subprocess.run([sys.executable, str(BOUND_SCRIPT), "--teacher", "t", "--encoder", "e", "--views", "far"],
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert bad.returncode == 2 and "choose from clean, reconstructed" in bad.stderr
