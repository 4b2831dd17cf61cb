"""One control step's computation, shared by the flight loop and ``cmnav replay``.

A step turns a camera frame and the vehicle telemetry into the policy's action: the contract's
preprocessing (``runtime.contract.images``), the 15-value state (``observation_state``), one ONNX
step with the GRU hidden state, and the clip to [-1, 1].  :func:`compute_step` is pure (it reads
its inputs and touches nothing else) so the flight loop can run it in a worker thread with a
deadline and replay can run it on recorded inputs; :class:`PolicyMemory` holds what carries from
one step to the next (GRU state, previous action) and counts its resets, so a replay knows where
the flight reset it (offboard entered, new goal).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .camera.frame import Frame
from .contract import clip_action, observation_state, preprocess_depth, preprocess_gray
from .contract.constants import ACTION_DIM
from .model import ModelOutput, PolicyModel
from .state import VehicleState


@dataclass(frozen=True)
class StepInputs:
    """Everything a step is computed from besides the frame.

    Telemetry on the policy side: ``pos_enu_m`` and ``goal_enu_m`` in the local ENU world frame
    (m), ``quat_enu_flu`` (w, x, y, z) body FLU -> world ENU, ``vel_body_flu_m_s`` (m/s) and
    ``angvel_body_flu_rad_s`` (rad/s) in body FLU.  Memory: ``hidden`` (H,) float32 GRU state,
    ``prev_action`` (3,) float32 previous clipped action, ``hidden_epoch`` = how many times the
    memory was reset before this step.
    """

    pos_enu_m: np.ndarray
    quat_enu_flu: np.ndarray
    vel_body_flu_m_s: np.ndarray
    angvel_body_flu_rad_s: np.ndarray
    goal_enu_m: np.ndarray
    hidden: np.ndarray
    prev_action: np.ndarray
    hidden_epoch: int


@dataclass(frozen=True)
class StepResult:
    """A computed step: its inputs, the 15-value state, the ONNX outputs (raw action, next hidden,
    latent), the action clipped to [-1, 1] (float32), and when each stage ended (ns, the clock
    passed to :func:`compute_step`)."""

    inputs: StepInputs
    observation_state: np.ndarray
    output: ModelOutput
    action_clipped: np.ndarray
    t_preprocessed_ns: int
    t_observed_ns: int
    t_inferred_ns: int
    t_started_ns: int = 0  # when compute_step began (in the flight loop: on the worker thread)


class PolicyMemory:
    """The recurrent part of the policy between steps: GRU hidden state and previous action."""

    def __init__(self, model: PolicyModel) -> None:
        self._model = model
        self.hidden = model.initial_hidden()
        self.prev_action = np.zeros(ACTION_DIM, dtype=np.float32)
        self.epoch = 0

    def reset(self) -> None:
        """Zero the GRU state and the previous action (offboard (re)entered, or a new goal)."""
        self.hidden = self._model.initial_hidden()
        self.prev_action = np.zeros(ACTION_DIM, dtype=np.float32)
        self.epoch += 1

    def inputs(self, state: VehicleState, goal_enu_m: np.ndarray) -> StepInputs:
        """This step's inputs from a telemetry snapshot and the goal (local ENU, m)."""
        return StepInputs(
            pos_enu_m=np.asarray(state.pos_enu_m, dtype=np.float64),
            quat_enu_flu=np.asarray(state.quat_enu_flu, dtype=np.float64),
            vel_body_flu_m_s=np.asarray(state.vel_body_flu_m_s, dtype=np.float64),
            angvel_body_flu_rad_s=np.asarray(state.angvel_body_flu_rad_s, dtype=np.float64),
            goal_enu_m=np.asarray(goal_enu_m, dtype=np.float64),
            hidden=self.hidden,
            prev_action=self.prev_action,
            hidden_epoch=self.epoch,
        )

    def advance(self, result: StepResult) -> None:
        """The step's command went out: carry its next hidden state and clipped action forward."""
        self.hidden = result.output.hidden_next
        self.prev_action = result.action_clipped


def compute_step(
    model: PolicyModel, frame: Frame, inputs: StepInputs, clock_ns: Callable[[], int] = time.monotonic_ns
) -> StepResult:
    """Preprocess ``frame``, build the state, run the model, clip the action.

    Raises ``runtime.contract.ImageContractError`` for a frame the contract cannot preprocess.
    """
    t_started_ns = clock_ns()
    gray = preprocess_gray(frame.gray_u8)
    depth = preprocess_depth(frame.depth_m)
    t_preprocessed_ns = clock_ns()
    state = observation_state(
        inputs.pos_enu_m, inputs.goal_enu_m, inputs.quat_enu_flu, inputs.vel_body_flu_m_s,
        inputs.angvel_body_flu_rad_s, inputs.prev_action,
    )  # fmt: skip
    t_observed_ns = clock_ns()
    output = model.step(gray, depth, state, inputs.hidden)
    t_inferred_ns = clock_ns()
    return StepResult(
        inputs=inputs,
        observation_state=state,
        output=output,
        action_clipped=clip_action(output.action).astype(np.float32),
        t_preprocessed_ns=t_preprocessed_ns,
        t_observed_ns=t_observed_ns,
        t_inferred_ns=t_inferred_ns,
        t_started_ns=t_started_ns,
    )
