"""Receiver throughput: frames demodulated per second, as a ratio to the 1000 frames/s rig.

Input: synthetic luminance (``iscd.decode.comms.synth``) of an 8x8 array sending PWM-16 with
100 ppm clock drift, seen by an f/4 (saturating) and an f/8 camera, pushed into a
:class:`~iscd.decode.comms.packets.PacketAssembler` in blocks of 100 frame pairs, as the
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

``--assembler [SCENE]`` instead times the packet assembler alone on a rendered scene
(default: the daemon's 8x8 PWM-8 HDR scene at 30 m; pwm16: PWM-16 at 50 m; single: one
LED at 40 m): the frames are rendered once (:mod:`iscd.sim`), their luminance extracted by
the pipeline (:class:`iscd.decode.stream.StreamDecoder`, whose pushes to the assembler are
recorded), then only :meth:`PacketAssembler.push` is timed on that luminance in the
daemon's blocks of 16 pairs: seconds per packet (the blocks that complete one), per block
that completes none, and the assembler's share of a 1000 fps core; the baseline is the
bare clean-frame decision of a packet's frames (as below), measured in the same process.

Each line prints frames/s, the ratio to 1000 frames/s (>= 1 keeps up on one core) and the
time per frame as a multiple of a baseline measured in the same process: the bare
clean-frame decision of the same frames with the clock and centroids given (one
vectorized distance + argmin per frame: the floor of any demodulator). BLAS is limited
to one thread, as in the daemon.

    .venv/bin/python benchmarks/bench_receiver.py [--quick] [--packets N]
    .venv/bin/python -m benchmarks.bench_receiver --assembler [default|pwm16|single] [--repeats R]
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

from iscd.core.airinterface import AirInterface  # noqa: E402
from iscd.core.config import TransmitterConfig  # noqa: E402
from iscd.decode.tracking.luminance import SpotLuminance, follow_and_measure, grid_sample, roi_mean  # noqa: E402
from iscd.decode.comms.packets import PacketAssembler  # noqa: E402
from iscd.decode.comms.settings import ReceiverConfig  # noqa: E402
from iscd.decode.comms.synth import SynthCamera, render_spots, synth_recording  # noqa: E402

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


def _captured_luminance(scene: str, packets: int) -> tuple[list[tuple], object]:
    """Render ``packets`` packets of ``scene``, run the pipeline on them and return the
    luminance blocks it pushed into its packet assembler, and the assembler's arguments."""
    from iscd.core.airinterface import AirInterface as Air
    from iscd.core.config import default_config
    from iscd.eval.sweeps import frames_for_packets
    from iscd.decode.stream import StreamDecoder
    from iscd.sim.presets import override, single_led
    from iscd.sim.scene import Scene

    cfg = default_config()
    if scene == "pwm16":
        cfg = override(cfg, transmitter={"levels": 16}, scene={"distance_m": 50.0})
    elif scene == "single":
        cfg = single_led(cfg, 40.0)
    sc = Scene(cfg)
    n = frames_for_packets(sc, Air.from_config(cfg.transmitter), packets)
    pushes: list[tuple] = []
    made: list[tuple] = []
    orig = PacketAssembler.push

    def spy(self: PacketAssembler, *a: object) -> list:
        if not made:
            made.append((self.tx, self.fps, self.e / self.fps, self.cfg))
        pushes.append(tuple(np.array(x) if x is not None else None for x in a))
        return orig(self, *a)

    PacketAssembler.push = spy  # type: ignore[method-assign]
    try:
        dec = StreamDecoder(cfg)
        Lb = np.empty((16, sc.height, sc.width), np.uint8)
        Rb = np.empty_like(Lb)
        for s0 in range(0, n, 16):
            ids = np.arange(s0, min(n, s0 + 16))
            for i, k in enumerate(ids):
                sc.render_pair_into(int(k), Lb[i], Rb[i])
            dec.push(ids, ids / sc.fps, Lb[:ids.size], Rb[:ids.size])
        dec.finish()
    finally:
        PacketAssembler.push = orig  # type: ignore[method-assign]
    return pushes, made[0]


def bench_assembler(scene: str, packets: int, repeats: int) -> dict[str, float]:
    """Seconds per packet and per packet-less block of :meth:`PacketAssembler.push` on the
    captured luminance of ``scene`` (best of ``repeats`` runs), and the baseline."""
    from iscd.core.jit import warm_up

    pushes, (tx, fps, exposure_s, cfg) = _captured_luminance(scene, packets)
    warm_up()
    best_pkt, best_blk, n_pkt = float("inf"), float("inf"), 0
    for _ in range(repeats + 1):  # the first run also compiles what warm_up did not
        asm = PacketAssembler(tx, fps, exposure_s, cfg)
        t_pkt, t_blk, n_blk, n_pkt = 0.0, 0.0, 0, 0
        for args in pushes:
            t0 = time.perf_counter()
            got = asm.push(*args)
            dt = time.perf_counter() - t0
            if got:
                t_pkt += dt
                n_pkt += len(got)
            else:
                t_blk += dt
                n_blk += 1
        if n_pkt:
            best_pkt = min(best_pkt, t_pkt / n_pkt)
        best_blk = min(best_blk, t_blk / max(n_blk, 1))
    # baseline: the bare clean-frame decision of one packet's frames (both cameras, given
    # centroids: one vectorized distance + argmin), as in the throughput cases above
    L = np.stack([np.concatenate([a[2] for a in pushes]), np.concatenate([a[3] for a in pushes])])
    n_fr = int(np.ceil(asm.packet_frames))
    Lp = L[:, :n_fr]
    mu = np.nanpercentile(Lp, np.linspace(2, 98, tx.levels), axis=1).transpose(1, 2, 0)  # (C, N, M)
    t_base = best_time(lambda: np.nansum((Lp[..., None] - mu[:, None]) ** 2, axis=0).argmin(-1),
                       10 * repeats)
    period_s = asm.period_frames / fps
    return {"packet_s": best_pkt, "block_s": best_blk, "packets": n_pkt, "baseline_s": t_base,
            "core_share": (best_pkt + best_blk * (asm.period_frames / 16 - 1)) / period_s}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="one packet, one repeat (a smoke test)")
    ap.add_argument("--packets", type=int, default=3, help="packets per run (default 3)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per case, best kept")
    ap.add_argument("--assembler", nargs="?", const="default", choices=("default", "pwm16", "single"),
                    help="time the packet assembler alone on a rendered scene's luminance")
    args = ap.parse_args(argv)
    if args.assembler:
        r = bench_assembler(args.assembler, max(args.packets, 2), 1 if args.quick else args.repeats)
        print(f"packet assembler, scene {args.assembler}: {r['packets']} packets; "
              f"{r['packet_s'] * 1e3:.1f} ms per packet ({r['packet_s'] / r['baseline_s']:.0f} x baseline), "
              f"{r['block_s'] * 1e6:.0f} us per 16-pair block without a packet "
              f"({r['block_s'] / r['baseline_s']:.2f} x baseline); {r['core_share']:.3f} of a core at 1000 fps; "
              f"baseline (clean-frame argmin of a packet) {r['baseline_s'] * 1e3:.2f} ms")
        return 0
    n_packets, repeats, n_img = (1, 1, 100) if args.quick else (args.packets, args.repeats, 500)
    print(f"receiver, 8x8 LEDs, PWM-16, f/4 + f/8, {n_packets} packet(s) of "
          f"{AirInterface(levels=16).packet_symbols} symbols, 2 frames/symbol")
    print(f"{'case':<14}{'frames/s':>12}{'x 1000 fps':>12}{'x baseline':>12}")
    for name, fps, rel in bench(n_packets, repeats, n_img):
        print(f"{name:<14}{fps:>12.0f}{fps / RIG_FPS:>12.2f}{rel:>12.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
