"""Ranging throughput: range estimates per second, as a ratio to the 1000 frames/s rig.

Cases (rendered, saturating LED spots with realistic noise):
- ``1 LED``: one 16x16 patch pair per call (a single traffic light, one frame);
- ``8x8 per LED``: 64 12x12 patch pairs in one batched call (per-LED ranges of an array
  in one frame, the patch size, window and search limit StereoRanger uses there);
- ``8x8 whole``: one 40x40 patch pair per call (the whole array in one estimate).

Each line prints estimates/s, frames/s (calls/s: one call covers one frame) and its ratio
to 1000 frames/s (>= 1 keeps up on one core), and the time per call as a multiple of a
baseline measured in the same process: one ``np.fft.fft2`` of the same batch of patches.

Then the live ranger (:class:`iscd.decode.ranging.stereo.StereoRanger`, what the pipeline runs every
frame) on rendered frames in blocks of 16 pairs, as the daemon calls it: the embedded default
scene (8x8 array at 30 m, HDR f/4 + f/8) and one LED at 40 m. Per method: microseconds per
frame (the issue's budget: <= ~100 us so that the whole decode loop reaches 3x the 1000 fps
rate), frames/s and the speed-up over the 2-D ``iscd`` method measured in the same run.
BLAS is limited to one thread (set before numpy is imported), as in the daemon: the small
batched products only lose time to thread hand-offs.

    .venv/bin/python benchmarks/bench_ranging.py [--quick] [--methods iscd,dissertation,...] [--no-live]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Sequence

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from iscd.decode.ranging.estimators import METHODS, get_estimator  # noqa: E402
from iscd.decode.ranging.synth import disk_spots, sensor  # noqa: E402

TARGET_PER_S = 1000.0
"""frames per second of the rig"""
ARRAY_PITCH_PX = 4.2


def best_time(fn: Callable[[], object], min_total_s: float, repeats: int) -> float:
    """Best (minimum) seconds per call over ``repeats`` rounds of at least ``min_total_s``."""
    fn()                                            # warm-up (caches, imports)
    best = float("inf")
    for _ in range(repeats):
        n, t0 = 0, time.perf_counter()
        while True:
            fn()
            n += 1
            dt = time.perf_counter() - t0
            if dt >= min_total_s:
                break
        best = min(best, dt / n)
    return best


def make_pairs(n: int, size: int, rng: np.random.Generator, spots: int = 1) -> tuple[np.ndarray, np.ndarray]:
    if spots == 1:
        cx = size / 2 - 0.5 + rng.uniform(-0.5, 0.5, n)
        d = rng.uniform(-1, 1, n)
        left = disk_spots(n, (size, size), cx + d / 2, size / 2 - 0.3, 1.2, peak=500)
        right = disk_spots(n, (size, size), cx - d / 2, size / 2 - 0.3, 1.2, peak=500)
    else:                                            # an 8x8 array, 4.2 px pitch
        g = (np.arange(8) - 3.5) * 4.2
        gx, gy = np.meshgrid(g, g)
        cx = (size / 2 - 0.5 + gx.ravel())[None, :].repeat(n, 0)
        cy = (size / 2 - 0.5 + gy.ravel())[None, :].repeat(n, 0)
        left = disk_spots(n, (size, size), cx + 0.3, cy, 0.6, peak=400)
        right = disk_spots(n, (size, size), cx - 0.3, cy, 0.6, peak=400)
    return sensor(left, rng, 40, 0.26, 78), sensor(right, rng, 40, 0.26, 78)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short timing rounds (a smoke run, noisier numbers)")
    ap.add_argument("--methods", default="iscd-fast,iscd,dissertation,poc,cv2,skimage,centroid",
                    help="comma-separated estimators to time (default: the project's and all peers)")
    ap.add_argument("--no-live", action="store_true", help="skip the live-ranger section (rendered frames)")
    args = ap.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for m in methods:
        if m not in METHODS:
            ap.error(f"unknown method {m!r} (known: {', '.join(METHODS)})")
    min_total, repeats = (0.05, 2) if args.quick else (0.4, 5)
    rng = np.random.default_rng(0)
    cases = [("1 LED", *make_pairs(1, 16, rng), 1, {}),
             ("8x8 per LED", *make_pairs(64, 12, rng), 64,
              {"iscd": {"window_sigma_px": 0.7 * ARRAY_PITCH_PX, "window_rounds": 1,
                        "max_shift_px": ARRAY_PITCH_PX / 2}}),
             ("8x8 whole", *make_pairs(1, 40, rng, spots=64), 1, {"iscd": {"max_shift_px": ARRAY_PITCH_PX / 2},
                                                                  "iscd-fast": {"max_shift_px": ARRAY_PITCH_PX / 2}})]
    print(f"ranging throughput; target {TARGET_PER_S:.0f} frames/s (ratio >= 1 keeps up on one core); "
          f"x fft2 = time per call / one np.fft.fft2 of the same batch")
    print(f"{'case':<12} {'method':<14} {'estimates/s':>12} {'frames/s':>9} {'ratio':>7} {'us/call':>10} {'x fft2':>8}")
    for name, left, right, per_call, opts in cases:
        t_fft = best_time(lambda: np.fft.fft2(left), min_total, repeats)
        for m in methods:
            est = get_estimator(m, **opts.get(m, {}))
            t = best_time(lambda: est.estimate(left, right), min_total, repeats)
            print(f"{name:<12} {m:<14} {per_call / t:12.0f} {1 / t:9.0f} {1 / t / TARGET_PER_S:7.2f} "
                  f"{t * 1e6:10.1f} {t / t_fft:8.1f}")
    if not args.no_live:
        live(min_total, repeats, 96 if args.quick else 320)
    return 0


LIVE_BLOCK = 16
"""pairs per call, the daemon's block"""


def live(min_total: float, repeats: int, frames: int) -> None:
    """Time :class:`iscd.decode.ranging.stereo.StereoRanger` on rendered frames (module docstring)."""
    from iscd.calibration.io import StereoCalibration
    from iscd.core.config import default_config
    from iscd.decode.tracking.detect import detect_array
    from iscd.sim.presets import single_led
    from iscd.sim.scene import Scene
    from iscd.decode.ranging.stereo import RangingSettings, StereoRanger

    print(f"\nlive ranger (StereoRanger.measure, blocks of {LIVE_BLOCK} pairs, running background)")
    print(f"{'scene':<26} {'method':<10} {'us/frame':>9} {'frames/s':>9} {'ratio':>7} {'x iscd':>7}")
    for name, cfg in (("8x8 array 30 m (default)", default_config()),
                      ("1 LED 40 m", single_led(default_config(), 40.0))):
        scene = Scene(cfg)
        L = np.empty((frames, scene.height, scene.width), np.uint8)
        R = np.empty_like(L)
        for i in range(frames):
            scene.render_pair_into(i, L[i], R[i])
        rows, cols = cfg.transmitter.rows, cfg.transmitter.cols
        fl, fr = detect_array(L[:64], rows, cols), detect_array(R[:64], rows, cols)
        if fl is None or fr is None:
            raise SystemExit(f"bench: the transmitter of {name!r} was not detected")
        cal = StereoCalibration.ideal(cfg.camera)
        times = {}
        for m in ("iscd", "iscd-fast"):
            rg = StereoRanger(cal, RangingSettings(method=m))

            def run() -> None:
                for a in range(0, frames, LIVE_BLOCK):
                    rg.measure(L[a:a + LIVE_BLOCK], R[a:a + LIVE_BLOCK], fl, fr)

            times[m] = best_time(run, min_total, repeats) / frames
        for m in ("iscd-fast", "iscd"):
            t = times[m]
            print(f"{name:<26} {m:<10} {t * 1e6:9.1f} {1 / t:9.0f} {1 / t / TARGET_PER_S:7.2f} {times['iscd'] / t:7.1f}")


if __name__ == "__main__":
    sys.exit(main())
