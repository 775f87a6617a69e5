"""Benchmark: the recording's writer (issue 18), pairs/s and MB/s per mode, as a ratio to a
raw sequential write of the same bytes in the same process.

Per mode, N stereo pairs of 512x512 uint8 are offered from this thread (the frame loop's
side) to a :class:`iscd.recording.recorder.Recorder` writing into ``--dir``; a pair that a
full spool refuses is offered again 50 us later, so the writer sets the pace. The clock
runs from the first offer until the last pair is written and the file sealed (fsync'ed;
``--no-fsync``: handed to the page cache only, what the writer's own work costs). The
baseline, measured just before in the same process and folder: the same number of bytes
written with ``os.write`` in 8 MiB chunks to one file (then fsync'ed, unless --no-fsync).
The two alternate ``--reps`` times (a shared VM's disk swings by 4x from one second to the
next); the medians and the median of the per-repetition ratios are printed. Also printed:
what an accepted offer costs the frame loop (us a pair: the copy into the spool).

Modes: ``full`` (whole pairs, 524 kB), ``roi`` (two 90x90 windows: the 8x8 default array's
needed_windows(), 16.3 kB), ``roi-1led`` (two 15x15 windows: the one-LED scene's, 0.5 kB),
``blackbox`` (roi windows held armed, then one trigger writes what is held: the dump's rate).

    .venv/bin/python benchmarks/bench_record.py [--quick] [--dir DIR] [--modes full roi ...]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from iscd.recording import pairfile
from iscd.recording.pairfile import record_size
from iscd.recording.recorder import MiB, Recorder, RecordSettings

H = W = 512
FPS = 1000.0
CHUNK = 8 * MiB
WINDOWS = {"full": None, "roi": ((211, 211, 301, 301), (182, 211, 272, 301)),
           "roi-1led": ((249, 249, 264, 264), (179, 249, 194, 264)),
           "blackbox": ((211, 211, 301, 301), (182, 211, 272, 301))}
PAIRS = {"full": (1000, 200), "roi": (20000, 2000), "roi-1led": (40000, 4000), "blackbox": (20000, 2000)}
"""Pairs per mode (full run, --quick)."""


class _NoSync:
    """``os`` for the file writer without fsync (--no-fsync)."""

    def __getattr__(self, name: str) -> object:
        return (lambda fd: None) if name == "fsync" else getattr(os, name)


_NoSync = _NoSync()  # type: ignore[misc,assignment]


def raw_write(folder: Path, nbytes: int, sync: bool = True) -> float:
    """MB/s (1e6 bytes/s) of ``nbytes`` written with os.write in 8 MiB chunks (then fsync'ed
    with ``sync``)."""
    buf = memoryview(np.random.default_rng(1).integers(0, 256, CHUNK, dtype=np.uint8).tobytes())
    path = folder / "raw.bin"
    t = time.perf_counter()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        left = nbytes
        while left > 0:
            left -= os.write(fd, buf[:min(left, CHUNK)])
        if sync:
            os.fsync(fd)
    finally:
        os.close(fd)
    dt = time.perf_counter() - t
    path.unlink()
    return nbytes / dt / 1e6


def record(folder: Path, mode: str, n: int, sync: bool = True) -> dict[str, float]:
    """Offer n pairs to a recorder in ``mode``; pairs/s, MB/s and the offer cost."""
    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, (H, W), dtype=np.uint8)
    right = rng.integers(0, 256, (H, W), dtype=np.uint8)
    windows = WINDOWS[mode]
    blackbox = mode == "blackbox"
    st = replace(RecordSettings(), dir=str(folder), mode="blackbox" if blackbox else ("full" if windows is None else "roi"),
                 fsync_s=0.0, rotate_mb=4096.0, queue_mb=512.0 if blackbox else 256.0, pre_s=n / FPS + 1, post_s=0.0)
    run = folder / f"run-{mode}"
    rec = Recorder(run, st, width=W, height=H, dtype=np.uint8, fps=FPS)
    if not sync:
        pairfile.os = _NoSync  # type: ignore[attr-defined]
    offer_s = 0.0
    t0 = time.perf_counter()
    for i in range(n):
        while True:
            t = time.perf_counter()
            ok = rec.offer(i, i * 1_000_000, i * 1_000_000, i // 16, left, right, windows)
            if ok:
                offer_s += time.perf_counter() - t
                break
            time.sleep(50e-6)  # the spool is full: the writer sets the pace
    if blackbox:  # what is held goes out on a trigger: time the dump alone
        t0 = time.perf_counter()
        rec.trigger("bench")
        rec.offer(n, n * 1_000_000, n * 1_000_000, n // 16, left, right, windows)
    try:
        rec.close()
    finally:
        pairfile.os = os  # type: ignore[attr-defined]
    dt = time.perf_counter() - t0
    c = rec.counters()
    written = int(c["record_written"])
    nbytes = rec.bytes_written
    shutil.rmtree(run, ignore_errors=True)
    return {"pairs": written, "pair_bytes": nbytes / max(written, 1), "pairs_per_s": written / dt,
            "mb_per_s": nbytes / dt / 1e6, "offer_us": offer_s / n * 1e6, "bytes": nbytes}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer pairs, one repetition (a few seconds)")
    ap.add_argument("--dir", help="folder to write in (default: a temporary folder under $TMPDIR)")
    ap.add_argument("--modes", nargs="*", choices=list(WINDOWS), default=list(WINDOWS))
    ap.add_argument("--reps", type=int, default=None, help="alternating repetitions (default 3, quick 1)")
    ap.add_argument("--no-fsync", action="store_true", help="to the page cache only (no fsync at the end)")
    args = ap.parse_args(argv)
    reps = args.reps or (1 if args.quick else 3)
    sync = not args.no_fsync
    root = Path(tempfile.mkdtemp(prefix="iscd-bench-record-", dir=args.dir))
    try:
        print(f"writing into {root} ({'fsync at the end' if sync else 'page cache, no fsync'}), {reps} "
              f"repetition(s); load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
        print(f"{'mode':9} {'B/pair':>8} {'pairs':>6} {'pairs/s':>9} {'x 1000fps':>9} {'MB/s':>7} "
              f"{'raw MB/s':>8} {'x raw':>6} {'offer us':>8}")
        for mode in args.modes:
            n = PAIRS[mode][1 if args.quick else 0]
            expect = n * record_size(*(WINDOWS[mode] or ((0, 0, W, H),) * 2), 1)
            runs, raws = [], []
            for _ in range(reps):
                raws.append(raw_write(root, expect, sync))
                runs.append(record(root, mode, n, sync))
            med = lambda k: float(np.median([r[k] for r in runs]))  # noqa: E731
            raw = float(np.median(raws))
            ratio = float(np.median([r["mb_per_s"] / b for r, b in zip(runs, raws)]))
            print(f"{mode:9} {runs[0]['pair_bytes']:8.0f} {runs[0]['pairs']:6d} {med('pairs_per_s'):9.0f} "
                  f"{med('pairs_per_s') / FPS:9.2f} {med('mb_per_s'):7.1f} {raw:8.1f} {ratio:6.2f} "
                  f"{med('offer_us'):8.1f}", flush=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
