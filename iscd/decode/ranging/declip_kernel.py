"""The one-LED core refill (:func:`iscd.decode.ranging.projected.declip_cells` with one cell
per patch) as one compiled loop.

A single LED's patches saturate at short range in the brighter camera; the live ranging
refills each clipped core from a round log-quadratic fitted to the unsaturated pixels
around it, frame by frame. The numpy reference does that with ~40 small array operations a
block (Python overhead: ~0.3 ms a block for two cameras' 16 frames); this kernel walks each
frame's cell once, builds the 4 x 4 weighted normal equations and solves them by Gaussian
elimination with partial pivoting. Same selection of pixels, same model and clamps; the
refilled values agree with the reference to ~1e-9 relative (summation order and the solver
differ; tests/test_declip_kernel.py). Units DN; coordinates px, centred on the cell.
"""

from __future__ import annotations

import math

import numpy as np

from iscd.core.jit import njit, register_warm


@njit
def _solve4(m: np.ndarray, v: np.ndarray, out: np.ndarray) -> bool:
    """out = m^-1 v for a 4 x 4 m (copied), partial pivoting; False when singular."""
    a = m.copy()
    b = v.copy()
    for c in range(4):
        p = c
        big = abs(a[c, c])
        for r in range(c + 1, 4):
            if abs(a[r, c]) > big:
                big = abs(a[r, c])
                p = r
        if big == 0.0 or not math.isfinite(big):
            return False
        if p != c:
            for k in range(4):
                t = a[c, k]
                a[c, k] = a[p, k]
                a[p, k] = t
            t = b[c]
            b[c] = b[p]
            b[p] = t
        for r in range(c + 1, 4):
            f = a[r, c] / a[c, c]
            for k in range(c, 4):
                a[r, k] -= f * a[c, k]
            b[r] -= f * b[c]
    for c in range(3, -1, -1):
        s = b[c]
        for k in range(c + 1, 4):
            s -= a[c, k] * out[k]
        out[c] = s / a[c, c]
    return True


@njit
def _declip_one(out: np.ndarray, sat: np.ndarray, top: np.ndarray, tmap: np.ndarray, cidx: np.ndarray,
                mem: np.ndarray, fit_floor: float, min_pixels: int, max_gain: float, refilled: np.ndarray) -> None:
    """out (n, P) float64 patches (flat), refilled in place; sat (n, P) bool; top (n,) DN;
    tmap (n, P) DN added to top; cidx (ch, cw) the cell's flat pixel indices; mem (ch, cw)."""
    n = out.shape[0]
    ch, cw = cidx.shape
    S = np.zeros((ch, cw), np.bool_)
    use = np.zeros((ch, cw), np.bool_)
    ata = np.empty((4, 4))
    atb = np.empty(4)
    coef = np.empty(4)
    av = np.empty(4)
    xc = (cw - 1) / 2.0
    yc = (ch - 1) / 2.0
    for f in range(n):
        anyf = False
        for a in range(ch):
            for b in range(cw):
                s = mem[a, b] and sat[f, cidx[a, b]]
                S[a, b] = s
                anyf = anyf or s
        if not anyf:
            continue
        for i in range(4):
            atb[i] = 0.0
            for j in range(4):
                ata[i, j] = 0.0
        nuse = 0
        for a in range(ch):
            for b in range(cw):
                # within one pixel (chessboard) of a clipped one, not clipped, in the cell,
                # and above the floor
                near = False
                for da in range(-1, 2):
                    for db in range(-1, 2):
                        aa = a + da
                        bb = b + db
                        if 0 <= aa < ch and 0 <= bb < cw and S[aa, bb]:
                            near = True
                p = cidx[a, b]
                v = out[f, p]
                tv = top[f] + tmap[f, p]
                u = near and not S[a, b] and mem[a, b] and v > fit_floor * tv
                use[a, b] = u
                if not u:
                    continue
                nuse += 1
                x = b - xc
                y = a - yc
                av[0] = 1.0
                av[1] = x
                av[2] = y
                av[3] = x * x + y * y
                lv = math.log(max(v, 1e-6))
                for i in range(4):
                    atb[i] += v * lv * av[i]
                    for j in range(4):
                        ata[i, j] += v * av[i] * av[j]
        for i in range(4):
            ata[i, i] += 1e-9
        if not _solve4(ata, atb, coef):
            continue
        if not (coef[3] < 0) or nuse < min_pixels:
            continue
        refilled[f] = True
        for a in range(ch):
            for b in range(cw):
                if not S[a, b]:
                    continue
                x = b - xc
                y = a - yc
                model = math.exp(min(coef[0] + coef[1] * x + coef[2] * y + coef[3] * (x * x + y * y), 60.0))
                p = cidx[a, b]
                tv = top[f] + tmap[f, p]
                out[f, p] = min(max(model, tv), max_gain * tv)


register_warm(_declip_one, lambda: (np.zeros((1, 9)), np.zeros((1, 9), np.bool_), np.ones(1), np.zeros((1, 9)),
                                    np.arange(9, dtype=np.int64).reshape(3, 3), np.ones((3, 3), np.bool_),
                                    0.03, 5, 30.0, np.zeros(1, np.bool_)))


def declip_one_cell(patches: np.ndarray, saturated: np.ndarray, top: np.ndarray | float, index: np.ndarray,
                    member: np.ndarray, top_map: np.ndarray | None = None, *, fit_floor: float = 0.03,
                    min_pixels: int = 5, max_gain: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`iscd.decode.ranging.projected.declip_cells` for one cell per patch, compiled.

    Parameters
    ----------
    patches : ndarray of float
        (n, h, w) background-removed patches, DN.
    saturated : ndarray of bool
        (n, h, w) the clipped pixels.
    top : float or ndarray
        Scalar or (n,): the value a clipped pixel has, DN (plus ``top_map``).
    index, member : ndarray
        (ch, cw) the cell's flat pixel indices into an (h, w) patch and which belong to the
        LED (:class:`iscd.decode.ranging.projected.Cells`, its only cell).
    top_map : ndarray, optional
        (h, w) or (n, h, w), DN.
    fit_floor, min_pixels, max_gain : float, int, float
        As :func:`~iscd.decode.ranging.projected.declip_cells`.

    Returns
    -------
    patches : ndarray of float64
        (n, h, w) refilled copy, DN.
    refilled : ndarray of bool
        (n,) frames whose core was refilled.
    """
    n, h, w = patches.shape
    out = np.array(patches, dtype=np.float64, copy=True).reshape(n, h * w)
    sat = np.ascontiguousarray(saturated, dtype=np.bool_).reshape(n, h * w)
    # writable copies: a read-only array (what broadcast_to gives) is another type to Numba,
    # compiled at its first use instead of at the warm-up
    t = np.array(np.broadcast_to(np.asarray(top, dtype=np.float64), (n,)))
    if top_map is None:
        tm = np.zeros((n, h * w))
    else:
        tm = np.array(np.broadcast_to(np.asarray(top_map, dtype=np.float64), (n, h, w))).reshape(n, h * w)
    refilled = np.zeros(n, np.bool_)
    _declip_one(out, sat, t, tm, np.ascontiguousarray(index, dtype=np.int64),
                np.ascontiguousarray(member, dtype=np.bool_), float(fit_floor), int(min_pixels), float(max_gain),
                refilled)
    return out.reshape(n, h, w), refilled
