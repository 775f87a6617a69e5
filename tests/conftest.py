"""Shared test fixtures: where ../shared is, and the slow-test switch.

Tests marked ``@pytest.mark.slow`` (soaks, full-length benchmarks) run only with
``ISCD_SLOW=1``; CI runs their short forms.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def shared_path(*parts: str) -> Path:
    """A path under ../shared, or skip the test with the reason when it is absent."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"needs {p} (the project's shared data beside the checkout), which is absent")
    return p


@pytest.fixture
def shared() -> Path:
    return shared_path()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if os.environ.get("ISCD_SLOW") == "1":
        return
    skip = pytest.mark.skip(reason="slow test: set ISCD_SLOW=1 to run it")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
