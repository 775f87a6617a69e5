"""Receiver variants on randomized motion scenes: which ``[tracking]`` options generalize.

    python -m iscd.eval.variants [--cases a40,a100,still45,a40v5] [--seeds 1,2,3,4]
                                 [--variants default,background,...]

Each case is one LED (PWM-8, f/4 + f/4, b = 0.6 m, no distractors) with its motion fixed
(distance, speed, vibration amplitude, approach to 25 m) and everything else drawn by
:func:`iscd.sim.randomize.randomized` from a seed derived from the case and ``--seeds``
(vibration model, PSF, glare, diffuser, blooming, noise, exposure, LED drift...). Every
variant decodes the same rendered frames with its own :class:`~iscd.decode.stream.StreamDecoder`;
packets are scored against the simulator's truth as ``iscd eval`` scores them. Prints one
line per scene (packets delivered of 2, SER per variant) and a total per variant.

The point: a receiver option is worth making the default only if it delivers more packets
over scenes it was not tuned on (docs/receiver.md has the table this printed).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

VARIANTS: dict[str, dict[str, Any]] = {
    "default": {},
    "one_pass": {"follow_passes": 0},
    "background": {"background": True},
    "background_w15": {"background": True, "window_scale": 1.5},
    "spot": {"background": True, "window_follows_spot": True},
    "spot_w15": {"background": True, "window_follows_spot": True, "window_scale": 1.5},
    "ic4": {"receiver": {"ic_iterations": 4}},
    "window48": {"receiver": {"channel_window_symbols": 48}},
    "window192": {"receiver": {"channel_window_symbols": 192}},
}
"""``[tracking]`` keys of each variant (and ``[receiver]`` keys under ``"receiver"``)."""

CASES: dict[str, tuple[float, float, float]] = {
    "still45": (45.0, 0.0, 0.3),
    "a40": (50.0, 11.1, 0.3),
    "a40v5": (50.0, 11.1, 0.5),
    "a100": (100.0, 27.8, 0.3),
}
"""Case -> (start distance m, closing speed m/s, vibration RMS px)."""


def scene_config(case: str, seed: int, randomize: bool = True):  # -> Config
    """The randomized config of ``case`` for ``seed`` (the physics seed is 1000 + seed +
    100 x the case's index, so cases never share a draw); ``randomize=False``: the
    simulator's default physics with the case's motion (0.05 px air jitter)."""
    from iscd.core.config import default_config
    from iscd.sim.presets import override, single_led
    from iscd.sim.randomize import randomized

    d0, speed, vib = CASES[case]
    base = override(single_led(default_config(), d0, seed=seed), camera={"f_number_right": 4.0},
                    scene={"distractors": []})
    if not randomize:
        return override(base, scene={"speed_mps": speed, "vibration_px": vib, "jitter_px": 0.05,
                                     "min_distance_m": 25.0})
    return randomized(base, 1000 + seed + 100 * list(CASES).index(case),
                      motion={"distance_m": d0, "speed_mps": speed, "vibration_px": vib,
                              "min_distance_m": 25.0})


def run_scene(cfg, variants: Sequence[str], packets: int = 2, block: int = 16) -> dict[str, tuple[int, float]]:
    """Decode ``packets`` whole packets of ``cfg`` with every variant on the same frames;
    returns variant -> (packets delivered bit-exact, SER over the found packets)."""
    from iscd.core.airinterface import AirInterface
    from iscd.eval.sweeps import CommsResult, ReceiverMode, _decoder_cfg, _score, frames_for_packets
    from iscd.decode.stream import StreamDecoder
    from iscd.sim.scene import Scene

    sc = Scene(cfg)
    air = AirInterface.from_config(cfg.transmitter)
    n = frames_for_packets(sc, air, packets)
    decs: dict[str, tuple[StreamDecoder, list[dict]]] = {}
    for v in variants:
        c = _decoder_cfg(cfg, ReceiverMode("both", "both"))
        keys = dict(VARIANTS[v])
        rx = keys.pop("receiver", {})
        c = c.with_keys("tracking", **keys).with_keys("receiver", **rx)
        decs[v] = (StreamDecoder(c), [])
    L = np.empty((block, sc.height, sc.width), np.uint8)
    R = np.empty_like(L)
    for s in range(0, n, block):
        ids = np.arange(s, min(s + block, n))
        for i, k in enumerate(ids):
            sc.render_pair_into(int(k), L[i], R[i])
        for d, recs in decs.values():
            recs += [r for r in d.push(ids, ids / sc.fps, L[:ids.size], R[:ids.size]) if r["type"] == "packet"]
    truth = sc.truth(np.arange(n))
    out = {}
    tx = cfg.transmitter
    for v, (d, recs) in decs.items():
        recs += [r for r in d.finish() if r["type"] == "packet"]
        res = CommsResult(mode=ReceiverMode(v), levels=tx.levels, n_leds=tx.n_leds,
                          data_symbols=air.data_symbols, packet_s=1.0,
                          payload_bytes=air.payload_bytes, packets_sent=packets)
        _score(res, recs, truth, air, packets, 0.5 / tx.symbol_rate_hz)
        out[v] = (res.exact, res.ser)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m iscd.eval.variants", description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--seeds", default="1,2,3,4", help="comma-separated scene seeds")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    ap.add_argument("--block", type=int, default=16, help="pairs per decode step (default 16, the daemon's)")
    ap.add_argument("--default-physics", action="store_true",
                    help="the simulator's default physics instead of randomized draws")
    a = ap.parse_args(argv)
    try:
        cases = [c for c in a.cases.split(",") if c]
        variants = [v for v in a.variants.split(",") if v]
        seeds = [int(s) for s in a.seeds.split(",") if s]
    except ValueError as exc:
        print(f"variants: bad --seeds: {exc}", file=sys.stderr)
        return 2
    if a.block < 1:
        print(f"variants: --block must be >= 1 pair, got {a.block}", file=sys.stderr)
        return 2
    bad = [c for c in cases if c not in CASES] + [v for v in variants if v not in VARIANTS]
    if bad:
        print(f"variants: unknown case or variant: {', '.join(bad)}", file=sys.stderr)
        return 2
    total = {v: 0 for v in variants}
    for case in cases:
        for seed in seeds:
            cfg = scene_config(case, seed, randomize=not a.default_physics)
            res = run_scene(cfg, variants, block=a.block)
            for v, (ok, _) in res.items():
                total[v] += ok
            o, s = cfg.optics, cfg.scene
            print(f"{case} seed {seed} [{s.vibration_model}, psf {o.psf_model}, glare {o.glare_model}, "
                  f"exposure {cfg.camera.exposure_s * 1e3:.2f} ms] | "
                  + "  ".join(f"{v}: {ok}/2 SER {ser:.4f}" for v, (ok, ser) in res.items()), flush=True)
    n = 2 * len(cases) * len(seeds)
    print("delivered: " + "  ".join(f"{v} {k}/{n}" for v, k in total.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
