"""Benchmark: the whole daemon on the embedded default (mock rig), as a user runs it.

    python -m benchmarks.bench_daemon [--duration S] [--hog] [--quick] [--config FILE]

Runs ``iscd run --duration S --out TMP.jsonl`` as a child process and reports, from the
daemon's own final stats record: frames dropped, CRC-valid packets, p50/p99 latency; and
from the operating system: the CPU of the daemon and all its processes together
(acquisition, demodulation worker, resource tracker: user + system time of every waited-for
descendant, ``getrusage(RUSAGE_CHILDREN)``) over the run's wall time, in cores. ``--hog``
runs a busy loop holding one core beside it the whole time (the test car's computer runs
other software too). The targets of issue 11 are printed beside each figure.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path


def _hog(stop: "multiprocessing.synchronize.Event") -> None:  # pragma: no cover - a busy loop
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


def run(duration_s: float, hog: bool = False, config: str | None = None) -> dict:
    """One daemon run; returns its final stats record plus ``cpu_cores_tree`` and ``wall_s``."""
    out = Path(tempfile.mkdtemp(prefix="iscd-bench-")) / "run.jsonl"
    exe = Path(sys.executable).with_name("iscd")
    cmd = [str(exe) if exe.exists() else sys.executable, *([] if exe.exists() else ["-m", "iscd"]),
           "run", "--duration", str(duration_s), "--out", str(out)]
    if config:
        cmd += ["--config", config]
    stop = multiprocessing.Event()
    hogger = multiprocessing.Process(target=_hog, args=(stop,), daemon=True) if hog else None
    if hogger:
        hogger.start()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.monotonic() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if hogger:
        stop.set()
        hogger.join(5)
        hogger.kill()
    if proc.returncode != 0:
        raise SystemExit(f"bench_daemon: iscd run failed (exit {proc.returncode}): {proc.stderr.strip()[-500:]}")
    recs = [json.loads(x) for x in out.read_text().splitlines() if x.strip()]
    final = [r for r in recs if r.get("type") == "stats"][-1]
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    # latency of the steady state: the per-second stats after the first 3 s (the first
    # ones hold the start-up: detection; the final one the drain at the end)
    steady = [r for r in recs if r.get("type") == "stats" and not r.get("final") and r.get("uptime_s", 0) >= 3.0
              and r.get("latency_ms_p99") is not None]
    p99 = sorted(r["latency_ms_p99"] for r in steady)
    final["steady_p99_median_ms"] = p99[len(p99) // 2] if p99 else None
    final["steady_p99_max_ms"] = p99[-1] if p99 else None
    # each process's CPU share in the steady seconds (the daemon's own per-second meter)
    per: dict[str, float] = {}
    for name in ("frame_loop", "acquisition", "demod_worker"):
        v = sorted(x for r in steady if (x := (r.get("cpu_cores_by_process") or {}).get(name)) is not None)
        if v:
            per[name] = v[len(v) // 2]
    final["steady_cores_by_process"] = per
    final["steady_cores"] = (sorted(r["cpu_cores"] for r in steady)[len(steady) // 2]
                             if steady and all(r.get("cpu_cores") is not None for r in steady) else None)
    final["cpu_cores_tree"] = cpu / wall
    final["wall_s"] = wall
    final["packets_seen"] = sum(1 for r in recs if r.get("type") == "packet")
    return final


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=40.0, help="seconds of decoding (default 40)")
    ap.add_argument("--hog", action="store_true", help="a busy loop holds one core beside the daemon")
    ap.add_argument("--config", help="a config file (default: the embedded default)")
    ap.add_argument("--quick", action="store_true", help="a short run (6 s) to check that it works")
    a = ap.parse_args(argv)
    d = 6.0 if a.quick else a.duration
    r = run(d, a.hog, a.config)
    beside = " beside a busy loop holding one core" if a.hog else ""
    print(f"iscd run --duration {d:g}{beside}: {r['pairs_decoded']} pairs decoded, "
          f"frames dropped {r['frames_dropped']} (target 0), ring dropped {r['ring_dropped']}, "
          f"packets ok {r['packets_ok']} bad {r['packets_bad']} (target >= {int(27 * d / 40)} in {d:g} s), "
          f"latency p99 per second after 3 s: median {r['steady_p99_median_ms']} ms, worst "
          f"{r['steady_p99_max_ms']} ms (target p99 <= 20); over every pair of the run: p99 "
          f"{r.get('latency_run_ms_p99')} ms, max {r.get('latency_run_ms_max')} ms; "
          f"overload max level {r.get('overload_max_level')}")
    print(f"  CPU of the daemon and all its processes: {r['cpu_cores_tree']:.3f} cores over {r['wall_s']:.1f} s "
          f"wall, start-up and shutdown included (target <= 1.0); machine load before: "
          f"{os.getloadavg()[0]:.2f}")
    per = ", ".join(f"{k} {v:.3f}" for k, v in r["steady_cores_by_process"].items())
    print(f"  steady seconds (after 3 s), median per second: all {r['steady_cores']} cores; {per}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
