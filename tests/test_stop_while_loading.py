"""A stop (SIGTERM, Ctrl-C) while the compiled kernels load: the first start after an install
compiles them for minutes, and the daemon used to finish compiling before it looked at the
stop. Now the loading asks before each kernel, the wait for the demodulation worker asks
every 0.2 s, and a daemon stopped meanwhile never starts its cameras: it writes its final
stats record and exits."""

from __future__ import annotations

from pathlib import Path

import pytest

from fakes import LIGHT, read_records
from iscd.core import config as C
from iscd.core import jit
from iscd.service import daemon as daemon_module
from iscd.service.daemon import Daemon


def test_loading_stops_between_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[int] = []
    fake = [((lambda i=i: calls.append(i)), tuple) for i in range(5)]
    monkeypatch.setattr(jit, "_REGISTRY", fake)
    jit.warm_up()
    assert calls == [0, 1, 2, 3, 4]
    calls.clear()
    jit.warm_up(should_stop=lambda: len(calls) >= 2)
    assert calls == [0, 1]  # the rest left once a stop is asked for


def test_a_daemon_stopped_while_loading_never_starts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The stop arrives during the loading (here: as the second kernel is asked for): the run
    returns promptly with a final stats record, no pair acquired, and nothing left running."""
    real = list(jit._REGISTRY)
    d: Daemon | None = None
    asked: list[int] = []

    def second_asks_stop() -> None:
        asked.append(1)
        assert d is not None
        d.request_stop()

    after: list[int] = []
    monkeypatch.setattr(jit, "_REGISTRY", real[:1] + [(second_asks_stop, tuple), (lambda: after.append(1), tuple)]
                        + real[1:])
    started: list[int] = []
    real_start = daemon_module._Run.start

    def start(self: object) -> None:
        started.append(1)
        real_start(self)

    monkeypatch.setattr(daemon_module._Run, "start", start)
    out = tmp_path / "out.jsonl"
    d = Daemon(C.loads(LIGHT), out=str(out), duration_s=30.0, install_signals=False)
    final = d.run()
    assert asked == [1] and after == [] and started == []  # the rest not loaded, the cameras not started
    recs = read_records(out)
    assert recs and recs[-1]["type"] == "stats" and recs[-1]["final"] is True
    assert final["final"] is True and final["frames_in"] == 0 and final["pairs_decoded"] == 0  # no camera started
    assert not [r for r in recs if r["type"] in ("packet", "range")]
