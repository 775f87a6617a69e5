"""Shared test fixtures: where ../shared is, the slow-test switch, a fake clock, and the
GenICam harvesters' release. The test doubles themselves live in ``fakes.py`` beside this
file (``from fakes import FakeCamera, wait_until, ...``).

Tests marked ``@pytest.mark.slow`` (soaks, full-length benchmarks) run only with
``ISCD_SLOW=1``; CI runs their short forms.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from fakes import FakeClock, NoDaemon

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


@pytest.fixture
def fake_clock(monkeypatch: pytest.MonkeyPatch) -> FakeClock:
    """Virtual time: ``fake_clock.install(module)`` makes that module's ``time`` the
    clock (undone after the test); ``fake_clock.sleep(s)`` / ``advance(s)`` move it."""
    clock = FakeClock()
    clock._mp = monkeypatch
    return clock


@pytest.fixture(scope="module")
def release_harvesters() -> Iterator[None]:
    """Release the GenICam harvesters (producer handles) after a module's tests; use it
    with ``pytestmark = pytest.mark.usefixtures("release_harvesters")``."""
    yield
    gc = sys.modules.get("iscd.drivers.genicam")
    if gc is not None:
        gc.release_all()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if os.environ.get("ISCD_SLOW") == "1":
        return
    skip = pytest.mark.skip(reason="slow test: set ISCD_SLOW=1 to run it")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def rendered_default():
    """(left, right) (256, 512, 512) uint8: the embedded default scene (8x8 HDR PWM-8 at
    30 m, textured background, noise), frames 0-255, rendered once per test session."""
    import numpy as np

    from iscd.core.config import default_config
    from iscd.sim.scene import Scene

    sc = Scene(default_config())
    n = 256
    L = np.empty((n, sc.height, sc.width), np.uint8)
    R = np.empty_like(L)
    for i in range(n):
        sc.render_pair_into(i, L[i], R[i])
    L.setflags(write=False)
    R.setflags(write=False)
    return L, R


@pytest.fixture
def no_daemon(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any attempt to build the daemon fails the test (bad input must stop before it)."""
    import iscd.service.daemon

    monkeypatch.setattr(iscd.service.daemon, "Daemon", NoDaemon)
