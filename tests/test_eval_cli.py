"""``iscd eval``: the command, its report (Markdown + PNG + JSON) and its one-line errors."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from iscd.cli.main import main
from iscd.core.config import default_config
from iscd.eval import report
from iscd.eval.suites import EvalPlan, run_plan

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _has_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def test_ranging_report_tables_match_results_json(tmp_path: Path) -> None:
    out = tmp_path / "rep"
    rc = main(["eval", "--quick", "--suite", "ranging", "--frames", "160", "--distances", "40",
               "--methods", "iscd,poc", "--out", str(out)])
    assert rc == 0
    data = json.loads((out / "results.json").read_text())
    assert data["settings"]["frames"] == 160 and data["settings"]["suites"] == ["ranging"]
    (row,) = data["ranging"]
    assert row["distance_m"] == 40.0 and set(row["methods"]) == {"iscd", "poc"}
    assert row["frames_rendered"] == 160 and 0 < row["frames_ranged"] < 160
    md = (out / "report.md").read_text()
    assert "## Ranging" in md and "## HDR" not in md
    for m, st in row["methods"].items():
        assert st["mae_m"] < 0.5  # 40 m, 0.05 px jitter: a few cm
        assert f"{st['mae_m']:.4f}" in md and f"{st['rmse_m']:.4f}" in md
    assert "Ratio of MAE, iscd" in md and "/ peer" in md and "As emitted by the ranger" in md
    assert re.search(r"Reproduce: `iscd eval .*--frames=160", md)
    if _has_matplotlib():
        assert (out / "ranging.png").read_bytes()[:8] == PNG_MAGIC
        assert "![range error vs distance](ranging.png)" in md


def test_comms_report_counts_and_rates(tmp_path: Path) -> None:
    out = tmp_path / "c"
    rc = main(["eval", "--quick", "--suite", "comms", "--distances", "45", "--packets", "2",
               "--rules", "iscd,dissertation", "--out", str(out)])
    assert rc == 0
    data = json.loads((out / "results.json").read_text())
    rows = data["comms"]
    # OOK and PWM-8, each with left-only and diversity, each with both rules
    assert len(rows) == 8
    assert {(r["levels"], r["cameras"], r["rule"]) for r in rows} == {
        (m, c, r) for m in (2, 8) for c in ("left", "both") for r in ("iscd", "dissertation")}
    for r in rows:
        assert r["packets_sent"] == 2 and r["symbols"] == 600 * r["found"]
        payload = {2: 71, 8: 221}[r["levels"]]
        assert r["goodput_kbps"] == pytest.approx(8 * payload * r["exact"] / (2 * 653 / 500) / 1000)
        bps = {2: 1, 8: 3}[r["levels"]]
        assert r["throughput_kbps"] == pytest.approx(bps * 600 / (653 / 500) * (1 - r["ser"]) / 1000)
        # every symbol error costs at least one and at most log2(M) bits
        assert r["symbol_errors"] <= r["bit_errors"] <= bps * r["symbol_errors"]
        assert r["undetected"] == 0
    md = (out / "report.md").read_text()
    assert "fig. 3.8" in md and md.count("| 45 |") == 8
    if _has_matplotlib():
        assert (out / "comms.png").read_bytes()[:8] == PNG_MAGIC


def test_report_without_matplotlib_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def missing() -> None:
        raise ImportError("No module named 'matplotlib'")

    monkeypatch.setattr(report, "_plt", missing)
    res = run_plan(default_config(), EvalPlan(suites=("ranging",), quick=True, frames=100,
                                              methods=("centroid",), ranging_distances=(50.0,)))
    path = report.write_report(res, tmp_path)
    md = path.read_text()
    assert "matplotlib is not installed" in md and "![" not in md
    assert not list(tmp_path.glob("*.png"))
    assert "| 50 |" in md


@pytest.mark.parametrize("argv, message", [
    (["--frames", "0"], "--frames"),
    (["--packets", "0"], "--packets"),
    (["--methods", "iscd,bogus"], "unknown method 'bogus'"),
    (["--rules", "ml"], "unknown rule 'ml'"),
    (["--distances", "40,far"], "'far' is not a number"),
    (["--distances", "0.2"], "outside"),
    (["--config", "/nonexistent/iscd.toml"], "config file not found"),
    (["--suite", "comms", "--traces", "t"], "--traces: only with --suite motion"),
    (["--suite", "motion", "--recording", "r", "--traces", "t"], "--traces: not with --recording"),
])
def test_bad_input_is_one_line_exit_2(argv: list[str], message: str, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["eval", "--quick", "--out", str(tmp_path / "x"), *argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert message in err and len(err.splitlines()) == 1 and err.startswith("iscd eval: error:")


def test_out_must_be_a_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["eval", "--quick", "--suite", "ranging", "--out", str(f)]) == 2
    assert "is not a folder" in capsys.readouterr().err


def test_help_lists_the_options(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["eval", "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    for opt in ("--quick", "--out", "--suite", "--frames", "--seed", "--packets"):
        assert opt in text
