"""Recurrent PPO pieces, and `cmnav train policy` / `cmnav eval policy` for a few iterations on
a tiny env with a tiny encoder."""

import json
import subprocess
import sys
from dataclasses import asdict

import pytest
import torch

from runtime.contract.constants import OBS_LATENT
from training.checkpoint import checkpoint_fingerprint, load_train_state, read_card, save_weights
from training.cmwae.model import Cmwae, make_config
from training.policy.evaluate import reached_goal
from training.policy.network import POLICY_SIZES, ActorCritic, RunningNorm, load_policy
from training.policy.ppo import PpoConfig, Rollout, gae, ppo_update
from training.policy.train import init_from_policy
from tests.training.test_fastpath import torchrun_digests

pytestmark = pytest.mark.timeout(300)


def test_unroll_replays_the_stepwise_rollout_with_resets():
    torch.manual_seed(0)
    model = ActorCritic(POLICY_SIZES["tiny"])
    model.obs_norm.update(torch.randn(100, 79) * 3 + 1)
    steps, n = 6, 3
    obs = torch.randn(steps, n, 79)
    starts = torch.zeros(steps, n, dtype=torch.bool)
    starts[0, 0] = starts[3, 1] = starts[4, 2] = True
    hidden0 = torch.randn(n, model.hidden_size)
    h, means, values = hidden0, [], []
    for t in range(steps):
        h = torch.where(starts[t].unsqueeze(-1), torch.zeros_like(h), h)
        mean, value, h = model.step(obs[t], h)
        means.append(mean)
        values.append(value)
    mean_u, value_u = model.unroll(obs, hidden0, starts)
    torch.testing.assert_close(mean_u, torch.stack(means))
    torch.testing.assert_close(value_u, torch.stack(values))


def test_gae_matches_a_hand_computation():
    gamma, lam = 0.9, 0.8
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.tensor([[0.5], [1.0], [1.5]])
    dones = torch.tensor([[False], [True], [False]])
    rollout = Rollout(torch.zeros(3, 1, 79), torch.zeros(3, 1, dtype=torch.bool), torch.zeros(3, 1, 3), torch.zeros(3, 1),
                      values, rewards, dones, torch.zeros(1, 4), torch.tensor([2.0]))  # fmt: skip
    adv, ret = gae(rollout, gamma, lam)
    d2 = 3.0 + gamma * 2.0 - 1.5
    d1 = 2.0 - 1.0  # the episode ended: no bootstrap
    d0 = 1.0 + gamma * 1.0 - 0.5
    expected = torch.tensor([[d0 + gamma * lam * d1], [d1], [d2]])
    torch.testing.assert_close(adv, expected)
    torch.testing.assert_close(ret, expected + values)


def test_target_kl_ends_the_update_at_the_first_minibatch_past_it():
    """With little action noise (a fine-tuned student's std 0.1) a large step moves the policy far
    from the rollout's; --target-kl stops the epochs where a minibatch's KL passes 1.5x it."""
    torch.manual_seed(0)
    model = ActorCritic(POLICY_SIZES["tiny"])
    model.obs_norm.update(torch.randn(100, 79))
    with torch.no_grad():
        model.log_std.fill_(-2.3)
    steps, n = 8, 8
    obs, hidden0 = torch.randn(steps, n, 79), torch.zeros(n, model.hidden_size)
    starts = torch.zeros(steps, n, dtype=torch.bool)
    starts[0] = True
    with torch.no_grad():
        mean, values = model.unroll(obs, hidden0, starts)
        dist = torch.distributions.Normal(mean, model.log_std.exp())
        actions = dist.sample()
        rollout = Rollout(obs, starts, actions, dist.log_prob(actions).sum(-1), values, torch.randn(steps, n),
                          torch.zeros(steps, n, dtype=torch.bool), hidden0, torch.zeros(n))  # fmt: skip

    def update(target_kl, reduce_mean=None):
        tuned = ActorCritic(POLICY_SIZES["tiny"])
        tuned.load_state_dict(model.state_dict())
        config = PpoConfig(epochs=4, minibatches=4, lr=1e-3, target_kl=target_kl)
        stats = ppo_update(tuned, torch.optim.Adam(tuned.parameters(), lr=config.lr), rollout, config, torch.Generator().manual_seed(0),
                           reduce_mean=reduce_mean)  # fmt: skip
        with torch.no_grad():
            moved = torch.distributions.Normal(tuned.unroll(obs, hidden0, starts)[0], dist.scale)
            return stats, float(torch.distributions.kl_divergence(dist, moved).sum(-1).mean())

    free, free_kl = update(None)
    capped, capped_kl = update(1e-3)
    assert free["updates"] == 16
    assert 1 <= capped["updates"] < 16
    assert capped_kl < free_kl / 3
    # Under torchrun the stop follows the processes' mean KL (reduce_mean), not this process's own.
    assert update(1e-3, reduce_mean=lambda kl: kl * 0)[0]["updates"] == 16
    assert update(1e-3, reduce_mean=lambda kl: kl + 1)[0]["updates"] == 0
    with pytest.raises(ValueError, match="target_kl"):
        PpoConfig(target_kl=0.0).validate(8)


def test_target_kl_stops_every_torchrun_process_at_the_same_minibatch(tmp_path):
    """Under torchrun each process has its own rollout, so its own KL: the stop is decided on their
    mean (the unit test above shows the decision follows it), so every process takes the same steps
    and they end with the same weights."""
    out = tmp_path / "teacher"
    digests = torchrun_digests("train", "teacher", "--size", "tiny", "--envs", "8", "--rollout", "16", "--minibatches", "4", "--lr", "1e-2",
                               "--target-kl", "1e-4", "--steps", "1024", "--out", str(out))  # fmt: skip
    assert digests[0] == digests[1]
    assert read_card(out, "policy")["meta"]["train"]["ppo"]["target_kl"] == 1e-4


def test_running_norm_equals_the_statistics_of_all_batches():
    norm = RunningNorm(4)
    batches = [torch.randn(n, 4) * s + m for n, s, m in ((10, 1.0, 0.0), (50, 3.0, 2.0), (7, 0.5, -1.0))]
    for b in batches:
        norm.update(b)
    everything = torch.cat(batches)
    torch.testing.assert_close(norm.mean, everything.mean(0), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(norm.var, everything.var(0, unbiased=False), rtol=1e-4, atol=1e-5)
    assert int(norm.count) == 67


def _cmnav(*args):
    proc = subprocess.run([sys.executable, "-m", "cmnav", *args], capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout, proc.stderr


@pytest.fixture(scope="module")
def encoders(tmp_path_factory):
    root = tmp_path_factory.mktemp("encoders")
    config = make_config("tiny")
    for name, seed in (("enc", 0), ("other", 1)):
        torch.manual_seed(seed)
        save_weights(root / name, Cmwae(config), "cmwae", asdict(config), 0, {"train": {"scheme": "s2"}})
    return root


TRAIN = ["train", "policy", "--size", "tiny", "--envs", "8", "--rollout", "16", "--minibatches", "2",
         "--checkpoint-every", "4", "--curriculum-window", "2", "--max-level", "3"]  # fmt: skip


def test_train_policy_moves_the_curriculum_checkpoints_resumes_and_evaluates(encoders, tmp_path):
    out = tmp_path / "policy"
    # 12 iterations x 16 steps = 192 steps per env, past the 150-step timeout: every env ends at
    # least one episode.  An untrained policy rarely succeeds, so windows of 2 episodes move
    # the curriculum down from level 2.
    _, stderr = _cmnav(*TRAIN, "--encoder", str(encoders / "enc"), "--out", str(out), "--steps", "1536", "--start-level", "2")
    card = read_card(out, "policy")
    assert card["step"] == 1536 and card["meta"]["iteration"] == 12
    assert card["meta"]["curriculum_level"] < 2
    assert load_train_state(out)["curriculum"]["changes"] >= 1
    assert "train policy:" in stderr and "env-steps/s" in stderr
    assert list((out / "tensorboard").glob("events.out.tfevents.*"))
    first = {k: v.clone() for k, v in load_policy(out)[0].state_dict().items()}

    assert load_train_state(out)["optimizer"]["param_groups"][0]["lr"] == pytest.approx(3e-4)
    # --lr applies to the resumed run too (the optimizer state alone would keep the old rate)
    _cmnav(*TRAIN, "--encoder", str(encoders / "enc"), "--out", str(out), "--steps", "2048", "--resume", "--lr", "1e-4")
    card = read_card(out, "policy")
    assert card["step"] == 2048 and card["meta"]["iteration"] == 16
    assert load_train_state(out)["optimizer"]["param_groups"][0]["lr"] == pytest.approx(1e-4)
    resumed = load_policy(out)[0].state_dict()
    assert any(not torch.equal(first[k], resumed[k]) for k in first if k != "obs_norm.count")

    stdout, _ = _cmnav("eval", "policy", "--policy", str(out), "--encoder", str(encoders / "enc"), "--levels", "0,3",
                       "--episodes", "2", "--out", str(tmp_path / "eval"), "--json")  # fmt: skip
    result = json.loads(stdout.strip().splitlines()[-1])
    cells = {(c["condition"], c["level"]): c for c in result["cells"]}
    assert set(cells) == {(cond, lv) for cond in ("clean", "corrupted", "projector-off") for lv in (0, 3)}
    for cell in cells.values():
        assert cell["episodes"] == 2
        assert cell["success_pct"] + cell["timeout_pct"] + cell["crash_pct"] == pytest.approx(100.0)
        low, high = cell["success_ci95_pct"]
        assert 0.0 <= low <= cell["success_pct"] <= high <= 100.0 and high - low > 30.0  # two episodes say little
        assert cell["success_pct"] <= cell["reached_pct"] <= 100.0  # a success ends within 1 m: it reached the goal
    assert "| condition | level | episodes | success % | 95 % interval | timeout % | crash % | reached % |" in stdout
    assert len(list((tmp_path / "eval").glob("clean_level00_ep*.png"))) == 2
    assert (tmp_path / "eval" / "table2.md").read_text().count("\n") == 8


def test_eval_refuses_an_encoder_the_policy_was_not_trained_with(encoders, tmp_path):
    out = tmp_path / "policy"
    _cmnav(*TRAIN, "--encoder", str(encoders / "enc"), "--out", str(out), "--steps", "128")
    proc = subprocess.run([sys.executable, "-m", "cmnav", "eval", "policy", "--policy", str(out), "--encoder",
                           str(encoders / "other"), "--episodes", "1"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "was trained on encoder" in proc.stderr and "pass --encoder the checkpoint the policy was trained with" in proc.stderr
    assert f"--init-from {out}" in proc.stderr


def test_init_from_fine_tunes_a_policy_on_another_encoder(encoders, tmp_path):
    source = tmp_path / "policy"
    _cmnav(*TRAIN, "--encoder", str(encoders / "enc"), "--out", str(source), "--steps", "128")
    tuned = tmp_path / "tuned"
    _cmnav(*TRAIN, "--encoder", str(encoders / "other"), "--init-from", str(source), "--out", str(tuned), "--steps", "128")
    meta = read_card(tuned, "policy")["meta"]
    assert meta["encoder_fingerprint"] == checkpoint_fingerprint(encoders / "other")
    assert meta["init_from"] == {"dir": str(source), "fingerprint": checkpoint_fingerprint(source), "env_steps": 128,
                                 "encoder_fingerprint": checkpoint_fingerprint(encoders / "enc"),
                                 "latent_stats_reestimated": True}  # fmt: skip
    start, trained = load_policy(source)[0], load_policy(tuned)[0]
    assert int(trained.obs_norm.count) > int(start.obs_norm.count)  # continued from the source's statistics
    # The network's size must match the source's.
    proc = subprocess.run([sys.executable, "-m", "cmnav", *TRAIN[:2], "--size", "paper", "--envs", "8", "--rollout", "16",
                           "--encoder", str(encoders / "other"), "--init-from", str(source), "--out", str(tmp_path / "x"),
                           "--steps", "128"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 2 and "pass the --size it was trained with" in proc.stderr


def test_init_from_restandardises_the_latent_on_the_new_encoder(encoders, tmp_path):
    source = tmp_path / "policy"
    _cmnav(*TRAIN, "--encoder", str(encoders / "enc"), "--out", str(source), "--steps", "128")
    start = load_policy(source)[0]

    class Resets:  # the env's first observations, as init_from_policy reads them
        def __init__(self):
            self.generator = torch.Generator().manual_seed(0)
            self.batches = []

        def reset(self):
            self.batches.append(torch.randn(8, 79, generator=self.generator) * 3 + 2)
            return self.batches[-1]

    model, env = ActorCritic(POLICY_SIZES["tiny"]), Resets()
    init_from_policy(model, str(source), checkpoint_fingerprint(encoders / "other"), env)
    latents = torch.cat(env.batches)[:, OBS_LATENT]
    torch.testing.assert_close(model.obs_norm.mean[OBS_LATENT], latents.mean(0))
    torch.testing.assert_close(model.obs_norm.var[OBS_LATENT], latents.var(0, unbiased=False))
    state = slice(0, OBS_LATENT.start)
    torch.testing.assert_close(model.obs_norm.mean[state], start.obs_norm.mean[state])
    for name, tensor in start.state_dict().items():
        if not name.startswith("obs_norm"):
            torch.testing.assert_close(model.state_dict()[name], tensor, msg=name)

    # Same encoder: the statistics are kept as trained.
    same = ActorCritic(POLICY_SIZES["tiny"])
    init_from_policy(same, str(source), checkpoint_fingerprint(encoders / "enc"), Resets())
    torch.testing.assert_close(same.obs_norm.mean, start.obs_norm.mean)


def test_ppo_fine_tune_warms_the_critic_up_first_with_the_noise_set_and_the_inputs_kept(encoders, tmp_path):
    """A distilled student fine-tuned by PPO (here on the squares episodes): for
    --critic-warmup-iterations only its value head learns, its action noise starts at
    --init-log-std, and with --freeze-obs-norm its input statistics never move."""
    source = tmp_path / "policy"
    _cmnav(*TRAIN, "--encoder", str(encoders / "enc"), "--out", str(source), "--steps", "128")
    tuned = tmp_path / "tuned"
    fine_tune = [*TRAIN, "--encoder", str(encoders / "enc"), "--out", str(tuned), "--init-from", str(source), "--init-log-std", "-2",
                 "--critic-warmup-iterations", "2", "--freeze-obs-norm", "--squares-episode-fraction", "0.5", "--target-kl", "0.02"]  # fmt: skip
    _cmnav(*fine_tune, "--steps", "256")  # 2 iterations of 8 envs x 16 steps: the warm-up
    start, warmed = load_policy(source)[0].state_dict(), load_policy(tuned)[0].state_dict()
    card = read_card(tuned, "policy")
    assert card["meta"]["init_from"]["log_std_set_to"] == -2.0
    assert card["meta"]["train"]["env_overrides"] == {"squares_episode_fraction": 0.5}
    assert card["meta"]["train"]["ppo"]["target_kl"] == 0.02
    torch.testing.assert_close(warmed["log_std"], torch.full((3,), -2.0))
    assert not torch.equal(warmed["value_head.weight"], start["value_head.weight"])
    for name, tensor in start.items():
        if not name.startswith("value_head") and name != "log_std":
            assert torch.equal(warmed[name], tensor), name  # the policy and its normaliser as distilled

    _cmnav(*fine_tune, "--steps", "512", "--resume")  # the same command resumed: 2 iterations of PPO after the warm-up
    tuned_state = load_policy(tuned)[0].state_dict()
    assert not torch.equal(tuned_state["action_head.weight"], start["action_head.weight"])
    for name in ("obs_norm.mean", "obs_norm.var", "obs_norm.count"):
        assert torch.equal(tuned_state[name], start[name]), name

    # What makes no sense is refused, naming the fix.
    proc = subprocess.run([sys.executable, "-m", "cmnav", *TRAIN, "--encoder", str(encoders / "enc"), "--out", str(tmp_path / "x"),
                           "--steps", "128", "--init-log-std", "-2"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 2 and "give --init-from POLICY_DIR" in proc.stderr and "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "cmnav", *TRAIN, "--encoder", str(encoders / "enc"), "--out", str(tmp_path / "x"),
                           "--steps", "128", "--init-log-std", "-2", "--resume"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 2 and "holds no training state to resume" in proc.stderr and "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "cmnav", *TRAIN, "--encoder", str(encoders / "enc"), "--out", str(tmp_path / "x"),
                           "--teacher", str(source), "--critic-warmup-iterations", "2", "--target-kl", "0.02"], capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 2 and "--critic-warmup-iterations, --target-kl fine-tune by PPO" in proc.stderr and "drop --teacher" in proc.stderr


def test_reached_is_the_runtimes_rule_any_entry_within_a_metre_before_the_end():
    goal = [5.0, 0.0, 2.0]
    through = [[0.0, 0.0, 2.0], [4.2, 0.0, 2.0], [5.0, 0.9, 2.0], [6.5, 1.5, 2.0]]  # passed within 0.9 m, ended 2.1 m off
    assert reached_goal(through, goal)
    assert not reached_goal([[0.0, 0.0, 2.0], [3.9, 0.5, 2.5], [4.3, 1.0, 2.0]], goal)  # never nearer than 1.2 m
