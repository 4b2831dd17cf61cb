"""Every test under tests/e2e flies SITL vehicles in real time: marked ``flight`` (see pyproject);
the few flights elsewhere carry the mark themselves."""

from pathlib import Path

import pytest

E2E = Path(__file__).parent / "e2e"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if E2E in item.path.parents:
            item.add_marker(pytest.mark.flight)
