"""`cmnav bench train`: how fast training runs on one device, as ratios measured in one run.

1. The frozen encoder alone: frames/s of a batch in each precision and layout (fp32 default,
   fp32 channels_last, bf16 channels_last; training.fastpath) on rendered frames, each as a
   ratio to fp32's default, and bf16's latent error against fp32.
2. Policy training: env-steps/s for N envs with the encoder on fp32 default and on the fast path
   ``auto`` picks, and the share of each stage: rendering, preprocessing + corruption, the frozen
   encoder, physics, the policy's action sampling, and the PPO update (timed on the rollout just
   collected).  Each N runs a short rollout in :class:`training.policy.env.NavEnv` (the training
   configuration: a random half of the envs corrupted each step, kicks, jitter) at level ``level``
   with the paper-size policy, after warm-up steps that load kernels and fill caches.
3. The privileged teacher's env (no 224 render, no encoder) with its PPO update: env-steps/s.
   And the field (``training.policy.field``, DAgger's ``--field``) for the first N on the ``auto``
   path: with the simulated D455's stereo matching and with its parametric stand-in
   (``--field-depth approx``), their ratio in the same run.
4. CMWAE training: optimizer steps/s in each precision.
5. With ``recorded`` flight logs: bf16's latent error against fp32 on the recorded frames, and with
   ``policy_dir`` the change of the policy's action it causes, each model carrying its own GRU
   state through every flight.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace

import torch

from training.cmwae.loss import cmwae_loss
from training.cmwae.model import Cmwae, make_config
from training.cmwae.train import load_cmwae
from training.fastpath import FastPath, FrozenEncoder, choose_fast_path, latent_parity, read_cpu_flags
from training.policy.env import CurriculumConfig, NavEnv, NavEnvConfig, parity_frames
from training.policy.field import FIELD_DEPTHS, field_env_overrides
from training.policy.network import POLICY_SIZES, ActorCritic
from training.policy.ppo import PpoConfig, ReturnNormalizer, ppo_update
from training.policy.train import collect_rollout

from .device import device_name, synchronize

STAGES = ("render", "preprocess", "encode", "physics", "policy", "ppo_update")
TEACHER_STAGES = ("privileged", "physics", "policy", "ppo_update")
FIELD_STAGES = ("render", "stereo", "gray", "preprocess", "encode", "physics", "policy", "ppo_update")
FP32_DEFAULT = FastPath(torch.float32, False, "the reference: fp32, default layout")


@dataclass(frozen=True)
class TrainBenchConfig:
    env_counts: tuple[int, ...] = (16, 64)
    device: str = "cpu"
    encoder_dir: str | None = None  # default: a freshly initialised encoder of encoder_size
    encoder_size: str = "paper"
    policy_size: str = "paper"
    rollout_steps: int = 16
    warmup_steps: int = 2
    level: int = 10
    seed: int = 0
    encoder_batch: int = 64  # frames per encoder call in section 1
    encoder_repeats: int = 3
    teacher_envs: int = 1024
    cmwae_batch: int = 32
    cmwae_steps: int = 3
    recorded: tuple[str, ...] = ()  # flight logs (MCAP) for the parity on recorded frames
    policy_dir: str | None = None  # the policy whose action parity is measured on them


def quick(config: TrainBenchConfig) -> TrainBenchConfig:
    """A seconds-long smoke run of the whole path, not a measurement."""
    return replace(config, env_counts=(2,), encoder_size="tiny", policy_size="tiny", rollout_steps=4, warmup_steps=1, level=2,
                   encoder_batch=4, encoder_repeats=1, teacher_envs=8, cmwae_batch=4, cmwae_steps=1)  # fmt: skip


def _paths(device: torch.device) -> dict[str, FastPath]:
    """fp32 default, fp32 channels_last, bf16 channels_last (on the CPU; on CUDA what auto picks)."""
    if device.type != "cpu":
        return {"fp32": FP32_DEFAULT, "auto": choose_fast_path("auto", device)}
    return {"fp32": FP32_DEFAULT, "fp32 channels_last": FastPath(torch.float32, True, "bench"),
            "bf16 channels_last": FastPath(torch.bfloat16, True, "bench")}  # fmt: skip


def _encoder_for(encoder, path: FastPath):
    return encoder if path == FP32_DEFAULT else FrozenEncoder(encoder, path)


@torch.no_grad()
def encoder_speeds(encoder, config: TrainBenchConfig, device: torch.device) -> list[dict]:
    gray, depth = parity_frames(encoder, device, count=config.encoder_batch, level=config.level, seed=config.seed)
    rows = []
    for name, path in _paths(device).items():
        fast = _encoder_for(encoder, path)
        fast(gray, depth)  # warm-up: oneDNN primitives, weight reorders
        synchronize(device)
        t0 = time.perf_counter()
        for _ in range(config.encoder_repeats):
            fast(gray, depth)
        synchronize(device)
        rows.append({"path": name, "frames_per_s": config.encoder_batch * config.encoder_repeats / (time.perf_counter() - t0)})
        if path.bf16:
            rows[-1]["parity"] = latent_parity(encoder, fast, gray, depth).to_json()
    for row in rows:
        row["ratio_to_fp32"] = row["frames_per_s"] / rows[0]["frames_per_s"]
    return rows


def _rollout_row(env: NavEnv, policy: ActorCritic, config: TrainBenchConfig, device: torch.device, stages) -> dict:
    n = env.num_envs
    ppo = PpoConfig(rollout_steps=config.rollout_steps, minibatches=min(4, n))
    normalizer = ReturnNormalizer(n, ppo.gamma, device)
    optimizer = torch.optim.Adam(policy.parameters(), lr=ppo.lr)
    obs = env.reset()
    hidden = policy.initial_hidden(n, device)
    starts = torch.ones(n, dtype=torch.bool, device=device)
    warm = replace(ppo, rollout_steps=config.warmup_steps)
    _, hidden, starts, obs, _ = collect_rollout(policy, env, obs, hidden, starts, normalizer, warm)
    env.stage_seconds = dict.fromkeys(env.stage_seconds, 0.0)
    t0 = time.perf_counter()
    rollout, hidden, starts, obs, _ = collect_rollout(policy, env, obs, hidden, starts, normalizer, ppo)
    synchronize(device)
    t_collect = time.perf_counter() - t0
    policy.train()
    t1 = time.perf_counter()
    ppo_update(policy, optimizer, rollout, ppo, torch.Generator().manual_seed(0))
    synchronize(device)
    t_update = time.perf_counter() - t1
    seconds = dict(env.stage_seconds)
    seconds["policy"] = max(t_collect - sum(seconds.values()), 0.0)  # sampling, buffers, bookkeeping
    seconds["ppo_update"] = t_update
    total = t_collect + t_update
    steps = n * config.rollout_steps
    return {
        "envs": n, "env_steps": steps, "env_steps_per_s": steps / total, "collect_env_steps_per_s": steps / t_collect,
        "share": {k: seconds[k] / total for k in stages}, "ms_per_step": {k: 1e3 * seconds[k] / config.rollout_steps for k in stages},
    }  # fmt: skip


def _level_config(n: int, level: int) -> NavEnvConfig:
    return NavEnvConfig(num_envs=n, curriculum=CurriculumConfig(start_level=level, min_level=level, max_level=level))


def cmwae_train_speeds(config: TrainBenchConfig, device: torch.device) -> list[dict]:
    generator = torch.Generator().manual_seed(config.seed)
    gray = torch.rand(config.cmwae_batch, 1, 224, 224, generator=generator).to(device)
    depth = torch.rand(config.cmwae_batch, 1, 224, 224, generator=generator).to(device)
    rows = []
    for name, path in _paths(device).items():
        torch.manual_seed(config.seed)
        model = path.prepare_trained(Cmwae(make_config(config.encoder_size)).to(device))
        optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)

        def step() -> None:
            with path.autocast(device):
                z, recon = model(path.image(gray), path.image(depth))
            loss = cmwae_loss(recon.float(), depth, z.float(), 10.0)["loss"]
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

        step()  # warm-up
        synchronize(device)
        t0 = time.perf_counter()
        for _ in range(config.cmwae_steps):
            step()
        synchronize(device)
        rows.append({"path": name, "steps_per_s": config.cmwae_steps / (time.perf_counter() - t0)})
    for row in rows:
        row["ratio_to_fp32"] = row["steps_per_s"] / rows[0]["steps_per_s"]
    return rows


def run_train_bench(config: TrainBenchConfig) -> dict:
    device = torch.device(config.device)
    torch.manual_seed(config.seed)
    if config.encoder_dir is not None:
        encoder = load_cmwae(config.encoder_dir, device)[0].encoder
        encoder_name = config.encoder_dir
    else:
        encoder = Cmwae(make_config(config.encoder_size)).encoder.to(device).eval()
        encoder_name = f"untrained {config.encoder_size}-size CMWAE encoder"
    auto = choose_fast_path("auto", device)
    encoders = encoder_speeds(encoder, config, device)
    rows = []
    for n in config.env_counts:
        for name, path in {"fp32": FP32_DEFAULT, f"auto ({auto.name})": auto}.items():
            env = NavEnv(_level_config(n, config.level), _encoder_for(encoder, path), device, seed=config.seed)
            policy = ActorCritic(POLICY_SIZES[config.policy_size]).to(device)
            rows.append({"precision": name, **_rollout_row(env, policy, config, device, STAGES)})
    teacher_env = NavEnv(_level_config(config.teacher_envs, config.level), None, device, seed=config.seed)
    teacher_policy = ActorCritic(replace(POLICY_SIZES[config.policy_size], obs_dim=teacher_env.config.privileged_obs_dim)).to(device)
    teacher = _rollout_row(teacher_env, teacher_policy, config, device, TEACHER_STAGES)
    field_rows = []
    for depth, corruption in FIELD_DEPTHS.items():
        field_config = replace(_level_config(config.env_counts[0], config.level), corruption=corruption, **field_env_overrides())
        env = NavEnv(field_config, _encoder_for(encoder, auto), device, seed=config.seed)
        policy = ActorCritic(POLICY_SIZES[config.policy_size]).to(device)
        field_rows.append({"field_depth": depth, **_rollout_row(env, policy, config, device, FIELD_STAGES)})
    for row in field_rows:
        row["ratio_to_stereo"] = row["env_steps_per_s"] / field_rows[0]["env_steps_per_s"]
    return {"device": device_name(device), "cpu": cpu_name(), "cpu_bf16_flags": sorted(f for f in read_cpu_flags() if "bf16" in f),
            "encoder": encoder_name, "threads": torch.get_num_threads(), "auto_path": {"name": auto.name, "reason": auto.reason},
            "config": asdict(config), "encoder_speed": encoders, "rows": rows, "teacher": teacher, "field": field_rows,
            "cmwae_train": cmwae_train_speeds(config, device),
            "recorded_parity": recorded_parity(encoder, config, device) if config.recorded else None}  # fmt: skip


@torch.no_grad()
def recorded_parity(encoder, config: TrainBenchConfig, device: torch.device) -> dict:
    """bf16 against fp32 on every step of the recorded flights: the latent's error (relative to its
    per-dimension std over all steps) and, with a policy, the action's, each carrying its own GRU state."""
    from export.policy_onnx import flight_inputs
    from training.policy.network import load_policy

    policy = load_policy(config.policy_dir, device)[0] if config.policy_dir else None
    fast = FrozenEncoder(encoder, FastPath(torch.bfloat16, device.type == "cpu", "bench"))
    latents = {"fp32": [], "bf16": []}
    action_error, steps = 0.0, 0
    for log_path in config.recorded:
        flight = flight_inputs(log_path, policy.hidden_size if policy else 1)
        gray, depth = torch.from_numpy(flight.gray).to(device), torch.from_numpy(flight.depth).to(device)
        z = {"fp32": torch.cat([encoder(gray[i : i + 32], depth[i : i + 32]) for i in range(0, len(flight), 32)]),
             "bf16": torch.cat([fast(gray[i : i + 32], depth[i : i + 32]) for i in range(0, len(flight), 32)])}  # fmt: skip
        for name in z:
            latents[name].append(z[name].float())
        steps += len(flight)
        if policy is None:
            continue
        state = torch.from_numpy(flight.state).to(device)
        hidden = {name: policy.initial_hidden(1, device) for name in z}
        for i in range(len(flight)):
            actions = {}
            for name in z:
                if flight.resets[i]:
                    hidden[name] = policy.initial_hidden(1, device)
                actions[name], _, hidden[name] = policy.step(torch.cat([state[i : i + 1], z[name][i : i + 1]], dim=1), hidden[name])
            action_error = max(action_error, float((actions["bf16"] - actions["fp32"]).abs().max()))
    reference, bf16 = torch.cat(latents["fp32"]), torch.cat(latents["bf16"])
    rel = (bf16 - reference) / reference.std(dim=0).clamp_min(1e-6)
    return {"flights": len(config.recorded), "steps": steps, "latent_max_rel": float(rel.abs().max()),
            "latent_rms_rel": float(rel.square().mean().sqrt()),
            "action_max_abs": action_error if policy is not None else None}  # fmt: skip


def cpu_name() -> str:
    """The CPU's model name from /proc/cpuinfo (or the platform's processor string)."""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or platform.machine()


def _stage_table(columns: tuple[str, ...], stages: tuple[str, ...], rows: list[tuple[tuple[str, ...], dict]]) -> list[str]:
    """A markdown table: ``columns``, then each stage's share of the time (%), a row per (cells, shares)."""
    lines = ["| " + " | ".join([*columns, *(f"{s} %" for s in stages)]) + " |", "|" + "---|" * (len(columns) + len(stages))]
    lines += ["| " + " | ".join([*cells, *(f"{100 * share[s]:.1f}" for s in stages)]) + " |" for cells, share in rows]
    return lines


def format_train_bench(result: dict) -> str:
    cfg = result["config"]
    lines = [
        f"bench train on {result['device']}: {result['cpu']} (bf16 flags: {', '.join(result['cpu_bf16_flags']) or 'none'}), "
        f"{result['threads']} torch threads; encoder: {result['encoder']}; level {cfg['level']}; auto picks "
        f"{result['auto_path']['name']} ({result['auto_path']['reason']})",
        "",
        f"Frozen encoder, batch of {cfg['encoder_batch']} rendered frames:",
        "",
        "| path | frames/s | x fp32 default | bf16 latent error (max / RMS of the std) |",
        "|---|---|---|---|",
    ]
    for row in result["encoder_speed"]:
        parity = row.get("parity")
        error = f"{parity['max_rel']:.4f} / {parity['rms_rel']:.4f}" if parity else "-"
        lines.append(f"| {row['path']} | {row['frames_per_s']:.1f} | {row['ratio_to_fp32']:.2f} | {error} |")
    t = result["teacher"]
    lines += [
        "",
        f"Policy training (PPO, rollout {cfg['rollout_steps']} steps):",
        "",
        *_stage_table(("envs", "encoder", "env-steps/s (with PPO update)", "env-steps/s (collect only)"), STAGES,
                      [((str(r["envs"]), r["precision"], f"{r['env_steps_per_s']:.1f}", f"{r['collect_env_steps_per_s']:.1f}"), r["share"])
                       for r in result["rows"]]),
        "",
        "Privileged teacher (state + 32x18 clean depth, no encoder), with its PPO update:",
        "",
        *_stage_table(("envs", "env-steps/s (with PPO update)", "env-steps/s (collect only)"), TEACHER_STAGES,
                      [((str(t["envs"]), f"{t['env_steps_per_s']:.1f}", f"{t['collect_env_steps_per_s']:.1f}"), t["share"])]),
        "",
        f"The field (--field, encoder on {result['auto_path']['name']}), with the PPO update:",
        "",
        *_stage_table(("envs", "depth", "env-steps/s", "x stereo"), FIELD_STAGES,
                      [((str(r["envs"]), r["field_depth"], f"{r['env_steps_per_s']:.1f}", f"{r['ratio_to_stereo']:.2f}"), r["share"])
                       for r in result["field"]]),
        "",
        f"CMWAE training (batch {cfg['cmwae_batch']}, {cfg['encoder_size']} size):",
        "",
        "| path | steps/s | x fp32 default |",
        "|---|---|---|",
    ]
    lines += [f"| {r['path']} | {r['steps_per_s']:.2f} | {r['ratio_to_fp32']:.2f} |" for r in result["cmwae_train"]]
    parity = result.get("recorded_parity")
    if parity:
        action = "-" if parity["action_max_abs"] is None else f"{parity['action_max_abs']:.4f}"
        lines += ["", f"bf16 against fp32 on {parity['steps']} recorded steps of {parity['flights']} flights: latent error max "
                  f"{parity['latent_max_rel']:.4f} / RMS {parity['latent_rms_rel']:.4f} of its std; policy action max {action}"]  # fmt: skip
    return "\n".join(lines)
