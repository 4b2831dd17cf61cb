"""Every test under tests/e2e flies SITL vehicles in real time: marked ``flight`` (see pyproject);
the few flights elsewhere carry the mark themselves.

OpenMP threads sleep as soon as they wait (``OMP_WAIT_POLICY=PASSIVE``, inherited by every
process a test starts): the suite runs two workers on two cores, each starting torch, numba and
OpenCV processes, and threads that spin-wait for their team steal the cores the others compute
on.  Measured on this 2-core machine, one ``cmnav eval policy`` of the training tests: 10 s alone;
two at once 44 s each spinning, 12 s each passive (three at once, spinning: 124 s, past a
test's timeout in CI).  Set before any test imports torch."""

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

E2E = Path(__file__).parent / "e2e"


@pytest.fixture(scope="session")
def goal_seeker(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The goal-seeker model (``export.goal_seeker``), written once per worker: the flights' model."""
    from export.goal_seeker import export_goal_seeker

    path = tmp_path_factory.mktemp("models") / "goal-seeker.onnx"
    export_goal_seeker(str(path))
    return path


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if E2E in item.path.parents:
            item.add_marker(pytest.mark.flight)
