"""The whole test suite N times in a row while a busy loop holds one core (issue 13: the
suite must not depend on having the machine to itself).

    python -m benchmarks.suite_beside_busy_loop [--runs 3] [-- PYTEST_ARGS...]

Starts a process spinning on one core, runs ``python -m pytest -q -p no:cacheprovider`` (plus
PYTEST_ARGS) ``--runs`` times one after another, prints each run's closing line and wall time,
stops the busy loop, and exits 1 if any run failed. Takes ~6 minutes a run on 2 cores.
"""

from __future__ import annotations

import argparse
import multiprocessing
import subprocess
import sys
import time
from collections.abc import Sequence

from benchmarks.bench_daemon import _hog


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="runs of the suite in a row (default 3)")
    ap.add_argument("pytest_args", nargs="*", help="passed on to pytest (after --)")
    a = ap.parse_args(argv)
    stop = multiprocessing.Event()
    hog = multiprocessing.Process(target=_hog, args=(stop,), daemon=True)
    hog.start()
    failed = 0
    try:
        for i in range(1, a.runs + 1):
            t0 = time.monotonic()
            p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *a.pytest_args],
                               capture_output=True, text=True)
            last = (p.stdout.strip().splitlines() or [""])[-1]
            print(f"run {i}: exit {p.returncode}, {time.monotonic() - t0:.0f} s: {last}", flush=True)
            failed += p.returncode != 0
    finally:
        stop.set()
        hog.join(5)
        if hog.is_alive():
            hog.kill()
    print(f"{a.runs - failed} of {a.runs} runs green beside a busy loop holding one core")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
