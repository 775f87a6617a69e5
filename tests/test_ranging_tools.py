"""Smoke runs of the ranging benchmark and the comparison table (short forms)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

from iscd.decode.ranging import compare


def _load_bench() -> ModuleType:
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_ranging.py"
    spec = importlib.util.spec_from_file_location("bench_ranging", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


bench_ranging = _load_bench()


def test_benchmark_quick_runs(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench_ranging.main(["--quick", "--methods", "iscd-fast,iscd,dissertation"]) == 0
    out = capsys.readouterr().out
    for case in ("1 LED", "8x8 per LED", "8x8 whole", "live ranger", "8x8 array 30 m", "1 LED 40 m"):
        assert case in out
    assert "ratio" in out and "x fft2" in out


def test_benchmark_refuses_unknown_method() -> None:
    with pytest.raises(SystemExit):
        bench_ranging.main(["--quick", "--methods", "magic"])


def test_comparison_table_runs(capsys: pytest.CaptureFixture[str]) -> None:
    assert compare.main(["--n", "12", "--methods", "iscd,centroid"]) == 0
    out = capsys.readouterr().out
    assert "| case | iscd | centroid |" in out
    assert "HDR" in out and "8x8 array" in out
