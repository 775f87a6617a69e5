"""The campaign report's SVG plot (:mod:`iscd.campaign.chart`): well-formed, one pair of bars
per finished task with heights proportional to the packets, SER points in log-scale order
(0 at the floor), range points with their MAE bars, names escaped; the tick helper."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from typing import Any

import pytest

from iscd.campaign.chart import PANEL_H, campaign_svg, nice_ticks

NS = "{http://www.w3.org/2000/svg}"


def row(name: str, found: int = 4, delivered: int = 3, ser: float | None = 0.01, median: float | None = 30.0,
        mae: float | None = 0.02, status: str = "ok") -> dict[str, Any]:
    return {"name": name, "status": status, "packets_found": found, "packets_delivered": delivered, "ser": ser,
            "range_median_m": median, "range_mae_m": mae}


def parse(svg: str) -> ET.Element:
    return ET.fromstring(svg)


def test_bars_are_proportional_to_the_packets_and_failed_tasks_are_left_out() -> None:
    rows = [row("a", 8, 8), row("b", 4, 2), row("bad", status="failed"), row("c", 0, 0)]
    root = parse(campaign_svg(rows))
    bars = [r for r in root.iter(f"{NS}rect") if r.get("fill") in ("#1f77b4", "#ff7f0e")
            and r.get("width") != "10"]  # the legend's squares aside
    heights = [float(b.get("height")) for b in bars]
    assert len(bars) == 6  # found and delivered for a, b, c
    assert heights[0] == pytest.approx(heights[1]) and heights[2] == pytest.approx(heights[0] / 2, abs=0.15)
    assert heights[3] == pytest.approx(heights[0] / 4, abs=0.15) and heights[4] == heights[5] == 0
    assert max(heights) <= PANEL_H
    names = [t.text for t in root.iter(f"{NS}text")][-3:]
    assert names == ["a", "b", "c"]


def test_ser_points_follow_a_log_scale_and_zero_sits_at_the_floor() -> None:
    rows = [row("a", 20, ser=1e-1), row("b", 20, ser=1e-2), row("c", 20, ser=1e-3), row("d", 20, ser=0.0),
            row("e", 20, ser=None)]
    root = parse(campaign_svg(rows))
    ys = [float(c.get("cy")) for c in root.iter(f"{NS}circle")][:4]  # the SER panel's points come first
    assert ys[0] < ys[1] < ys[2] < ys[3]  # lower SER is lower in the panel (larger y)
    assert ys[1] - ys[0] == pytest.approx(ys[2] - ys[1], abs=0.2)  # a decade is a decade
    floor = 0.5 / (20 * 100)  # half of one error in the most symbols found
    assert (ys[3] - ys[2]) / (ys[2] - ys[1]) == pytest.approx(math.log10(1e-3 / floor), abs=0.01)


def test_range_points_carry_their_mae_bars() -> None:
    rows = [row("a", median=20.0, mae=0.5), row("b", median=40.0, mae=None), row("c", median=None)]
    root = parse(campaign_svg(rows))
    lines = [ln for ln in root.iter(f"{NS}line") if ln.get("stroke-width") == "1.5"]
    assert len(lines) == 2
    (a, b) = lines
    span_a = float(a.get("y1")) - float(a.get("y2"))
    assert span_a > 0 and float(b.get("y1")) == float(b.get("y2"))  # no MAE: no bar
    ya = [float(c.get("cy")) for c in root.iter(f"{NS}circle")][-2:]
    assert ya[0] > ya[1]  # 20 m below 40 m
    assert span_a / (ya[0] - ya[1]) == pytest.approx(1.0 / 20.0, rel=0.01)  # 2 x 0.5 m against 20 m


def test_without_truth_or_finished_tasks_it_says_so_and_names_are_escaped() -> None:
    root = parse(campaign_svg([row("<x & y>", ser=None)]))
    texts = [t.text for t in root.iter(f"{NS}text")]
    assert "no truth: no SER" in texts and texts[-1] == "<x & y>"
    nan = parse(campaign_svg([row("a", ser=float("nan"), median=float("inf"), mae=float("nan"))]))
    assert {"no truth: no SER", "no ranges"} <= {t.text for t in nan.iter(f"{NS}text")}  # not a crash
    empty = parse(campaign_svg([row("a", status="failed")]))
    assert any("nothing to plot" in (t.text or "") for t in empty.iter(f"{NS}text"))


def test_many_tasks_stay_a_readable_width() -> None:
    svg = campaign_svg([row(f"t{i:03d}") for i in range(300)])
    root = parse(svg)
    assert float(root.get("width")) <= 78 + 16 + 300 * 14 + 1
    assert len([c for c in root.iter(f"{NS}circle")]) == 600


@pytest.mark.parametrize("lo,hi", [(0, 1), (0, 8), (19.7, 40.3), (-3.2, 0.01), (5, 5), (0.0012, 0.0019), (0, 1234)])
def test_nice_ticks_cover_the_range_with_round_steps(lo: float, hi: float) -> None:
    t = nice_ticks(lo, hi)
    assert t[0] <= lo and t[-1] >= hi and 2 <= len(t) <= 12
    steps = {round(b - a, 9) for a, b in zip(t, t[1:])}
    assert len(steps) == 1
    step = steps.pop()
    mant = step / 10 ** math.floor(math.log10(step))
    assert any(mant == pytest.approx(m) for m in (1, 2, 5))


def test_nice_ticks_refuses_a_non_finite_range() -> None:
    with pytest.raises(ValueError, match="finite"):
        nice_ticks(0.0, math.inf)
