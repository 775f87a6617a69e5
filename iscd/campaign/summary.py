"""The campaign's summary: ``summary.parquet`` and ``summary.csv`` (one row per task, the
columns of :data:`iscd.campaign.rows.COLUMNS`) and ``report.md`` with plots
(``campaign.png``; without matplotlib the report says so and has none, as ``iscd eval``)."""

from __future__ import annotations

import csv
import math
import os
import time
import uuid
from pathlib import Path
from typing import Any, Sequence

from iscd.campaign.rows import COLUMNS

NO_PYARROW = "pyarrow is not installed, so there is no summary.parquet (pip install pyarrow)"


def summary_rows(results: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per task result, with every column of :data:`COLUMNS`.

    Parameters
    ----------
    results : sequence of dict
        Task results (:func:`iscd.campaign.tasks.run_task`), in manifest order.

    Returns
    -------
    list of dict
        Column -> value, None where empty.
    """
    rows = []
    for r in results:
        row = {c: None for c, _, _ in COLUMNS}
        row.update(r.get("figures") or {})
        row.update(name=r["name"], kind=r.get("kind"), status=r.get("status"), error=r.get("error") or "",
                   reused=bool(r.get("reused")), wall_s=r.get("wall_s"), identity=r.get("identity") or "")
        rows.append({c: row[c] for c, _, _ in COLUMNS})
    return rows


def _replace(path: Path, write: Any) -> None:
    """Write ``path`` through a temporary name and rename it when complete."""
    tmp = path.with_name(f"{path.name}.part-{uuid.uuid4().hex[:8]}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_csv(rows: Sequence[dict[str, Any]], path: Path) -> None:
    """``summary.csv`` at ``path`` from :func:`summary_rows` ``rows``: a header of the
    column names, an empty cell for None (written under a temporary name, then renamed)."""
    def w(tmp: Path) -> None:
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            out = csv.writer(f)
            out.writerow([c for c, _, _ in COLUMNS])
            for r in rows:
                out.writerow(["" if r[c] is None else r[c] for c, _, _ in COLUMNS])
    _replace(path, w)


def write_parquet(rows: Sequence[dict[str, Any]], path: Path) -> bool:
    """``summary.parquet`` with typed columns (string, int64, float64, bool).

    Parameters
    ----------
    rows : sequence of dict
        :func:`summary_rows`.
    path : Path
        The file (written under a temporary name, then renamed).

    Returns
    -------
    bool
        False when pyarrow is not installed (nothing written).
    """
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return False
    types = {"str": pa.string(), "int": pa.int64(), "float": pa.float64(), "bool": pa.bool_()}
    schema = pa.schema([(c, types[t]) for c, t, _ in COLUMNS])
    table = pa.table({c: [r[c] for r in rows] for c, _, _ in COLUMNS}, schema=schema)
    _replace(path, lambda tmp: pq.write_table(table, tmp))
    return True


def read_summary(path: str | Path) -> list[dict[str, Any]]:
    """The rows of ``path``, a ``summary.parquet``, as {column: value} dicts in the file's
    order (for tests and notebooks)."""
    import pyarrow.parquet as pq

    return pq.read_table(path).to_pylist()


def write_report(rows: Sequence[dict[str, Any]], out: Path, *, command: str, runner: str,
                 seconds: float) -> list[str]:
    """``report.md`` (and ``campaign.png`` when matplotlib is there).

    Parameters
    ----------
    rows : sequence of dict
        :func:`summary_rows`.
    out : Path
        The campaign's output folder.
    command : str
        The command line, quoted in the report.
    runner : str
        What ran the tasks (``a LocalCluster of 2 worker processes``).
    seconds : float
        The campaign's wall time, s.

    Returns
    -------
    list of str
        The notes (what is missing: plots, Parquet) the report states.
    """
    from iscd.eval.report import NO_MATPLOTLIB, _table, fmt, fmt_rate

    notes = []
    plots = _plot(rows, out / "campaign.png")
    if not plots:
        notes.append(NO_MATPLOTLIB)
    if not (out / "summary.parquet").exists():
        notes.append(NO_PYARROW)
    ok = [r for r in rows if r["status"] == "ok"]
    failed = [r for r in rows if r["status"] != "ok"]
    lines = [f"# Campaign report", "",
             f"`{command}`", "",
             f"{time.strftime('%Y-%m-%d %H:%M:%S %Z')}; {len(rows)} tasks: {len(ok)} ok "
             f"({sum(bool(r['reused']) for r in ok)} reused from an earlier run), {len(failed)} failed; "
             f"{seconds:.1f} s on {runner}.", ""]
    lines += [f"Note: {n}." for n in notes] + ([""] if notes else [])
    header = ["task", "status", "pairs", "dropped", "found", "CRC ok", "delivered/sent", "SER", "goodput kbit/s",
              "ranges", "median range m", "range MAE m", "decode s", "wall s"]

    def cells(r: dict[str, Any]) -> list[str]:
        if r["status"] != "ok":
            return [r["name"], "failed"] + ["-"] * (len(header) - 2)
        sent = "-" if r["packets_sent"] is None else str(r["packets_sent"])
        return [r["name"], "ok" + (" (reused)" if r["reused"] else ""), str(r["pairs"]), str(r["frames_dropped"]),
                str(r["packets_found"]), str(r["packets_ok"]), f"{r['packets_delivered']}/{sent}",
                fmt_rate(r["ser"]), fmt(r["goodput_kbps"], 2), str(r["ranges"]), fmt(r["range_median_m"], 2),
                fmt(r["range_mae_m"], 3), fmt(r["decode_s"], 2), fmt(r["wall_s"], 2)]
    lines += ["## Tasks", "", _table(header, (cells(r) for r in rows)), ""]
    if failed:
        lines += ["## Failed", ""] + [f"- `{r['name']}`: {r['error']}" for r in failed] + [""]
    if plots:
        lines += ["## Plots", "", "![packets, SER and range per task](campaign.png)", ""]
    lines += ["Columns: summary.csv / summary.parquet (docs/campaign.md); each task's records: tasks/NAME.jsonl.", ""]
    _replace(out / "report.md", lambda tmp: tmp.write_text("\n".join(lines)))
    return notes


def _plot(rows: Sequence[dict[str, Any]], path: Path) -> bool:
    """Packets found/delivered, SER and range (with its MAE) per task; False without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    ok = [r for r in rows if r["status"] == "ok"]
    if not ok:
        return True
    names = [r["name"] for r in ok]
    x = list(range(len(ok)))
    fig, ax = plt.subplots(3, 1, figsize=(max(6.0, 0.45 * len(ok) + 2), 9), sharex=True)
    ax[0].bar([i - 0.2 for i in x], [r["packets_found"] for r in ok], 0.4, label="found")
    ax[0].bar([i + 0.2 for i in x], [r["packets_delivered"] for r in ok], 0.4, label="delivered")
    ax[0].set_ylabel("packets")
    ax[0].legend()
    ser = [(i, r["ser"]) for i, r in zip(x, ok) if r["ser"] is not None]
    if ser:
        floor = 0.5 / max(1, max(r["packets_found"] for r in ok) * 100)
        ax[1].semilogy([i for i, _ in ser], [max(s, floor) for _, s in ser], "o")
        ax[1].set_ylabel("SER (0 drawn at the floor)")
    else:
        ax[1].text(0.5, 0.5, "no truth: no SER", ha="center", transform=ax[1].transAxes)
    med = [(i, r["range_median_m"], r["range_mae_m"]) for i, r in zip(x, ok) if r["range_median_m"] is not None]
    if med:
        ax[2].errorbar([i for i, _, _ in med], [m for _, m, _ in med],
                       yerr=[0.0 if e is None or not math.isfinite(e) else e for _, _, e in med], fmt="o")
    ax[2].set_ylabel("median range, m (bar: MAE)")
    ax[2].set_xticks(x)
    ax[2].set_xticklabels(names, rotation=60, ha="right", fontsize=7)
    fig.subplots_adjust(left=0.1, right=0.98, top=0.98, bottom=0.16, hspace=0.12)  # fixed: tight_layout draws twice
    _replace(path, lambda tmp: fig.savefig(tmp, dpi=90, format="png"))
    plt.close(fig)
    return True
