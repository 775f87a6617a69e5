"""The evaluation report: Markdown tables, PNG plots (matplotlib, Agg) and results.json.

:func:`write_report` writes ``report.md``, ``results.json`` and one PNG per figure into a
folder. matplotlib is imported lazily (it is a test extra); without it the report is
written without plots and says so (:data:`NO_MATPLOTLIB`).

Column meanings (docs/eval.md): SER / BER over the data symbols of the packets found; PER =
share of the sent packets not delivered bit-exact; goodput = payload bits of CRC-valid,
bit-exact packets per second of transmission; (4.4) = the dissertation's throughput
log2(M) N F / dt (1 - SER) / 1000.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from iscd.eval import reference as ref
from iscd.eval.suites import CommsRow, EvalResults, MotionRow, RangingRow

NO_MATPLOTLIB = ("matplotlib is not installed, so this report has no plots "
                 "(pip install matplotlib, or the project's test extra: pip install -e '.[test]')")


# ----------------------------------------------------------------------------- formatting

def fmt_rate(x: float | None) -> str:
    """An error rate: ``0``, ``3.2e-03``, or ``-`` when undefined."""
    if x is None or not math.isfinite(x):
        return "-"
    return "0" if x == 0 else f"{x:.2e}"


def fmt(x: float | None, digits: int = 3, signed: bool = False) -> str:
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x:+.{digits}f}" if signed else f"{x:.{digits}f}"


def modulation(levels: int) -> str:
    return "OOK" if levels == 2 else f"PWM-{levels}"


def _table(header: list[str], rows: Iterable[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def reception_key(row: CommsRow) -> tuple[float | None, float | None, str]:
    """(left f-number, right f-number, reception) as in the dissertation's table 4.2."""
    cams = row.result.mode.cameras
    if cams == "left":
        return (row.f_left, None, "single")
    if cams == "right":
        return (None, row.f_right, "single")
    return (row.f_left, row.f_right, "diversity" if row.f_left == row.f_right else "hdr")


# ----------------------------------------------------------------------------- sections

def comms_table(rows: list[CommsRow], dissertation_col: bool = True) -> str:
    header = ["distance m", "modulation", "receiver", "found/sent", "symbols", "SER", "BER", "PER",
              "goodput kbps", "(4.4) kbps"]
    if dissertation_col:
        header.append("dissertation SER (fig. 3.8)")
    body = []
    for r in sorted(rows, key=lambda r: (r.levels, r.distance_m, r.result.mode.rule, r.result.mode.name)):
        c = r.result
        line = [f"{r.distance_m:g}", modulation(r.levels), c.mode.label,
                f"{c.found}/{c.packets_sent}" + (f" (+{c.spurious} spurious)" if c.spurious else ""),
                str(c.symbols), fmt_rate(c.ser), fmt_rate(c.ber), fmt_rate(c.per),
                fmt(c.goodput_kbps, 3), fmt(c.throughput_kbps, 3)]
        if dissertation_col:
            line.append(ref.fig_3_8_ser(r.levels, r.distance_m)[0] if c.mode.cameras == "both" else "")
        body.append(line)
    return _table(header, body)


def table_4_2(rows: list[CommsRow]) -> str:
    """The dissertation's table 4.2 beside ours: minimum over the distances of (4.4), and of
    the goodput, per reception mode and modulation."""
    best: dict[tuple[str, str], dict[int, tuple[float, float, float]]] = defaultdict(dict)
    keys: dict[tuple[str, str], tuple[float | None, float | None, str]] = {}
    for r in rows:
        c = r.result
        k = (c.mode.rule, c.mode.name)
        keys[k] = reception_key(r)
        cur = best[k].get(r.levels, (math.inf, math.inf, 0.0))
        tp = c.throughput_kbps if math.isfinite(c.throughput_kbps) else 0.0
        gp = c.goodput_kbps if math.isfinite(c.goodput_kbps) else 0.0
        best[k][r.levels] = (min(cur[0], tp), min(cur[1], gp), max(cur[2], r.distance_m))
    header = ["reception", "rule", "PWM-8 (4.4) min", "dissertation", "PWM-8 goodput min",
              "PWM-16 (4.4) min", "dissertation", "PWM-16 goodput min"]
    body = []
    order = sorted(best, key=lambda k: (k[0] != "iscd", _mode_order(keys[k]), k[1]))
    for k in order:
        line = [k[1], k[0]]
        for m in (8, 16):
            v = best[k].get(m)
            d = ref.table_4_2(*keys[k], m)
            line += [fmt(v[0], 2) if v else "-", fmt(d, 2) if d is not None else "-",
                     fmt(v[1], 2) if v else "-"]
        body.append(line)
    return _table(header, body)


def _mode_order(key: tuple[float | None, float | None, str]) -> tuple[int, float]:
    lf, rf, rec = key
    return ({"single": 0, "diversity": 1, "hdr": 2}[rec], (rf or 0) + (0 if lf is None else 0.5))


def is_project_method(method: str) -> bool:
    """The project's own estimators (``iscd``, ``iscd-fast``); the others are its peers."""
    return method.startswith("iscd")


def ranging_tables(rows: list[RangingRow]) -> str:
    if not rows:
        return ""
    rows = sorted(rows, key=lambda r: r.distance_m)
    methods = list(rows[0].result.errors_m)
    parts = []
    for title, attr, signed in (("Mean absolute error, m", "mae", False), ("Bias (mean signed error), m", "bias", True),
                                ("RMSE, m", "rmse", False)):
        body = []
        for r in rows:
            st = {m: r.result.stats(m) for m in methods}
            line = [f"{r.distance_m:g}", str(st[methods[0]].n)]
            if attr == "mae":
                line.append(fmt(r.jitter_floor_mae_m, 4))
            body.append(line + [fmt(getattr(st[m], attr), 4, signed) for m in methods])
        extra = ["jitter floor"] if attr == "mae" else []
        parts.append(f"**{title}**\n\n" + _table(["distance m", "frames", *extra] + methods, body))
    own = [m for m in methods if is_project_method(m)]
    peers = [m for m in methods if not is_project_method(m)]
    for mine in own:
        if not peers:
            break
        body = []
        for r in rows:
            mi = r.result.stats(mine).mae
            body.append([f"{r.distance_m:g}"] + [fmt(mi / r.result.stats(m).mae, 2) for m in peers])
        live = " (the live pipeline's method)" if mine == rows[0].result.project_method else ""
        parts.append(f"**Ratio of MAE, {mine}{live} / peer**, every scored frame (below 1: {mine} is "
                     "better)\n\n" + _table(["distance m"] + peers, body))
        body = []
        for r in rows:
            mi = r.result.stats_emitted(mine).mae
            share = float(np.mean(r.result.emitted_by_all())) if r.result.frames.size else float("nan")
            body.append([f"{r.distance_m:g}", f"{100 * share:.1f} %"]
                        + [fmt(mi / r.result.stats_emitted(m).mae, 2) for m in peers])
        parts.append(f"**Ratio of MAE, {mine} / peer, on the frames every ranger emits** (the same "
                     "frames for every method: those that pass the common spot-SNR gate)\n\n"
                     + _table(["distance m", "frames emitted"] + peers, body))
    body = []
    for r in rows:
        body.append([f"{r.distance_m:g}"] + [
            f"{100 * r.result.reported_share(m):.0f} % / {fmt(r.result.stats_reported(m).mae, 4)}"
            for m in methods])
    parts.append("**As emitted by the ranger** (after its own spot-SNR and match-quality gate): share of "
                 "the scored frames with a range / MAE of those, m\n\n" + _table(["distance m"] + methods, body))
    failed = []
    for r in rows:
        for m in methods:
            f = r.result.stats(m).failed
            if f:
                failed.append(f"{m} at {r.distance_m:g} m: {f}")
    if failed:
        parts.append("Frames without a finite range (not in the statistics): " + "; ".join(failed) + ".")
    return "\n\n".join(parts)


def _motion_groups(rows: list[MotionRow]) -> list[tuple[Any, Any, list[MotionRow]]]:
    """(case, pooled oracle result, rows) per motion case, in the order first run."""
    from iscd.eval.oracle import pool

    groups: dict[str, list[MotionRow]] = {}
    for r in rows:
        groups.setdefault(r.case.key, []).append(r)
    return [(rs[0].case, pool([r.result for r in rs]), rs) for rs in groups.values()]


def _ser_cell(res: Any) -> str:
    c = res.receiver
    return f"{fmt_rate(c.ser)} ({c.exact}/{c.packets_sent})"


def motion_ser_table(rows: list[MotionRow]) -> str:
    """SER of the receiver (packets delivered bit-exact / sent) against speed and vibration:
    one row per transmitter and motion, one column per vibration amplitude, seeds pooled."""
    groups = _motion_groups(rows)
    vibs = sorted({g[0].vibration_px for g in groups})
    lines: dict[tuple, dict[float, str]] = {}
    for case, res, _ in groups:
        who = f"{'1 LED' if case.leds == 1 else '8x8'} ({case.cameras})"
        motion = (f"{case.speed_kmh:g} km/h, {case.start_m:g} -> {case.end_m:g} m" if case.speed_kmh
                  else f"still, {case.start_m:g} m")
        extra = ", ".join(f"{k}={v}" for k, v in case.scene)
        lines.setdefault((case.leds, case.speed_kmh, who, motion + (f" ({extra})" if extra else "")), {})[
            case.vibration_px] = _ser_cell(res)
    body = [[k[2], k[3]] + [cells.get(v, "") for v in vibs] for k, cells in sorted(lines.items())]
    return _table(["transmitter", "motion"] + [f"vibration {v:g} px" for v in vibs], body)


def motion_split_table(rows: list[MotionRow]) -> str:
    """Per case: the receiver's scores, the oracle stages' SER on the common packets and the
    split (what following, timing and the channel estimate cost; the decision floor)."""
    from iscd.eval.oracle import CHAIN, FLOOR, REFERENCE, SPLIT

    header = (["case", "seeds", "found/sent", "delivered", "SER (found)", "common"] + list(CHAIN)
              + [s[0] for s in SPLIT] + [FLOOR] + list(REFERENCE))
    body = []
    for case, res, rs in _motion_groups(rows):
        c = res.receiver
        sp = res.split()
        body.append([case.label, str(len(rs)), f"{c.found}/{c.packets_sent}", f"{c.exact}/{c.packets_sent}",
                     fmt_rate(c.ser), f"{len(res.common())}/{len(res.packets)}"]
                    + [fmt_rate(res.ser(s)) for s in CHAIN]
                    + [_signed_rate(sp[s[0]]) for s in SPLIT] + [fmt_rate(sp[FLOOR])]
                    + [fmt_rate(res.ser(s)) if s in res.stages else "-" for s in REFERENCE])
    return _table(header, body)


def motion_found_table(rows: list[MotionRow]) -> str:
    """Per case and stage: SER over the packets that stage demodulated, and how many it
    demodulated / delivered with a valid CRC (of those sent)."""
    groups = _motion_groups(rows)
    stages = [s for s in groups[0][1].stages] if groups else []
    body = []
    for case, res, _ in groups:
        sent = len(res.packets)
        line = [case.label]
        for s in stages:
            if s not in res.stages:
                line.append("-")
                continue
            found = sum(p.stages[s].found for p in res.packets)
            ok = sum(p.stages[s].crc_ok for p in res.packets)
            line.append(f"{fmt_rate(res.ser(s, res.packets))} ({found}/{ok}/{sent})")
        body.append(line)
    return _table(["case"] + stages, body)


def _signed_rate(x: float) -> str:
    if x is None or not math.isfinite(x):
        return "-"
    return "0" if x == 0 else f"{x:+.2e}"


def motion_profile_tables(rows: list[MotionRow]) -> str:
    """Per case the SER in equal stretches along the packets' data (first to last), per
    stage, on the common packets."""
    parts = []
    for case, res, _ in _motion_groups(rows):
        body = [[s] + [fmt_rate(x) for x in res.profile(s)] for s in res.stages]
        first = _rows_of(rows, case)[0].result.packets
        parts.append(f"**{case.label}** ({len(res.common())} common packets of {len(res.packets)}; packets "
                     + ", ".join(f"{p.z_start_m:.0f} -> {p.z_end_m:.0f} m" for p in first)
                     + ")\n\n" + _table(["stage"] + [f"bin {i + 1}" for i in range(res.bins)], body))
    return "\n\n".join(parts)


def _rows_of(rows: list[MotionRow], case: Any) -> list[MotionRow]:
    return [r for r in rows if r.case.key == case.key]


def motion_section(rows: list[MotionRow], settings: dict[str, Any]) -> list[str]:
    """The report's motion section (issue 12): SER against speed and vibration, the
    oracle split and the error profiles."""
    notes = sorted({r.note for r in rows if r.note} | {n for r in rows for n in r.result.notes})
    out = ["", "## Motion: a moving car, and where its errors come from (issue 12)", "",
           f"PWM-8; one LED: b = 0.6 m, f/4 + f/4 (both cameras); 8x8: b = 0.25 m, HDR f/4 + f/8; "
           f"{settings.get('motion_seeds')} seed(s) a case, pooled"
           + (", quick form (short packets)" if settings.get("quick") else "") + ". "
           "SER over the packets found; in brackets packets delivered bit-exact / sent.", "",
           motion_ser_table(rows), "",
           "**Oracle split** (iscd.eval.oracle): the stages decode the same frames with one more part of "
           "the receiver replaced by the truth -- true LED positions (luminance at the true centres, "
           "the receiver's window), true symbol timing, true channel (true-level estimates per 8-symbol "
           "stretch from windows of 32 or 96 symbols or the whole packet, the best per packet). Stage SERs are over the 'common' packets (every stage "
           "demodulated them); following + timing + channel + decision/noise = receiver. References: "
           "true labels (the receiver's own channel estimate fitted on the true levels instead of its "
           "decisions, true positions and timing: what decision feedback costs), "
           "one true channel per packet (staleness), genie luminance (background-subtracted sum within "
           "the spot's radius R = f D / 2Z + 2 x blur, background from the nearest all-dark frames; "
           "true positions and timing) with the receiver's and with the true channel.", "",
           motion_split_table(rows), "",
           "Every stage on the packets it demodulated: SER (demodulated / CRC-valid / sent packets).", "",
           motion_found_table(rows), "",
           "**Error profiles**: SER in equal stretches along the data symbols of each packet "
           "(bin 1 = first), over the common packets.", "",
           motion_profile_tables(rows)]
    if notes:
        out += ["", "Notes: " + "; ".join(notes) + "."]
    return out


# ----------------------------------------------------------------------------- plots

def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _colors(rows: Iterable[CommsRow]) -> dict[str, Any]:
    """One colour per receiver mode name (the same for both rules and in every panel)."""
    plt = _plt()
    names = sorted({r.result.mode.name for r in rows})
    cmap = plt.get_cmap("tab10" if len(names) <= 10 else "tab20")
    return {n: cmap(i % cmap.N) for i, n in enumerate(names)}


def _ser_axis(ax: Any, rows: list[CommsRow], title: str, colors: dict[str, Any] | None = None) -> None:
    """SER vs distance, one curve per receiver; zeros drawn hollow at 1/(2 n symbols)."""
    colors = colors or _colors(rows)
    by_mode: dict[str, list[CommsRow]] = defaultdict(list)
    for r in rows:
        by_mode[r.result.mode.label].append(r)
    for label, rs in by_mode.items():
        rs = sorted(rs, key=lambda r: r.distance_m)
        x = np.array([r.distance_m for r in rs])
        ser = np.array([r.result.ser for r in rs])
        floor = np.array([0.5 / max(r.result.symbols, 1) for r in rs])
        y = np.where(ser > 0, ser, floor)
        ls = "--" if rs[0].result.mode.rule == "dissertation" else "-"
        line, = ax.plot(x, y, ls, label=label, color=colors.get(rs[0].result.mode.name))
        zero = ser == 0
        ax.plot(x[~zero], y[~zero], "o", color=line.get_color())
        ax.plot(x[zero], y[zero], "o", mfc="none", color=line.get_color())
    ax.set_yscale("log")
    ax.set_xlabel("distance (m)")
    ax.set_ylabel("symbol error rate")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)


def plot_comms(rows: list[CommsRow], path: Path) -> None:
    plt = _plt()
    levels = sorted({r.levels for r in rows}, reverse=True)
    fig, axes = plt.subplots(1, len(levels) + 1, figsize=(5.2 * (len(levels) + 1), 4.2))
    for ax, m in zip(axes, levels):
        sub = [r for r in rows if r.levels == m]
        _ser_axis(ax, sub, f"one LED, {modulation(m)}, b = 0.6 m", _colors(rows))
        ax.axvspan(min(r.distance_m for r in sub) - 1, 55.0, color="0.9", zorder=0,
                   label="dissertation fig. 3.8: error-free")
        bx = [d for d in sorted({r.distance_m for r in sub}) if ref.fig_3_8_ser(m, d)[1] is not None]
        bnd = [ref.fig_3_8_ser(m, d)[1] for d in bx]
        pos = [(d, b) for d, b in zip(bx, bnd) if b and b > 0]
        if pos:
            ax.plot([p[0] for p in pos], [p[1] for p in pos], "kv", label="dissertation fig. 3.8 (bound)")
        ax.legend(fontsize=7)
    ax = axes[-1]
    for m in levels:
        for label, rs in _group(r for r in rows if r.levels == m):
            if rs[0].result.mode.rule != "iscd":
                continue
            rs = sorted(rs, key=lambda r: r.distance_m)
            x = [r.distance_m for r in rs]
            line, = ax.plot(x, [r.result.goodput_kbps for r in rs], "o-", label=f"{modulation(m)} {label} goodput")
            ax.plot(x, [r.result.throughput_kbps for r in rs], "x:", color=line.get_color(),
                    label=f"{modulation(m)} {label} (4.4)")
    ax.set_xlabel("distance (m)")
    ax.set_ylabel("kbps")
    ax.set_title("goodput and throughput (4.4), project rule", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fec_table(rows: list[CommsRow]) -> str:
    """v1 against v2 per point: delivered, packet loss, SER, goodput, and the (4.4)
    throughput beside the dissertation's table 4.2 minimum for that reception."""
    header = ["distance m", "reception", "air interface", "delivered/sent", "packet loss", "SER",
              "goodput kbps", "(4.4) kbps", "dissertation (4.4) min"]
    body = []
    for r in sorted(rows, key=lambda r: (r.f_right, r.distance_m, r.note)):
        c = r.result
        d = ref.table_4_2(*reception_key(r), r.levels)
        body.append([f"{r.distance_m:g}", c.mode.label, r.note, f"{c.exact}/{c.packets_sent}",
                     fmt_rate(c.per), fmt_rate(c.ser), fmt(c.goodput_kbps, 3), fmt(c.throughput_kbps, 3),
                     fmt(d, 2) if d is not None else "-"])
    return _table(header, body)


def plot_fec(rows: list[CommsRow], path: Path) -> None:
    """Goodput and packet loss against distance, one line per air interface and reception,
    beside the dissertation's table 4.2 minimum of (4.4)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.4))
    groups: dict[tuple[str, str], list[CommsRow]] = defaultdict(list)
    for r in rows:
        groups[(r.result.mode.label, r.note)].append(r)
    for (label, air), rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: r.distance_m)
        x = [r.distance_m for r in rs]
        ls = ":" if air == "v1" else "-"
        line, = axes[0].plot(x, [r.result.goodput_kbps for r in rs], "o" + ls, label=f"{label}, {air}")
        axes[1].plot(x, [r.result.per for r in rs], "o" + ls, color=line.get_color(), label=f"{label}, {air}")
    for key, style in (((4.0, 8.0, "hdr"), "--"), ((4.0, 4.0, "diversity"), "-.")):
        d = ref.table_4_2(*key, 16)
        if d is not None and any(reception_key(r) == key for r in rows):
            axes[0].axhline(d, color="gray", ls=style, lw=0.8,
                            label=f"dissertation (4.4) min, {key[2]} f/{key[0]:g}+f/{key[1]:g}: {d} kbps")
    axes[0].set_ylabel("goodput, kbps (payload bits of delivered packets / s)")
    axes[1].set_ylabel("packet loss (not delivered exact)")
    axes[0].set_title("8x8 PWM-16: goodput, v1 (dotted) and v2", fontsize=10)
    axes[1].set_title("8x8 PWM-16: packet loss", fontsize=10)
    for ax in axes:
        ax.set_xlabel("distance (m)")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _group(rows: Iterable[CommsRow]) -> list[tuple[str, list[CommsRow]]]:
    g: dict[str, list[CommsRow]] = defaultdict(list)
    for r in rows:
        g[r.result.mode.label].append(r)
    return list(g.items())


def plot_hdr(rows: list[CommsRow], path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(13.5, 8.4))
    modes: dict[str, Any] = {}
    colors = _colors(rows)
    for col, m in enumerate((8, 16)):
        sub = [r for r in rows if r.levels == m]
        _ser_axis(axes[0, col], sub, f"8x8 array, PWM-{m}, b = 0.25 m: SER", colors)
        ax = axes[1, col]
        for label, rs in _group(sub):
            rs = sorted(rs, key=lambda r: r.distance_m)
            ls = "--" if rs[0].result.mode.rule == "dissertation" else "-"
            line, = ax.plot([r.distance_m for r in rs], [r.result.throughput_kbps for r in rs], "o" + ls,
                            color=colors.get(rs[0].result.mode.name), label=label)
            modes.setdefault(label, line)
        refs = [ax.axhline(ref.TABLE_4_2_ERROR_FREE_KBPS[m], color="k", lw=0.8,
                           label=f"(4.4) with SER = 0: {ref.TABLE_4_2_ERROR_FREE_KBPS[m]} kbps")]
        for key, style in (((4.0, 8.0, "hdr"), ":"), ((4.0, 4.0, "diversity"), "-.")):
            d = ref.table_4_2(*key, m)
            if d is not None:
                refs.append(ax.axhline(d, color="gray", ls=style, lw=0.8,
                                       label=f"dissertation min, {key[2]} f/{key[0]:g}+f/{key[1]:g}: {d} kbps"))
        ax.set_xlabel("distance (m)")
        ax.set_ylabel("throughput (4.4), kbps")
        ax.set_title(f"PWM-{m}: throughput (4.4)", fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(handles=refs, fontsize=7, loc="lower right")
    fig.legend(handles=list(modes.values()), fontsize=7, loc="center right",
               title="dashed: dissertation rule", title_fontsize=7)
    fig.tight_layout(rect=(0, 0, 0.86, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_ranging(rows: list[RangingRow], path: Path) -> None:
    plt = _plt()
    rows = sorted(rows, key=lambda r: r.distance_m)
    methods = list(rows[0].result.errors_m)
    x = [r.distance_m for r in rows]
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2))
    for m in methods:
        st = [r.result.stats(m) for r in rows]
        kw: dict[str, Any] = {"lw": 2.4} if is_project_method(m) else {"lw": 1.0}
        axes[0].plot(x, [s.mae for s in st], "o-", label=m, **kw)
        axes[1].plot(x, [s.bias for s in st], "o-", label=m, **kw)
        axes[2].plot(x, [s.rmse for s in st], "o-", label=m, **kw)
    axes[0].plot(x, [r.jitter_floor_mae_m for r in rows], "k--", lw=0.8, label="air jitter alone")
    axes[0].axhline(ref.FIG_3_7_BOUND_M["dissertation"], color="k", ls=":", lw=0.8,
                    label="dissertation fig. 3.7: bicubic+POC < 0.5 m")
    axes[0].axhline(ref.FIG_3_7_BOUND_M["poc"], color="gray", ls="-.", lw=0.8,
                    label="dissertation fig. 3.7: POC ~0.8 m at 55-60 m")
    for ax, t in zip(axes, ("mean absolute error (m)", "bias (m)", "RMSE (m)")):
        ax.set_xlabel("distance (m)")
        ax.set_ylabel(t)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_yscale("log")
    axes[2].set_yscale("log")
    axes[1].set_yscale("symlog", linthresh=0.01)
    axes[0].set_title("per-frame range error (cf. dissertation fig. 3.7)", fontsize=10)
    fig.legend(handles=axes[0].get_lines(), fontsize=7, loc="lower center", ncol=6)
    fig.tight_layout(rect=(0, 0.14, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def make_plots(results: EvalResults, out: Path) -> tuple[dict[str, str], str | None]:
    """PNG files per section (name -> file name) and a note when plots are missing."""
    try:
        _plt()
    except ImportError:
        return {}, NO_MATPLOTLIB
    plots: dict[str, str] = {}
    if results.comms:
        plot_comms(results.comms, out / "comms.png")
        plots["comms"] = "comms.png"
    if results.hdr:
        plot_hdr(results.hdr, out / "hdr.png")
        plots["hdr"] = "hdr.png"
    if results.ranging:
        plot_ranging(results.ranging, out / "ranging.png")
        plots["ranging"] = "ranging.png"
    if results.fec:
        plot_fec(results.fec, out / "fec.png")
        plots["fec"] = "fec.png"
    return plots, None


# ----------------------------------------------------------------------------- the document

def markdown(results: EvalResults, plots: dict[str, str] | None = None, note: str | None = None,
             command: str | None = None) -> str:
    plots = plots or {}
    s = results.settings
    out = ["# iscd evaluation report", ""]
    out.append(f"Simulated with the project's physics simulator and decoded by the real receiver "
               f"(detection, tracking, timing, channel estimation; no truth given to it). "
               f"Seed {s.get('seed')}, {'quick' if s.get('quick') else 'full'} run, "
               f"{results.seconds:.0f} s.")
    if command:
        out += ["", f"Reproduce: `{command}`"]
    if note:
        out += ["", f"**Note:** {note}"]
    if results.comms:
        out += ["", "## Communication: one LED (dissertation chapter 3, fig. 3.8)", "",
                f"One LED, b = 0.6 m, f/4 + f/4, 100 ppm LED clock drift, random LED phase, "
                f"{s.get('packets')} packets a point (F = 600 data symbols each). "
                f"Dissertation: OOK and PWM-8 error-free to 55 m, PWM-8 SER < 6e-3 at 60 m.", ""]
        if "comms" in plots:
            out += [f"![SER, goodput and throughput vs distance]({plots['comms']})", "",
                    "Hollow markers: no symbol error (drawn at 1/(2 x symbols)); dashed: dissertation rule.", ""]
        out.append(comms_table(results.comms))
    if results.hdr:
        out += ["", "## HDR and diversity: 8x8 array (dissertation chapter 4, table 4.2)", "",
                f"8x8 LEDs, 6 cm pitch, b = 0.25 m, left f/4, right f/4 / f/8 / f/16, "
                f"{s.get('packets')} packets a point. Minimum over "
                f"{', '.join(f'{d:g}' for d in s.get('hdr_distances_m', []))} m of the throughput (4.4) "
                f"and of the goodput, kbps, beside the dissertation's table 4.2 "
                f"(error-free (4.4): 88.2 kbps PWM-8, 117.6 kbps PWM-16):", "",
                table_4_2(results.hdr), ""]
        if "hdr" in plots:
            out += [f"![HDR SER and throughput vs distance]({plots['hdr']})", ""]
        out += ["Per point:", "", comms_table(results.hdr, dissertation_col=False)]
    if results.approach:
        out += ["", "## A car approaching", "",
                "8x8 array, PWM-8, HDR f/4 + f/8, closing at 40 km/h from 50 m for two packets (to about "
                "21 m), 0.3 px RMS rig vibration. (Closer than ~17 m, where the light grows 30 % within "
                "the channel window and both cameras saturate, the receiver does not decode yet.)", "",
                comms_table(results.approach, dissertation_col=False)]
    if results.motion:
        out += motion_section(results.motion, s)
    if results.fec:
        out += ["", "## Air interface v1 against v2 (forward error correction)", "",
                f"8x8 PWM-16, b = 0.25 m, the same scene (seed) per point for each air interface, "
                f"{s.get('packets')} packets a point; v2's packets carry a PHY header and Reed-Solomon "
                f"parity (docs/air-interface.md), so each holds fewer payload bytes (v1 19 196, "
                f"RS(255,223) 16 732, RS(255,191) 14 321) and is delivered despite symbol errors. "
                f"Goodput = payload bits of delivered packets per second; the dissertation's (4.4) "
                f"counts every data symbol of a packet even when the packet is lost.", ""]
        if "fec" in plots:
            out += [f"![goodput and packet loss, v1 and v2]({plots['fec']})", ""]
        out.append(fec_table(results.fec))
    if results.ranging:
        out += ["", "## Ranging (dissertation chapter 3, fig. 3.7)", "",
                f"One LED, PWM-8, b = 0.6 m, f/4, right camera defocused (0.3 px), independent air "
                f"jitter 0.05 px RMS per camera, textured background, {s.get('frames')} frames a point. "
                f"Per-frame errors (no filtering) against the true distance, on the frames after "
                f"acquisition in which the LED is lit (on for >= 10 % of the exposure; the same "
                f"frames for every method). Every method ranges the same patches (cut where the "
                f"receiver's tracked fit puts the LED). 'jitter floor': the MAE that the air jitter alone causes. Dissertation: {ref.FIG_3_7_RANGING['dissertation']}; "
                f"{ref.FIG_3_7_RANGING['poc']}. Earlier work: {ref.EARLIER_WORK}.", ""]
        if "ranging" in plots:
            out += [f"![range error vs distance]({plots['ranging']})", ""]
        out.append(ranging_tables(results.ranging))
    out.append("")
    return "\n".join(out)


def write_report(results: EvalResults, out: str | Path, command: str | None = None) -> Path:
    """Write ``report.md``, ``results.json`` and the PNG plots into ``out`` (created if
    missing); returns the report's path."""
    d = Path(out)
    d.mkdir(parents=True, exist_ok=True)
    plots, note = make_plots(results, d)
    (d / "results.json").write_text(json.dumps(results.as_dict(), indent=1) + "\n")
    path = d / "report.md"
    path.write_text(markdown(results, plots, note, command))
    return path
