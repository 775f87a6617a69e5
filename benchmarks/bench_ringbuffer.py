"""Benchmark: stereo pairs per second through the shared-memory ring, across processes.

A producer process writes 512x512 uint8 pairs into a :class:`iscd.rig.ringbuffer.StereoRing`
as fast as the queue has room; this process reads them (zero-copy, and with a copy out).
Printed as ratios to the 1000 pairs/s the 1000 fps rig needs and to a baseline measured in
the same run: a plain in-process numpy copy of the same bytes (two 512x512 uint8 images
per pair). A paced run at 1000 pairs/s reports the producer-to-consumer latency.

    .venv/bin/python benchmarks/bench_ringbuffer.py [--quick] [--pairs N]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
from collections.abc import Sequence

import numpy as np

from iscd.rig.ringbuffer import StereoRing

H = W = 512
TARGET = 1000.0  # pairs/s: the rig's 1000 fps


def _images() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    return (rng.integers(0, 256, (H, W), dtype=np.uint8),
            rng.integers(0, 256, (H, W), dtype=np.uint8))


def _producer(ring: StereoRing, n: int, fps: float) -> None:
    """Spawned: write n pairs; with fps > 0 paced at that rate, else as fast as the queue
    has room (no pair dropped)."""
    left, right = _images()
    t0 = time.monotonic()
    for i in range(n):
        if fps > 0:
            wait = t0 + i / fps - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        else:
            while ring.queued >= ring.capacity:
                time.sleep(20e-6)
        slot = ring.reserve()
        slot.left[...] = left
        slot.right[...] = right
        ring.commit(slot, frame_id=i)
    ring.finish()


def baseline_copy(n: int) -> float:
    """Pairs/s of a plain in-process numpy copy of the same bytes."""
    left, right = _images()
    dst_l, dst_r = np.empty_like(left), np.empty_like(right)
    t = time.perf_counter()
    for _ in range(n):
        np.copyto(dst_l, left)
        np.copyto(dst_r, right)
    return n / (time.perf_counter() - t)


def through_ring(n: int, *, copy_out: bool, fps: float = 0.0, capacity: int = 32,
                 ) -> tuple[float, np.ndarray, int]:
    """(pairs/s, latencies in µs, dropped) of n pairs from a producer process."""
    ctx = mp.get_context("spawn")
    with StereoRing.create(height=H, width=W, capacity=capacity) as ring:
        proc = ctx.Process(target=_producer, args=(ring, n, fps))
        proc.start()
        lat = np.empty(n, dtype=np.int64)
        got = 0
        t_first = t_last = 0.0
        out = (np.empty((H, W), np.uint8), np.empty((H, W), np.uint8))
        try:
            while True:
                p = ring.read(timeout_s=30.0)
                if p is None:
                    break
                now = time.monotonic_ns()
                if got == 0:
                    t_first = time.perf_counter()
                lat[got] = now - p.commit_ns
                if copy_out:
                    p.copy(out)
                else:
                    int(p.left[0, 0]) + int(p.right[-1, -1])  # touch the slot
                p.release()
                got += 1
                t_last = time.perf_counter()
        finally:
            proc.join(60)
        dropped = ring.stats().dropped_overflow
    rate = (got - 1) / (t_last - t_first) if got > 1 else float("nan")
    return rate, lat[:got] / 1e3, dropped


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer pairs (a few seconds)")
    ap.add_argument("--pairs", type=int, default=None,
                    help="pairs per run (default 4000, quick 600)")
    args = ap.parse_args(argv)
    n = args.pairs or (600 if args.quick else 4000)
    paced_n = 300 if args.quick else 2000
    mb = 2 * H * W / 1e6

    base = baseline_copy(n)
    zc, _, d0 = through_ring(n, copy_out=False)
    cp, _, d1 = through_ring(n, copy_out=True)
    _, lat, d2 = through_ring(paced_n, copy_out=False, fps=TARGET, capacity=100)

    print(f"pairs of 2 x {H}x{W} uint8 ({mb:.2f} MB/pair), {n} pairs per run")
    print(f"baseline  in-process numpy copy:        {base:9.0f} pairs/s  "
          f"{base / TARGET:6.2f}x target")
    for label, rate, dropped in (("ring -> other process, zero-copy read", zc, d0),
                                 ("ring -> other process, copy out    ", cp, d1)):
        print(f"{label}: {rate:9.0f} pairs/s  {rate / TARGET:6.2f}x target  "
              f"{rate / base:5.2f}x baseline  (dropped {dropped})")
    print(f"paced {TARGET:.0f} pairs/s, {paced_n} pairs: commit->read latency p50 "
          f"{np.percentile(lat, 50):.0f} us, p99 {np.percentile(lat, 99):.0f} us, "
          f"max {lat.max():.0f} us, dropped {d2}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
