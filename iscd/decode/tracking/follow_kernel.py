"""The per-frame LED following and luminance as one compiled kernel.

:func:`follow_and_measure_compiled` does exactly what the numpy reference
:func:`iscd.decode.tracking.luminance.follow_and_measure` does -- per camera and frame the LEDs'
patches, their background (each pixel's least value over the block), which LEDs are lit,
the shift and scale of the array from box centroids (:func:`~iscd.decode.tracking.luminance.
refine_in_patches`, accelerated rounds), then the Gaussian-weighted luminance (eq. 3.10
with smooth weights, :func:`~iscd.decode.tracking.luminance.gauss_in_patches`) -- in fused loops
that read each LED's pixels straight out of the frames (no patch copies, no temporaries
of the size of the block; only the luminance converts a frame's patches to float64 once,
over their bounding box). It works in float64 where the reference works partly in
float32: the two agree to ~1e-5 px in position and ~1e-5 relative in luminance
(``tests/test_frame_kernels.py``).

Conventions as in :mod:`iscd.decode.tracking.luminance`: x right, y down, pixel centres at
integers, positions in px, luminance in DN; a patch at the image edge is moved inside.
"""

from __future__ import annotations

import math

import numpy as np

from iscd.core.jit import njit
from iscd.decode.tracking.luminance import LIT_SHARE, patch_half


@njit(fastmath={"reassoc", "contract", "nsz", "arcp"})
def _box_cover(c: float, p: float, w: float) -> float:
    """Share of pixel [p - 0.5, p + 0.5] inside the box [c - w/2, c + w/2] (0..1)."""
    a = c - 0.5 * w
    v = min(a + w, p + 0.5) - max(a, p - 0.5)
    return 0.0 if v < 0.0 else (1.0 if v > 1.0 else v)


@njit(fastmath={"reassoc", "contract", "nsz", "arcp"})
def _gauss_row(out: np.ndarray, e0: float, a2: float, K: int) -> float:
    """out[k] = exp(a2 (e0 + k)^2) for k < K by the recurrence w_k+1 = w_k r_k,
    r_k+1 = r_k exp(2 a2) (three exponentials instead of K); returns the sum."""
    w = math.exp(a2 * e0 * e0)
    r = math.exp(a2 * (2.0 * e0 + 1.0))
    q = math.exp(2.0 * a2)
    s = 0.0
    for k in range(K):
        out[k] = w
        s += w
        w *= r
        r *= q
    return s


_GAUSS_SAFE = 600.0
"""|a2| (e0 + k)^2 below which every Gaussian weight of a patch row is a normal float
(exp(-600) ~ 1e-261): such a row may be scaled by 1 / exp(a2 e0^2)."""


@njit(fastmath={"reassoc", "contract", "nsz", "arcp"})
def _gauss_start(e0: float, a2: float, K: int) -> tuple[float, float]:
    """The first weight and ratio (w_0, r_0) of :func:`_gauss_row`'s recurrence, the row
    divided by its first weight exp(a2 e0^2) (one exponential a row; a weighted mean
    does not change but for rounding) unless a weight could leave the normal floats
    (an LED far outside its patch): then :func:`_gauss_row`'s own."""
    e1 = e0 + (K - 1)
    r = math.exp(a2 * (2.0 * e0 + 1.0))
    if -a2 * max(e0 * e0, e1 * e1) >= _GAUSS_SAFE:
        return math.exp(a2 * e0 * e0), r
    return 1.0, r


@njit
def _percentile90(v: np.ndarray) -> float:
    """numpy's default (linear) 90th percentile of a 1-D array."""
    s = np.sort(v)
    n = s.size
    if n == 0:
        return math.nan
    pos = 0.9 * (n - 1)
    lo = int(math.floor(pos))
    hi = min(lo + 1, n - 1)
    fr = pos - lo
    return s[lo] + (s[hi] - s[lo]) * fr


@njit
def _disc_count(img, bg, has_bg: bool, m: float, xa: int, ya: int, K: int, cx: float, cy: float,
                r2: float, level: float) -> float:
    """Over the patch pixels within sqrt(r2) px of (cx, cy), of the light above the
    background (``bg`` per pixel, else ``m``): the largest value when ``level`` is -inf,
    else how many exceed ``level``."""
    best = -math.inf
    cnt = 0.0
    for a in range(K):
        dy = ya + a - cy
        for b in range(K):
            dx = xa + b - cx
            if dx * dx + dy * dy <= r2:
                v = float(img[ya + a, xa + b]) - (float(bg[ya + a, xa + b]) if has_bg else m)
                best = max(best, v)
                if v > level:
                    cnt += 1.0
    return best if level == -math.inf else cnt


_FAST = {"reassoc", "contract", "nsz", "arcp"}
"""fastmath flags that let LLVM vectorize the sums (reassociation), but keep inf/NaN."""


# The helpers below read pixels through a frame block's flat view (``fr.reshape(-1)``) at
# unsigned offsets ``(f H + y) W + x``: an unsigned index has no negative-index wrap-around,
# so the inner loops compile to plain loads. Short rows (a patch is ~15 px) do not
# vectorize; the helpers instead take two or three rows per pass, which share the
# weights' loads and overlap the rows' sums.


@njit(fastmath=_FAST)
def _patch_sum_min(ff: np.ndarray, p0: np.uint64, uW: np.uint64, K: int) -> tuple:
    """Sum and least value (int32) of the K x K pixels from flat offset ``p0`` (row
    stride ``uW``)."""
    uK = np.uint64(K)
    tot = np.int32(0)
    m = np.int32(ff[p0])
    pf = p0
    a = 0
    while a + 2 < K:
        p2 = pf + uW
        p3 = p2 + uW
        t1 = np.int32(0)
        t2 = np.int32(0)
        t3 = np.int32(0)
        m1 = m
        m2 = m
        m3 = m
        for b in range(uK):
            v1 = np.int32(ff[pf + b])
            v2 = np.int32(ff[p2 + b])
            v3 = np.int32(ff[p3 + b])
            t1 += v1
            t2 += v2
            t3 += v3
            m1 = min(m1, v1)
            m2 = min(m2, v2)
            m3 = min(m3, v3)
        tot += t1 + t2 + t3
        m = min(m, min(m1, min(m2, m3)))
        pf = p3 + uW
        a += 3
    while a < K:
        t1 = np.int32(0)
        m1 = m
        for b in range(uK):
            v1 = np.int32(ff[pf + b])
            t1 += v1
            m1 = min(m1, v1)
        tot += t1
        m = min(m, m1)
        pf += uW
        a += 1
    return tot, m


@njit(fastmath=_FAST)
def _least_over_frames(ff: np.ndarray, F: int, H: int, W: int, x: int, y: int, bw: int,
                       bh: int, out: np.ndarray) -> None:
    """out[r bw + c] = the least value over the F frames of pixel (x + c, y + r) (int32),
    for the bw x bh px from (x, y): row by row, rows that vectorize when long."""
    ubw = np.uint64(bw)
    for f in range(F):
        for r in range(bh):
            pf = np.uint64((f * H + y + r) * W + x)
            pd = np.uint64(r * bw)
            if f == 0:
                for c in range(ubw):
                    out[pd + c] = np.int32(ff[pf + c])
            else:
                for c in range(ubw):
                    out[pd + c] = min(out[pd + c], np.int32(ff[pf + c]))


@njit(fastmath=_FAST)
def _lower_background(ff: np.ndarray, F: int, H: int, W: int, x0: np.ndarray, y0: np.ndarray,
                      ids: np.ndarray, K: int, bgf: np.ndarray, stf: np.ndarray, blk: int,
                      rise: float, mask: np.ndarray, lb: np.ndarray) -> None:
    """Fold one camera's block into its per-pixel background (flat ``bgf`` float32, stamps
    ``stf``): every pixel that the patches (x0, y0 (F, N), LEDs ``ids``) of some frame
    cover is relaxed by ``rise`` once (stamp != ``blk``), then lowered to its least value
    over those frames -- the values :class:`~iscd.decode.tracking.luminance.PixelBackground`
    gives (as the per-patch, per-frame loop did). When the patches stay put over the block and
    their bounding box is no larger than the patches together (an array's: they overlap),
    over the box: a coverage mask, one relaxation and the least value over the frames
    in long rows; else patch by patch. ``mask`` (uint8) and ``lb`` (int32) hold
    len(ids) K^2 values."""
    nb = ids.size
    uK = np.uint64(K)
    uW = np.uint64(W)
    urise = np.float32(rise)
    fixed = True
    for f in range(1, F):
        for jb in range(nb):
            i = ids[jb]
            if x0[f, i] != x0[0, i] or y0[f, i] != y0[0, i]:
                fixed = False
    bx0, by0, bx1, by1 = W, H, 0, 0
    for jb in range(nb):
        i = ids[jb]
        bx0 = min(bx0, x0[0, i])
        by0 = min(by0, y0[0, i])
        bx1 = max(bx1, x0[0, i] + K)
        by1 = max(by1, y0[0, i] + K)
    BW, BH = bx1 - bx0, by1 - by0
    if fixed and nb > 0 and BW * BH <= mask.size:
        uBW = np.uint64(BW)
        for p in range(BW * BH):
            mask[p] = 0
        for jb in range(nb):
            i = ids[jb]
            pd = np.uint64((y0[0, i] - by0) * BW + x0[0, i] - bx0)
            for a in range(K):
                for b in range(uK):
                    mask[pd + b] = 1
                pd += uBW
        _least_over_frames(ff, F, H, W, bx0, by0, BW, BH, lb)
        for r in range(BH):
            pb = np.uint64((by0 + r) * W + bx0)
            pd = np.uint64(r * BW)
            for c in range(uBW):  # branch-free (vectorizes): uncovered pixels kept
                cov = mask[pd + c] != 0
                st = stf[pb + c]
                fresh = cov and st != blk
                stf[pb + c] = blk if fresh else st
                u = bgf[pb + c] + urise if fresh else bgf[pb + c]
                v = np.float32(lb[pd + c])
                bgf[pb + c] = v if cov and v < u else u
        return
    # patch by patch: relax every covered pixel once, then lower it
    for f in range(1 if fixed else F):
        for jb in range(nb):
            i = ids[jb]
            pb = np.uint64(y0[f, i] * W + x0[f, i])
            for a in range(K):
                for b in range(uK):
                    if stf[pb + b] != blk:
                        stf[pb + b] = blk
                        bgf[pb + b] += urise
                pb += uW
    for jb in range(nb):
        i = ids[jb]
        if fixed:
            _least_over_frames(ff, F, H, W, x0[0, i], y0[0, i], K, K, lb)
            pb = np.uint64(y0[0, i] * W + x0[0, i])
            pd = np.uint64(0)
            for a in range(K):
                for b in range(uK):
                    v = np.float32(lb[pd + b])
                    if v < bgf[pb + b]:
                        bgf[pb + b] = v
                pb += uW
                pd += uK
        else:
            for f in range(F):
                pb = np.uint64(y0[f, i] * W + x0[f, i])
                pf = np.uint64(f * H * W) + pb
                for a in range(K):
                    for b in range(uK):
                        v = np.float32(ff[pf + b])
                        if v < bgf[pb + b]:
                            bgf[pb + b] = v
                    pb += uW
                    pf += uW


@njit(fastmath=_FAST)
def _weighted_patch(buf: np.ndarray, p0: np.uint64, uBW: np.uint64, K: int, wx: np.ndarray,
                    wy: np.ndarray) -> float:
    """sum over a, b of wy[a] wx[b] buf[p0 + a BW + b] (float64; three rows a pass)."""
    uK = np.uint64(K)
    s = 0.0
    pd = p0
    a = 0
    while a + 2 < K:
        r1 = 0.0
        r2 = 0.0
        r3 = 0.0
        p2 = pd + uBW
        p3 = p2 + uBW
        for b in range(uK):
            u = wx[b]
            r1 += buf[pd + b] * u
            r2 += buf[p2 + b] * u
            r3 += buf[p3 + b] * u
        s += wy[a] * r1 + wy[a + 1] * r2 + wy[a + 2] * r3
        pd = p3 + uBW
        a += 3
    while a < K:
        r1 = 0.0
        for b in range(uK):
            r1 += buf[pd + b] * wx[b]
        s += wy[a] * r1
        pd += uBW
        a += 1
    return s


@njit(fastmath=_FAST)
def _follow_kernel(L, R, starts: np.ndarray, half: int, w: float, iterations: int,
                   sel: np.ndarray, lit_ref: np.ndarray, lit_share: float, max_px: float,
                   scale: bool, accelerate: bool, sigmas: np.ndarray,
                   out_c: np.ndarray, out_lum: np.ndarray, out_light: np.ndarray,
                   has_bg: bool, bg_l: np.ndarray, bg_r: np.ndarray, st_l: np.ndarray,
                   st_r: np.ndarray, blk: int, rise: float, bg_lum: bool, spot_r: float,
                   out_area: np.ndarray) -> None:
    """See :func:`follow_and_measure_compiled`. starts (2F, N, 2) px (left frames first);
    lit_ref (2,) the remembered light of a lit LED per camera (< 0: none); sigmas (2,) px.
    Writes out_c (2F, N, 2) px, out_lum (2F, N) DN, out_light (2,). With ``has_bg`` the
    per-pixel backgrounds bg_l/bg_r (H, W) float32 and their stamps st_l/st_r (H, W) are
    first updated with the block's patches (:class:`~iscd.decode.tracking.luminance.PixelBackground`,
    block number ``blk``, ``rise`` DN) and which LEDs are lit is judged on the light above
    them; with ``bg_lum`` the centroids and luminance use that light too. With ``spot_r`` > 0 out_area (2,) gets the lit spots' mean half-maximum area
    within spot_r px of their refined centres (:func:`~iscd.decode.tracking.luminance.half_max_area`).

    Pixels are read through flat views with unsigned indices (``(f H + y) W + x``: no
    negative-index wrap-around in the inner loops, which then compile to plain loads)."""
    F = L.shape[0]
    N = starts.shape[1]
    n = sel.size
    K = 2 * half + 1
    uK = np.uint64(K)
    FF = 2 * F
    Lf = L.reshape(-1)
    Rf = R.reshape(-1)
    bgl_f = bg_l.reshape(-1)
    bgr_f = bg_r.reshape(-1)
    x0 = np.empty((FF, N), np.int64)
    y0 = np.empty((FF, N), np.int64)
    for g in range(2):
        fr = L if g == 0 else R
        H, W = fr.shape[1], fr.shape[2]
        for f in range(F):
            for i in range(N):
                xa = int(np.rint(starts[g * F + f, i, 0])) - half
                ya = int(np.rint(starts[g * F + f, i, 1])) - half
                x0[g * F + f, i] = min(max(xa, 0), W - K)
                y0[g * F + f, i] = min(max(ya, 0), H - K)
    # ---- the per-pixel backgrounds: relaxed once per block, then lowered to every pixel
    # the LEDs' patches show in this block (all LEDs when the luminance uses it, else only
    # the selected ones, whose lit judgement alone needs it). The result does not depend
    # on the order (a pixel is relaxed before its first lowering in the block, and the
    # least value is order-free): each pixel is relaxed once and lowered once, to its
    # least value over the frames whose patches cover it (:func:`_lower_background`).
    if has_bg:
        nb = N if bg_lum else n
        ids = np.empty(nb, np.int64)
        for jb in range(nb):
            ids[jb] = jb if bg_lum else sel[jb]
        mask = np.empty(nb * K * K, np.uint8)
        lb = np.empty(nb * K * K, np.int32)
        for g in range(2):
            fr = L if g == 0 else R
            _lower_background(Lf if g == 0 else Rf, F, fr.shape[1], fr.shape[2],
                              x0[g * F:(g + 1) * F], y0[g * F:(g + 1) * F], ids, K,
                              bgl_f if g == 0 else bgr_f, (st_l if g == 0 else st_r).reshape(-1),
                              blk, rise, mask, lb)
    # ---- per selected LED and frame: patch sum, patch minimum, and (patches that stay
    # put over the block) each pixel's least value over the block's frames
    pmin = np.empty((FF, n))
    shown = np.empty((FF, n))
    lit = np.empty((FF, n), np.bool_)
    least = np.empty(2 * n * K * K, np.int32)
    for g in range(2):
        fr = L if g == 0 else R
        ff = Lf if g == 0 else Rf
        H, W = fr.shape[1], fr.shape[2]
        uW = np.uint64(W)
        fixed = F > 1 and not has_bg
        for f in range(F):
            for j in range(n):
                i = sel[j]
                if x0[g * F + f, i] != x0[g * F, i] or y0[g * F + f, i] != y0[g * F, i]:
                    fixed = False
        for j in range(n):
            i = sel[j]
            for f in range(F):
                q = g * F + f
                tot, m = _patch_sum_min(ff, np.uint64((f * H + y0[q, i]) * W + x0[q, i]), uW, K)
                pmin[q, j] = m
                shown[q, j] = np.int64(tot) - (0 if has_bg else K * K * np.int64(m))
        if fixed:
            # each pixel's least value over the block: at once over the selected patches'
            # bounding box when that is small (an array's), else patch by patch
            bx0, by0, bx1, by1 = W, H, 0, 0
            for j in range(n):
                i = sel[j]
                bx0 = min(bx0, x0[g * F, i])
                by0 = min(by0, y0[g * F, i])
                bx1 = max(bx1, x0[g * F, i] + K)
                by1 = max(by1, y0[g * F, i] + K)
            boxed = (bx1 - bx0) * (by1 - by0) <= least.size
            if boxed:
                _least_over_frames(ff, F, H, W, bx0, by0, bx1 - bx0, by1 - by0, least)
            for j in range(n):
                i = sel[j]
                xa, ya = x0[g * F, i], y0[g * F, i]
                if boxed:
                    BW, p0 = bx1 - bx0, (ya - by0) * (bx1 - bx0) + xa - bx0
                else:
                    _least_over_frames(ff, F, H, W, xa, ya, K, K, least)
                    BW, p0 = K, 0
                sb = 0
                for a in range(K):
                    pd = np.uint64(p0 + a * BW)
                    for b in range(np.uint64(K)):
                        sb += np.int64(least[pd + b])
                for f in range(F):
                    q = g * F + f
                    shown[q, j] += K * K * pmin[q, j] - sb
        if has_bg:
            # the light above the held per-pixel background instead: the patch sum less
            # the background's sum under the patch (both exact in float64: the same value
            # as the sum of the differences), the latter once per place of the patch
            bgf = bgl_f if g == 0 else bgr_f
            for j in range(n):
                i = sel[j]
                xp, yp = -1, -1
                sbg = 0.0
                for f in range(F):
                    q = g * F + f
                    xa, ya = x0[q, i], y0[q, i]
                    if xa != xp or ya != yp:
                        xp, yp = xa, ya
                        sbg = 0.0
                        for a in range(K):
                            pb = np.uint64((ya + a) * W + xa)
                            rb = 0.0
                            for b in range(uK):
                                rb += float(bgf[pb + b])
                            sbg += rb
                    shown[q, j] -= sbg
        per = _percentile90(shown[g * F:(g + 1) * F].ravel())
        out_light[g] = per
        ref = per if lit_ref[g] < 0 else max(per, lit_ref[g])
        thr = lit_share * ref
        for f in range(F):
            for j in range(n):
                lit[g * F + f, j] = shown[g * F + f, j] >= thr
    # ---- rounds of box centroids -> per-frame shift and scale
    cc = starts.copy()
    c0 = starts
    d = np.zeros((FF, 2))
    sc = np.zeros(FF)
    ctr = np.zeros((FF, 2))
    prev_d = np.zeros((FF, 2))
    prev_sc = np.zeros(FF)
    wx = np.empty(K)
    wy = np.empty(K)
    xw = np.empty(K)
    off = np.empty((n, 2))
    wt = np.empty(n)
    for it in range(iterations):
        for q in range(FF):
            g = 0 if q < F else 1
            f = q - g * F
            fr = L if g == 0 else R
            ff = Lf if g == 0 else Rf
            bgf = bgl_f if g == 0 else bgr_f
            H, W = fr.shape[1], fr.shape[2]
            uW = np.uint64(W)
            for j in range(n):
                i = sel[j]
                cx, cy = cc[q, i, 0], cc[q, i, 1]
                xa, ya = x0[q, i], y0[q, i]
                # the box covers only these pixels (the weights are 0 elsewhere)
                b0 = min(max(int(math.floor(cx - 0.5 * w - 0.5)) - xa, 0), K - 1)
                b1 = min(max(int(math.ceil(cx + 0.5 * w + 0.5)) - xa, 0), K - 1) + 1
                a0 = min(max(int(math.floor(cy - 0.5 * w - 0.5)) - ya, 0), K - 1)
                a1 = min(max(int(math.ceil(cy + 0.5 * w + 0.5)) - ya, 0), K - 1) + 1
                for k in range(b0, b1):
                    wx[k] = _box_cover(cx, float(xa + k), w)
                for k in range(a0, a1):
                    wy[k] = _box_cover(cy, float(ya + k), w)
                # and the end pixels the box only touches add exactly 0: leave them out
                while b0 < b1 and wx[b0] == 0.0:
                    b0 += 1
                while b1 > b0 and wx[b1 - 1] == 0.0:
                    b1 -= 1
                while a0 < a1 and wy[a0] == 0.0:
                    a0 += 1
                while a1 > a0 and wy[a1 - 1] == 0.0:
                    a1 -= 1
                tot = 0.0
                sx = 0.0
                sy = 0.0
                swx = 0.0
                sxw = 0.0
                for k in range(b0, b1):
                    xw[k] = wx[k] * (xa + k)
                    swx += wx[k]
                    sxw += xw[k]
                m = pmin[q, j]
                ub0 = np.uint64(b0)
                ub1 = np.uint64(b1)
                pb = np.uint64((ya + a0) * W + xa)
                pf = np.uint64(f * H * W) + pb
                uW2 = uW + uW
                a = a0
                if bg_lum:  # light above each pixel's background
                    while a + 1 < a1:  # two rows a pass
                        pf2 = pf + uW
                        pb2 = pb + uW
                        ra = 0.0
                        rx = 0.0
                        ra2 = 0.0
                        rx2 = 0.0
                        for b in range(ub0, ub1):
                            u = wx[b]
                            t = xw[b]
                            v = float(ff[pf + b]) - float(bgf[pb + b])
                            v2 = float(ff[pf2 + b]) - float(bgf[pb2 + b])
                            ra += v * u
                            rx += v * t
                            ra2 += v2 * u
                            rx2 += v2 * t
                        tot += wy[a] * ra + wy[a + 1] * ra2
                        sx += wy[a] * rx + wy[a + 1] * rx2
                        sy += wy[a] * ra * (ya + a) + wy[a + 1] * ra2 * (ya + a + 1)
                        pf += uW2
                        pb += uW2
                        a += 2
                    if a < a1:
                        ra = 0.0
                        rx = 0.0
                        for b in range(ub0, ub1):
                            v = float(ff[pf + b]) - float(bgf[pb + b])
                            ra += v * wx[b]
                            rx += v * xw[b]
                        tot += wy[a] * ra
                        sx += wy[a] * rx
                        sy += wy[a] * ra * (ya + a)
                else:
                    while a + 1 < a1:  # two rows a pass
                        pf2 = pf + uW
                        ra = 0.0
                        rx = 0.0
                        ra2 = 0.0
                        rx2 = 0.0
                        for b in range(ub0, ub1):
                            u = wx[b]
                            t = xw[b]
                            v = float(ff[pf + b])
                            v2 = float(ff[pf2 + b])
                            ra += v * u
                            rx += v * t
                            ra2 += v2 * u
                            rx2 += v2 * t
                        ra -= m * swx  # light above the patch minimum
                        rx -= m * sxw
                        ra2 -= m * swx
                        rx2 -= m * sxw
                        tot += wy[a] * ra + wy[a + 1] * ra2
                        sx += wy[a] * rx + wy[a + 1] * rx2
                        sy += wy[a] * ra * (ya + a) + wy[a + 1] * ra2 * (ya + a + 1)
                        pf += uW2
                        a += 2
                    if a < a1:
                        ra = 0.0
                        rx = 0.0
                        for b in range(ub0, ub1):
                            v = float(ff[pf + b])
                            ra += v * wx[b]
                            rx += v * xw[b]
                        ra -= m * swx
                        rx -= m * sxw
                        tot += wy[a] * ra
                        sx += wy[a] * rx
                        sy += wy[a] * ra * (ya + a)
                safe = tot if tot > 0 else 1.0
                off[j, 0] = sx / safe - cx
                off[j, 1] = sy / safe - cy
                wt[j] = max(tot, 0.0) if lit[q, j] else 0.0
            norm = 0.0
            for j in range(n):
                norm += wt[j]
            sn = norm if norm > 0 else 1.0
            dx = 0.0
            dy = 0.0
            for j in range(n):
                dx += wt[j] * off[j, 0]
                dy += wt[j] * off[j, 1]
            d[q, 0] = dx / sn
            d[q, 1] = dy / sn
            sc[q] = 0.0
            ctr[q, 0] = 0.0
            ctr[q, 1] = 0.0
            if scale and n > 1:
                mx = 0.0
                my = 0.0
                for j in range(n):
                    mx += wt[j] * cc[q, sel[j], 0]
                    my += wt[j] * cc[q, sel[j], 1]
                mx /= sn
                my /= sn
                den = 0.0
                num = 0.0
                for j in range(n):
                    gx = cc[q, sel[j], 0] - mx
                    gy = cc[q, sel[j], 1] - my
                    den += wt[j] * (gx * gx + gy * gy)
                    num += wt[j] * (gx * off[j, 0] + gy * off[j, 1])
                sc[q] = num / (den if den > 0 else 1.0)
                ctr[q, 0] = mx
                ctr[q, 1] = my
        if it == 1 and accelerate:
            # the rounds form a geometric series: add its remaining terms (ratio pooled
            # over the block's frames, both cameras)
            den2 = 0.0
            num2 = 0.0
            for q in range(FF):
                for k in range(2):
                    den2 += prev_d[q, k] * prev_d[q, k]
                    num2 += d[q, k] * prev_d[q, k]
            rho = min(max(num2 / den2, 0.0), 0.8) if den2 > 0 else 0.0
            for q in range(FF):
                d[q, 0] *= 1.0 / (1.0 - rho)
                d[q, 1] *= 1.0 / (1.0 - rho)
            den2 = 0.0
            num2 = 0.0
            for q in range(FF):
                den2 += prev_sc[q] * prev_sc[q]
                num2 += sc[q] * prev_sc[q]
            rho = min(max(num2 / den2, 0.0), 0.8) if den2 > 0 else 0.0
            for q in range(FF):
                sc[q] *= 1.0 / (1.0 - rho)
        for q in range(FF):
            prev_d[q, 0] = d[q, 0]
            prev_d[q, 1] = d[q, 1]
            prev_sc[q] = sc[q]
            for i in range(N):
                for k in range(2):
                    step = d[q, k] + sc[q] * (cc[q, i, k] - ctr[q, k])
                    v = cc[q, i, k] + step - c0[q, i, k]
                    v = min(max(v, -max_px), max_px)
                    cc[q, i, k] = c0[q, i, k] + v
    # ---- the lit spots' size: pixels above half the peak near each refined centre
    out_area[0] = math.nan
    out_area[1] = math.nan
    if spot_r > 0:
        r2 = spot_r * spot_r
        for g in range(2):
            fr = L if g == 0 else R
            bgi = bg_l if g == 0 else bg_r
            tot_a = 0.0
            n_a = 0
            for f in range(F):
                q = g * F + f
                for j in range(n):
                    if not lit[q, j]:
                        continue
                    i = sel[j]
                    xa, ya = x0[q, i], y0[q, i]
                    cx, cy = cc[q, i, 0], cc[q, i, 1]
                    peak = _disc_count(fr[f], bgi, bg_lum, pmin[q, j], xa, ya, K, cx, cy, r2, -math.inf)
                    if not peak > 0:
                        continue
                    tot_a += _disc_count(fr[f], bgi, bg_lum, pmin[q, j], xa, ya, K, cx, cy, r2, 0.5 * peak)
                    n_a += 1
            if n_a > 0:
                out_area[g] = tot_a / n_a
    # ---- Gaussian-weighted luminance of every LED at its refined position. The pixels
    # of a frame's patches are first converted to float64 once, into a buffer over their
    # bounding box when that is no larger than the patches together (an array's patches
    # overlap: each pixel converted once, in long rows that vectorize), else read in place.
    buf = np.empty(N * K * K)
    gx = np.empty((K, N))
    gy = np.empty((K, N))
    wvx = np.empty(N)
    wvy = np.empty(N)
    wrx = np.empty(N)
    wry = np.empty(N)
    wsx = np.empty(N)
    wsy = np.empty(N)
    for g in range(2):
        fr = L if g == 0 else R
        ff = Lf if g == 0 else Rf
        bgf = bgl_f if g == 0 else bgr_f
        H, W = fr.shape[1], fr.shape[2]
        a2 = -0.5 / (sigmas[g] * sigmas[g])
        q2 = math.exp(2.0 * a2)
        for f in range(F):
            q = g * F + f
            bx0, by0, bx1, by1 = W, H, 0, 0
            for i in range(N):
                bx0 = min(bx0, x0[q, i])
                by0 = min(by0, y0[q, i])
                bx1 = max(bx1, x0[q, i] + K)
                by1 = max(by1, y0[q, i] + K)
            BW = bx1 - bx0
            uBW = np.uint64(BW)
            boxed = BW * (by1 - by0) <= N * K * K
            if boxed:
                for y in range(by0, by1):
                    pb = np.uint64(y * W + bx0)
                    pf = np.uint64(f * H * W) + pb
                    pd = np.uint64((y - by0) * BW)
                    if bg_lum:
                        for x in range(uBW):
                            buf[pd + x] = float(ff[pf + x]) - float(bgf[pb + x])
                    else:
                        for x in range(uBW):
                            buf[pd + x] = float(ff[pf + x])
            # the weights (:func:`_gauss_row`'s recurrence) of all the LEDs at once: a
            # loop over the LEDs that vectorizes
            for i in range(N):
                wvx[i], wrx[i] = _gauss_start(x0[q, i] - cc[q, i, 0], a2, K)
                wvy[i], wry[i] = _gauss_start(y0[q, i] - cc[q, i, 1], a2, K)
                wsx[i] = 0.0
                wsy[i] = 0.0
            for k in range(K):
                for i in range(N):
                    gx[k, i] = wvx[i]
                    wsx[i] += wvx[i]
                    wvx[i] *= wrx[i]
                    wrx[i] *= q2
                    gy[k, i] = wvy[i]
                    wsy[i] += wvy[i]
                    wvy[i] *= wry[i]
                    wry[i] *= q2
            for i in range(N):
                xa, ya = x0[q, i], y0[q, i]
                for k in range(K):
                    wx[k] = gx[k, i]
                    wy[k] = gy[k, i]
                s = 0.0
                if boxed:
                    s = _weighted_patch(buf, np.uint64((ya - by0) * BW + xa - bx0), uBW, K, wx, wy)
                else:
                    for a in range(K):
                        pb = np.uint64((ya + a) * W + xa)
                        pf = np.uint64(f * H * W) + pb
                        r = 0.0
                        if bg_lum:
                            for b in range(uK):
                                r += (float(ff[pf + b]) - float(bgf[pb + b])) * wx[b]
                        else:
                            for b in range(uK):
                                r += float(ff[pf + b]) * wx[b]
                        s += wy[a] * r
                out_lum[q, i] = s / (wsx[i] * wsy[i])
    out_c[:] = cc


def _warm_args() -> tuple:
    fr = np.zeros((2, 16, 16), np.uint8)
    st = np.full((4, 2, 2), 8.0)
    bg = np.full((16, 16), np.inf, np.float32)
    stamp = np.zeros((16, 16), np.int64)
    return (fr, fr, st, 3, 3.0, 3, np.arange(2), np.full(2, -1.0), 0.25, 1.5, True, True,
            np.ones(2), np.empty((4, 2, 2)), np.empty((4, 2)), np.empty(2),
            True, bg, bg.copy(), stamp, stamp.copy(), 1, 0.25, True, 2.0, np.empty(2))


def _warm_args16() -> tuple:
    a = list(_warm_args())
    a[0] = a[1] = np.zeros((2, 16, 16), np.uint16)
    return tuple(a)


from iscd.core.jit import register_warm  # noqa: E402

register_warm(_follow_kernel, _warm_args)
register_warm(_follow_kernel, _warm_args16)


_NO_BG = np.zeros((1, 1), np.float32)
_NO_STAMP = np.zeros((1, 1), np.int64)
"""Placeholders for the kernel's background arguments when there is no background."""


def follow_and_measure_compiled(frames: list[np.ndarray], starts: list[np.ndarray], size: int,
                                sigmas: list[float], use: np.ndarray | None = None,
                                iterations: int = 3, lit_light: np.ndarray | None = None,
                                info: dict | None = None, backgrounds: list | None = None,
                                spot_radius_px: float | None = None, subtract: bool = True, *,
                                lit_share: float | None = None, max_px: float = 1.5,
                                scale: bool = True, accelerate: bool = True,
                                new_block: bool = True) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The compiled :func:`iscd.decode.tracking.luminance.follow_and_measure` (same arguments,
    same results to float tolerance) for two cameras.

    An image smaller than a patch falls back to the reference.

    Parameters
    ----------
    frames : list of ndarray
        (left, right) (F, H, W) frames of one integer dtype, DN.
    starts : list of ndarray
        Per camera (N, 2) or (F, N, 2) LED centres (x, y), px.
    size : int
        The following box, px.
    sigmas : list of float
        Per camera the Gaussian window sigma, px.
    use : ndarray, optional
        Indices of the LEDs whose centroids steer (all by default).
    iterations : int
        Centroid rounds.
    lit_light : ndarray, optional
        (2,) per camera the patch light of a lit LED from earlier blocks, DN summed over the
        patch.
    info : dict, optional
        Gets ``"light"`` (2,), DN summed over the patch, and with ``spot_radius_px``
        ``"spot_area"`` (2,), px^2.
    backgrounds : list of PixelBackground, optional
        Per camera a :class:`~iscd.decode.tracking.luminance.PixelBackground` (updated in place, as
        the reference does).
    spot_radius_px : float, optional
        Measure the lit spots' half-maximum area within this radius, px.
    subtract : bool
        With ``backgrounds``: centroids and luminance of the light above the background.
    lit_share : float, optional
        Share of a lit LED's light that lets an LED steer (default
        :data:`~iscd.decode.tracking.luminance.LIT_SHARE`).
    max_px : float
        Largest correction per LED and axis, px.
    scale : bool
        Also fit a scale of the array.
    accelerate : bool
        Extrapolate the rounds' geometric series in the second round.
    new_block : bool
        These frames are a new block for the backgrounds (as the reference takes it).

    Returns
    -------
    centres : list of ndarray
        Per camera the refined centres (F, N, 2), px.
    luminance : list of ndarray
        Per camera the luminance (F, N), DN.

    Raises
    ------
    ValueError
        If ``frames`` is not two cameras, or the backgrounds do not match them.

    References
    ----------
    Dissertation, eq. (3.10) (with Gaussian weights).
    """
    lit_share = LIT_SHARE if lit_share is None else lit_share

    if len(frames) != 2:
        raise ValueError(f"follow_and_measure_compiled takes two cameras, got {len(frames)}")
    # writable C-contiguous arguments (a read-only array is another type to Numba)
    L, R = (f if isinstance(f, np.ndarray) and f.flags.c_contiguous and f.flags.writeable
            else np.require(f, requirements=["C", "W"]) for f in frames)
    if L.dtype != R.dtype:
        R = R.astype(L.dtype)
    F = L.shape[0]
    half = max(patch_half(size, max_px), int(np.ceil(3.5 * max(sigmas))) + 1)
    K = 2 * half + 1
    if min(L.shape[1:] + R.shape[1:]) < K:  # an image smaller than a patch: the reference
        from iscd.decode.tracking.luminance import follow_and_measure  # repeats its edge pixels

        return follow_and_measure([L, R], starts, size, sigmas, use, iterations, lit_light, info,
                                  backgrounds, spot_radius_px, subtract, new_block)
    st = np.empty((2 * F,) + np.shape(starts[0])[-2:], np.float64)
    st[:F] = np.asarray(starts[0], dtype=np.float64)
    st[F:] = np.asarray(starts[1], dtype=np.float64)
    N = st.shape[1]
    sel = np.arange(N, dtype=np.int64) if use is None else np.require(
        np.asarray(use, dtype=np.int64), requirements=["C", "W"])
    ref = np.array([-1.0, -1.0]) if lit_light is None else np.array(lit_light, dtype=np.float64).reshape(2)
    c = np.empty_like(st)
    lum = np.empty((2 * F, N))
    light = np.empty(2)
    if backgrounds is None:
        has_bg, bgs, sts, blk, rise = False, (_NO_BG, _NO_BG), (_NO_STAMP, _NO_STAMP), 0, 0.0
    else:
        if len(backgrounds) != 2 or backgrounds[0].rise_dn != backgrounds[1].rise_dn:
            raise ValueError("backgrounds: one PixelBackground per camera, with one rise_dn")
        for b, fr in zip(backgrounds, (L, R)):
            if b.bg.shape != fr.shape[1:]:
                raise ValueError(f"background of {b.bg.shape} px for frames of {fr.shape[1:]} px")
            b.block += int(new_block)
        if backgrounds[0].block != backgrounds[1].block:
            raise ValueError("backgrounds: the two cameras' maps are at different blocks")
        has_bg = True
        bgs = tuple(b.bg for b in backgrounds)
        sts = tuple(b.stamp for b in backgrounds)
        blk, rise = backgrounds[0].block, backgrounds[0].rise_dn
    area = np.empty(2)
    spot_r = -1.0 if spot_radius_px is None else float(min(spot_radius_px, half))
    _follow_kernel(L, R, st, half, float(size), iterations, sel, ref, lit_share, max_px, scale,
                   accelerate, np.array(sigmas, dtype=np.float64).reshape(2), c, lum, light,
                   has_bg, bgs[0], bgs[1], sts[0], sts[1], blk, rise, has_bg and subtract, spot_r, area)
    if info is not None:
        info["light"] = light
        if spot_radius_px is not None:
            info["spot_area"] = area
    return [c[:F], c[F:]], [lum[:F], lum[F:]]
