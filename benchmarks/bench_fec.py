"""Benchmark: Reed-Solomon encode and decode of one 19 kB packet, iscd's kernel beside the
libraries, and the residual packet error rate of each v2 code mode against the SER.

The packet: 8x8 PWM-16, F = 600 data symbol times = 19 200 coded bytes, RS(255,223)
(77 codewords). Decoding is timed with errors and erasures near the limit in every
codeword (2e + f = nsym - 2: e = 7, f = 16 for RS(255,223)) -- the worst case that still
decodes, far beyond the link's usual few errors. Each library decodes the same words:

* ``iscd`` -- :mod:`iscd.core.fec` (compiled with Numba, a batch of codewords per call);
* ``reedsolo`` -- the pure-Python package; ``creedsolo`` -- its Cython extension (built
  only from source with ``--cythonize``; skipped if absent);
* ``galois`` -- ``galois.ReedSolomon`` (vectorized over the batch; its decoder takes no
  erasures, so it is given errors only at its limit, e = 16).

Then ``--per`` packets per point through :func:`iscd.eval.fec.per_curve`: residual PER of
each mode at SER 1e-3 .. 1e-1, uniform errors and one LED of the 8x8 dark (``--out DIR``
writes ``fec_per.csv`` and, with matplotlib, ``fec_per.png``).

    python -m benchmarks.bench_fec [--quick] [--per N] [--out DIR]
"""

from __future__ import annotations

import argparse
import csv
import importlib
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from iscd.core.airinterface_v2 import AirInterfaceV2
from iscd.core.fec import RSCode
from iscd.eval.fec import per_curve

TARGET_MS = 20.0
SERS = [1e-3, 3e-3, 1e-2, 2e-2, 3e-2, 5e-2, 1e-1]


def _best(fn: Callable[[], object], reps: int) -> float:
    """Best of ``reps`` wall times of fn(), ms."""
    best = np.inf
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def _words(seed: int = 0) -> tuple[AirInterfaceV2, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The packet's codewords (clean), with errors+erasures, their erasure flags, the
    errors-only variant at t, and the lengths."""
    air = AirInterfaceV2.for_capacity(600, levels=16, rows=8, cols=8, fec="rs255_223")
    rng = np.random.default_rng(seed)
    lay = air._layout
    n_cw, nmax, nsym = lay.lengths.size, int(lay.lengths.max()), air.mode.nsym
    data = rng.integers(0, 256, (n_cw, nmax), dtype=np.uint8)
    clean = np.zeros((n_cw, nmax), np.uint8)
    par = RSCode(nsym).encode(data, lay.k)
    for c in range(n_cw):
        clean[c, :lay.k[c]] = data[c, :lay.k[c]]
        clean[c, lay.k[c]:lay.lengths[c]] = par[c]
    mixed, errs = clean.copy(), clean.copy()
    er = np.zeros(clean.shape, bool)
    e, f = 7, 16
    for c in range(n_cw):
        pos = rng.choice(int(lay.lengths[c]), nsym, replace=False)
        mixed[c, pos[:e + f]] ^= rng.integers(1, 256, e + f).astype(np.uint8)
        er[c, pos[e:e + f]] = True
        errs[c, pos[:nsym // 2]] ^= rng.integers(1, 256, nsym // 2).astype(np.uint8)
    return air, clean, mixed, er, errs, lay.lengths


def bench_libraries(reps: int) -> list[tuple[str, float, float, bool, str]]:
    """(library, encode ms, decode ms, decoded exactly, note) per library."""
    air, clean, mixed, er, errs, lengths = _words()
    nsym = air.mode.nsym
    k = lengths - nsym
    out = []
    code = RSCode(nsym)
    code.decode(mixed.copy(), lengths, er)  # compile / load the kernels
    w = mixed.copy()
    enc = _best(lambda: code.encode(clean, k), reps)
    dec = _best(lambda: code.decode(w.copy(), lengths, er), reps)
    code.decode(w, lengths, er)
    out.append(("iscd", enc, dec, bool(np.array_equal(w, clean)), "errors+erasures e=7 f=16"))
    payload = np.random.default_rng(1).integers(0, 256, air.payload_len, dtype=np.uint8).tobytes()
    lv = air.encode_data(payload)
    out.append(("iscd packet", _best(lambda: air.encode_data(payload), reps),
                _best(lambda: air.decode_data(lv), reps), air.decode_data(lv).payload == payload,
                "levels -> payload, clean (de-interleave, syndromes, CRC)"))
    for name in ("reedsolo", "creedsolo"):
        try:
            mod = importlib.import_module(name)
        except ImportError:
            out.append((name, np.nan, np.nan, False, "not installed"))
            continue
        rs = mod.RSCodec(nsym, nsize=255)
        rows = [bytearray(clean[c, :k[c]].tobytes()) for c in range(k.size)]
        bad = [(bytearray(mixed[c, :lengths[c]].tobytes()), np.flatnonzero(er[c]).tolist()) for c in range(k.size)]
        r = 1 if name == "reedsolo" else reps
        enc = _best(lambda: [rs.encode(m) for m in rows], r)
        got = []
        dec = _best(lambda: got.append([bytes(rs.decode(b, erase_pos=e)[1]) for b, e in bad]), r)
        ok = all(g == clean[c, :lengths[c]].tobytes() for c, g in enumerate(got[-1]))
        out.append((name, enc, dec, ok, "errors+erasures e=7 f=16"))
    try:
        import galois
    except ImportError:
        out.append(("galois", np.nan, np.nan, False, "not installed"))
        return out
    full = np.flatnonzero(lengths == lengths.max())  # galois: one (shortened) length per batch
    RS = galois.ReedSolomon(255, 255 - nsym, c=0)
    GF = RS.field
    msgs = GF(clean[full, :int(k.max())])
    RS.decode(GF(errs[full, :int(lengths.max())]))  # compile
    enc = _best(lambda: RS.encode(msgs), reps) * lengths.size / full.size
    dec_out = []
    dec = _best(lambda: dec_out.append(RS.decode(GF(errs[full, :int(lengths.max())]))), max(1, reps // 2))
    dec *= lengths.size / full.size
    ok = bool(np.array_equal(np.asarray(dec_out[-1]), clean[full, :int(k.max())]))
    out.append(("galois", enc, dec, ok, "errors only e=16 (no erasure decoding); scaled to the packet"))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions and PER packets")
    ap.add_argument("--per", type=int, default=None, help="packets per PER point (default 40, quick 3)")
    ap.add_argument("--out", type=Path, default=None, help="write fec_per.csv (and .png) here")
    a = ap.parse_args(argv)
    reps = 2 if a.quick else 7
    print("one 19 200-byte packet (8x8 PWM-16, F = 600), RS(255,223), 77 codewords; best of "
          f"{reps} (reedsolo: 1), ms on one core")
    print(f"{'library':<12} {'encode ms':>10} {'decode ms':>10}  exact  what")
    rows = bench_libraries(reps)
    for name, enc, dec, ok, note in rows:
        print(f"{name:<12} {enc:>10.2f} {dec:>10.2f}  {'yes' if ok else 'NO ':>5}  {note}")
    iscd_dec = rows[0][2]
    print(f"iscd decode {iscd_dec:.2f} ms per packet at the limit (target <= {TARGET_MS:g})")
    n = a.per if a.per is not None else (3 if a.quick else 40)
    pts = per_curve(SERS, n)
    print(f"\nresidual PER ({n} packets per point; lost + wrong, wrong must be 0)")
    modes = list(dict.fromkeys(p.fec for p in pts))
    for imp in ("uniform", "dark_led"):
        print(f"{imp:<9} SER: " + " ".join(f"{s:>8.0e}" for s in SERS))
        for m in modes:
            sel = [p for p in pts if p.fec == m and p.impairment == imp]
            print(f"  {m:<14} " + " ".join(f"{p.per:>8.3f}" for p in sel)
                  + ("   WRONG DELIVERED" if any(p.wrong for p in sel) else ""))
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        with open(a.out / "fec_per.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["fec", "impairment", "ser", "packets", "lost", "wrong", "per", "corrected_mean"])
            for p in pts:
                w.writerow([p.fec, p.impairment, p.ser, p.packets, p.lost, p.wrong, p.per, p.corrected_mean])
        try:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            return 0
        fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
        for ax, imp in zip(axes, ("uniform", "dark_led")):
            for m in modes:
                sel = [p for p in pts if p.fec == m and p.impairment == imp]
                ax.semilogx([p.ser for p in sel], [max(p.per, 0.5 / n) for p in sel], "o-", label=m)
            ax.set_yscale("log")
            ax.set_xlabel("symbol error rate")
            ax.set_title(f"8x8 PWM-16, {imp.replace('_', ' ')}")
            ax.grid(True, which="both", alpha=0.3)
        axes[0].set_ylabel(f"residual PER (floor: 0 of {n})")
        axes[0].legend()
        fig.tight_layout()
        fig.savefig(a.out / "fec_per.png", dpi=100)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
