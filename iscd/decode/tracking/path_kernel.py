"""Compiled twins of :mod:`iscd.decode.tracking.trajectory`'s per-block steps.

:func:`path_step_compiled` and :func:`final_select_compiled` give the same values as
:func:`~iscd.decode.tracking.trajectory.path_step` and
:func:`~iscd.decode.tracking.trajectory.final_select` (tests/test_trajectory.py: to 1e-9 px),
in a few microseconds a block instead of the ~1 ms the small numpy operations cost in
Python overhead. Units px, DN, frames.
"""

from __future__ import annotations

import math

import numpy as np

from iscd.core.jit import njit, register_warm


@njit
def _p90_sorted(s: np.ndarray, n: int) -> float:
    """numpy's default (linear) 90th percentile of the sorted s[:n]."""
    pos = 0.9 * (n - 1)
    lo = int(math.floor(pos))
    hi = min(lo + 1, n - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


@njit
def _weights(lum: np.ndarray, floor: np.ndarray, sel: np.ndarray, share: float,
             c: np.ndarray, cur: np.ndarray, out: np.ndarray) -> None:
    """out (F,): the light of the lit selected LEDs of each frame the following refined."""
    F, N = lum.shape
    n = sel.size
    above = np.empty(F)
    srt = np.empty(F)
    for f in range(F):
        out[f] = 0.0
    if F == 0:
        return
    for j in range(n):
        i = sel[j]
        for f in range(F):
            v = lum[f, i] - floor[i]
            v = v if math.isfinite(v) else 0.0
            above[f] = v
            # insertion into the sorted srt[:f] (a block is a few tens of frames)
            m = f
            while m > 0 and srt[m - 1] > v:
                srt[m] = srt[m - 1]
                m -= 1
            srt[m] = v
        ref = _p90_sorted(srt, F)
        if not ref > 0:
            continue
        thr = share * ref
        for f in range(F):
            if above[f] >= thr:
                out[f] += above[f]
    for f in range(F):
        if out[f] == 0.0:
            continue
        moved = False
        for i in range(N):
            if c[f, i, 0] != cur[f, i, 0] or c[f, i, 1] != cur[f, i, 1]:
                moved = True
                break
        if not moved:
            out[f] = 0.0


@njit
def _smooth(c: np.ndarray, w: np.ndarray, anchor: np.ndarray, has_anchor: bool,
            sigma: float, reach: float, out: np.ndarray) -> None:
    """:func:`~iscd.decode.tracking.trajectory.smooth_path` into out (F, N, 2)."""
    F, N = c.shape[0], c.shape[1]
    wmin = math.inf
    for f in range(F):
        if w[f] > 0:
            wmin = min(wmin, w[f])
    if wmin == math.inf:
        for f in range(F):
            for i in range(N):
                for k in range(2):
                    out[f, i, k] = anchor[i, k] if has_anchor else c[f, i, k]
        return
    near = math.exp(-2.0) * wmin
    ok = np.zeros(F, np.bool_)
    R = int(math.floor(reach * sigma))
    gk = np.empty(2 * R + 1)  # the Gaussian by offset
    for d in range(-R, R + 1):
        gk[d + R] = math.exp(-0.5 * (d / sigma) ** 2)
    for f in range(F):
        q0, q1 = max(0, f - R), min(F, f + R + 1)
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for q in range(q0, q1):
            if w[q] > 0:
                dt = float(q - f)
                g = gk[q - f + R] * w[q]
                s0 += g
                s1 += g * dt
                s2 += g * dt * dt
        if not s0 >= near:
            continue
        ok[f] = True
        det = s0 * s2 - s1 * s1
        lin = det > 1e-6 * max(s0 * s2, 1e-300)
        # the line's value at f: sum over q of g_q (s2 - s1 dt_q) / det c_q (or g_q / s0),
        # over the LEDs' coordinates as one contiguous row (vectorizes)
        of = out[f].reshape(-1)
        of[:] = 0.0
        for q in range(q0, q1):
            if w[q] > 0:
                dt = float(q - f)
                g = gk[q - f + R] * w[q]
                a = g * (s2 - s1 * dt) / det if lin else g / s0
                cq = c[q].reshape(-1)
                for j in range(of.size):
                    of[j] += a * cq[j]
    # the others bridged: linear between the smoothed frames around them (the anchor at
    # frame -1 before the first), held beyond the ends
    for f in range(F):
        if ok[f]:
            continue
        lo = -1
        for q in range(f - 1, -1, -1):
            if ok[q]:
                lo = q
                break
        hi = -1
        for q in range(f + 1, F):
            if ok[q]:
                hi = q
                break
        for i in range(N):
            for k in range(2):
                if lo >= 0:
                    tl, vl = float(lo), out[lo, i, k]
                elif has_anchor:
                    tl, vl = -1.0, anchor[i, k]
                else:
                    tl, vl = math.nan, 0.0
                if hi >= 0:
                    vh = out[hi, i, k]
                    if math.isnan(tl):
                        out[f, i, k] = vh
                    else:
                        out[f, i, k] = vl + (vh - vl) * (f - tl) / (hi - tl)
                else:
                    out[f, i, k] = vl


@njit
def _path_step(c: np.ndarray, lum: np.ndarray, cur: np.ndarray, floor: np.ndarray,
               sel: np.ndarray, anchor: np.ndarray, has_anchor: bool, share: float,
               sigma: float, reach: float, out: np.ndarray) -> float:
    F = c.shape[0]
    w = np.empty(F)
    _weights(lum, floor, sel, share, c, cur, w)
    _smooth(c, w, anchor, has_anchor, sigma, reach, out)
    moved = 0.0
    for f in range(F):
        for i in range(c.shape[1]):
            for k in range(2):
                moved = max(moved, abs(out[f, i, k] - cur[f, i, k]))
    return moved


@njit
def _final_select(c: np.ndarray, lum: np.ndarray, cur: np.ndarray, path: np.ndarray,
                  floor: np.ndarray, sel: np.ndarray, share: float, out: np.ndarray) -> float:
    F, N = c.shape[0], c.shape[1]
    w = np.empty(F)
    _weights(lum, floor, sel, share, c, cur, w)
    change = 0.0
    for f in range(F):
        src = c if w[f] > 0 else path
        for i in range(N):
            for k in range(2):
                out[f, i, k] = src[f, i, k]
                change = max(change, abs(src[f, i, k] - c[f, i, k]))
    return change


@njit
def _path_block(c: np.ndarray, lum: np.ndarray, cur: np.ndarray, floor: np.ndarray,
                sel: np.ndarray, anchor: np.ndarray, has_anchor: np.ndarray, share: float,
                final_share: float, sigma: float, reach: float, out_path: np.ndarray,
                out_final: np.ndarray, out_mc: np.ndarray) -> None:
    """Every camera g of c (G, F, N, 2) at once: :func:`_path_step` into out_path[g] and
    :func:`_final_select` into out_final[g]; out_mc = (largest move, largest change)."""
    G = c.shape[0]
    moved = 0.0
    change = 0.0
    for g in range(G):
        moved = max(moved, _path_step(c[g], lum[g], cur[g], floor[g], sel, anchor[g], has_anchor[g],
                                      share, sigma, reach, out_path[g]))
        change = max(change, _final_select(c[g], lum[g], cur[g], out_path[g], floor[g], sel,
                                           final_share, out_final[g]))
    out_mc[0] = moved
    out_mc[1] = change


def _f64(a: np.ndarray) -> np.ndarray:
    return np.require(np.asarray(a, dtype=np.float64), requirements=["C", "W"])


def path_block_compiled(centres: list[np.ndarray], lums: list[np.ndarray], starts: list[np.ndarray],
                        floors: list[np.ndarray], anchors: list[np.ndarray | None],
                        use: np.ndarray | None, *, lit_share: float, final_share: float,
                        sigma_frames: float, reach_sigmas: float
                        ) -> tuple[list[np.ndarray], float, list[np.ndarray], float]:
    """:func:`~iscd.decode.tracking.trajectory.path_block`, compiled: one call for every camera.

    Parameters
    ----------
    centres : list of ndarray
        Per camera (F, N, 2) a following pass's centres, px.
    lums : list of ndarray
        Per camera (F, N) its luminance, DN.
    starts : list of ndarray
        Per camera (F, N, 2) or (N, 2) where the pass started, px.
    floors : list of ndarray
        Per camera (N,) a dark LED's luminance, DN.
    anchors : list of ndarray or None
        Per camera (N, 2) the last block's path end, px.
    use : ndarray or None
        The LEDs that steer (all by default).
    lit_share : float
        Share of the block's 90th percentile light that makes a frame steer the path.
    final_share : float
        Share that lets a frame keep its own centres.
    sigma_frames : float
        Smoothing in time, frames.
    reach_sigmas : float
        The smoothing reads frames within this many ``sigma_frames``.

    Returns
    -------
    paths : list of ndarray
        Per camera (F, N, 2), px.
    moved : float
        Largest distance of a path from its starts, px.
    final : list of ndarray
        Per camera (F, N, 2) where the luminance is taken, px.
    change : float
        Largest distance of those from ``centres``, px.
    """
    c = np.stack(centres).astype(np.float64, copy=False)  # (a new C-contiguous array)
    G, F, N = c.shape[:3]
    lum = np.stack(lums).astype(np.float64, copy=False)
    cur = np.empty_like(c)
    for g in range(G):
        cur[g] = starts[g]
    floor = np.stack(floors).astype(np.float64, copy=False)
    anc = np.zeros((G, N, 2))
    has = np.zeros(G, np.bool_)
    for g, a in enumerate(anchors):
        if a is not None:
            anc[g] = a
            has[g] = True
    sel = np.arange(N, dtype=np.int64) if use is None else np.require(
        np.asarray(use, dtype=np.int64), requirements=["C", "W"])
    path = np.empty_like(c)
    final = np.empty_like(c)
    mc = np.empty(2)
    _path_block(c, lum, cur, floor, sel, anc, has, float(lit_share), float(final_share),
                float(sigma_frames), float(reach_sigmas), path, final, mc)
    return list(path), float(mc[0]), list(final), float(mc[1])


def _warm_step() -> tuple:
    c = np.zeros((4, 2, 2))
    return (c, np.ones((4, 2)), c.copy(), np.zeros(2), np.arange(2), np.zeros((2, 2)), True,
            0.25, 1.5, 4.0, np.empty_like(c))


def _warm_final() -> tuple:
    c = np.zeros((4, 2, 2))
    return (c, np.ones((4, 2)), c.copy(), c.copy(), np.zeros(2), np.arange(2), 0.1, np.empty_like(c))


def _warm_block() -> tuple:
    c = np.zeros((2, 4, 2, 2))
    return (c, np.ones((2, 4, 2)), c.copy(), np.zeros((2, 2)), np.arange(2), np.zeros((2, 2, 2)),
            np.ones(2, np.bool_), 0.25, 0.1, 1.5, 4.0, np.empty_like(c), np.empty_like(c), np.empty(2))


register_warm(_path_step, _warm_step)
register_warm(_final_select, _warm_final)
register_warm(_path_block, _warm_block)
