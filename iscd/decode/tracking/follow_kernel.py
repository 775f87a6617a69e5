"""The per-frame LED following and luminance as one compiled kernel.

:func:`follow_and_measure_compiled` does exactly what the numpy reference
:func:`iscd.decode.tracking.luminance.follow_and_measure` does -- per camera and frame the LEDs'
patches, their background (each pixel's least value over the block), which LEDs are lit,
the shift and scale of the array from box centroids (:func:`~iscd.decode.tracking.luminance.
refine_in_patches`, accelerated rounds), then the Gaussian-weighted luminance (eq. 3.10
with smooth weights, :func:`~iscd.decode.tracking.luminance.gauss_in_patches`) -- in fused loops
that read each LED's pixels straight out of the frames (no patch copies, no temporaries
of the size of the block). It works in float64 where the reference works partly in
float32: the two agree to ~1e-5 px in position and ~1e-5 relative in luminance
(``tests/test_frame_kernels.py``).

Conventions as in :mod:`iscd.decode.tracking.luminance`: x right, y down, pixel centres at
integers, positions in px, luminance in DN; a patch at the image edge is moved inside.
"""

from __future__ import annotations

import math

import numpy as np

from iscd.core.jit import njit


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
    within spot_r px of their refined centres (:func:`~iscd.decode.tracking.luminance.half_max_area`)."""
    F = L.shape[0]
    N = starts.shape[1]
    n = sel.size
    K = 2 * half + 1
    FF = 2 * F
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
    # the selected ones, whose lit judgement alone needs it)
    if has_bg:
        nb = N if bg_lum else n
        for g in range(2):
            fr = L if g == 0 else R
            bgi = bg_l if g == 0 else bg_r
            sti = st_l if g == 0 else st_r
            for f in range(F):
                for jb in range(nb):
                    i = jb if bg_lum else sel[jb]
                    xa, ya = x0[g * F + f, i], y0[g * F + f, i]
                    for a in range(K):
                        row = fr[f, ya + a, xa:xa + K]
                        brow = bgi[ya + a, xa:xa + K]
                        srow = sti[ya + a, xa:xa + K]
                        for b in range(K):
                            if srow[b] != blk:
                                srow[b] = blk
                                brow[b] += np.float32(rise)
                            v = np.float32(row[b])
                            if v < brow[b]:
                                brow[b] = v
    # ---- per selected LED and frame: patch sum, patch minimum, and (patches that stay
    # put over the block) each pixel's least value over the block's frames
    pmin = np.empty((FF, n))
    shown = np.empty((FF, n))
    lit = np.empty((FF, n), np.bool_)
    bg = np.empty((K, K), np.int32)
    for g in range(2):
        fr = L if g == 0 else R
        fixed = F > 1
        for f in range(F):
            for j in range(n):
                i = sel[j]
                if x0[g * F + f, i] != x0[g * F, i] or y0[g * F + f, i] != y0[g * F, i]:
                    fixed = False
        for j in range(n):
            i = sel[j]
            if fixed:
                xa, ya = x0[g * F, i], y0[g * F, i]
                for a in range(K):
                    for b in range(K):
                        bg[a, b] = np.int32(fr[0, ya + a, xa + b])
            for f in range(F):
                q = g * F + f
                xa, ya = x0[q, i], y0[q, i]
                tot = np.int32(0)
                m = np.int32(fr[f, ya, xa])
                for a in range(K):
                    for b in range(K):
                        v = np.int32(fr[f, ya + a, xa + b])
                        tot += v
                        m = min(m, v)
                        if fixed:
                            bg[a, b] = min(bg[a, b], v)
                pmin[q, j] = m
                shown[q, j] = np.int64(tot) - K * K * np.int64(m)
            if fixed:
                sb = 0
                for a in range(K):
                    for b in range(K):
                        sb += np.int64(bg[a, b])
                for f in range(F):
                    q = g * F + f
                    shown[q, j] += K * K * pmin[q, j] - sb
        if has_bg:  # the light above the held per-pixel background instead
            bgi = bg_l if g == 0 else bg_r
            for j in range(n):
                i = sel[j]
                for f in range(F):
                    q = g * F + f
                    xa, ya = x0[q, i], y0[q, i]
                    sv = 0.0
                    for a in range(K):
                        row = fr[f, ya + a, xa:xa + K]
                        brow = bgi[ya + a, xa:xa + K]
                        for b in range(K):
                            sv += float(row[b]) - float(brow[b])
                    shown[q, j] = sv
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
                tot = 0.0
                sx = 0.0
                sy = 0.0
                swx = 0.0
                sxw = 0.0
                for k in range(b0, b1):
                    xw[k] = wx[k] * (xa + k)
                    swx += wx[k]
                    sxw += xw[k]
                fr = L if q < F else R
                bgi = bg_l if q < F else bg_r
                f = q if q < F else q - F
                m = pmin[q, j]
                for a in range(a0, a1):
                    row = fr[f, ya + a, xa:xa + K]
                    ra = 0.0
                    rx = 0.0
                    if bg_lum:  # light above each pixel's background
                        brow = bgi[ya + a, xa:xa + K]
                        for b in range(b0, b1):
                            v = float(row[b]) - float(brow[b])
                            ra += v * wx[b]
                            rx += v * xw[b]
                    else:
                        for b in range(b0, b1):
                            v = float(row[b])
                            ra += v * wx[b]
                            rx += v * xw[b]
                        ra -= m * swx  # light above the patch minimum
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
    # ---- Gaussian-weighted luminance of every LED at its refined position
    for g in range(2):
        fr = L if g == 0 else R
        bgi = bg_l if g == 0 else bg_r
        a2 = -0.5 / (sigmas[g] * sigmas[g])
        for f in range(F):
            q = g * F + f
            for i in range(N):
                xa, ya = x0[q, i], y0[q, i]
                cx, cy = cc[q, i, 0], cc[q, i, 1]
                swx = _gauss_row(wx, xa - cx, a2, K)
                swy = _gauss_row(wy, ya - cy, a2, K)
                s = 0.0
                for a in range(K):
                    row = fr[f, ya + a, xa:xa + K]
                    r = 0.0
                    if bg_lum:
                        brow = bgi[ya + a, xa:xa + K]
                        for b in range(K):
                            r += (float(row[b]) - float(brow[b])) * wx[b]
                    else:
                        for b in range(K):
                            r += float(row[b]) * wx[b]
                    s += wy[a] * r
                out_lum[q, i] = s / (swx * swy)
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
                                scale: bool = True, accelerate: bool = True
                                ) -> tuple[list[np.ndarray], list[np.ndarray]]:
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
    from iscd.decode.tracking.luminance import LIT_SHARE, patch_half

    lit_share = LIT_SHARE if lit_share is None else lit_share

    if len(frames) != 2:
        raise ValueError(f"follow_and_measure_compiled takes two cameras, got {len(frames)}")
    # writable C-contiguous arguments (a read-only array is another type to Numba)
    L, R = (np.require(f, requirements=["C", "W"]) for f in frames)
    if L.dtype != R.dtype:
        R = R.astype(L.dtype)
    F = L.shape[0]
    half = max(patch_half(size, max_px), int(np.ceil(3.5 * max(sigmas))) + 1)
    K = 2 * half + 1
    if min(L.shape[1:] + R.shape[1:]) < K:  # an image smaller than a patch: the reference
        from iscd.decode.tracking.luminance import follow_and_measure  # repeats its edge pixels

        return follow_and_measure([L, R], starts, size, sigmas, use, iterations, lit_light, info,
                                  backgrounds, spot_radius_px, subtract)
    st = np.empty((2 * F,) + np.shape(starts[0])[-2:], np.float64)
    st[:F] = np.asarray(starts[0], dtype=np.float64)
    st[F:] = np.asarray(starts[1], dtype=np.float64)
    N = st.shape[1]
    sel = np.arange(N, dtype=np.int64) if use is None else np.asarray(use, dtype=np.int64)
    ref = np.full(2, -1.0) if lit_light is None else np.asarray(lit_light, dtype=np.float64).reshape(2)
    c = np.empty_like(st)
    lum = np.empty((2 * F, N))
    light = np.empty(2)
    sel = np.require(sel, requirements=["C", "W"])
    ref = np.require(ref, requirements=["C", "W"])
    if backgrounds is None:
        has_bg, bgs, sts, blk, rise = False, (_NO_BG, _NO_BG), (_NO_STAMP, _NO_STAMP), 0, 0.0
    else:
        if len(backgrounds) != 2 or backgrounds[0].rise_dn != backgrounds[1].rise_dn:
            raise ValueError("backgrounds: one PixelBackground per camera, with one rise_dn")
        for b, fr in zip(backgrounds, (L, R)):
            if b.bg.shape != fr.shape[1:]:
                raise ValueError(f"background of {b.bg.shape} px for frames of {fr.shape[1:]} px")
            b.block += 1
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
