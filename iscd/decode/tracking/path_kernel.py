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
        # the line's value at f: sum over q of g_q (s2 - s1 dt_q) / det c_q (or g_q / s0)
        for i in range(N):
            for k in range(2):
                out[f, i, k] = 0.0
        for q in range(q0, q1):
            if w[q] > 0:
                dt = float(q - f)
                g = gk[q - f + R] * w[q]
                a = g * (s2 - s1 * dt) / det if lin else g / s0
                for i in range(N):
                    for k in range(2):
                        out[f, i, k] += a * c[q, i, k]
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


def _f64(a: np.ndarray) -> np.ndarray:
    return np.require(np.asarray(a, dtype=np.float64), requirements=["C", "W"])


def _args(c, lum, cur, floor, use):
    c, lum = _f64(c), _f64(lum)
    cur = _f64(np.broadcast_to(cur, c.shape))
    sel = np.arange(c.shape[1], dtype=np.int64) if use is None else np.require(
        np.asarray(use, dtype=np.int64), requirements=["C", "W"])
    return c, lum, cur, _f64(floor), sel


def path_step_compiled(centres: np.ndarray, lum: np.ndarray, starts: np.ndarray,
                       floor: np.ndarray, anchor: np.ndarray | None, use: np.ndarray | None,
                       *, lit_share: float, sigma_frames: float, reach_sigmas: float
                       ) -> tuple[np.ndarray, float]:
    """:func:`~iscd.decode.tracking.trajectory.path_step`, compiled (same arguments)."""
    c, lum, cur, floor, sel = _args(centres, lum, starts, floor, use)
    out = np.empty_like(c)
    has = anchor is not None
    a = _f64(anchor) if has else np.zeros(c.shape[1:])
    moved = _path_step(c, lum, cur, floor, sel, a, has, float(lit_share), float(sigma_frames),
                       float(reach_sigmas), out)
    return out, float(moved)


def final_select_compiled(centres: np.ndarray, lum: np.ndarray, starts: np.ndarray,
                          path: np.ndarray, floor: np.ndarray, use: np.ndarray | None,
                          *, lit_share: float) -> tuple[np.ndarray, float]:
    """:func:`~iscd.decode.tracking.trajectory.final_select`, compiled (same arguments)."""
    c, lum, cur, floor, sel = _args(centres, lum, starts, floor, use)
    out = np.empty_like(c)
    change = _final_select(c, lum, cur, _f64(path), floor, sel, float(lit_share), out)
    return out, float(change)


def _warm_step() -> tuple:
    c = np.zeros((4, 2, 2))
    return (c, np.ones((4, 2)), c.copy(), np.zeros(2), np.arange(2), np.zeros((2, 2)), True,
            0.25, 1.5, 4.0, np.empty_like(c))


def _warm_final() -> tuple:
    c = np.zeros((4, 2, 2))
    return (c, np.ones((4, 2)), c.copy(), c.copy(), np.zeros(2), np.arange(2), 0.1, np.empty_like(c))


register_warm(_path_step, _warm_step)
register_warm(_final_select, _warm_final)
