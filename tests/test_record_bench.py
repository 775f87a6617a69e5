"""Smoke run of benchmarks/bench_record.py (issue 18): the writer's rate per mode and its
ratio to a raw write of the same bytes are printed (the figures live in docs/recording.md,
never in a timed assertion here)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest


def test_record_benchmark_quick_prints_rates_and_ratios(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import bench_record

    assert bench_record.main(["--quick", "--dir", str(tmp_path), "--modes", "roi", "blackbox"]) == 0
    out = capsys.readouterr().out
    for mode in ("roi", "blackbox"):
        m = re.search(rf"^{mode} +(\d+) +(\d+) +([\d.]+) +([\d.]+) +([\d.]+) +([\d.]+) +([\d.]+) +([\d.]+)$", out, re.M)
        assert m, out
        assert int(m.group(1)) == 16264 and int(m.group(2)) >= 2000 and float(m.group(6)) > 0  # B/pair, pairs, raw
    assert list(tmp_path.iterdir()) == []  # nothing left behind
