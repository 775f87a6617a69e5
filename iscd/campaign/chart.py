"""The campaign report's plot, written as SVG text: per task, packets found and delivered
(bars), the SER (log scale; 0 drawn at a floor) and the median range with its MAE (error
bar), three panels over one task axis.

Written directly, not through matplotlib: the figure is a few rectangles, circles and lines
per task, and matplotlib took 0.12 s for 12 tasks and 1.5 s for 300 on this 2-core machine
(its tick machinery), in the client, after the last task -- a serial part of every campaign
that no worker count shrinks (docs/campaign.md). This takes about a millisecond per hundred
tasks and needs no plotting package; browsers and Markdown viewers show SVG.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any
from xml.sax.saxutils import escape

PANEL_H = 170.0
"""Height of each panel's plotting area, px."""
LEFT, RIGHT, TOP, GAP = 78.0, 16.0, 26.0, 34.0
"""Margins, px: left (y labels), right, above the first panel, between panels."""
LABELS_H = 96.0
"""Room under the last panel for the task names (rotated), px."""
COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c")
"""found, delivered, points."""


def nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values (1, 2 or 5 times a power of ten apart) covering [lo, hi].

    Parameters
    ----------
    lo, hi : float
        The data's range (hi >= lo; equal values get a unit-wide range around them).
    n : int
        Ticks wanted (about).

    Returns
    -------
    list of float
        Increasing; the first <= lo and the last >= hi.
    """
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"nice_ticks: the range must be finite, got {lo}, {hi}")
    if hi < lo:
        lo, hi = hi, lo
    if hi == lo:
        lo, hi = lo - 0.5, hi + 0.5
    raw = (hi - lo) / max(1, n - 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    first = math.floor(lo / step + 1e-9) * step
    ticks = []
    t = first
    while t < hi + step * 1e-9 or len(ticks) < 2:
        ticks.append(round(t, 12))
        t += step
    if ticks[-1] < hi:
        ticks.append(round(t, 12))
    return ticks


def _fmt(v: float) -> str:
    return f"{v:g}"


class _Panel:
    """One panel: its top edge (px) and the map from a value to its y, px."""

    def __init__(self, top: float, lo: float, hi: float, log: bool = False) -> None:
        self.top, self.lo, self.hi, self.log = top, lo, hi, log

    def y(self, v: float) -> float:
        if self.log:
            v, lo, hi = math.log10(v), math.log10(self.lo), math.log10(self.hi)
        else:
            lo, hi = self.lo, self.hi
        return self.top + PANEL_H * (1.0 - (v - lo) / (hi - lo))


def campaign_svg(rows: Sequence[dict[str, Any]]) -> str:
    """The campaign's plot as an SVG document.

    Parameters
    ----------
    rows : sequence of dict
        The summary's rows (:func:`iscd.campaign.summary.summary_rows`); only those with
        status ``ok`` are drawn, in order. Used: ``name``, ``packets_found``,
        ``packets_delivered``, ``ser`` (None: no truth), ``range_median_m`` and
        ``range_mae_m`` (m; None: no ranges). A non-finite SER or range counts as none.

    Returns
    -------
    str
        ``<svg ...>...</svg>``: panel 1 packets found and delivered (bars), panel 2 the SER
        (log scale, an SER of 0 drawn at the floor 0.5 / (100 x the most packets found):
        below anything a task of that size can measure), panel 3 the median range, m, with
        the MAE as an error bar. Without ok rows, a one-line message.
    """
    ok = [r for r in rows if r.get("status") == "ok"]
    n = len(ok)
    slot = max(240.0 / max(n, 1), 40.0 if n <= 20 else max(14.0, 800.0 / n))  # px per task
    width = LEFT + RIGHT + max(n, 1) * slot
    height = TOP + 3 * PANEL_H + 2 * GAP + LABELS_H
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0f}" height="{height:.0f}" '
           f'viewBox="0 0 {width:.0f} {height:.0f}" font-family="sans-serif" font-size="11">',
           f'<rect width="{width:.0f}" height="{height:.0f}" fill="white"/>']
    if not ok:
        out += [f'<text x="{width / 2:.0f}" y="{height / 2:.0f}" text-anchor="middle">no task finished: '
                f'nothing to plot</text>', "</svg>"]
        return "\n".join(out)
    x = [LEFT + (i + 0.5) * slot for i in range(n)]
    tops = [TOP + k * (PANEL_H + GAP) for k in range(3)]

    def frame(p: _Panel, ticks: list[float], label: str, tick_text: Any = _fmt) -> None:
        out.append(f'<rect x="{LEFT:.1f}" y="{p.top:.1f}" width="{n * slot:.1f}" height="{PANEL_H:.1f}" '
                   f'fill="none" stroke="#444"/>')
        for t in ticks:
            yy = p.y(t)
            out.append(f'<line x1="{LEFT - 4:.1f}" x2="{LEFT + n * slot:.1f}" y1="{yy:.1f}" y2="{yy:.1f}" '
                       f'stroke="#ddd"/><text x="{LEFT - 6:.1f}" y="{yy + 4:.1f}" text-anchor="end">'
                       f'{tick_text(t)}</text>')
        cy = p.top + PANEL_H / 2
        out.append(f'<text transform="translate(14,{cy:.1f}) rotate(-90)" text-anchor="middle">'
                   f'{escape(label)}</text>')

    # 1: packets found / delivered
    found = [int(r.get("packets_found") or 0) for r in ok]
    deliv = [int(r.get("packets_delivered") or 0) for r in ok]
    ticks = nice_ticks(0.0, float(max(found + deliv + [1])))
    p = _Panel(tops[0], 0.0, ticks[-1])
    frame(p, ticks, "packets")
    w = 0.4 * slot
    for xi, f, d in zip(x, found, deliv):
        for x0, v, c in ((xi - w, f, COLORS[0]), (xi, d, COLORS[1])):
            out.append(f'<rect x="{x0:.1f}" y="{p.y(v):.1f}" width="{w:.1f}" height="{p.y(0) - p.y(v):.1f}" '
                       f'fill="{c}"/>')
    for k, (name, c) in enumerate((("found", COLORS[0]), ("delivered", COLORS[1]))):
        lx = LEFT + 78 * k
        out.append(f'<rect x="{lx:.1f}" y="{tops[0] - 16:.1f}" width="10" height="10" fill="{c}"/>'
                   f'<text x="{lx + 14:.1f}" y="{tops[0] - 7:.1f}">{name}</text>')

    # 2: SER, log scale, 0 drawn at the floor
    ser = [(xi, float(r["ser"])) for xi, r in zip(x, ok)
           if r.get("ser") is not None and math.isfinite(float(r["ser"]))]  # else: not measured
    floor = 0.5 / max(1, max(found) * 100)
    if ser:
        lo_dec = math.floor(math.log10(floor))
        hi_dec = max(lo_dec + 1, math.ceil(math.log10(max(max(s for _, s in ser), floor))))
        p = _Panel(tops[1], 10.0 ** lo_dec, 10.0 ** hi_dec, log=True)
        frame(p, [10.0 ** e for e in range(lo_dec, hi_dec + 1)], "SER (0 at the floor)",
              lambda t: f"1e{round(math.log10(t))}")
        for xi, s in ser:
            out.append(f'<circle cx="{xi:.1f}" cy="{p.y(max(s, floor)):.1f}" r="3.5" fill="{COLORS[2]}"/>')
    else:
        p = _Panel(tops[1], 0.0, 1.0)
        frame(p, [], "SER")
        out.append(f'<text x="{LEFT + n * slot / 2:.1f}" y="{tops[1] + PANEL_H / 2:.1f}" '
                   f'text-anchor="middle">no truth: no SER</text>')

    # 3: median range with its MAE
    med = [(xi, float(r["range_median_m"]), r.get("range_mae_m")) for xi, r in zip(x, ok)
           if r.get("range_median_m") is not None and math.isfinite(float(r["range_median_m"]))]
    err = [0.0 if e is None or not math.isfinite(float(e)) else float(e) for _, _, e in med]
    if med:
        ticks = nice_ticks(min(m - e for (_, m, _), e in zip(med, err)), max(m + e for (_, m, _), e in zip(med, err)))
    else:
        ticks = [0.0, 1.0]
    p = _Panel(tops[2], ticks[0], ticks[-1])
    frame(p, ticks, "median range, m (bar: MAE)")
    for (xi, m, _), e in zip(med, err):
        out.append(f'<line x1="{xi:.1f}" x2="{xi:.1f}" y1="{p.y(m - e):.1f}" y2="{p.y(m + e):.1f}" '
                   f'stroke="{COLORS[2]}" stroke-width="1.5"/><circle cx="{xi:.1f}" cy="{p.y(m):.1f}" r="3.5" '
                   f'fill="{COLORS[2]}"/>')
    if not med:
        out.append(f'<text x="{LEFT + n * slot / 2:.1f}" y="{tops[2] + PANEL_H / 2:.1f}" '
                   f'text-anchor="middle">no ranges</text>')

    # the task names under the last panel
    base = tops[2] + PANEL_H + 8
    size = 10 if slot >= 16 else 8
    for xi, r in zip(x, ok):
        out.append(f'<text transform="translate({xi + 3:.1f},{base:.1f}) rotate(-60)" text-anchor="end" '
                   f'font-size="{size}">{escape(str(r.get("name", "")))}</text>')
    out.append("</svg>")
    return "\n".join(out)
