"""The batched navigation environment the policy trains and is evaluated in (PAPER.md §Policy,
§Simulation; DESIGN §5).

N envs step together on one device at the control rate (15 Hz): render depth + textured gray
at the camera pose (``sim.render``), preprocess like the runtime (``sim.preprocess_torch``),
optionally corrupt the depth (``sim.degradation``), encode with the frozen encoder, build the
79-value observation exactly as the runtime does (``contract_torch``), and after the policy acts,
map the action to a body velocity command (the contract's mapping) that the velocity-tracking
dynamics follow for one control period, with collisions checked every physics sub-step.

Episodes end in a crash (any contact) or after 10 s: success if the vehicle is then within 1 m of
the goal, else timeout (Aerial Gym's rule, which its reward assumes: a policy is paid for
staying at the goal, so reaching it must not end the episode).  With ``end_at_goal`` (a training
option) they end instead as the runtime's do: in success at the first step within 1 m, paid what
staying there would at most have earned (below).  An ended env is reset at once to a new room at
the curriculum's current level (training), or stays ended (evaluation, ``auto_reset=False``).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import asdict, dataclass, field, fields, replace

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from runtime.contract.constants import (
    CONTROL_PERIOD_S,
    DEPTH_MAX_M,
    EPISODE_DURATION_S,
    GOAL_REACHED_RADIUS_M,
    IMAGE_SIZE_PX,
    LATENT_DIM,
    OBSERVATION_DIM,
    STATE_DIM,
)
from runtime.contract.action import ActionLimits
from sim.camera import CameraModel, MountJitter, camera_pose, sample_mount_jitter
from sim.collision import DEFAULT_VEHICLE_RADIUS_M, collides
from sim.degradation import EPISODE_SQUARES, RL_TRAINING, PatchScheme, ProjectorOffModel, corrupt_depth, patch_masks
from sim.delay import DelayLine, delay_steps
from sim.dynamics import (COMMAND_DELAY_PARAMS, PER_ENV_PARAMS, DynamicsParams, DynamicsRandomization, QuadrotorDynamics,
                          QuadState, sample_dynamics)  # fmt: skip
from sim.estimate import StateEstimateConfig, StateEstimator
from sim.preprocess_torch import preprocess_depth_batch, preprocess_gray_batch
from sim.render import RenderOutput, render
from sim.sensor import D455, StereoConfig, StereoDepthSensor
from sim.sensor.approx import StereoApproxConfig, approx_stereo_depth
from sim.sensor.gray import GrayCamera, GrayCameraConfig, GrayFrame, sample_brightness
from sim.rotations import quat_from_euler, quat_multiply, quat_rotate, quat_rotate_inverse, rotate_about_z
from sim.world import WorldBatch, WorldConfig, env_seed, make_worlds

from ..fastpath import frozen_encoder

from .contract_torch import action_to_velocity_flu_batch, observation_state_batch

RUNNING, SUCCESS, CRASH, TIMEOUT = 0, 1, 2, 3
OUTCOMES = {SUCCESS: "success", CRASH: "crash", TIMEOUT: "timeout"}
CORRUPTION_MODES = ("none", "train", "episode", "projector-off", "stereo", "stereo-projector-off", "stereo-approx",
                    "stereo-approx-projector-off")  # fmt: skip
# The modes whose depth is the simulated D455's stereo depth (sim.sensor), projector on or off.
STEREO_MODES = {"stereo": True, "stereo-projector-off": False}
# ... and those of its parametric stand-in (sim.sensor.approx: 3x the env-steps/s, its error stated in docs/sensor.md).
APPROX_STEREO_MODES = {"stereo-approx": True, "stereo-approx-projector-off": False}
LEVEL_SAMPLING = ("curriculum", "uniform")
SQUARES_PRIVILEGED = ("clean", "reconstructed")  # NavEnvConfig.squares_privileged


@dataclass(frozen=True)
class RewardConfig:
    """PAPER.md §Reward with Aerial Gym's values: r(x, e) = m * exp(-x^2 e) attraction terms,
    m * (exp(-x^2 e) - 1) action penalties (in [-m, 0]), progress, a (20 - dist)/20 term and the
    crash penalty.  Positive terms are scaled by 1 + positive_scale_per_progress x curriculum
    progress (level / max level)."""

    goal_attraction: float = 5.0
    goal_attraction_exp: float = 1.0 / 3.5
    goal_close: float = 5.0
    goal_close_exp: float = 2.0
    progress_gain: float = 10.0  # per metre closer
    progress_away_gain: float = 20.0  # per metre farther
    distance_term_range_m: float = 20.0  # (range - dist) / range
    action_change_penalty: tuple[float, float, float] = (0.8, 0.8, 0.8)
    action_change_exp: tuple[float, float, float] = (3.333, 5.0, 3.33)
    action_penalty: tuple[float, float, float] = (0.1, 1.5, 1.5)
    action_exp: tuple[float, float, float] = (0.3, 1.0, 2.0)
    crash_penalty: float = 100.0
    positive_scale_per_progress: float = 2.0


@dataclass(frozen=True)
class CurriculumConfig:
    """Level k = k obstacles.  After each ``window_episodes`` finished episodes, the level goes up
    by ``step_up`` when the window's success rate exceeds ``up_threshold`` and down by
    ``step_down`` below ``down_threshold``, within [min_level, max_level]."""

    start_level: int = 0
    min_level: int = 0
    max_level: int = 20
    step_up: int = 1
    step_down: int = 1
    up_threshold: float = 0.7
    down_threshold: float = 0.3
    window_episodes: int = 256

    def validate(self) -> None:
        if not 0 <= self.min_level <= self.start_level <= self.max_level:
            raise ValueError(
                f"curriculum levels must satisfy 0 <= min_level ({self.min_level}) <= start_level "
                f"({self.start_level}) <= max_level ({self.max_level})"
            )
        if not 0.0 <= self.down_threshold < self.up_threshold <= 1.0:
            raise ValueError(f"curriculum thresholds {self.down_threshold}/{self.up_threshold} must satisfy 0 <= down < up <= 1")
        if self.window_episodes < 1 or self.step_up < 0 or self.step_down < 0:
            raise ValueError("curriculum window_episodes must be >= 1 and steps >= 0")


@dataclass(frozen=True)
class NavEnvConfig:
    num_envs: int = 64
    episode_duration_s: float = EPISODE_DURATION_S
    physics_substeps: int = 7  # per control period: 15 Hz x 7 = 105 Hz, like the SITL's 100 Hz
    # none: clean depth; train: each step a random subset of envs (corrupted_env_fraction) gets
    # fresh 1-30 px patches to 50%; episode: every env keeps one such mask for its whole episode
    # (Table II "corrupted"); projector-off: sim.degradation.ProjectorOffModel on every frame;
    # stereo / stereo-projector-off: depth matched from rendered IR images by the simulated D455
    # (sim.sensor, ``stereo`` with its projector on / off), in place of the rendered depth.
    corruption: str = "train"
    corrupted_env_fraction: float = 0.5
    corruption_scheme: PatchScheme = RL_TRAINING
    stereo: StereoConfig = D455  # the stereo modes' sensor (their mode sets its projector)
    # With any mode: this fraction of episodes see depth as a D455 without its projector instead.
    projector_off_episode_fraction: float = 0.0
    # With train: this fraction of the other episodes keep one mask of large squares
    # (sim.degradation.EPISODE_SQUARES: 50-100 px to 20-50 %) for the whole episode instead of the
    # per-step patches.
    squares_episode_fraction: float = 0.0
    # curriculum: every new episode at the curriculum's level; uniform: each at a level drawn
    # uniformly from [min_level, max_level] (distillation covers every level Table II tests).
    level_sampling: str = "curriculum"
    # Disturbances: with this probability per env and control step, a kick: a random force
    # (|F| <= kick_force_max_n) for one control period and an attitude impulse (a rotation of at
    # most kick_angle_max_rad), standing in for force and torque kicks.
    kick_probability: float = 0.05
    kick_force_max_n: float = 3.0
    kick_angle_max_rad: float = math.radians(10.0)
    camera_jitter: bool = True  # mount error per episode: U(-5, 5) cm, U(-3, 3) deg
    start_yaw_range_rad: float = math.pi / 3  # initial heading: goal bearing + U(-range, range)
    vehicle_radius_m: float = DEFAULT_VEHICLE_RADIUS_M
    # The teacher's privileged depth (DESIGN §5): clean depth of the same camera field of view,
    # ray cast at privileged_render_px and min-pooled by privileged_pool (the nearest surface in
    # each cell, so that a 0.1 m rod is not lost between rays), normalised like the contract's.
    privileged_render_px: tuple[int, int] = (64, 36)  # width, height (the D455's 16:9)
    privileged_pool: int = 2
    # The teacher's depth under the masks an episode keeps (the squares episodes, the ``episode``
    # mode's): "clean" (it sees through them), or "reconstructed": in the render pixels the mask
    # covers for at least half their area, the depth the encoder reconstructs from the student's
    # gray + masked depth (NavEnv's ``decoder`` on the student's latent), i.e. what the student can
    # know there through the paper's cross-modal encoder, so that its labels are ones it can follow.
    squares_privileged: str = "clean"
    world: WorldConfig = WorldConfig()
    # The vehicle's response; its command_delay_*_s (the autopilot's, e.g. PX4_SIH_V1_16's) hold
    # the commands back per axis at the physics rate, as sim.dynamics.CommandDelay does.
    dynamics: DynamicsParams = DynamicsParams(ground_contact=False)
    reward: RewardConfig = RewardConfig()
    curriculum: CurriculumConfig = CurriculumConfig()
    # The field (training.policy.field; all off by default).  action_limits: a field config's
    # caps on speed and inclination, applied by the runtime's mapping (None: the contract's).
    action_limits: ActionLimits | None = None
    gray_camera: GrayCameraConfig | None = None  # None: the renderer's clean gray
    # Image-to-command latency (s), drawn per episode uniformly in [low, high]: the command a frame
    # leads to starts this long after the frame was taken (and holds until the next one's).
    latency_range_s: tuple[float, float] = (0.0, 0.0)
    state_estimate: StateEstimateConfig | None = None  # None: the policy sees the true state
    # Per-episode vehicle parameters (and command delays) drawn around ``dynamics``.
    dynamics_randomization: DynamicsRandomization | None = None
    # End an episode in success at its first step within GOAL_REACHED_RADIUS_M of the goal (the
    # runtime's rule: `cmnav fly` hovers and holds there), paid the reward of hovering at the goal
    # itself for every step left (:meth:`NavEnv.goal_hover_reward`), so that arriving is never worth
    # less than staying.  Training only: Table II keeps the paper's rule and counts ``reached``.
    end_at_goal: bool = False

    @property
    def max_steps(self) -> int:
        return int(round(self.episode_duration_s / CONTROL_PERIOD_S))

    @property
    def privileged_depth_px(self) -> tuple[int, int]:
        """(width, height) of the teacher's depth after pooling."""
        width, height = self.privileged_render_px
        return width // self.privileged_pool, height // self.privileged_pool

    @property
    def privileged_obs_dim(self) -> int:
        width, height = self.privileged_depth_px
        return STATE_DIM + width * height

    def validate(self) -> None:
        if self.num_envs < 1:
            raise ValueError(f"num_envs={self.num_envs} must be >= 1")
        if self.corruption not in CORRUPTION_MODES:
            raise ValueError(f"corruption={self.corruption!r} must be one of {CORRUPTION_MODES}")
        for key in ("corrupted_env_fraction", "projector_off_episode_fraction", "squares_episode_fraction"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise ValueError(f"{key}={getattr(self, key)} must lie in [0, 1]")
        if self.squares_episode_fraction > 0.0 and self.corruption != "train":
            raise ValueError(f"squares_episode_fraction={self.squares_episode_fraction} needs corruption='train' "
                             f"(it replaces that mode's per-step patches), not {self.corruption!r}")  # fmt: skip
        if self.squares_privileged not in SQUARES_PRIVILEGED:
            raise ValueError(f"squares_privileged={self.squares_privileged!r} must be one of {SQUARES_PRIVILEGED}")
        if self.level_sampling not in LEVEL_SAMPLING:
            raise ValueError(f"level_sampling={self.level_sampling!r} must be one of {LEVEL_SAMPLING}")
        if self.physics_substeps < 1:
            raise ValueError(f"physics_substeps={self.physics_substeps} must be >= 1")
        width, height = self.privileged_render_px
        if self.privileged_pool < 1 or width % self.privileged_pool or height % self.privileged_pool or min(width, height) < 4:
            raise ValueError(f"privileged_render_px={self.privileged_render_px} must be >= 4 px and divisible by "
                             f"privileged_pool={self.privileged_pool}")  # fmt: skip
        low, high = self.latency_range_s
        if not 0.0 <= low <= high <= 1.0:
            raise ValueError(f"latency_range_s={self.latency_range_s} must satisfy 0 <= low <= high <= 1 s")
        if self.episode_duration_s <= 0.0:
            raise ValueError(f"episode_duration_s={self.episode_duration_s} must be > 0")
        self.dynamics.validate()
        for part in (self.gray_camera, self.state_estimate, self.dynamics_randomization):
            if part is not None:
                part.validate()
        self.curriculum.validate()
        self.world.validate()

    @property
    def physics_dt_s(self) -> float:
        return CONTROL_PERIOD_S / self.physics_substeps

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class StepOutput:
    """obs [N, D] (after any auto-reset: the new episode's first observation; D = 79, or the
    privileged size for a teacher env), reward [N], done [N] bool (the episode ended this step),
    outcome [N] int (RUNNING/SUCCESS/CRASH/TIMEOUT), level [N] (the level of the episode that
    ran this step), reward_terms: batch means; teacher_obs [N, P]: the privileged observation of
    the same states, where the env was asked for it (DAgger)."""

    obs: Tensor
    reward: Tensor
    done: Tensor
    outcome: Tensor
    level: Tensor
    reward_terms: dict[str, float] = field(default_factory=dict)
    teacher_obs: Tensor | None = None


def pad_world_slots(world: WorldBatch, num_slots: int) -> WorldBatch:
    """The same worlds with ``num_slots`` obstacle slots (extra slots are invalid padding)."""
    pad = num_slots - world.num_slots
    if pad < 0:
        raise ValueError(f"cannot shrink {world.num_slots} obstacle slots to {num_slots}")
    if pad == 0:
        return world

    def grow(t: Tensor) -> Tensor:
        return torch.cat([t, torch.zeros(t.shape[0], pad, *t.shape[2:], dtype=t.dtype, device=t.device)], dim=1)

    return replace(
        world,
        box_center_m=grow(world.box_center_m),
        box_half_extent_m=grow(world.box_half_extent_m),
        box_yaw_rad=grow(world.box_yaw_rad),
        box_valid=grow(world.box_valid),
    )


class Curriculum:
    """The level schedule of :class:`CurriculumConfig` over a window of finished episodes."""

    def __init__(self, config: CurriculumConfig) -> None:
        config.validate()
        self.config = config
        self.level = config.start_level
        self.changes = 0
        self._window: deque[bool] = deque()

    @property
    def progress(self) -> float:
        return self.level / max(self.config.max_level, 1)

    def record(self, successes: list[bool]) -> None:
        c = self.config
        for success in successes:
            self._window.append(success)
            if len(self._window) < c.window_episodes:
                continue
            rate = sum(self._window) / len(self._window)
            self._window.clear()
            new = self.level
            if rate > c.up_threshold:
                new = min(self.level + c.step_up, c.max_level)
            elif rate < c.down_threshold:
                new = max(self.level - c.step_down, c.min_level)
            if new != self.level:
                self.level = new
                self.changes += 1

    def state_dict(self) -> dict:
        return {"level": self.level, "changes": self.changes, "window": list(self._window)}

    def load_state_dict(self, state: dict) -> None:
        self.level, self.changes = int(state["level"]), int(state["changes"])
        self._window = deque(bool(x) for x in state["window"])


def parity_frames(encoder: nn.Module, device: torch.device | str, count: int = 64, level: int = 5,
                  seed: int = 0) -> tuple[Tensor, Tensor]:  # fmt: skip
    """(gray, depth) [count, 1, 224, 224] rendered at the start of ``count`` rooms at ``level``,
    half of them with the training corruption: the frames a fast encoder path is checked on."""
    config = NavEnvConfig(num_envs=count, curriculum=CurriculumConfig(start_level=level, min_level=level, max_level=level))
    env = NavEnv(config, encoder, device, seed=seed, fixed_level=level)
    env._reset_envs(torch.arange(count))
    return env.render_inputs()


def env_encoder(encoder: nn.Module, precision: str, device: torch.device | str, seed: int = 0) -> nn.Module:
    """The frozen encoder the envs run, on the CPU's fast path for ``precision``
    (training.fastpath), bf16 checked for parity on rendered frames first."""
    return frozen_encoder(encoder, precision, device, lambda: parity_frames(encoder, device, seed=seed))


class NavEnv:
    """N navigation envs (see the module doc).  ``encoder`` maps (gray, depth) [N, 1, 224, 224]
    to the latent [N, 64] and is frozen here; without one the env is the teacher's: its
    observation is the 15 state values then the privileged low-resolution clean depth, and no
    224 image is rendered.  ``teacher_obs``: also give the privileged observation of every state
    (``StepOutput.teacher_obs``, :meth:`teacher_observation`) for DAgger.  ``fixed_level``:
    every episode at this level and no curriculum (evaluation).  ``decoder``: the encoder's depth
    decoder, for ``squares_privileged="reconstructed"``.  Episode seeds derive from
    ``seed``, the env index and the episode count, so the same seed gives the same rooms
    whatever policy flies them."""

    def __init__(
        self,
        config: NavEnvConfig,
        encoder: nn.Module | None,
        device: torch.device | str = "cpu",
        seed: int = 0,
        fixed_level: int | None = None,
        auto_reset: bool = True,
        teacher_obs: bool = False,
        decoder: nn.Module | None = None,
    ) -> None:
        config.validate()
        if config.squares_privileged == "reconstructed" and (encoder is None or decoder is None):
            raise ValueError("squares_privileged='reconstructed' gives the teacher the encoder's reconstruction under the "
                             "squares: the env needs the encoder and its decoder")  # fmt: skip
        self.config = config
        self.device = torch.device(device)
        self.encoder = None if encoder is None else encoder.to(self.device).eval().requires_grad_(False)
        self.decoder = None if decoder is None else decoder.to(self.device).eval().requires_grad_(False)
        self.with_teacher_obs = teacher_obs
        width, height = config.privileged_render_px
        self.privileged_camera = CameraModel(width_px=width, height_px=height)
        self.num_envs = config.num_envs
        self.seed = seed
        self.fixed_level = fixed_level
        self.auto_reset = auto_reset
        self.curriculum = Curriculum(config.curriculum)
        self.camera = CameraModel()
        self.dynamics = QuadrotorDynamics(config.dynamics)
        self.projector_off = ProjectorOffModel()
        self.stereo_sensor = None
        if config.corruption in STEREO_MODES:
            self.stereo_sensor = StereoDepthSensor(replace(config.stereo, projector_on=STEREO_MODES[config.corruption]))
        self.stereo_approx = None
        if config.corruption in APPROX_STEREO_MODES:
            self.stereo_approx = StereoApproxConfig(projector_on=APPROX_STEREO_MODES[config.corruption])
        self.generator = torch.Generator().manual_seed(seed)
        self.stage_seconds = {"render": 0.0, "stereo": 0.0, "gray": 0.0, "preprocess": 0.0, "encode": 0.0, "physics": 0.0,
                              "privileged": 0.0}  # fmt: skip
        n = self.num_envs
        self._init_field(config)
        self._slots = max(1, config.curriculum.max_level if fixed_level is None else fixed_level)
        self.episode_index = torch.zeros(n, dtype=torch.long)
        self.world: WorldBatch | None = None
        self.state: QuadState | None = None
        self.jitter: MountJitter | None = None
        self.step_count = torch.zeros(n, dtype=torch.long, device=self.device)
        self.prev_action = torch.zeros(n, 3, device=self.device)
        self.prev_dist_m = torch.zeros(n, device=self.device)
        self.episode_level = torch.zeros(n, dtype=torch.long, device=self.device)
        self.episode_masks = torch.zeros(n, IMAGE_SIZE_PX, IMAGE_SIZE_PX, dtype=torch.bool)
        self.projector_off_episode = torch.zeros(n, dtype=torch.bool)
        self.squares_episode = torch.zeros(n, dtype=torch.bool)  # holds its episode_masks (squares_episode_fraction)
        self.active = torch.ones(n, dtype=torch.bool, device=self.device)
        self.last_render: RenderOutput | None = None
        self.last_latent: Tensor | None = None  # [N, 64] the student's latent of the current observation
        self.last_gray: GrayFrame | None = None

    def _init_field(self, config: NavEnvConfig) -> None:
        """The field's parts (NavEnvConfig's field options): each exists only when configured, so
        an env without them draws nothing more from its generator than before they existed."""
        n, dt_s, dev = self.num_envs, config.physics_dt_s, self.device
        self.gray_camera = None if config.gray_camera is None else GrayCamera(config.gray_camera, self.camera)
        self.brightness = torch.ones(n)
        self.estimator = None
        if config.state_estimate is not None:
            self.estimator = StateEstimator(config.state_estimate, n, dt_s, dev)
        # Image-to-command latency: the policy's body-frame command, per env.
        self.latency_s = torch.zeros(n)
        self.latency_steps = torch.zeros(n, dtype=torch.long)
        self._latency_line = None
        if config.latency_range_s[1] > 0.0:
            self._latency_line = DelayLine(DelayLine.capacity_for(config.latency_range_s[1], dt_s), n, 4, dev)
        # The vehicle: per-env parameters and the autopilot's command delays (xy, xy, z, yaw).
        randomization = config.dynamics_randomization
        self.dynamics_per_env: dict[str, Tensor] = {}
        nominal_delays_s = torch.tensor([getattr(config.dynamics, k) for k in COMMAND_DELAY_PARAMS])
        most_s = float(nominal_delays_s.max()) * (1.0 + (randomization.delay_fraction if randomization else 0.0))
        self.command_delay_s = nominal_delays_s.repeat(n, 1)  # [N, 3] xy, z, yaw
        self.command_delay_steps = delay_steps(self.command_delay_s, dt_s)[:, [0, 0, 1, 2]]
        self._command_line = None
        if most_s > 0.0:
            self._command_line = DelayLine(DelayLine.capacity_for(most_s, dt_s), n, 4, dev)

    # ---- episodes -------------------------------------------------------------------------
    @property
    def level(self) -> int:
        return self.curriculum.level if self.fixed_level is None else self.fixed_level

    def _episode_seed(self, env: int) -> int:
        return env_seed(self.seed, env * 1_000_003 + int(self.episode_index[env]))

    def reset(self) -> Tensor:
        """Start a new episode in every env; returns the first observations [N, 79]."""
        self._reset_envs(torch.arange(self.num_envs))
        self.active.fill_(True)
        return self._observe()

    def _reset_envs(self, envs: Tensor) -> None:
        cfg = self.config
        envs = envs.cpu()
        if cfg.level_sampling == "uniform" and self.fixed_level is None:
            c = cfg.curriculum
            levels = torch.randint(c.min_level, c.max_level + 1, (len(envs),), generator=self.generator).tolist()
        else:
            levels = [self.level] * len(envs)
        worlds = [
            pad_world_slots(make_worlds([level], seed=self._episode_seed(int(i)), config=cfg.world), self._slots)
            for i, level in zip(envs, levels)
        ]
        fresh = WorldBatch(**{f.name: torch.cat([getattr(w, f.name) for w in worlds]) for f in fields(WorldBatch)})
        fresh = fresh.to(self.device)
        self.episode_index[envs] += 1
        dev_envs = envs.to(self.device)
        to_goal = fresh.goal_m - fresh.start_m
        bearing = torch.atan2(to_goal[:, 1], to_goal[:, 0])
        u = torch.rand(len(envs), generator=self.generator).to(self.device) * 2.0 - 1.0
        fresh_state = QuadState.at_rest(fresh.start_m, bearing + u * cfg.start_yaw_range_rad)
        if cfg.camera_jitter:
            fresh_jitter = sample_mount_jitter(len(envs), self.generator, device=self.device)
        else:
            fresh_jitter = MountJitter(torch.zeros(len(envs), 3, device=self.device),
                                       torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=self.device).repeat(len(envs), 1))  # fmt: skip
        if self.world is None:
            self.world, self.state, self.jitter = fresh, fresh_state, fresh_jitter
        else:
            for f in fields(WorldBatch):
                getattr(self.world, f.name)[dev_envs] = getattr(fresh, f.name)
            for f in fields(QuadState):
                current, value = getattr(self.state, f.name), getattr(fresh_state, f.name)
                if current is None:
                    continue
                # A new episode's controller integral (None at rest) starts at zero.
                current[dev_envs] = 0.0 if value is None else value
            self.jitter.offset_body_flu_m[dev_envs] = fresh_jitter.offset_body_flu_m
            self.jitter.quat_body_cam[dev_envs] = fresh_jitter.quat_body_cam
        self.step_count[dev_envs] = 0
        self.prev_action[dev_envs] = 0.0
        self.prev_dist_m[dev_envs] = torch.linalg.vector_norm(fresh.goal_m - fresh.start_m, dim=-1)
        self.episode_level[dev_envs] = torch.tensor(levels, device=self.device)
        if cfg.projector_off_episode_fraction > 0.0:
            self.projector_off_episode[envs] = torch.rand(len(envs), generator=self.generator) < cfg.projector_off_episode_fraction
        if cfg.corruption == "episode":
            coverage = cfg.corruption_scheme.sample_coverage(len(envs), self.generator)
            self.episode_masks[envs] = patch_masks(coverage, cfg.corruption_scheme, self.generator)
        if cfg.squares_episode_fraction > 0.0:
            squares = (torch.rand(len(envs), generator=self.generator) < cfg.squares_episode_fraction) & ~self.projector_off_episode[envs]
            self.squares_episode[envs] = squares
            if bool(squares.any()):
                coverage = EPISODE_SQUARES.sample_coverage(int(squares.sum()), self.generator)
                self.episode_masks[envs[squares]] = patch_masks(coverage, EPISODE_SQUARES, self.generator)
        self._reset_field(envs, fresh_state)

    def _reset_field(self, envs: Tensor, fresh_state: QuadState) -> None:
        """Draw the new episodes' field parameters (only those configured) and clear their delay
        lines: before its first command an env hovers (the runtime's hover setpoint before
        offboard starts), and its estimate starts at the true start state."""
        cfg, k, dev_envs = self.config, len(envs), envs.to(self.device)
        if cfg.dynamics_randomization is not None:
            drawn = sample_dynamics(cfg.dynamics, cfg.dynamics_randomization, k, self.generator)
            for name in PER_ENV_PARAMS:
                self.dynamics_per_env.setdefault(name, torch.zeros(self.num_envs, device=self.device))[dev_envs] = drawn[name].to(self.device)
            self.command_delay_s[envs] = torch.stack([drawn[name] for name in COMMAND_DELAY_PARAMS], dim=-1)
            self.command_delay_steps[envs] = delay_steps(self.command_delay_s[envs], cfg.physics_dt_s)[:, [0, 0, 1, 2]]
        if self._latency_line is not None:
            low, high = cfg.latency_range_s
            self.latency_s[envs] = low + (high - low) * torch.rand(k, generator=self.generator)
            self.latency_steps[envs] = delay_steps(self.latency_s[envs], cfg.physics_dt_s)
        hover = torch.zeros(k, 4, device=self.device)
        for line in (self._latency_line, self._command_line):
            if line is not None:
                line.fill(dev_envs, hover)
        if self.estimator is not None:
            self.estimator.reset(envs, fresh_state, self.generator)
        if self.gray_camera is not None:
            self.brightness[envs] = sample_brightness(cfg.gray_camera, k, self.generator)

    # ---- observation ------------------------------------------------------------------------
    def _timed(self, stage: str, t0: float) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        now = time.perf_counter()
        self.stage_seconds[stage] += now - t0
        return now

    def render_inputs(self) -> tuple[Tensor, Tensor]:
        """The encoder's inputs for the current poses: (gray, depth) [N, 1, 224, 224] in the
        contract's normalisation, depth corrupted per ``config.corruption``."""
        cfg = self.config
        t0 = time.perf_counter()
        cam_pos, cam_quat = camera_pose(self.state.pos_enu_m, self.state.quat_enu_flu, self.camera, self.jitter)
        out = render(self.world, cam_pos, cam_quat, self.camera)
        self.last_render = out  # the clean frames of the current observation (camera resolution, before any corruption)
        t0 = self._timed("render", t0)
        depth_m = out.depth_m
        if self.stereo_sensor is not None:
            # The D455's own depth at its matching resolution (the gray camera's rays, twice the
            # pixels): the contract's preprocessing resizes it to 224 x 224 like any camera's.
            # Ended episodes (Table II's, which do not reset) are not matched: their frames are
            # never flown on; they keep the rendered depth, resized to the matching grid.
            live = self.live_envs()
            if len(live) == self.num_envs:
                depth_m = self.stereo_sensor.measure(self.world, cam_pos, cam_quat, self.generator).depth_m
            else:
                grid = (self.stereo_sensor.camera.height_px, self.stereo_sensor.camera.width_px)
                depth_m = F.interpolate(out.depth_m.unsqueeze(1), size=grid, mode="nearest").squeeze(1)
                if len(live):
                    live_dev = live.to(self.device)
                    depth_m[live_dev] = self.stereo_sensor.measure(self.world.select(live_dev), cam_pos[live_dev],
                                                                   cam_quat[live_dev], self.generator).depth_m  # fmt: skip
            t0 = self._timed("stereo", t0)
        elif self.stereo_approx is not None:  # on the camera's own grid
            depth_m = approx_stereo_depth(depth_m, out.gray_u8, self.camera.fx_px, self.stereo_approx, self.generator)
            t0 = self._timed("stereo", t0)
        elif cfg.corruption == "projector-off":
            depth_m, _ = self.projector_off.apply(depth_m, out.gray_u8, self.camera.fx_px, self.generator)
        elif bool(self.projector_off_episode.any()):
            off = self.projector_off_episode.nonzero().squeeze(1).to(self.device)
            depth_m = depth_m.clone()
            depth_m[off], _ = self.projector_off.apply(depth_m[off], out.gray_u8[off], self.camera.fx_px, self.generator)
        gray_u8 = out.gray_u8
        if self.gray_camera is not None:
            vel_cam, angvel_cam = self._camera_motion(cam_quat)
            self.last_gray = self.gray_camera.capture(out.gray_u8, out.depth_m, self.brightness, vel_cam, angvel_cam, self.generator)
            gray_u8 = self.last_gray.gray_u8
            t0 = self._timed("gray", t0)
        gray = preprocess_gray_batch(gray_u8)
        depth = preprocess_depth_batch(depth_m)
        if cfg.corruption == "train":
            chosen = ((torch.rand(self.num_envs, generator=self.generator) < cfg.corrupted_env_fraction)
                      & ~self.projector_off_episode & ~self.squares_episode).nonzero().squeeze(1)  # fmt: skip
            if len(chosen):
                coverage = cfg.corruption_scheme.sample_coverage(len(chosen), self.generator)
                masks = patch_masks(coverage, cfg.corruption_scheme, self.generator)
                depth[chosen.to(self.device)] = corrupt_depth(depth[chosen.to(self.device)], masks)
            squares = self.squares_episode.nonzero().squeeze(1)
            if len(squares):
                depth[squares.to(self.device)] = corrupt_depth(depth[squares.to(self.device)], self.episode_masks[squares])
        elif cfg.corruption == "episode":
            depth = corrupt_depth(depth, self.episode_masks)
        self._timed("preprocess", t0)
        return gray.unsqueeze(1), depth.unsqueeze(1)

    def _camera_motion(self, cam_quat_enu_cam: Tensor) -> tuple[Tensor, Tensor]:
        """([N, 3] linear velocity m/s, [N, 3] angular velocity rad/s) of the camera in its frame C
        now (the true motion: it is what blurs the image)."""
        s = self.state
        angvel_enu = quat_rotate(s.quat_enu_flu, s.angvel_body_flu_rad_s)
        return quat_rotate_inverse(cam_quat_enu_cam, s.vel_enu_m_s), quat_rotate_inverse(cam_quat_enu_cam, angvel_enu)

    def privileged_depth(self) -> Tensor:
        """[N, W*H] the teacher's clean depth at the current camera poses (see NavEnvConfig),
        normalised by DEPTH_MAX_M to [0, 1] (nothing is invalid: the room is closed)."""
        t0 = time.perf_counter()
        cam_pos, cam_quat = camera_pose(self.state.pos_enu_m, self.state.quat_enu_flu, self.privileged_camera, self.jitter)
        depth_m = render(self.world, cam_pos, cam_quat, self.privileged_camera).depth_m
        depth = torch.nan_to_num(depth_m, nan=DEPTH_MAX_M, posinf=DEPTH_MAX_M)
        depth = torch.where(depth <= 0.0, torch.full_like(depth, DEPTH_MAX_M), depth)
        if self.config.squares_privileged == "reconstructed":
            depth = self._reconstruct_masked(depth)
        pool = self.config.privileged_pool
        nearest = -F.max_pool2d(-depth.unsqueeze(1), pool).flatten(1)
        self._timed("privileged", t0)
        return (nearest * (1.0 / DEPTH_MAX_M)).clamp(0.0, 1.0)

    def _reconstruct_masked(self, depth_m: Tensor) -> Tensor:
        """``depth_m`` [N, H, W] (the privileged render) with the pixels under the episode-long masks
        replaced by the decoder's reconstruction from the student's current latent."""
        holding = torch.ones_like(self.squares_episode) if self.config.corruption == "episode" else self.squares_episode
        envs = holding.nonzero().squeeze(1)
        if not len(envs):
            return depth_m
        size = tuple(depth_m.shape[-2:])
        masked = F.interpolate(self.episode_masks[envs].unsqueeze(1).float(), size=size, mode="area").squeeze(1) >= 0.5
        with torch.inference_mode():
            recon = self.decoder(self.last_latent[envs.to(self.device)])
        recon_m = F.interpolate(recon.float(), size=size, mode="area").squeeze(1) * DEPTH_MAX_M
        depth_m = depth_m.clone()
        dev_envs = envs.to(self.device)
        depth_m[dev_envs] = torch.where(masked.to(self.device), recon_m, depth_m[dev_envs])
        return depth_m

    def _state_observation(self, estimated: bool = False) -> Tensor:
        """[N, 15] the contract's state values of the true state, or (``estimated``, with a state
        estimate configured) of the autopilot's estimate of it, as the runtime receives it."""
        s = self.state if not estimated or self.estimator is None else self.estimator.estimate(self.generator)
        return observation_state_batch(
            s.pos_enu_m, self.world.goal_m, s.quat_enu_flu, s.vel_enu_m_s, s.angvel_body_flu_rad_s, self.prev_action
        )

    def teacher_observation(self) -> Tensor:
        """[N, 15 + W*H] the privileged observation of the current states."""
        return torch.cat([self._state_observation(), self.privileged_depth()], dim=-1)

    def live_envs(self) -> Tensor:
        """[K] int64 (CPU) the envs whose episode runs: all of them but Table II's ended ones
        (``auto_reset=False``), whose observations are no longer flown on."""
        return self.active.cpu().nonzero().squeeze(1)

    def _observe(self) -> Tensor:
        if self.encoder is None:
            return self.teacher_observation()
        gray, depth = self.render_inputs()
        t0 = time.perf_counter()
        live = self.live_envs().to(self.device)
        with torch.inference_mode():
            if len(live) == self.num_envs:  # training's envs always: no copy of the batch
                latent = self.encoder(gray, depth).float()
            else:  # ended episodes' latents are zero: never flown on
                latent = torch.zeros(self.num_envs, LATENT_DIM, device=self.device)
                if len(live):
                    latent[live] = self.encoder(gray[live], depth[live]).float()
        self._timed("encode", t0)
        assert latent.shape == (self.num_envs, LATENT_DIM)
        self.last_latent = latent
        obs = torch.cat([self._state_observation(estimated=True), latent.clone()], dim=-1)
        assert obs.shape[-1] == OBSERVATION_DIM
        return obs

    # ---- step -------------------------------------------------------------------------------
    def step(self, action: Tensor) -> StepOutput:
        """Apply raw policy actions [N, 3] for one control period."""
        cfg = self.config
        t0 = time.perf_counter()
        action = action.detach().to(self.device).float().clamp(-1.0, 1.0)
        cmd_flu = action_to_velocity_flu_batch(action, cfg.action_limits)
        kick_force, kick_rotation = self._sample_kicks()
        crashed = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        dt_s = CONTROL_PERIOD_S / cfg.physics_substeps
        state = self.state
        if kick_rotation is not None:
            state = replace(state, quat_enu_flu=quat_multiply(state.quat_enu_flu, kick_rotation))
        for _ in range(cfg.physics_substeps):
            arriving_flu = cmd_flu
            if self._latency_line is not None:  # the command of an older frame may still be the newest sent
                self._latency_line.push(cmd_flu)
                arriving_flu = self._latency_line.read(self.latency_steps)
            # PX4 resolves a body velocity setpoint by the current heading (yaw only).
            vel_cmd_enu, yaw_rate_cmd = rotate_about_z(arriving_flu[:, :3], state.yaw_enu_rad()), arriving_flu[:, 3]
            if self._command_line is not None:  # the autopilot's own delay, per axis
                self._command_line.push(torch.cat([vel_cmd_enu, yaw_rate_cmd.unsqueeze(-1)], dim=-1))
                acting = self._command_line.read(self.command_delay_steps)
                vel_cmd_enu, yaw_rate_cmd = acting[:, :3], acting[:, 3]
            if self.estimator is not None:  # the autopilot holds its estimate, not the truth, at the setpoint
                vel_cmd_enu = vel_cmd_enu - self.estimator.velocity_error_m_s()
            new = self.dynamics.step(state, vel_cmd_enu, yaw_rate_cmd, dt_s, kick_force, self.dynamics_per_env)
            # Crashed (and ended) envs stay where they are.
            frozen = (crashed | ~self.active).unsqueeze(-1)
            state = QuadState(*(_keep_frozen(frozen, getattr(state, f.name), getattr(new, f.name)) for f in fields(QuadState)))
            crashed |= collides(self.world, state.pos_enu_m, cfg.vehicle_radius_m) & self.active
            if self.estimator is not None:
                self.estimator.record(state, self.generator)
        self.state = state
        self.step_count += self.active.long()
        t0 = self._timed("physics", t0)

        dist_m = torch.linalg.vector_norm(self.world.goal_m - state.pos_enu_m, dim=-1)
        # As in Aerial Gym, whose reward this is: reaching the goal does not end the episode (the
        # reward pays for staying there); at 10 s it ends in success within 1 m, else timeout.
        ended = (self.step_count >= cfg.max_steps) & ~crashed & self.active
        within = dist_m < GOAL_REACHED_RADIUS_M
        success = (within & ~crashed & self.active) if cfg.end_at_goal else (ended & within)
        timeout = ended & ~success
        outcome = torch.full((self.num_envs,), RUNNING, dtype=torch.long, device=self.device)
        outcome[success] = SUCCESS
        outcome[crashed] = CRASH
        outcome[timeout] = TIMEOUT
        reward, terms = self._reward(action, dist_m, crashed)
        if cfg.end_at_goal:
            steps_left = (cfg.max_steps - self.step_count).clamp_min(0).float()
            arrival = torch.where(success, steps_left * self.goal_hover_reward(), torch.zeros_like(reward))
            reward = reward + arrival
            terms["arrival"] = float(arrival.mean())
        reward = torch.where(self.active, reward, torch.zeros_like(reward))
        done = (outcome != RUNNING) & self.active
        level = self.episode_level.clone()
        self.prev_action = action
        self.prev_dist_m = dist_m

        if self.fixed_level is None and bool(done.any()):
            self.curriculum.record((outcome[done] == SUCCESS).tolist())
        if bool(done.any()):
            if self.auto_reset:
                self._reset_envs(done.nonzero().squeeze(1))
            else:
                self.active &= ~done
        obs = self._observe()
        teacher_obs = self.teacher_observation() if self.with_teacher_obs else None
        return StepOutput(obs, reward, done, outcome, level, terms, teacher_obs)

    def _sample_kicks(self) -> tuple[Tensor | None, Tensor | None]:
        cfg = self.config
        if cfg.kick_probability <= 0.0:
            return None, None
        n = self.num_envs
        kicked = (torch.rand(n, generator=self.generator) < cfg.kick_probability).float().unsqueeze(-1)
        if not bool(kicked.any()):
            return None, None
        direction = torch.randn(n, 3, generator=self.generator)
        direction = direction / torch.linalg.vector_norm(direction, dim=-1, keepdim=True).clamp_min(1e-9)
        force = direction * torch.rand(n, 1, generator=self.generator) * cfg.kick_force_max_n * kicked
        angles = (torch.rand(n, 3, generator=self.generator) * 2.0 - 1.0) * cfg.kick_angle_max_rad * kicked
        rotation = quat_from_euler(angles[:, 0], angles[:, 1], angles[:, 2])
        return force.to(self.device), rotation.to(self.device)

    def goal_hover_reward(self) -> float:
        """One step's reward for hovering on the goal itself (distance 0, still, zero action): the
        most a step within the goal radius can earn, at the curriculum's current scale."""
        r = self.config.reward
        return (r.goal_attraction + r.goal_close + 1.0) * self._positive_scale()  # the distance term is 1 at the goal

    def _positive_scale(self) -> float:
        r = self.config.reward
        return 1.0 + r.positive_scale_per_progress * self.curriculum.progress

    def _reward(self, action: Tensor, dist_m: Tensor, crashed: Tensor) -> tuple[Tensor, dict[str, float]]:
        r = self.config.reward
        dev = self.device
        attraction = r.goal_attraction * torch.exp(-dist_m.square() * r.goal_attraction_exp)
        close = r.goal_close * torch.exp(-dist_m.square() * r.goal_close_exp)
        delta_m = self.prev_dist_m - dist_m
        progress = torch.where(delta_m > 0, r.progress_gain * delta_m, r.progress_away_gain * delta_m)
        distance = (r.distance_term_range_m - dist_m) / r.distance_term_range_m
        change = action - self.prev_action
        change_pen = (torch.tensor(r.action_change_penalty, device=dev)
                      * (torch.exp(-change.square() * torch.tensor(r.action_change_exp, device=dev)) - 1.0)).sum(-1)  # fmt: skip
        action_pen = (torch.tensor(r.action_penalty, device=dev)
                      * (torch.exp(-action.square() * torch.tensor(r.action_exp, device=dev)) - 1.0)).sum(-1)  # fmt: skip
        positive = (attraction + close + progress.clamp_min(0.0) + distance.clamp_min(0.0)) * self._positive_scale()
        negative = progress.clamp_max(0.0) + distance.clamp_max(0.0) + change_pen + action_pen
        reward = torch.where(crashed, torch.full_like(dist_m, -r.crash_penalty), positive + negative)
        terms = {
            "attraction": float(attraction.mean()),
            "close": float(close.mean()),
            "progress": float(progress.mean()),
            "distance": float(distance.mean()),
            "action_change_penalty": float(change_pen.mean()),
            "action_penalty": float(action_pen.mean()),
            "crash": float(crashed.float().mean() * -r.crash_penalty),
        }
        return reward, terms

    def trajectory_point(self) -> Tensor:
        """[N, 3] current positions (world ENU, m), for plots."""
        return self.state.pos_enu_m.detach().cpu().clone()


def _keep_frozen(frozen: Tensor, old: Tensor | None, new: Tensor | None) -> Tensor | None:
    """``new`` where the env moves on, ``old`` where it is frozen (a state field that is None,
    e.g. an integral the controller does not keep, stays None)."""
    if new is None:
        return None
    return torch.where(frozen, new if old is None else old, new)
