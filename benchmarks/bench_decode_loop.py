"""Benchmark: the decode loop alone (detection/tracking, luminance, demodulation, ranging
every frame) on pre-rendered frames, as the daemon runs it.

    python -m benchmarks.bench_decode_loop [--frames N] [--block B] [--scene default|pwm16|single] [--quick] [--paced]

The frames are rendered first (not timed), then fed to :class:`iscd.decode.stream.StreamDecoder`
in blocks of ``--block`` pairs exactly as the daemon does. Prints pairs/s, the ratio to the
1000 fps camera rate (the target: >= 10 for an 8x8 array with ranging every frame)
and the ratio to an in-process baseline (copying each pair's two 512x512 frames, the least
any decoder must do) so the numbers survive a noisy machine. Also the share of time in
each stage.

``--paced`` also feeds the blocks at the camera rate, as the daemon gets them (sleeping until
each block's last pair is due), and prints this thread's CPU per pair both ways: on a VM whose
idle vCPU halts (the CI machine kind), the same work costs more CPU after each sleep than back to
back, which is why the daemon's frame loop takes more of a core than the ratios above suggest
(docs/realtime.md, "Session 28").
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from collections.abc import Sequence

import numpy as np

SCENES = ("default", "pwm16", "single")
PROFILE_SORT = "cumulative"
PROFILE_LINES = 18


def _config(scene: str):  # -> Config
    from iscd.core.config import default_config
    from iscd.sim.presets import override, single_led

    cfg = default_config()
    if scene == "pwm16":
        return override(cfg, transmitter={"levels": 16}, scene={"distance_m": 50.0})
    if scene == "single":
        return single_led(cfg, 40.0)
    return cfg


def bench(n_frames: int, block: int, scene: str, profile: bool = False, paced: bool = False) -> dict[str, float]:
    from iscd.decode.stream import StreamDecoder
    from iscd.sim.scene import Scene

    cfg = _config(scene)
    sc = Scene(cfg)
    H, W = cfg.camera.height, cfg.camera.width
    L = np.empty((n_frames, H, W), np.uint8)
    R = np.empty_like(L)
    for i in range(n_frames):
        sc.render_pair_into(i, L[i], R[i])
    ids = np.arange(n_frames)
    t_s = ids / cfg.camera.fps
    dec = StreamDecoder(cfg)
    from iscd.core.jit import warm_up

    warm_up()  # compiled kernels loaded (or compiled) before the clock starts, as the daemon does
    # time spent demodulating (in line here; the daemon does it in a worker process)
    from iscd.decode.comms.packets import PacketAssembler

    demod_s = [0.0, 0.0]  # wall, CPU
    asm_push = PacketAssembler.push

    def timed_push(self, *a, **k):
        t = time.perf_counter()
        c = time.process_time()
        try:
            return asm_push(self, *a, **k)
        finally:
            demod_s[0] += time.perf_counter() - t
            demod_s[1] += time.process_time() - c

    PacketAssembler.push = timed_push  # type: ignore[method-assign]  (restored below)
    # acquisition (detection) happens once per run: do it before timing the steady state
    warm = dec.settings.acquire_frames
    dec.push(ids[:warm], t_s[:warm], L[:warm], R[:warm])
    if dec.track is None:
        raise SystemExit("bench: the transmitter was not acquired; nothing to measure")
    prof = cProfile.Profile() if profile else None
    buf_l = np.empty((block, H, W), np.uint8)
    buf_r = np.empty_like(buf_l)
    pre_demod, pre_demod_cpu = demod_s
    t0 = time.perf_counter()
    c0 = time.process_time()
    th0 = time.thread_time()
    if prof:
        prof.enable()
    for s in range(warm, n_frames, block):
        e = min(n_frames, s + block)
        # as the daemon: copy only the windows the decoder reads out of the ring
        win = dec.needed_windows()
        if win is None:
            buf_l[:e - s] = L[s:e]
            buf_r[:e - s] = R[s:e]
        else:
            (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = win
            buf_l[:e - s, ay0:ay1, ax0:ax1] = L[s:e, ay0:ay1, ax0:ax1]
            buf_r[:e - s, by0:by1, bx0:bx1] = R[s:e, by0:by1, bx0:bx1]
        dec.push(ids[s:e], t_s[s:e], buf_l[:e - s], buf_r[:e - s])
        if paced:  # the block's last pair is due (e - warm) / fps after the first
            wait = t0 + (e - warm) / cfg.camera.fps - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
    dec.finish()
    thread_cpu = time.thread_time() - th0
    if prof:
        prof.disable()
    PacketAssembler.push = asm_push  # type: ignore[method-assign]
    dt = time.perf_counter() - t0
    cpu = time.process_time() - c0
    n = n_frames - warm
    demod = demod_s[0] - pre_demod
    demod_cpu = demod_s[1] - pre_demod_cpu
    # baseline: copy every pair's two full frames (what a decoder that reads everything costs)
    t1 = time.perf_counter()
    for s in range(warm, n_frames, block):
        e = min(n_frames, s + block)
        buf_l[:e - s] = L[s:e]
        buf_r[:e - s] = R[s:e]
    base = n / (time.perf_counter() - t1)
    if prof:
        pstats.Stats(prof, stream=sys.stdout).sort_stats(PROFILE_SORT).print_stats(PROFILE_LINES)
    frame_loop = max(dt - demod, 1e-9)
    return {"pairs_per_s": n / dt, "realtime_ratio": n / dt / cfg.camera.fps, "baseline_pairs_per_s": base,
            "demod_share": demod / dt, "frame_loop_ratio": n / frame_loop / cfg.camera.fps,
            "frame_loop_to_baseline": (n / frame_loop) / base,
            "ratio_to_baseline": (n / dt) / base, "cpu_ratio": n / max(cpu, 1e-9) / cfg.camera.fps,
            "cpu_frame_loop_ratio": n / max(cpu - demod_cpu, 1e-9) / cfg.camera.fps, "packets_ok": dec.counters["packets_ok"],
            "packets_bad": dec.counters["packets_bad"], "ranges": dec.counters["ranges"], "pairs": n,
            "thread_cpu_us_per_pair": thread_cpu / n * 1e6}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3000, help="stereo pairs (default 3000, 2+ packets)")
    ap.add_argument("--block", type=int, default=16, help="pairs per decode step (the daemon's block_max)")
    ap.add_argument("--scene", choices=SCENES + ("all",), default="all",
                    help="default: 8x8 PWM-8 at 30 m (HDR f/4+f/8); pwm16: 8x8 PWM-16 at 50 m; "
                         "single: 1 LED at 40 m; all (default): each in turn")
    ap.add_argument("--profile", action="store_true", help="print where the time goes (cProfile, by cumulative time)")
    ap.add_argument("--quick", action="store_true", help="a short run (400 pairs) to check that it works")
    ap.add_argument("--paced", action="store_true",
                    help="also run at the camera rate (sleeping between blocks, as the daemon) and print "
                         "the CPU per pair both ways")
    a = ap.parse_args(argv)
    n = 400 if a.quick else a.frames
    for scene in (SCENES if a.scene == "all" else (a.scene,)):
        r = bench(n, a.block, scene, a.profile)
        print(f"decode loop, scene {scene}: {r['pairs']} pairs, {r['pairs_per_s']:.0f} pairs/s = "
              f"{r['realtime_ratio']:.2f} x the 1000 fps camera rate (target >= 10); "
              f"{r['ratio_to_baseline']:.3f} x the full-frame-copy baseline ({r['baseline_pairs_per_s']:.0f} pairs/s); "
              f"packets ok {r['packets_ok']} bad {r['packets_bad']}, ranges {r['ranges']}")
        print(f"  of which demodulation {r['demod_share']:.0%} (in line here; the daemon runs it in a worker "
              f"process): the frame loop alone {r['frame_loop_ratio']:.2f} x the camera rate, "
              f"{r['frame_loop_to_baseline']:.3f} x the full-frame-copy baseline")
        print(f"  by this process's CPU time (what a shared machine's other load does not inflate): "
              f"{r['cpu_ratio']:.2f} x the camera rate, the frame loop alone {r['cpu_frame_loop_ratio']:.2f} x")
        if a.paced:
            p = bench(n, a.block, scene, paced=True)
            print(f"  paced at the camera rate: {p['thread_cpu_us_per_pair']:.0f} us of CPU per pair, "
                  f"back to back {r['thread_cpu_us_per_pair']:.0f} us "
                  f"({p['thread_cpu_us_per_pair'] / r['thread_cpu_us_per_pair']:.2f} x)")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
