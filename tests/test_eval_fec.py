"""``iscd eval --suite fec``: goodput and packet loss of air interface v1 against v2 on the
same rendered 8x8 PWM-16 scenes, in results.json and the report (table and plot)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from iscd.cli.main import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_fec_suite_v1_beside_v2(tmp_path: Path) -> None:
    out = tmp_path / "f"
    rc = main(["eval", "--quick", "--suite", "fec", "--distances", "29", "--packets", "3", "--out", str(out)])
    assert rc == 0
    data = json.loads((out / "results.json").read_text())
    rows = {r["note"]: r for r in data["fec"]}
    assert set(rows) == {"v1", "v2 rs255_223", "v2 rs255_191"}
    payload = {"v1": 19196, "v2 rs255_223": 16732, "v2 rs255_191": 14321}
    period = {"v1": 653, "v2 rs255_223": 662, "v2 rs255_191": 662}
    for note, r in rows.items():
        assert r["distance_m"] == 29.0 and r["packets_sent"] == 3 and r["undetected"] == 0
        assert r["goodput_kbps"] == pytest.approx(8 * payload[note] * r["exact"] / (3 * period[note] / 500) / 1000)
    # this seed's scene (HDR f/4 + f/8 at 29 m, PWM-16): v2's code delivers every packet
    assert rows["v2 rs255_223"]["exact"] == 3 and rows["v2 rs255_191"]["exact"] == 3
    assert rows["v2 rs255_223"]["goodput_kbps"] > 100.0
    md = (out / "report.md").read_text()
    assert "## Air interface v1 against v2" in md and md.count("| 29 |") == 3
    if (out / "fec.png").exists():
        assert (out / "fec.png").read_bytes()[:8] == PNG_MAGIC and "(fec.png)" in md
