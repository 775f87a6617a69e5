"""Benchmark: how fast the mock rig (pace off) delivers stereo pairs of the default scene.

    python -m benchmarks.bench_mock_rig [--pairs N] [--quick]

Prints pairs/s, the ratio to the real-time rate (camera.fps, 1000 fps: must be >= 1.0 so
that the mock can feed a real-time daemon) and ratios against two baselines measured in the
same process, so the numbers survive a noisy machine, and the cost of the mock rig at the
real-time rate in CPU cores (fps / pairs per s; must be <= 0.2: the mock rig may take at
most a fifth of a core from the daemon it feeds; also by the reading thread's CPU time,
which excludes time taken by other processes on a shared machine):
* ``memcpy``: copying two 512x512 uint8 frames per pair between page-aligned buffers (the
  floor of any frame source);
* ``naive``: rendering every pixel of both frames with fresh noise (one ``cv2.randn``
  draw and the shot-noise/quantization arithmetic per pixel, no optics at all), which is
  what the windowed renderer avoids.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

import cv2
import numpy as np


def _rate(fn, n: int) -> float:
    """Calls of ``fn`` per second of wall-clock time, over ``n`` calls after one warm-up."""
    return _rate_cpu(fn, n)[0]


def _rate_cpu(fn, n: int) -> tuple[float, float]:
    """(calls per wall-clock second, calls per second of this thread's CPU time)."""
    fn(0)  # warm up (chunk caches, first allocation)
    t, c = time.perf_counter(), time.thread_time()
    for i in range(1, n + 1):
        fn(i)
    return n / (time.perf_counter() - t), n / max(time.thread_time() - c, 1e-9)


def _page_aligned(shape: tuple[int, ...]) -> np.ndarray:
    """A uint8 array starting on a 4 kB page: np.copyto between two such arrays takes the
    fast path (glibc's copy is 10-15x slower when the destination starts 1-31 bytes after
    the source modulo 4 kB, as unaligned fresh arrays often do on this machine)."""
    n = int(np.prod(shape))
    buf = np.empty(n + 4096, np.uint8)
    off = (-buf.ctypes.data) % 4096
    return buf[off:off + n].reshape(shape)


def bench(n_pairs: int) -> dict[str, float]:
    from iscd.drivers.mock import MockRig
    from iscd.core.config import default_config
    from iscd.sim.presets import override

    cfg = override(default_config(), rig={"pace": False})
    H, W = cfg.camera.height, cfg.camera.width
    rig = MockRig(cfg)
    left, right = rig.left, rig.right
    for cam in (left, right):
        cam.open()
        cam.start()

    def mock_pair(_: int) -> None:
        a = left.read()
        b = right.read()
        assert a.frame_id == b.frame_id

    src = _page_aligned((2, H, W))
    src[...] = np.random.default_rng(0).integers(0, 256, (2, H, W), dtype=np.uint8)
    dst = _page_aligned((2, H, W))

    def memcpy_pair(_: int) -> None:
        np.copyto(dst[0], src[0])
        np.copyto(dst[1], src[1])

    sig = np.full((H, W), 40.0, np.float32)
    out = np.empty((H, W), np.uint8)
    z = np.empty((H, W), np.float32)

    def naive_pair(_: int) -> None:
        for _c in range(2):
            x = np.sqrt(sig * np.float32(0.01275) + np.float32(0.065))
            cv2.randn(z, 0.0, 1.0)  # the same generator as the simulator
            x *= z
            x += sig
            np.clip(x, 0, 255, out=x)
            out[...] = x

    r_mem = _rate(memcpy_pair, max(50, n_pairs))
    r_naive = _rate(naive_pair, max(10, n_pairs // 20))
    r_mock, r_mock_cpu = _rate_cpu(mock_pair, n_pairs)
    r = {"pairs_per_s": r_mock, "cpu_pairs_per_s": r_mock_cpu, "fps": cfg.camera.fps,
         "memcpy_pairs_per_s": r_mem, "naive_pairs_per_s": r_naive}
    if hasattr(rig, "read_pair_into") and rig.pair_capable():  # both frames into caller buffers
        bl, br = _page_aligned((H, W)), _page_aligned((H, W))
        r["pair_into_pairs_per_s"] = _rate(lambda _: rig.read_pair_into(bl, br), n_pairs)
    return r


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=5000, help="pairs to time (default 5000)")
    ap.add_argument("--quick", action="store_true", help="a short run (300 pairs), for tests")
    args = ap.parse_args(argv)
    n = 300 if args.quick else max(10, args.pairs)
    r = bench(n)
    print(f"mock rig, pace off, default 8x8 scene 512x512: {r['pairs_per_s']:.0f} pairs/s "
          f"({n} pairs)")
    print(f"ratio vs real time ({r['fps']:.0f} fps): {r['pairs_per_s'] / r['fps']:.2f}")
    print(f"baseline memcpy of 2 frames: {r['memcpy_pairs_per_s']:.0f} pairs/s; "
          f"mock / memcpy = {r['pairs_per_s'] / r['memcpy_pairs_per_s']:.3f}")
    print(f"baseline naive full-frame render: {r['naive_pairs_per_s']:.0f} pairs/s; "
          f"mock / naive = {r['pairs_per_s'] / r['naive_pairs_per_s']:.1f}")
    print(f"mock rig cost at {r['fps']:.0f} fps: {r['fps'] / r['pairs_per_s']:.3f} cores "
          f"(target <= 0.2; by CPU time of the reading thread: "
          f"{r['fps'] / r['cpu_pairs_per_s']:.3f})")
    if "pair_into_pairs_per_s" in r:
        print(f"pairs at once (read_pair_into, into reused buffers): "
              f"{r['pair_into_pairs_per_s']:.0f} pairs/s = "
              f"{r['fps'] / r['pair_into_pairs_per_s']:.3f} cores at {r['fps']:.0f} fps")
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
