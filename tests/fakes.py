"""Shared test doubles and helpers (import them as ``from fakes import ...``; pytest puts
``tests/`` on ``sys.path``, and a spawned worker process inherits that path, so the
factories here can be handed to :class:`iscd.rig.acquisition.AcquisitionProcess`).

* :class:`FakeClock`: virtual time for code that reads a module's ``time``
  (``fake_clock.install(module)``, the ``fake_clock`` fixture in ``conftest.py``);
* :func:`wait_until`: poll a condition with a generous timeout instead of sleeping a
  fixed time and hoping;
* :class:`FakeCamera` and :func:`fake_rig`: a scripted :class:`~iscd.drivers.base.Camera` on a
  shared trigger clock, with injected faults;
* :data:`LIGHT` and :func:`run_daemon_until`: the daemon on a light mock transmitter, run
  until what a test waits for has been written (not for a fixed wall time);
* :func:`xfail_where`: parametrize values, some of them strict xfails with a reason.
"""

from __future__ import annotations

import contextlib
import json
import math
import shutil
import subprocess
import time
import types
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest

from iscd.drivers.base import Camera, CameraError, CameraLost, CameraSettings, CameraTimeout, Frame

T = TypeVar("T")


# ---------------------------------------------------------------------- time
class FakeClock:
    """Virtual time: :meth:`sleep` advances it at once, nothing else does.

    It has the ``time`` module's clock functions that the project uses (``monotonic``,
    ``monotonic_ns``, ``perf_counter``, ``time``, ``sleep``), so that a module reading its
    clock as ``time.monotonic()`` runs on it after ``install(module)`` (which replaces the
    module's ``time`` name for the test; the ``fake_clock`` fixture undoes it)."""

    def __init__(self, start_s: float = 1000.0) -> None:
        self._ns = round(start_s * 1e9)
        self.sleeps: list[float] = []
        """every :meth:`sleep` asked for, s (what the code under test waited)"""
        self._mp: pytest.MonkeyPatch | None = None

    def now(self) -> float:
        return self._ns / 1e9

    monotonic = perf_counter = time = now

    def monotonic_ns(self) -> int:
        return self._ns

    perf_counter_ns = time_ns = monotonic_ns

    def sleep(self, seconds: float) -> None:
        if seconds < 0:
            raise ValueError("sleep length must be non-negative")
        self.sleeps.append(seconds)
        self.advance(seconds)

    def advance(self, seconds: float) -> None:
        self._ns += round(seconds * 1e9)

    def install(self, *modules: Any) -> "FakeClock":
        """Make each module's clock this one until the test ends: its ``time`` name, and
        any module-level alias of a clock function (``_monotonic = time.monotonic``)."""
        assert self._mp is not None, "install() needs the fake_clock fixture"
        real = {getattr(time, f): f for f in _CLOCK_FUNCTIONS}
        for m in modules:
            if getattr(m, "time", None) is time:
                self._mp.setattr(m, "time", self)
            for name, value in list(vars(m).items()):
                if isinstance(value, types.BuiltinFunctionType) and value in real:
                    self._mp.setattr(m, name, getattr(self, real[value]))
        return self


_CLOCK_FUNCTIONS = ("monotonic", "monotonic_ns", "perf_counter", "perf_counter_ns", "time", "time_ns",
                    "sleep")


def wait_until(cond: Callable[[], T], timeout_s: float = 30.0, interval_s: float = 0.01,
               what: str = "the condition") -> T:
    """Poll ``cond()`` until it is truthy and return its value; fail the test after
    ``timeout_s`` s. The timeout is a safety net for a broken run, not a measurement: make
    it generous (a loaded machine is slow, never wrong)."""
    deadline = time.monotonic() + timeout_s
    while True:
        got = cond()
        if got:
            return got
        if time.monotonic() >= deadline:
            pytest.fail(f"{what}: not within {timeout_s:g} s")
        time.sleep(interval_s)


# ---------------------------------------------------------------------- parametrize
def xfail_where(values: Iterable[float], fails: dict[float, str]) -> list:
    """``values`` for ``pytest.mark.parametrize``; those in ``fails`` are strict xfails
    with the reason given."""
    return [pytest.param(v, marks=pytest.mark.xfail(strict=True, reason=fails[v])) if v in fails else v
            for v in values]


# ---------------------------------------------------------------------- cameras
PATTERN_SHAPE = (16, 24)


def pattern_image(t: int, side: str, shape: tuple[int, int] = PATTERN_SHAPE) -> np.ndarray:
    """A small image that names trigger ``t`` and the camera ``side`` (ground truth)."""
    base = np.arange(shape[0] * shape[1], dtype=np.int64).reshape(shape)
    return ((base * (3 if side == "left" else 5) + t * 7) % 256).astype(np.uint8)


class FakeCamera(Camera):
    """A camera of a rig whose trigger t fires at ``t0_ns + t * period_ns``; it shows
    ``image(t, name)`` (:func:`pattern_image` unless given).

    script: trigger -> fault, each fired once when that trigger is next:
      ``timeout`` (a CameraTimeout first), ``error`` (a CameraError first), ``lost``
      (CameraLost: the camera is gone; ``open_failures`` opens fail, then it restarts at
      the current trigger, its ids from 0 if ``reset_ids``), ``boom`` (a RuntimeError, a
      driver bug), ``bad`` (this trigger's image has the wrong size).
    skip: triggers that never arrive (the next one is read instead).
    paced: a read waits (on the host's monotonic clock) until its trigger has fired, and
      after the last trigger a read waits its timeout before CameraTimeout; unpaced, every
      read returns (or raises CameraTimeout at the end) at once. period_ns = 0: frames
      come as fast as they are read either way.
    """

    def __init__(self, name: str, n: int, t0_ns: int = 0, period_ns: int = 0, *,
                 script: dict[int, str] | None = None, open_failures: int = 0,
                 reset_ids: bool = False, skip: Iterable[int] = (),
                 image: Callable[[int, str], np.ndarray] = pattern_image, paced: bool = True) -> None:
        self.name = name
        self.n, self.t0_ns, self.period_ns = n, t0_ns, period_ns
        self.script = dict(script or {})
        self.open_failures = open_failures
        self.reset_ids = reset_ids
        self.skip = set(skip)
        self.image = image
        self.paced = paced
        self.cursor = 0
        self.id_base = 0
        self.state = "closed"
        self.injected_timeouts = 0
        self.exhausted_timeouts = 0
        self.configured: list[CameraSettings] = []
        self.opens = 0

    @property
    def exhausted(self) -> bool:
        return self.cursor >= self.n

    @property
    def opened(self) -> bool:
        return self.state in ("open", "running")

    @property
    def started(self) -> bool:
        return self.state == "running"

    def open(self) -> None:
        if self.state == "lost" and self.open_failures > 0:
            self.open_failures -= 1
            raise CameraError(f"{self.name}: device not found")
        self.opens += 1
        if self.state == "lost" and self.period_ns:  # triggers fired meanwhile are gone
            now_t = math.ceil((time.monotonic_ns() - self.t0_ns) / self.period_ns)
            if self.reset_ids:
                self.id_base = max(self.cursor, now_t)
            self.cursor = max(self.cursor, now_t)
        self.state = "open"

    def configure(self, settings: CameraSettings) -> CameraSettings:
        self.configured.append(settings)
        return settings

    def start(self) -> None:
        self.state = "running"

    def stop(self) -> None:
        if self.state == "running":
            self.state = "open"

    def close(self) -> None:
        if self.state != "lost":
            self.state = "closed"

    def read(self, timeout_s: float = 1.0) -> Frame:
        if self.state != "running":
            raise CameraError(f"{self.name}: not running ({self.state})")
        while self.cursor in self.skip:
            self.cursor += 1
        t = self.cursor
        if t >= self.n:
            if self.paced:
                time.sleep(timeout_s)
            self.exhausted_timeouts += 1
            raise CameraTimeout(f"{self.name}: no more frames")
        fault = self.script.pop(t, None)
        if fault == "timeout":
            self.injected_timeouts += 1
            raise CameraTimeout(f"{self.name}: injected timeout")
        if fault == "error":
            raise CameraError(f"{self.name}: injected error")
        if fault == "boom":
            raise RuntimeError(f"{self.name}: injected driver bug")
        if fault == "lost":
            self.state = "lost"
            raise CameraLost(f"{self.name}: injected unplug")
        ts = self.t0_ns + t * self.period_ns
        if self.paced:
            wait = (ts - time.monotonic_ns()) / 1e9
            if wait > timeout_s:
                time.sleep(timeout_s)
                raise CameraTimeout(f"{self.name}: not yet")
            if wait > 0:
                time.sleep(wait)
        self.cursor = t + 1
        img = self.image(t, self.name) if fault != "bad" else np.zeros((4, 4), np.uint8)
        return Frame(self.name, t - self.id_base, ts, img)


def fake_rig(n: int, period_ns: int, left_script: dict[int, str] | None = None,
             right_script: dict[int, str] | None = None, **right_kw: Any,
             ) -> tuple[FakeCamera, FakeCamera]:
    """Two :class:`FakeCamera` on one trigger clock starting 30 ms from now. Module level,
    so a spawned worker process can build it (via functools.partial)."""
    t0 = time.monotonic_ns() + 30_000_000
    return (FakeCamera("left", n, t0, period_ns, script=left_script),
            FakeCamera("right", n, t0, period_ns, script=right_script, **right_kw))


# ---------------------------------------------------------------------- the daemon
def render_pairs(cfg: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) (n, H, W) frames 0 .. n - 1 of ``cfg``'s simulated scene."""
    from iscd.sim.scene import Scene

    sc = Scene(cfg)
    left = np.empty((n, sc.height, sc.width), np.uint8)
    right = np.empty_like(left)
    for i in range(n):
        sc.render_pair_into(i, left[i], right[i])
    return left, right


LIGHT = """
[transmitter]
rows = 1
cols = 1
levels = 8
training_symbols = 40
data_symbols = 100
[camera]
baseline_m = 0.6
f_number_left = 4
f_number_right = 4
[scene]
distance_m = 30
seed = 7
[rig]
backend = "mock"
pace = false
"""
"""A light transmitter (one LED, packets of 153 symbols = 306 ms at 1000 fps) on the
unpaced mock rig: it makes each pair when the daemon takes it, and the daemon waits for its
decoder, so nothing is dropped for want of time however busy the machine is (another test
beside it under ``pytest -n 2``, a slow CI host). What a test of the daemon checks then
holds on any machine; the real-time claims use :data:`LIGHT_PACED`."""

LIGHT_PACED = LIGHT.replace("\npace = false\n", "\npace = true\n")
""":data:`LIGHT` on the paced mock rig (frames at 1000 fps in real time, like cameras):
for what is about keeping up (the overload policy, drops, latency)."""
assert "pace = true" in LIGHT_PACED


def read_records(path: Path) -> list[dict]:
    """The JSON Lines records of a daemon's output file."""
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


class StopWhen:
    """A daemon output (``Daemon.extra_outputs``) that keeps the records and asks the
    daemon to stop once ``done(records)`` holds; ``done`` is looked at on each packet and
    stats record."""

    def __init__(self, daemon: Any, done: Callable[[list[dict]], bool]) -> None:
        self.daemon, self.done = daemon, done
        self.records: list[dict] = []
        self.met_at_s: float | None = None
        """uptime of the stats record at or after which ``done`` held, s"""
        self._t0 = time.monotonic()

    def write(self, rec: dict) -> None:
        self.records.append(rec)
        if self.met_at_s is None and rec.get("type") in ("packet", "stats") and self.done(self.records):
            self.met_at_s = time.monotonic() - self._t0
            self.daemon.request_stop()

    def close(self) -> None:
        pass


def stats_records(recs: list[dict], final: bool | None = None) -> list[dict]:
    return [r for r in recs if r["type"] == "stats" and (final is None or bool(r.get("final")) == final)]


def run_daemon_until(text: str, tmp_path: Path, done: Callable[[list[dict]], bool],
                     timeout_s: float = 120.0) -> tuple[Any, list[dict], StopWhen]:
    """Run the daemon on config ``text`` until ``done(records so far)`` holds, at most
    ``timeout_s`` s of wall time (a safety net: a loaded machine only takes longer);
    returns the daemon, the records of its output file and the :class:`StopWhen`
    (``met_at_s`` None: the condition never held)."""
    from iscd.core import config as C
    from iscd.service.daemon import Daemon

    out = tmp_path / "out.jsonl"
    d = Daemon(C.loads(text), out=str(out), duration_s=timeout_s, install_signals=False)
    stop = StopWhen(d, done)
    d.extra_outputs.append(stop)
    d.run()
    return d, read_records(out), stop


# ---------------------------------------------------------------- command line and disks
class NoDaemon:
    """Stands in for iscd.service.daemon.Daemon: constructing it means a bad input got through."""

    def __init__(self, *a: object, **k: object) -> None:
        raise AssertionError("the daemon was started despite a bad input")


def cli(capsys: Any, *argv: str) -> tuple[int, str, str]:
    """``iscd ARGV`` in this process: (exit status, stdout, stderr); argparse's exits too."""
    from iscd.cli.main import main

    try:
        rc = main(list(argv))
    except SystemExit as e:  # argparse errors
        rc = int(e.code or 0)
    out, err = capsys.readouterr()
    return rc, out, err


def one_error_line(err: str, command: str) -> str:
    """The one ``iscd COMMAND: error: ...`` line of ``err`` (asserted: one line, no traceback)."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{err}"
    assert lines[0].startswith(f"iscd {command}: error: "), lines[0]
    assert "Traceback" not in err
    return lines[0]


@contextlib.contextmanager
def tmpfs(mnt: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` (mount's ``size=``, e.g. ``64k``) mounted at ``mnt`` (made here) for
    the ``with`` block; the test is skipped where mounting is not permitted."""
    import pytest

    mnt.mkdir()
    if shutil.which("mount") is None:
        pytest.skip("no mount command")
    p = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)],
                       capture_output=True, text=True)
    if p.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {p.stderr.strip() or p.returncode}")
    try:
        yield mnt
    finally:
        if subprocess.run(["umount", str(mnt)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(mnt)], capture_output=True)
