"""A task's row of the campaign summary, from its records (and the truth, where there is one).

:func:`figures` reads what ``iscd replay`` wrote (packet, range and stats records) and
gives the summary's figures; :data:`COLUMNS` is the table's schema. The same function
scores a JSONL written by ``iscd replay`` alone, so the two can be compared.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("name", "str", "the task's name (its outputs: tasks/NAME.jsonl, tasks/NAME.json)"),
    ("kind", "str", "recording (replayed) or simulate (rendered on the worker, then replayed)"),
    ("status", "str", "ok or failed"),
    ("error", "str", "why it failed, one line (empty when ok)"),
    ("reused", "bool", "true when this run found the task's output complete and its inputs unchanged"),
    ("pairs", "int", "stereo pairs decoded"),
    ("frames_dropped", "int", "frames of the recording without a partner (or ids missing in a run recording)"),
    ("packets_found", "int", "packet records (CRC-valid or not)"),
    ("packets_ok", "int", "CRC-valid packets"),
    ("packets_sent", "int", "whole packets in the recording (truth only)"),
    ("packets_delivered", "int", "bit-exact packets (truth), else CRC-valid packets"),
    ("ser", "float", "symbol error rate over the found packets' data symbols (truth only)"),
    ("ber", "float", "bit error rate, Gray mapping (truth only)"),
    ("goodput_kbps", "float", "payload bits of the delivered packets per second of recording, kbit/s"),
    ("ranges", "int", "range records (frames with a range)"),
    ("range_median_m", "float", "median range, m"),
    ("range_mean_m", "float", "mean range, m"),
    ("range_std_m", "float", "standard deviation of the ranges, m"),
    ("range_mae_m", "float", "mean absolute range error against the truth at each frame, m (truth only)"),
    ("range_bias_m", "float", "mean signed range error, m (truth only)"),
    ("range_rmse_m", "float", "root-mean-square range error, m (truth only)"),
    ("decode_s", "float", "time the decoder took (the stats record's wall_s), s"),
    ("wall_s", "float", "the task's wall time on its worker (hashing, rendering, decoding, writing), s"),
    ("identity", "str", "SHA-256 of the inputs' content, the task's parameters and the iscd version"),
)
"""(column, type, meaning) of the summary table, in order."""

FIGURES = ("pairs", "frames_dropped", "packets_found", "packets_ok", "packets_sent", "packets_delivered", "ser",
           "ber", "goodput_kbps", "ranges", "range_median_m", "range_mean_m", "range_std_m", "range_mae_m",
           "range_bias_m", "range_rmse_m")
"""The columns that are measurements of the recording (equal however it was run)."""


def iter_records(path: str | Path) -> Iterator[dict[str, Any]]:
    """The records of a JSON Lines file, one at a time (a long recording's records are not
    all held at once).

    Parameters
    ----------
    path : str or Path
        The file.

    Yields
    ------
    dict
        One per line, in order.
    """
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.strip():
                yield json.loads(line)


def read_records(path: str | Path) -> list[dict[str, Any]]:
    """``list(iter_records(path))``: every record of a JSON Lines file, in order."""
    return list(iter_records(path))


def _num(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def figures(records: Iterable[dict[str, Any]], cfg: Any, truth_dir: str | Path | None = None) -> dict[str, Any]:
    """The summary figures (:data:`FIGURES`) of one replay.

    Parameters
    ----------
    records : iterable of dict
        The replay's records; the last ``stats`` record gives pairs, drops and CRC counts.
    cfg : Config
        The config it was decoded with (``camera.fps`` for the recording's duration,
        ``[transmitter]`` for the scoring).
    truth_dir : str or Path, optional
        Folder with the simulator's truth: then packets are scored against it
        (:func:`iscd.eval.replay.score_against_truth`) and ranges against its distance.

    Returns
    -------
    dict
        Column -> value for :data:`FIGURES` (None where a figure does not exist, e.g. SER
        without truth) and ``decode_s``.
    """
    packets: list[dict[str, Any]] = []
    ranges: list[tuple[int, float]] = []
    stats: dict[str, Any] = {}
    for r in records:
        t = r.get("type")
        if t == "packet":
            packets.append(r)
        elif t == "range" and r.get("z_m") is not None and math.isfinite(r["z_m"]):
            ranges.append((int(r["frame"]), float(r["z_m"])))
        elif t == "stats":
            stats = r
    pairs = int(stats.get("pairs_decoded", 0))
    duration_s = pairs / float(cfg.camera.fps)
    out: dict[str, Any] = {k: None for k in FIGURES}
    out.update(pairs=pairs, frames_dropped=int(stats.get("frames_dropped", 0)), packets_found=len(packets),
               packets_ok=int(stats.get("packets_ok", sum(bool(p["crc_ok"]) for p in packets))),
               ranges=len(ranges))
    out["decode_s"] = stats.get("wall_s")
    truth = None
    if truth_dir is not None:
        from iscd.eval.replay import score_against_truth

        res, truth = score_against_truth(packets, truth_dir, cfg)
        delivered_bits = 8 * res.exact * res.payload_bytes
        out.update(packets_sent=res.packets_sent, packets_delivered=res.exact, ser=_num(res.ser),
                   ber=_num(res.ber))
    else:
        ok = [p for p in packets if p["crc_ok"]]
        delivered_bits = sum(4 * len(p.get("payload_hex", "")) for p in ok)
        out["packets_delivered"] = len(ok)
    out["goodput_kbps"] = delivered_bits / duration_s / 1000.0 if duration_s > 0 else None
    if ranges:
        # in frame order: the sums then do not depend on the order the records came out in
        # (a loaded machine reorders range records that a worker and the frame loop emit)
        ranges = sorted(ranges, key=lambda r: (r[0], r[1]))
        z = np.array([v for _, v in ranges])
        out.update(range_median_m=float(np.median(z)), range_mean_m=float(np.mean(z)), range_std_m=float(np.std(z)))
        if truth is not None:
            known = np.isin([f for f, _ in ranges], truth.frames)
            if known.any():
                frames = np.array([f for f, _ in ranges])[known]
                e = z[known] - truth.z_m[np.searchsorted(truth.frames, frames)]
                out.update(range_mae_m=float(np.mean(np.abs(e))), range_bias_m=float(np.mean(e)),
                           range_rmse_m=float(np.sqrt(np.mean(e * e))))
    return out
