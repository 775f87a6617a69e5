"""The campaign's summary: ``summary.parquet`` and ``summary.csv`` (one row per task, the
columns of :data:`iscd.campaign.rows.COLUMNS`) and ``report.md`` with its plot
(``campaign.svg``, :mod:`iscd.campaign.chart`)."""

from __future__ import annotations

import csv
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
    """``report.md`` and its plot ``campaign.svg``.

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
        The notes (what is missing: the Parquet file) the report states.
    """
    from iscd.campaign.chart import campaign_svg
    from iscd.eval.report import _table, fmt, fmt_rate

    notes = []
    _replace(out / "campaign.svg", lambda tmp: tmp.write_text(campaign_svg(rows), encoding="utf-8"))
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
    lines += ["## Plots", "", "![packets, SER and range per task](campaign.svg)", ""]
    lines += ["Columns: summary.csv / summary.parquet (docs/campaign.md); each task's records: tasks/NAME.jsonl.", ""]
    _replace(out / "report.md", lambda tmp: tmp.write_text("\n".join(lines)))
    return notes
