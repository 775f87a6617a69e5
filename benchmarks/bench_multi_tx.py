"""Benchmark: the decode loop's cost against the number of transmitters in view (issue 15).

    python -m benchmarks.bench_multi_tx [--counts 1,2,4,8] [--frames N] [--block B] [--profile] [--quick]

Each scene has ``k`` transmitters on their own clocks: an 8x8 array at 40 m in the middle
and ``k - 1`` single LEDs at 30-60 m around it (PWM-8, packets of 40 + 100 symbols so that
every transmitter is confirmed within the warm-up), decoded by
:class:`iscd.decode.multi.MultiDecoder` (``max_transmitters = k + 1``, shapes inferred).
Frames are rendered block by block outside the clock; only the decoder's pushes are timed,
after a warm-up in which every transmitter is acquired and confirmed. Demodulation runs in
line here and its time is left out of the frame loop's figure (the daemon runs it in a
worker process). Printed per ``k``: the frame loop's pairs/s as a ratio to the 1000 fps
camera rate, the ratio to the in-process full-frame-copy baseline (copying each pair's two
frames, timed in the same loop), the cost per pair relative to ``k = 1``, and the packets.
"""

from __future__ import annotations

import argparse
import cProfile
import math
import pstats
import sys
import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np


def scene_config(k: int):  # -> Config
    """The default rig with an 8x8 at 40 m and k - 1 single LEDs around it (none overlapping)."""
    from iscd.core.config import ExtraTransmitterConfig, default_config

    cfg = default_config()
    tx = replace(cfg.transmitter, data_symbols=100)
    extras = []
    for i in range(k - 1):
        ang = 2 * math.pi * i / 7 + 0.3
        z = 30.0 + 30.0 * i / 7
        r_px = 150.0
        # lateral/vertical offsets that put the LED r_px from the image centre at its distance
        f_px = cfg.camera.focal_length_m / cfg.camera.pixel_pitch_m
        extras.append(ExtraTransmitterConfig(rows=1, cols=1, distance_m=z, lateral_m=r_px * math.cos(ang) * z / f_px,
                                             vertical_m=r_px * math.sin(ang) * z / f_px,
                                             led_drift_ppm=float(np.linspace(-100, 100, 7)[i]), seed=100 + i))
    return cfg.replace(transmitter=tx, scene=replace(cfg.scene, distance_m=40.0, transmitters=extras,
                                                       distractors=[]))


def bench(k: int, n_frames: int, block: int, profile: bool = False, single: bool = False) -> dict[str, float]:
    """``single``: the one-transmitter StreamDecoder (max_transmitters = 1: no searcher) instead."""
    from iscd.core.jit import warm_up
    from iscd.decode.comms.packets import PacketAssembler
    from iscd.decode.multi import MultiDecoder
    from iscd.decode.stream import StreamDecoder
    from iscd.sim.scene import Scene

    cfg = scene_config(k)
    sc = Scene(cfg)
    dec = StreamDecoder(cfg) if single else MultiDecoder(cfg.with_keys("tracking", max_transmitters=k + 1))
    warm_up()
    H, W = cfg.camera.height, cfg.camera.width
    L = np.empty((block, H, W), np.uint8)
    R = np.empty_like(L)
    bl, br = np.empty_like(L), np.empty_like(L)
    demod = [0.0]
    asm_push = PacketAssembler.push

    def timed_push(self, *a, **kw):
        t = time.perf_counter()
        try:
            return asm_push(self, *a, **kw)
        finally:
            demod[0] += time.perf_counter() - t

    PacketAssembler.push = timed_push  # type: ignore[method-assign]  (restored below)
    warm = 700  # two packets of the 40 + 100-symbol transmitters: each acquired and confirmed
    t_push = t_copy = 0.0
    d0 = 0.0
    n_timed = 0
    prof = cProfile.Profile() if profile else None
    try:
        for f0 in range(0, n_frames, block):
            for i in range(block):
                sc.render_pair_into(f0 + i, L[i], R[i])
            ids = np.arange(f0, f0 + block)
            timed = f0 >= warm
            if timed and n_timed == 0:
                d0 = demod[0]
            t = time.perf_counter()
            if timed and prof:
                prof.enable()
            dec.push(ids, ids / cfg.camera.fps, L, R)
            if timed and prof:
                prof.disable()
            t1 = time.perf_counter()
            bl[:] = L  # the baseline: copy the pair's two full frames
            br[:] = R
            t2 = time.perf_counter()
            if timed:
                t_push += t1 - t
                t_copy += t2 - t1
                n_timed += block
        tracked = dec.counters.get("transmitters_tracked", int(dec.track is not None))
        dec.finish()
    finally:
        PacketAssembler.push = asm_push  # type: ignore[method-assign]
    if prof:
        pstats.Stats(prof, stream=sys.stdout).sort_stats("cumulative").print_stats(22)
    loop = max(t_push - (demod[0] - d0), 1e-9)
    return {"k": k, "pairs": n_timed, "tracked": tracked, "frame_loop_ratio": n_timed / loop / cfg.camera.fps,
            "to_baseline": (n_timed / loop) / (n_timed / max(t_copy, 1e-9)),
            "ms_per_pair": 1e3 * loop / n_timed, "packets_ok": dec.counters["packets_ok"],
            "packets_bad": dec.counters["packets_bad"], "confirmed": dec.counters.get("transmitters_confirmed", tracked)}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", default="1,2,4,8", help="numbers of transmitters, comma-separated (default 1,2,4,8)")
    ap.add_argument("--frames", type=int, default=3000, help="stereo pairs per scene, warm-up (700) included")
    ap.add_argument("--block", type=int, default=16, help="pairs per decode step (the daemon's block_max)")
    ap.add_argument("--profile", action="store_true", help="print where the time goes (cProfile, cumulative)")
    ap.add_argument("--quick", action="store_true", help="a short run (1, 2 transmitters, 1000 pairs) to check it works")
    a = ap.parse_args(argv)
    counts = [1, 2] if a.quick else [int(c) for c in a.counts.split(",")]
    n = 1000 if a.quick else a.frames
    first = None
    if 1 in counts:  # the reference: one StreamDecoder, no searcher (what max_transmitters = 1 runs)
        r = bench(1, n, a.block, False, single=True)
        print(f"1 transmitter, StreamDecoder alone (no searcher): frame loop {r['frame_loop_ratio']:.2f}x the "
              f"1000 fps camera rate, {r['to_baseline']:.3f}x the full-frame-copy baseline, "
              f"{r['ms_per_pair']:.3f} ms/pair, packets {r['packets_ok']} ok {r['packets_bad']} bad", flush=True)
    for k in counts:
        r = bench(k, n, a.block, a.profile)
        first = first or r["ms_per_pair"]
        print(f"{k} transmitter(s): {r['pairs']} pairs timed, {r['confirmed']} confirmed ({r['tracked']} tracked at "
              f"the end), frame loop {r['frame_loop_ratio']:.2f}x the 1000 fps camera rate, "
              f"{r['to_baseline']:.3f}x the full-frame-copy baseline, {r['ms_per_pair']:.3f} ms/pair "
              f"({r['ms_per_pair'] / first:.2f}x one transmitter's), packets {r['packets_ok']} ok "
              f"{r['packets_bad']} bad", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
