"""The daemon's one fan-out (:class:`iscd.outputs.Outputs`, issue 13): every record to every
output, a failing output counted and logged without stopping the others or the daemon."""

from __future__ import annotations

from pathlib import Path

from iscd.core import config as C
from iscd.outputs import JsonlWriter, Output, Outputs
from iscd.outputs.jsonl import read_records
from iscd.service.daemon import Daemon


class _Keep(Output):
    def __init__(self) -> None:
        self.got: list[dict] = []
        self.closed = 0

    def write(self, record: dict) -> None:
        self.got.append(record)

    def counters(self) -> dict[str, int]:
        return {"keep_records": len(self.got), "keep_label": "not a number"}  # type: ignore[dict-item]

    def close(self) -> None:
        self.closed += 1


class _Broken(Output):
    def write(self, record: dict) -> None:
        raise OSError("disk on fire")


def test_fanout_counts_a_failing_output_and_feeds_the_rest(tmp_path: Path, caplog) -> None:
    keep, broken = _Keep(), _Broken()
    jl = JsonlWriter(tmp_path / "r.jsonl")
    outs = Outputs([broken, keep, jl])
    for i in range(12):
        outs.write({"type": "stats", "frame": i})
    outs.close()
    assert [r["frame"] for r in keep.got] == list(range(12))
    assert [r["frame"] for r in read_records(tmp_path / "r.jsonl")] == list(range(12))
    c = outs.counters()
    assert c["output_errors"] == 12 and c["keep_records"] == 12 and "keep_label" not in c
    assert keep.closed == 1
    # rate-limited: the first five errors, not all twelve
    assert sum("disk on fire" in r.getMessage() for r in caplog.records) == 5


def test_daemon_goes_on_past_a_failing_output(tmp_path: Path) -> None:
    out = tmp_path / "out.jsonl"
    d = Daemon(C.loads("[daemon]\nstats_interval_s = 0.5\n"), out=str(out), duration_s=1.5,
               install_signals=False)
    d.extra_outputs.append(_Broken())
    final = d.run()
    recs = read_records(out)
    # every record before the final one (which counts them) failed there, none here
    assert len(recs) > 1 and final["output_errors"] == len(recs) - 1
    assert recs[-1]["type"] == "stats" and recs[-1]["output_errors"] >= 1
    assert final["pairs_decoded"] > 0
