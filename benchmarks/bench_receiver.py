"""Receiver throughput: frames demodulated per second, as a ratio to the 1000 frames/s rig.

Input: synthetic luminance (``iscd.receiver.synth``) of an 8x8 array sending PWM-16 with
100 ppm clock drift, seen by an f/4 (saturating) and an f/8 camera, pushed into a
:class:`~iscd.receiver.packets.PacketAssembler` in blocks of 100 frame pairs, as the
daemon does. Cases:

- ``iscd``: the default rule (header search, drift tracking, per-LED channel, straddling
  frames, decision-directed channel, both cameras);
- ``dissertation``: the dissertation's rule (same timing, pooled channel factors 3.11,
  clean-frame Euclidean decision 3.12);
- ``search``: no transmitter in view (noise), frames pushed 10 at a time: the cost of
  searching for headers while unlocked;
- ``roi_mean``: luminance extraction (3.10) of the 64 LEDs (3x3 ROI) in both 512x512 frames;
- ``follow+gauss``: what the pipeline does instead, per stereo pair: each frame's LED
  positions refined (shift and scale from 16 spot centroids) and the Gaussian-weighted
  luminance (``follow_and_measure``), in blocks of 16 pairs;
- ``spot``: the crosstalk/saturation-aware luminance (``SpotLuminance``, fitted once).

Each line prints frames/s, the ratio to 1000 frames/s (>= 1 keeps up on one core) and the
time per frame as a multiple of a baseline measured in the same process: the bare
clean-frame decision of the same frames with the clock and centroids given (one
vectorized distance + argmin per frame: the floor of any demodulator). BLAS is limited
to one thread, as in the daemon.

    .venv/bin/python benchmarks/bench_receiver.py [--quick] [--packets N]
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

from iscd.airinterface import AirInterface  # noqa: E402
from iscd.config import TransmitterConfig  # noqa: E402
from iscd.receiver.luminance import SpotLuminance, follow_and_measure, grid_sample, roi_mean  # noqa: E402
from iscd.receiver.packets import PacketAssembler  # noqa: E402
from iscd.receiver.settings import ReceiverConfig  # noqa: E402
from iscd.receiver.synth import SynthCamera, render_spots, synth_recording  # noqa: E402

RIG_FPS = 1000.0
BLOCK = 100


def best_time(fn: Callable[[], object], repeats: int) -> float:
    """Best (minimum) seconds of ``repeats`` calls after a warm-up call."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench(n_packets: int, repeats: int, n_image_frames: int) -> list[tuple[str, float, float]]:
    """[(case, frames/s, seconds per frame / baseline seconds per frame)]."""
    tx = TransmitterConfig(rows=8, cols=8, levels=16)
    air = AirInterface.from_config(tx)
    cams = [SynthCamera(peak_dn=500, led_gain_spread=0.05, read_noise_dn=2),
            SynthCamera(peak_dn=125, led_gain_spread=0.05, read_noise_dn=2)]
    rec = synth_recording(air, cams, n_packets=n_packets, drift_ppm=100.0, seed=1)
    n = rec.t_s.size
    ids = np.arange(n)

    def run(cfg: ReceiverConfig) -> Callable[[], int]:
        def go() -> int:
            asm = PacketAssembler(tx, rec.fps, rec.exposure_s, cfg)
            got = 0
            for a in range(0, n, BLOCK):
                got += len(asm.push(ids[a:a + BLOCK], rec.t_s[a:a + BLOCK],
                                    rec.L[0, a:a + BLOCK], rec.L[1, a:a + BLOCK]))
            if got != n_packets:
                raise RuntimeError(f"decoded {got} of {n_packets} packets")
            return got
        return go

    # baseline: clean frames at the true clock, true per-level centroids, argmin distance
    q = np.rint(rec.x * 15).astype(int)
    mu = np.stack([np.array([rec.L[c][q == s].mean() for s in range(16)]) for c in range(2)])
    clean = np.isclose(rec.x * 15, np.rint(rec.x * 15), atol=1e-6)  # frames inside a symbol

    def baseline() -> np.ndarray:
        Lc = rec.L[:, clean.all(1), :]
        return ((Lc[..., None] - mu[:, None, None, :]) ** 2).sum(0).argmin(-1)

    t_base = best_time(baseline, 10 * repeats) / n  # short: more repeats for a stable best
    rows = []
    for name, cfg in (("iscd", ReceiverConfig()), ("dissertation", ReceiverConfig(rule="dissertation"))):
        t = best_time(run(cfg), repeats) / n
        rows.append((name, 1.0 / t, t / t_base))

    noise = 20 + np.random.default_rng(2).normal(0, 1, rec.L.shape)

    def search() -> None:
        asm = PacketAssembler(tx, rec.fps, rec.exposure_s)
        for a in range(0, n, 10):
            asm.push(ids[a:a + 10], rec.t_s[a:a + 10], noise[0, a:a + 10], noise[1, a:a + 10])

    t = best_time(search, repeats) / n
    rows.append(("search", 1.0 / t, t / t_base))

    # luminance extraction on 512x512 frames
    g = np.arange(8)
    centres = np.stack(np.meshgrid(g * 4.2 + 230.3, g * 4.2 + 240.6), -1).reshape(-1, 2)
    frames = np.zeros((n_image_frames, 512, 512), np.uint8)
    frames[:, 220:290, 220:290] = render_spots(rec.x[:n_image_frames], centres - 220, (70, 70),
                                               peak_dn=600, sigma_px=0.9)
    t = best_time(lambda: roi_mean(frames, centres, 3), repeats) / n_image_frames / 2  # per camera
    rows.append(("roi_mean", 1.0 / (2 * t), 2 * t / t_base))
    use = grid_sample(8, 8)

    def follow() -> None:  # as the pipeline: blocks of 16 pairs, both cameras in one pass
        for a in range(0, n_image_frames, 16):
            follow_and_measure([frames[a:a + 16], frames[a:a + 16]], [centres, centres], 3, [0.9, 0.9], use)

    t = best_time(follow, repeats) / n_image_frames
    rows.append(("follow+gauss", 1.0 / t, t / t_base))
    spot = SpotLuminance(centres, 3).fit(frames[: min(300, n_image_frames)])
    t = best_time(lambda: spot(frames), repeats) / n_image_frames
    rows.append(("spot", 1.0 / (2 * t), 2 * t / t_base))
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="one packet, one repeat (a smoke test)")
    ap.add_argument("--packets", type=int, default=3, help="packets per run (default 3)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per case, best kept")
    args = ap.parse_args(argv)
    n_packets, repeats, n_img = (1, 1, 100) if args.quick else (args.packets, args.repeats, 500)
    print(f"receiver, 8x8 LEDs, PWM-16, f/4 + f/8, {n_packets} packet(s) of "
          f"{AirInterface(levels=16).packet_symbols} symbols, 2 frames/symbol")
    print(f"{'case':<14}{'frames/s':>12}{'x 1000 fps':>12}{'x baseline':>12}")
    for name, fps, rel in bench(n_packets, repeats, n_img):
        print(f"{name:<14}{fps:>12.0f}{fps / RIG_FPS:>12.2f}{rel:>12.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
