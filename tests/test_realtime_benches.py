"""Smoke runs of the real-time benchmarks (short forms; the speed goals live in their
output, never in a timed assertion here)."""

from __future__ import annotations

import re

import pytest


def test_decode_loop_benchmark_quick_prints_its_ratios(capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import bench_decode_loop

    assert bench_decode_loop.main(["--quick", "--scene", "single"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"[\d.]+ x the 1000 fps camera rate", out)
    assert re.search(r"[\d.]+ x the full-frame-copy baseline", out)
    assert "the frame loop alone" in out


def test_decode_loop_benchmark_profile_shows_where_the_time_goes(capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import bench_decode_loop

    assert bench_decode_loop.main(["--quick", "--scene", "single", "--profile"]) == 0
    out = capsys.readouterr().out
    assert "Ordered by: cumulative time" in out and "stream.py" in out and "(push)" in out


def test_decode_loop_benchmark_paced_reports_the_cpu_per_pair_both_ways(capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import bench_decode_loop

    assert bench_decode_loop.main(["--quick", "--scene", "single", "--paced"]) == 0
    out = capsys.readouterr().out
    m = re.search(r"paced at the camera rate: (\d+) us of CPU per pair, back to back (\d+) us \(([\d.]+) x\)", out)
    assert m and int(m.group(1)) > 0 and int(m.group(2)) > 0  # measured, not a speed goal
    assert float(m.group(3)) == pytest.approx(int(m.group(1)) / int(m.group(2)), rel=0.05)


def test_daemon_benchmark_quick_reports_the_whole_process_tree(capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import bench_daemon

    assert bench_daemon.main(["--quick"]) == 0
    out = capsys.readouterr().out
    m = re.search(r"all its processes: ([\d.]+) cores", out)
    assert m and 0.05 < float(m.group(1)) < 2.5  # a real measurement of a real run
    assert "frames dropped" in out and "packets ok" in out
