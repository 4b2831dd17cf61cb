"""--resume refuses to go on with a different task than the run started on (PPO and DAgger share
the check: training.policy.train.check_resumed_task)."""

from pathlib import Path

import pytest

from training.policy.train import check_resumed_task

OUT = Path("runs/student")
STATE = {"encoder_fingerprint": "enc-a", "vehicle": "px4", "end_at_goal": True}


def test_the_same_task_resumes():
    check_resumed_task(STATE, OUT, "models/enc", "enc-a", "px4", True)


@pytest.mark.parametrize(
    ("encoder", "vehicle", "end_at_goal", "message"),
    [
        ("enc-b", "px4", True, "was trained on encoder enc-a, but models/enc is enc-b; resume with the same --encoder"),
        (None, "px4", True, "was trained on encoder enc-a, but models/enc is None"),
        ("enc-a", "ideal", True, "was trained on the px4 vehicle, but --vehicle ideal was given"),
        ("enc-a", "px4", False, "episodes ending at the goal, but --end-at-goal was not given"),
    ],
)
def test_a_different_task_is_refused_with_the_fix(encoder, vehicle, end_at_goal, message):
    with pytest.raises(ValueError, match="start a new --out") as err:
        check_resumed_task(STATE, OUT, "models/enc", encoder, vehicle, end_at_goal)
    assert message in str(err.value)


def test_states_from_before_the_vehicle_was_recorded_are_the_ideal_vehicle_and_10_s_episodes():
    check_resumed_task({"encoder_fingerprint": None}, OUT, None, None, "ideal", False)
    with pytest.raises(ValueError, match="ideal vehicle"):
        check_resumed_task({"encoder_fingerprint": None}, OUT, None, None, "px4", False)
