"""``cmnav replay LOG.mcap``: feed a flight log back through the policy and compare actions.

Each recorded policy step is recomputed with :func:`runtime.policy_step.compute_step` (the flight
loop's own step code) from the recorded camera frame and the recorded telemetry and goal, with the
replay's own GRU state and previous action carried from step to step and reset wherever the
flight reset them (a new ``hidden_epoch``).  With the model that flew, the actions match the
recorded ones to float32 round-off (a determinism check); with another model the differences show
how it would have acted on the same inputs (open loop: the vehicle's motion stays as recorded).

Per step the difference is ``max_i |a_replay_i - a_recorded_i|`` over the 3 raw action values (NaN
on both sides counts as equal, NaN on one side as infinite); the report gives its maximum and mean
over the steps, and the per-step values.  A log cut short by a killed process replays up to its
last complete chunk.
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..camera.frame import Frame
from ..contract import ContractMismatchError, ImageContractError
from ..log.reader import FlightLogReader, LoggedFrame, LoggedStep, ReplayError
from ..log.topics import FRAME_TOPICS, STEP_TOPICS
from ..model import ModelLoadError, PolicyModel, check_outputs_finite, file_sha256
from ..policy_step import PolicyMemory, StepInputs, compute_step

log = logging.getLogger(__name__)

# Frames kept while waiting for the step that used them; the recorder writes a step a frame or
# two after its frame, so this is ample.
FRAME_WINDOW = 32

__all__ = ["ReplayError", "ReplayReport", "replay_log"]


@dataclass
class ReplayReport:
    """What a replay found.  Differences are of the raw action (dimensionless, in action units)."""

    log: str
    model: str
    model_sha256: str
    recorded_model: str | None
    recorded_model_sha256: str | None
    steps: int = 0  # steps recomputed and compared
    steps_without_frame: int = 0  # recorded steps whose frame the log lacks (dropped by the recorder)
    episodes: int = 0  # distinct GRU epochs (offboard entries / goals) among the steps
    max_abs_diff: float | None = None  # max over steps of the per-step difference
    mean_abs_diff: float | None = None  # mean over steps of the per-step difference
    max_latent_abs_diff: float | None = None
    stopped_early: str | None = None  # the log was cut or damaged there; steps before it were replayed
    frame_seq: list[int] = field(default_factory=list)
    per_step_max_abs_diff: list[float] = field(default_factory=list)

    @property
    def same_model(self) -> bool:
        return self.recorded_model_sha256 == self.model_sha256

    def to_json(self) -> dict:
        """JSON-ready (infinite differences become null, as in the flight log)."""
        out = asdict(self)
        out["same_model"] = self.same_model
        out["per_step_max_abs_diff"] = [d if math.isfinite(d) else None for d in self.per_step_max_abs_diff]
        for key in ("max_abs_diff", "mean_abs_diff", "max_latent_abs_diff"):
            if out[key] is not None and not math.isfinite(out[key]):
                out[key] = None
        return out

    def format(self) -> str:
        which = "the model that flew" if self.same_model else "a different model than the one that flew"
        lines = [
            f"replayed {self.steps} policy steps ({self.episodes} episode(s)) of {self.log}",
            f"model {self.model} ({which}; sha256 {self.model_sha256[:12]})",
        ]
        if self.steps:
            lines.append(
                f"raw action difference per step (max over the 3 values): max {self.max_abs_diff:.3g}, "
                f"mean {self.mean_abs_diff:.3g}; latent max {self.max_latent_abs_diff:.3g}"
            )
        if self.steps_without_frame:
            lines.append(f"{self.steps_without_frame} recorded step(s) had no frame in the log and were skipped")
        if self.stopped_early:
            lines.append(f"the log {self.stopped_early}: replayed up to there")
        return "\n".join(lines)


def replay_log(
    log_path: str | Path, model_path: str | Path | None = None, providers: tuple[str, ...] = ("CPUExecutionProvider",)
) -> ReplayReport:
    """Replay ``log_path`` through ``model_path`` (default: the model recorded in the log).

    Raises :class:`ReplayError` if the log is not a readable cmnav flight log or the model cannot
    be loaded.
    """
    reader = FlightLogReader(log_path)
    steps = reader.records(FRAME_TOPICS + STEP_TOPICS)
    frames: OrderedDict[int, LoggedFrame] = OrderedDict()
    model: PolicyModel | None = None
    memory: PolicyMemory | None = None
    report: ReplayReport | None = None
    epoch: int | None = None
    action_diffs: list[float] = []
    latent_diffs: list[float] = []
    for item in steps:
        if isinstance(item, LoggedFrame):
            frames[item.t_capture_ns] = item
            while len(frames) > FRAME_WINDOW:
                frames.popitem(last=False)
            continue
        if model is None:  # loaded at the first step, so a log that cannot be replayed fails first
            model = _load_model(reader, model_path, providers)
            memory = PolicyMemory(model)
            report = ReplayReport(
                log=str(reader.path), model=str(model.path), model_sha256=model.sha256,
                recorded_model=reader.metadata.get("model"), recorded_model_sha256=reader.metadata.get("model_sha256"),
            )  # fmt: skip
        assert memory is not None and report is not None
        frame = frames.get(item.t_capture_ns)
        if frame is None:
            report.steps_without_frame += 1
            continue
        if item.hidden_epoch != epoch:
            memory.reset()  # the flight reset its GRU state here (offboard entered, new goal)
            epoch = item.hidden_epoch
            report.episodes += 1
        try:
            result = compute_step(model, _frame(frame, item), _inputs(item, memory))
        except ImageContractError as err:
            raise ReplayError(f"{reader.path}: the frame of step {item.frame_seq} cannot be preprocessed ({err}): the log is damaged") from err
        memory.advance(result)
        action_diffs.append(_max_abs_diff(result.output.action, item.action_raw))
        latent_diffs.append(_max_abs_diff(result.output.latent, item.observation[15:]))
        report.frame_seq.append(item.frame_seq)
    reader.check_topics(FRAME_TOPICS + STEP_TOPICS, "replay needs the camera frames and the policy steps")
    if report is None:  # the channels exist but no step came through whole
        raise ReplayError(f"{reader.path} holds no complete policy step to replay" + (
            f"; it {reader.stopped_early}" if reader.stopped_early else ""))  # fmt: skip
    report.stopped_early = reader.stopped_early
    report.steps = len(action_diffs)
    report.per_step_max_abs_diff = action_diffs
    if action_diffs:
        report.max_abs_diff = float(np.max(action_diffs))
        report.mean_abs_diff = float(np.mean(action_diffs))
        report.max_latent_abs_diff = float(np.max(latent_diffs))
    log.info("replayed %d steps of %s: action max |diff| %s", report.steps, reader.path, report.max_abs_diff)
    return report


def _load_model(reader: FlightLogReader, model_path: str | Path | None, providers: tuple[str, ...]) -> PolicyModel:
    recorded = reader.metadata.get("model")
    if model_path is None:
        if not recorded:
            raise ReplayError(f"{reader.path} does not record which model flew: pass --model PATH")
        model_path = recorded
        if not Path(model_path).is_file():
            raise ReplayError(f"the model recorded in {reader.path} ({model_path}) is not there: pass --model PATH")
        recorded_sha = reader.metadata.get("model_sha256")
        if recorded_sha and file_sha256(model_path) != recorded_sha:
            log.warning("%s changed since the flight (sha256 differs from the log's); differences are expected", model_path)
    try:
        model = PolicyModel(model_path, providers)
        check_outputs_finite(model)
        return model
    except (ModelLoadError, ContractMismatchError) as err:
        raise ReplayError(f"cannot replay {reader.path} with {model_path}: {err}") from err


def _frame(frame: LoggedFrame, step: LoggedStep) -> Frame:
    return Frame(t_capture_ns=frame.t_capture_ns, depth_m=frame.depth_m, gray_u8=frame.gray_u8, seq=step.frame_seq)


def _inputs(step: LoggedStep, memory: PolicyMemory) -> StepInputs:
    return StepInputs(
        pos_enu_m=step.pos_enu_m, quat_enu_flu=step.quat_enu_flu, vel_body_flu_m_s=step.vel_body_flu_m_s,
        angvel_body_flu_rad_s=step.angvel_body_flu_rad_s, goal_enu_m=step.goal_enu_m, hidden=memory.hidden,
        prev_action=memory.prev_action, hidden_epoch=step.hidden_epoch,
    )  # fmt: skip


def _max_abs_diff(replayed: np.ndarray, recorded: np.ndarray) -> float:
    """max |replayed - recorded|; NaN on both sides is equal, NaN on one side is an infinite difference."""
    a = np.asarray(replayed, dtype=np.float64)
    b = np.asarray(recorded, dtype=np.float64)
    diff = np.abs(a - b)
    diff[np.isnan(a) & np.isnan(b)] = 0.0
    diff[np.isnan(diff)] = np.inf
    return float(diff.max()) if diff.size else 0.0
