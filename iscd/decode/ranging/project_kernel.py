"""The live ranging's per-pixel work as compiled kernels (identity rectification).

:meth:`iscd.decode.ranging.stereo.StereoRanger.measure` cuts each camera's patch out of a block of
frames, keeps a running per-pixel minimum of it (the background), takes each frame's
pedestal (median of the patch's outer ring after the background) and noise (1.4826 MAD),
a matched-filter signal and the row-weighted projection onto x that the ``"iscd-fast"``
estimator matches (:mod:`iscd.decode.ranging.projected`). Its numpy reference does this with a
dozen (n, h, w) temporaries; here one pass over each patch's pixels, read straight out
of the frames (pixels outside the image count as 0, as the reference's zero padding):

* :func:`patch_minimum` -- the block's per-pixel minimum of the patch (h, w);
* :func:`project_patches` -- per frame the pedestal and MAD of the ring residual, the
  matched-filter sum and the profile (n, w): the sums of the frame as it is
  (:func:`_project_raw`), the background taken off afterwards (:func:`_project_finish`,
  linear), so that the block's minimum can be taken in the same pass
  (:func:`_range_live`, the live case: minima, background, projections, correlation peak
  and ranges of a block in one call).

The ring medians are exact: the residuals are differences of integers, counted (the same
order statistics as np.median, without its partitioning); the sums are in float64 where
the reference sums partly in float32 (agreement ~1e-6 relative,
``tests/test_frame_kernels.py``).
"""

from __future__ import annotations

import numpy as np

from iscd.core.jit import njit, register_warm
from iscd.decode.ranging.spectral import _TINY, Peak1D, _spectral


_FAST = {"reassoc", "contract", "nsz", "arcp"}
"""fastmath flags that let LLVM vectorize the sums (reassociation), but keep inf/NaN."""


@njit
def _patch_minimum(fr, x0: int, y0: int, out: np.ndarray) -> None:
    """out (h, w) of the frames' dtype: the per-pixel minimum over the frames of the
    patch at (x0, y0), in-image pixels only (the rest is left as it is)."""
    n, H, W = fr.shape
    h, w = out.shape
    ya, yb = max(0, -y0), min(h, H - y0)
    xa, xb = max(0, -x0), min(w, W - x0)
    if ya >= yb or xa >= xb:
        return
    for a in range(ya, yb):  # native dtype, no branches: it vectorizes
        out[a, xa:xb] = fr[0, y0 + a, x0 + xa:x0 + xb]
    for f in range(1, n):
        for a in range(ya, yb):
            row = fr[f, y0 + a, x0 + xa:x0 + xb]
            oa = out[a, xa:xb]
            for b in range(xb - xa):
                oa[b] = min(oa[b], row[b])


def _w(a: np.ndarray, dtype: type) -> np.ndarray:
    """``a`` as a writable C-contiguous array of ``dtype`` (copied only if it is not one)."""
    return np.require(a, dtype=dtype, requirements=["C", "W"])


def patch_minimum(frames: np.ndarray, x0: int, y0: int, h: int, w: int) -> np.ndarray:
    """Per-pixel minimum over a block of frames of one patch.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN.
    x0, y0 : int
        Top-left pixel of the patch, px.
    h, w : int
        Patch size, px.

    Returns
    -------
    ndarray of float32
        (h, w) minimum, DN (0 outside the image).
    """
    fr = np.require(frames, requirements=["C", "W"])
    out = np.zeros((h, w), fr.dtype)
    _patch_minimum(fr, int(x0), int(y0), out)
    return out.astype(np.float32)


_HIST = 4096
"""bins of the ring medians' value histogram (a frame's ring residuals spanning more integer
values than this, or not integers, take np.median)"""


@njit
def _nth_bin(hist: np.ndarray, span: int, kth: int, two: bool) -> tuple[int, int]:
    """Bins of the ``kth`` and (``two``) the ``kth + 1``-th smallest value counted in
    ``hist[:span]`` (0-based; the second is the first if not ``two``)."""
    c = 0
    j = 0
    while j < span - 1:
        c += hist[j]
        if c > kth:
            break
        j += 1
    else:
        c += hist[j]
    a = j
    if not two or c > kth + 1:
        return a, a
    j += 1
    while j < span - 1 and hist[j] == 0:
        j += 1
    return a, j


@njit
def _dist_count(hist: np.ndarray, span: int, m: int, odd: bool, t: int) -> int:
    """Values counted in ``hist[:span]`` at distance ``t`` (in steps) from the centre:
    bins m - t and m + t (``odd``: m - t and m + 1 + t, the centre between m and m + 1)."""
    c = 0
    lo = m - t
    hi = m + 1 + t if odd else m + t
    if 0 <= lo < span:
        c += hist[lo]
    if hi != lo and 0 <= hi < span:
        c += hist[hi]
    return c


@njit
def _median_mad_int(iv: np.ndarray, lo: int, span: int, hist: np.ndarray) -> tuple[float, float]:
    """np.median of the k integers ``lo + (iv - lo)`` (all in [lo, lo + span)) and np.median of
    their absolute deviations from it, exactly (the same order statistics and the same
    ``(a + b) / 2``): one histogram, the median by its running count, the deviations' median by
    walking outwards from the median."""
    k = iv.size
    if span <= 24:  # a few values (the usual ring): count each by a vectorized compare
        for j in range(span):
            t = lo + j
            c = 0
            for i in range(k):
                c += 1 if iv[i] == t else 0
            hist[j] = c
    else:
        for j in range(span):
            hist[j] = 0
        for i in range(k):
            hist[iv[i] - lo] += 1
    half = k >> 1
    even = (k & 1) == 0
    a, b = _nth_bin(hist, span, half - 1 if even else half, even)
    p2 = a + b if even else 2 * a  # twice the median, relative to lo
    p = (float(lo + a) + float(lo + b)) / 2 if even else float(lo + a)
    # |x - p| in half steps: p2 even -> 0, 2, 4, ... (bins m -/+ t); odd -> 1, 3, ... (m - t, m + 1 + t)
    odd = (p2 & 1) == 1
    m = p2 >> 1
    kth = half - 1 if even else half
    c = 0
    t = 0
    da = -1
    db = -1
    while True:
        cnt = _dist_count(hist, span, m, odd, t)
        if cnt > 0:
            d2 = 2 * t + 1 if odd else 2 * t
            c += cnt
            if da < 0 and c > kth:
                da = d2
                if not even or c > kth + 1:
                    db = d2
                    break
            elif da >= 0:
                db = d2
                break
        t += 1
        if t > span:  # cannot happen (every value is within span of the median)
            break
    if even:
        return p, (0.5 * da + 0.5 * db) / 2
    return p, 0.5 * da


@njit
def _ring_rc(ring: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """The ring's flat indices in an (h, w) patch as rows and columns."""
    k = ring.size
    r_a = np.empty(k, np.int64)
    r_b = np.empty(k, np.int64)
    for i in range(k):
        r_a[i] = ring[i] // w
        r_b[i] = ring[i] % w
    return r_a, r_b


@njit
def _small_int_frames(fr) -> bool:
    """Whether the frames are of an integer type of at most 16 bits (their ring residuals
    against a background of integers are exact int32)."""
    probe = np.zeros(1, fr.dtype)
    probe[0] = 0.5
    return probe[0] == 0 and fr.itemsize <= 2


@njit(fastmath=_FAST)
def _project_raw(fr, x0: int, y0: int, h: int, r_a: np.ndarray, r_b: np.ndarray, snr_w: np.ndarray,
                 row_w: np.ndarray, prof: np.ndarray, s_raw: np.ndarray, rv: np.ndarray, mn: np.ndarray,
                 with_min: bool) -> None:
    """The one pass over the frames' pixels of the (h, w) patch at (x0, y0) (pixels outside
    the image count as 0): per frame the projection ``prof[f] = row_w @ patch`` (n, w), the
    matched-filter sum ``s_raw[f] = snr_w . patch`` and the ring's pixel values ``rv[f]``
    (n, k), all before the background; ``with_min``: also the per-pixel minimum over the
    frames ``mn`` (h, w, of the frames' dtype; 0 outside the image)."""
    n, H, W = fr.shape
    w = prof.shape[1]
    k = r_a.size
    xa = max(0, -x0)
    xb = min(w, W - x0)
    if with_min:
        mn[:] = 0
    inside = True
    for i in range(k):
        if not (0 <= y0 + r_a[i] < H and 0 <= x0 + r_b[i] < W):
            inside = False
    for f in range(n):
        frf = fr[f]
        s = 0.0
        pf = prof[f]
        for b in range(w):
            pf[b] = 0.0
        if xb > xa:
            for a in range(h):
                y = y0 + a
                if y < 0 or y >= H:
                    continue
                ra = row_w[a]
                row = frf[y, x0 + xa:x0 + xb]  # hoisted slices: the inner loops vectorize
                sw = snr_w[a * w + xa:a * w + xb]
                pp = pf[xa:xb]
                for b in range(xb - xa):
                    v = float(row[b])
                    pp[b] += ra * v
                    s += sw[b] * v
                if with_min:  # the row is in cache now; native dtype, no branches
                    ma = mn[a, xa:xb]
                    if f == 0:
                        for b in range(xb - xa):
                            ma[b] = row[b]
                    else:
                        for b in range(xb - xa):
                            ma[b] = min(ma[b], row[b])
        s_raw[f] = s
        # the ring's pixels (just read: in cache)
        rf = rv[f]
        if inside:
            for i in range(k):
                rf[i] = float(frf[y0 + r_a[i], x0 + r_b[i]])
        else:
            for i in range(k):
                y, x = y0 + r_a[i], x0 + r_b[i]
                rf[i] = float(frf[y, x]) if 0 <= y < H and 0 <= x < W else 0.0


@njit(fastmath=_FAST)
def _project_finish(bg: np.ndarray, r_a: np.ndarray, r_b: np.ndarray, rv: np.ndarray, int_frames: bool,
                    snr_w: np.ndarray, row_w: np.ndarray, prof: np.ndarray, s_raw: np.ndarray,
                    ped: np.ndarray, mad: np.ndarray, snr_sum: np.ndarray) -> None:
    """The background ``bg`` (h, w) taken off :func:`_project_raw`'s sums: per frame the
    pedestal (median of the ring residual ``rv - bg``) and its 1.4826 MAD, the matched-filter
    signal ``s_raw - snr_w . bg - pedestal * sum(snr_w)`` and the profile, in place,
    ``prof - row_w @ bg - pedestal * sum(row_w)``. ``int_frames``: ``rv`` holds the values
    of integer frames of at most 16 bits (:func:`_small_int_frames`)."""
    n, w = prof.shape
    h = bg.shape[0]
    k = r_a.size
    vals = np.empty(k)
    dev = np.empty(k)
    iv = np.empty(k, np.int32)
    hist = np.empty(_HIST, np.int64)
    r_bg = np.empty(k)
    r_bgi = np.empty(k, np.int32)
    # integer frames and a background of integers at the ring (the live case: minima of
    # the frames): the ring residuals are integers, their medians by counting (exact)
    integer = int_frames and k > 0
    for i in range(k):
        v = float(bg[r_a[i], r_b[i]])
        r_bg[i] = v
        if abs(v) < 1e9 and int(v) == v:
            r_bgi[i] = np.int32(v)
        else:
            integer = False
    sw_tot = 0.0
    for i in range(h * w):
        sw_tot += snr_w[i]
    rw_tot = 0.0
    for a in range(h):
        rw_tot += row_w[a]
    # the background's projection and matched-filter sum (the same for every frame)
    bg_prof = np.zeros(w)
    bg_snr = 0.0
    for a in range(h):
        ra = row_w[a]
        bga = bg[a]
        sw = snr_w[a * w:a * w + w]
        for b in range(w):
            v = float(bga[b])
            bg_prof[b] += ra * v
            bg_snr += sw[b] * v
    for f in range(n):
        rf = rv[f]
        counted = False
        if integer:
            for i in range(k):
                iv[i] = np.int32(rf[i]) - r_bgi[i]
            lo = iv[0]
            hi = iv[0]
            for i in range(1, k):
                lo = min(lo, iv[i])
                hi = max(hi, iv[i])
            if hi - lo < _HIST:
                p, md = _median_mad_int(iv, lo, hi - lo + 1, hist)
                counted = True
        if not counted:
            for i in range(k):
                vals[i] = rf[i] - r_bg[i]
            p = np.median(vals)  # selection, not a sort (exact: the same order statistic)
            for i in range(k):
                dev[i] = abs(vals[i] - p)
            md = np.median(dev)
        ped[f] = p
        mad[f] = 1.4826 * md
        snr_sum[f] = s_raw[f] - bg_snr - p * sw_tot
        pf = prof[f]
        for b in range(w):
            pf[b] -= bg_prof[b] + p * rw_tot


@njit
def _project(fr, x0: int, y0: int, bg: np.ndarray, ring: np.ndarray, snr_w: np.ndarray,
             row_w: np.ndarray, ped: np.ndarray, mad: np.ndarray, snr_sum: np.ndarray,
             prof: np.ndarray) -> None:
    """See :func:`project_patches`: :func:`_project_raw` then :func:`_project_finish`."""
    n = fr.shape[0]
    h, w = bg.shape
    r_a, r_b = _ring_rc(ring, w)
    s_raw = np.empty(n)
    rv = np.empty((n, ring.size))
    _project_raw(fr, x0, y0, h, r_a, r_b, snr_w, row_w, prof, s_raw, rv, np.empty((1, 1), fr.dtype), False)
    _project_finish(bg, r_a, r_b, rv, _small_int_frames(fr), snr_w, row_w, prof, s_raw, ped, mad, snr_sum)


def project_patches(frames: np.ndarray, x0: int, y0: int, background: np.ndarray, ring: np.ndarray,
                    snr_weights: np.ndarray, row_weights: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pedestal, noise, matched-filter signal and row-weighted profile of a patch, per frame.

    Per frame of ``frames`` (n, H, W), for the (h, w) patch at (x0, y0) px with its
    ``background`` (h, w) grey levels: the pedestal (median of the ring residual, ``ring``
    flat indices), its 1.4826 MAD, the matched-filter signal ``snr_weights . (patch - bg -
    pedestal)`` and the profile ``row_weights @ (patch - bg - pedestal)`` (n, w).

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN.
    x0, y0 : int
        Top-left pixel of the patch, px.
    background : ndarray
        (h, w) background of the patch, DN.
    ring : ndarray
        Flat indices of the patch's outer ring (:func:`iscd.decode.ranging.projected.ring_indices`).
    snr_weights : ndarray
        (h, w) matched-filter weights.
    row_weights : ndarray
        (h,) projection weights.

    Returns
    -------
    pedestal, mad, signal : ndarray
        Each (n,), DN.
    profile : ndarray
        (n, w), DN.
    """
    n = frames.shape[0]
    h, w = background.shape
    ped, mad, sig = np.empty(n), np.empty(n), np.empty(n)
    prof = np.empty((n, w))
    # writable, contiguous arguments: a read-only array is another type to Numba (and would
    # compile a second time at the first live call)
    _project(np.require(frames, requirements=["C", "W"]), int(x0), int(y0), _w(background, np.float32),
             _w(ring, np.int64), _w(snr_weights, np.float64), _w(row_weights, np.float64),
             ped, mad, sig, prof)
    return ped, mad, sig, prof


def _warm(dtype: type) -> tuple:
    fr = np.zeros((2, 8, 8), dtype)
    return (fr, 1, 1, np.zeros((4, 4), dtype))


def _warm_p(dtype: type) -> tuple:
    fr = np.zeros((2, 8, 8), dtype)
    return (fr, 1, 1, np.zeros((4, 4), np.float32), np.arange(4, dtype=np.int64), np.zeros(16),
            np.zeros(4), np.empty(2), np.empty(2), np.empty(2), np.empty((2, 4)))


for _dt in (np.uint8, np.uint16):
    register_warm(_patch_minimum, lambda _dt=_dt: _warm(_dt))
    register_warm(_project, lambda _dt=_dt: _warm_p(_dt))


# ---------------------------------------------------------------- the 1-D correlation peak
@njit(fastmath=_FAST)
def _rotated(xr: float, xi: float, m: float, om: float, pos: float) -> tuple[float, float]:
    """m * X exp(i om pos) as (real, imaginary): one term of the correlation at ``pos``."""
    c = np.cos(om * pos)
    s = np.sin(om * pos)
    return m * (xr * c - xi * s), m * (xr * s + xi * c)


@njit(fastmath=_FAST)
def _surface_at(xr: np.ndarray, xi: np.ndarray, cos_t: np.ndarray, sin_t: np.ndarray, mult: np.ndarray,
                j: int, w: int) -> float:
    """The correlation at integer lag ``j`` (the inverse transform at one sample)."""
    s = 0.0
    for k in range(xr.size):
        s += mult[k] * (xr[k] * cos_t[k, j] - xi[k] * sin_t[k, j])
    return s / w


@njit(fastmath=_FAST)
def _phase_sums(xr: np.ndarray, xi: np.ndarray, mult: np.ndarray, omega: np.ndarray, w2: np.ndarray,
                w2m: np.ndarray, harmonic: bool, pos: float, rot_re: np.ndarray, rot_im: np.ndarray
                ) -> None:
    """rot_re, rot_im (nk,) = mult X exp(i omega pos) (:func:`_rotated` of every bin); for
    harmonic bins (omega_k = k omega_1) by a rotation recurrence, two trigonometric calls in
    all instead of two per bin (agreement ~1e-15 relative)."""
    nk = xr.size
    if harmonic:
        c1 = np.cos(omega[1] * pos)
        s1 = np.sin(omega[1] * pos)
        c = 1.0
        s = 0.0
        for k in range(nk):
            m = mult[k]
            rot_re[k] = m * (xr[k] * c - xi[k] * s)
            rot_im[k] = m * (xr[k] * s + xi[k] * c)
            c, s = c * c1 - s * s1, s * c1 + c * s1
    else:
        for k in range(nk):
            rot_re[k], rot_im[k] = _rotated(xr[k], xi[k], mult[k], omega[k], pos)


@njit(fastmath=_FAST)
def _correlate(left: np.ndarray, right: np.ndarray, cos_t: np.ndarray, sin_t: np.ndarray,
               omega: np.ndarray, mult: np.ndarray, band: np.ndarray, w2: np.ndarray, w2m: np.ndarray,
               beta: float, max_shift: float, iterations: int, tiny: float,
               dx: np.ndarray, height: np.ndarray, sigma: np.ndarray) -> None:
    n, w = left.shape
    nk = omega.size
    xr = np.empty(nk)
    xi = np.empty(nk)
    rot_re = np.empty(nk)
    rot_im = np.empty(nk)
    # the bins are the rfft's (omega_k = 2 pi k / w): the rotations by recurrence
    harmonic = nk >= 2 and omega[0] == 0.0
    for k in range(2, nk):
        if abs(omega[k] - k * omega[1]) > 1e-12 * abs(omega[k]):
            harmonic = False
    half = (w + 1) // 2
    # the lags the integer peak search and its neighbours read (all w without a limit), in
    # the order of j, with their rows of the inverse transform's tables (contiguous in k)
    if max_shift >= 0 and 2 * (int(np.floor(max_shift)) + 1) + 1 < w:
        lm = int(np.floor(max_shift)) + 1
        js = np.empty(2 * lm + 1, np.int64)
        for q in range(lm + 1):
            js[q] = q
        for q in range(lm):
            js[lm + 1 + q] = w - lm + q
    else:
        js = np.arange(w)
    nj = js.size
    q_of = np.full(w, -1, np.int64)
    tab_c = np.empty((nj, nk))
    tab_s = np.empty((nj, nk))
    for q in range(nj):
        q_of[js[q]] = q
        for k in range(nk):
            tab_c[q, k] = cos_t[k, js[q]]
            tab_s[q, k] = sin_t[k, js[q]]
    surf = np.empty(nj)
    for f in range(n):
        # cross-power spectrum X = F_l conj(F_r), weighted |X|^-beta, band-limited
        lf = left[f]
        rf = right[f]
        for k in range(nk):
            lr = 0.0
            li = 0.0
            rr = 0.0
            ri = 0.0
            ck = cos_t[k]
            sk = sin_t[k]
            for j in range(w):
                lr += lf[j] * ck[j]
                li -= lf[j] * sk[j]
                rr += rf[j] * ck[j]
                ri -= rf[j] * sk[j]
            a = lr * rr + li * ri
            b = li * rr - lr * ri
            if beta == 0.5:
                g = 1.0 / np.sqrt(np.sqrt(a * a + b * b) + tiny)
                a *= g
                b *= g
            elif beta != 0.0:
                g = (np.sqrt(a * a + b * b) + tiny) ** (-beta)
                a *= g
                b *= g
            xr[k] = a * band[k]
            xi[k] = b * band[k]
        # the correlation at the integer lags searched (only those: |lag| <= max_shift) and
        # its integer peak (the first of equals, in the order of j)
        best = -np.inf
        i0 = 0
        for q in range(nj):
            tc = tab_c[q]
            ts = tab_s[q]
            v = 0.0
            for k in range(nk):
                v += mult[k] * (xr[k] * tc[k] - xi[k] * ts[k])
            v /= w
            surf[q] = v
            j = js[q]
            lag = j if j < half else j - w
            if max_shift >= 0 and abs(lag) > max_shift:
                continue
            if v > best:
                best = v
                i0 = j
        ql, qh = q_of[(i0 - 1) % w], q_of[(i0 + 1) % w]
        lo = surf[ql] if ql >= 0 else _surface_at(xr, xi, cos_t, sin_t, mult, (i0 - 1) % w, w)
        c0 = surf[q_of[i0]]
        hi = surf[qh] if qh >= 0 else _surface_at(xr, xi, cos_t, sin_t, mult, (i0 + 1) % w, w)
        den = lo - 2.0 * c0 + hi
        off = 0.5 * (lo - hi) / den if den < -tiny else 0.0
        pos = (i0 - w if i0 >= half else i0) + min(max(off, -0.5), 0.5)
        # Newton steps on the trigonometric interpolant
        for _ in range(iterations):
            _phase_sums(xr, xi, mult, omega, w2, w2m, harmonic, pos, rot_re, rot_im)
            a = 0.0
            b = 0.0
            for k in range(nk):
                a += rot_im[k] * omega[k]
                b += rot_re[k] * w2[k]
            step = -a / b if b > tiny else 0.0
            pos += min(max(step, -0.5), 0.5)
        _phase_sums(xr, xi, mult, omega, w2, w2m, harmonic, pos, rot_re, rot_im)
        tot = 0.0
        hr = 0.0
        hess = 0.0
        var = 0.0
        for k in range(nk):
            re = rot_re[k]
            im = rot_im[k]
            tot += mult[k] * np.sqrt(xr[k] * xr[k] + xi[k] * xi[k])
            hr += re
            hess += re * w2[k]
            var += im * im * w2m[k]
        dx[f] = pos
        height[f] = hr / tot if tot != 0.0 else np.nan
        sd = np.sqrt(2.0 * var)
        sigma[f] = sd / hess if hess > tiny else (np.inf if sd > 0 else np.nan)


_TABLES: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _tables(w: int, nk: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of 2 pi j k / w, (nk, w) (cached per w)."""
    t = _TABLES.get(w)
    if t is None:
        ang = 2.0 * np.pi * np.outer(np.arange(nk), np.arange(w)) / w
        t = (np.cos(ang), np.sin(ang))
        _TABLES[w] = t
    return t


def correlate_1d_compiled(left: np.ndarray, right: np.ndarray, beta: float = 0.5,
                          band_cutoff: float | None = 0.12, max_shift_px: float | None = None,
                          iterations: int = 2):  # -> Peak1D
    """The compiled :func:`iscd.decode.ranging.projected.correlate_1d` (same arguments and result).

    The transforms as sums over cached cos/sin tables (w is a few tens of px), the peak search
    and the Newton steps in the same loop, per profile pair (n, w).

    Parameters
    ----------
    left, right : ndarray
        (n, w) profiles, DN.
    beta : float
        Spectral weighting ``X / |X|^beta``.
    band_cutoff : float or None
        Gaussian band limit f_c, cycles/px (None: full band).
    max_shift_px : float or None
        Limit of the integer peak search, px.
    iterations : int
        Newton steps.

    Returns
    -------
    Peak1D
        As :func:`iscd.decode.ranging.projected.correlate_1d` (shifts and sigmas in px).

    References
    ----------
    Dissertation, eqs. (3.5), (3.6).
    """
    lf = _w(left, np.float64)
    rt = _w(right, np.float64)
    n, w = lf.shape
    omega, mult, band, w2, w2m = _spectral(int(w), band_cutoff)
    cos_t, sin_t = _tables(int(w), omega.size)
    dx, height, sigma = np.empty(n), np.empty(n), np.empty(n)
    omega, mult, band, w2, w2m = (_w(a, np.float64) for a in (omega, mult, band, w2, w2m))
    _correlate(lf, rt, cos_t, sin_t, omega, mult, band, w2, w2m, float(beta),
               -1.0 if max_shift_px is None else float(max_shift_px), int(iterations), _TINY,
               dx, height, sigma)
    return Peak1D(dx=dx, height=height, sigma=sigma)


def _warm_c() -> tuple:
    w, nk = 8, 5
    t = np.ones((nk, w))
    v = np.ones(nk)
    return (np.ones((2, w)), np.ones((2, w)), t, t, v, v, v, v, v, 0.5, 2.0, 2, 1e-12,
            np.empty(2), np.empty(2), np.empty(2))


register_warm(_correlate, _warm_c)


# ---------------------------------------------------------------- one call per block
@njit
def _block_minima(L, R, x0l: int, x0r: int, y0: int, out_l: np.ndarray, out_r: np.ndarray,
                  scratch: np.ndarray) -> None:
    """out_l, out_r (h, w) float32: both cameras' per-pixel patch minima over the block
    (:func:`patch_minimum` of each; 0 outside the image). ``scratch`` (h, w) of the frames'
    dtype (the minimum itself runs in it: integer minima vectorize)."""
    for g in range(2):
        out = out_l if g == 0 else out_r
        scratch[:] = 0
        _patch_minimum(L if g == 0 else R, x0l if g == 0 else x0r, y0, scratch)
        h, w = out.shape
        for a in range(h):
            for b in range(w):
                out[a, b] = np.float32(scratch[a, b])


def block_minima(left: np.ndarray, right: np.ndarray, x0l: int, x0r: int, y0: int, h: int, w: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Both cameras' per-pixel patch minima over a block of frames.

    :func:`patch_minimum` of each camera's patch in one call.

    Parameters
    ----------
    left, right : ndarray
        (n, H, W) frames of each camera, DN.
    x0l, x0r : int
        Left column of the left and right patch, px.
    y0 : int
        Top row of both patches, px.
    h, w : int
        Patch size, px.

    Returns
    -------
    min_left, min_right : ndarray of float32
        Each (h, w), DN.
    """
    L = np.require(left, requirements=["C", "W"])
    R = np.require(right, dtype=L.dtype, requirements=["C", "W"])
    out_l = np.empty((h, w), np.float32)
    out_r = np.empty((h, w), np.float32)
    _block_minima(L, R, int(x0l), int(x0r), int(y0), out_l, out_r, np.empty((h, w), L.dtype))
    return out_l, out_r


@njit
def _range_tail(off: float, ped_l, mad_l, sig_l, prof_l, mad_r, sig_r, prof_r, cos_t, sin_t, omega, mult,
                band, w2, w2m, beta: float, max_shift: float, iterations: int, tiny: float,
                floor_px: float, fb: float, quant_noise: float, min_snr: float, min_quality: float,
                z, disp, sigma_m, quality, valid, snr) -> None:
    """Both cameras' projections (:func:`_project`) to the block's ranges: the per-block
    noise, the weaker camera's SNR, the correlation peak and the range with its sigma (see
    :func:`range_block`). Not fastmath: the result arithmetic is numpy's, in numpy's order."""
    n = ped_l.size
    noise_l = max(np.sort(mad_l)[n // 2], quant_noise)
    noise_r = max(np.sort(mad_r)[n // 2], quant_noise)
    dx, height, sig = np.empty(n), np.empty(n), np.empty(n)
    _correlate(prof_l, prof_r, cos_t, sin_t, omega, mult, band, w2, w2m, beta, max_shift,
               iterations, tiny, dx, height, sig)
    for f in range(n):
        s = min(sig_l[f] / noise_l, sig_r[f] / noise_r)
        snr[f] = s
        dead = not (np.isfinite(height[f]) and np.isfinite(dx[f]))
        q = 0.0 if dead else height[f]
        quality[f] = q
        d = off + (np.nan if dead else dx[f])
        disp[f] = d
        zf = fb / d if (np.isfinite(d) and d > 0) else np.nan
        sp = np.sqrt(sig[f] ** 2 + floor_px ** 2)
        ok = np.isfinite(zf) and s >= min_snr and q >= min_quality
        valid[f] = ok
        z[f] = zf if ok else np.nan
        sigma_m[f] = zf * zf / fb * sp if ok else np.nan


@njit
def _range_block(L, R, x0l: int, x0r: int, y0: int, bg_l: np.ndarray, bg_r: np.ndarray,
                 ring: np.ndarray, snr_l: np.ndarray, snr_r: np.ndarray, row_l: np.ndarray,
                 row_r: np.ndarray, cos_t: np.ndarray, sin_t: np.ndarray, omega: np.ndarray,
                 mult: np.ndarray, band: np.ndarray, w2: np.ndarray, w2m: np.ndarray, beta: float,
                 max_shift: float, iterations: int, tiny: float, floor_px: float, fb: float,
                 quant_noise: float, min_snr: float, min_quality: float,
                 z: np.ndarray, disp: np.ndarray, sigma_m: np.ndarray, quality: np.ndarray,
                 valid: np.ndarray, snr: np.ndarray) -> None:
    """See :func:`range_block` (the inner kernels keep their own fastmath flags)."""
    n = L.shape[0]
    w = bg_l.shape[1]
    ped_l, mad_l, sig_l, prof_l = np.empty(n), np.empty(n), np.empty(n), np.empty((n, w))
    ped_r, mad_r, sig_r, prof_r = np.empty(n), np.empty(n), np.empty(n), np.empty((n, w))
    _project(L, x0l, y0, bg_l, ring, snr_l, row_l, ped_l, mad_l, sig_l, prof_l)
    _project(R, x0r, y0, bg_r, ring, snr_r, row_r, ped_r, mad_r, sig_r, prof_r)
    _range_tail(float(x0l - x0r), ped_l, mad_l, sig_l, prof_l, mad_r, sig_r, prof_r, cos_t, sin_t,
                omega, mult, band, w2, w2m, beta, max_shift, iterations, tiny, floor_px, fb,
                quant_noise, min_snr, min_quality, z, disp, sigma_m, quality, valid, snr)


@njit
def _range_live(L, R, geo: np.ndarray, par: np.ndarray, ring: np.ndarray, snr_w: np.ndarray,
                row_w: np.ndarray, cos_t: np.ndarray, sin_t: np.ndarray, spec: np.ndarray,
                held_l: np.ndarray, held_r: np.ndarray, cur_l: np.ndarray, cur_r: np.ndarray,
                out: np.ndarray, valid: np.ndarray) -> None:
    """A block's ranges, its block minima included, in one pass over each patch's pixels
    (the live case of :meth:`iscd.decode.ranging.stereo.StereoRanger.measure`; the same
    numbers as :func:`block_minima`, the running minimum and :func:`range_block`).

    ``geo`` (int64): x0l, x0r, y0, Newton iterations; ``par`` (float64): beta, max_shift
    (< 0: none), tiny, sigma floor (px), f*b, quantization noise, min SNR, min quality;
    ``snr_w`` (2, h*w) and ``row_w`` (2, h) the left and right weights; ``spec`` (5, nk) the
    spectral rows omega, mult, band, omega^2, omega^2/mult; ``held_l``/``held_r`` (h, w)
    float32 the minimum over the background's held blocks (+inf where none); out:
    ``cur_l``/``cur_r`` (h, w) float32 the block's own per-pixel minima (0 outside the
    image), ``out`` (5, n) z, disparity, sigma, quality, SNR and ``valid`` (n,)."""
    n = L.shape[0]
    h, w = cur_l.shape
    x0l, x0r, y0 = geo[0], geo[1], geo[2]
    r_a, r_b = _ring_rc(ring, w)
    k = ring.size
    int_frames = _small_int_frames(L)
    mn = np.empty((h, w), L.dtype)
    bg = np.empty((h, w), np.float32)
    res = []
    for g in range(2):
        fr = L if g == 0 else R
        cur = cur_l if g == 0 else cur_r
        held = held_l if g == 0 else held_r
        prof = np.empty((n, w))
        s_raw = np.empty(n)
        rv = np.empty((n, k))
        _project_raw(fr, x0l if g == 0 else x0r, y0, h, r_a, r_b, snr_w[g], row_w[g], prof, s_raw,
                     rv, mn, True)
        for a in range(h):
            for b in range(w):
                c = np.float32(mn[a, b])
                cur[a, b] = c
                bg[a, b] = min(c, held[a, b])
        ped, mad, sig = np.empty(n), np.empty(n), np.empty(n)
        _project_finish(bg, r_a, r_b, rv, int_frames, snr_w[g], row_w[g], prof, s_raw, ped, mad, sig)
        res.append((ped, mad, sig, prof))
    ped_l, mad_l, sig_l, prof_l = res[0]
    _, mad_r, sig_r, prof_r = res[1]
    _range_tail(float(x0l - x0r), ped_l, mad_l, sig_l, prof_l, mad_r, sig_r, prof_r, cos_t, sin_t,
                spec[0], spec[1], spec[2], spec[3], spec[4], par[0], par[1], geo[3], par[2], par[3],
                par[4], par[5], par[6], par[7], out[0], out[1], out[2], out[3], valid, out[4])


_SPECTRAL_W: dict[tuple[int, float | None], tuple[np.ndarray, ...]] = {}
"""writable copies of :func:`iscd.decode.ranging.spectral._spectral` per (w, band cutoff)"""


def range_block(left: np.ndarray, right: np.ndarray, x0l: int, x0r: int, y0: int, bg_left: np.ndarray,
                bg_right: np.ndarray, ring: np.ndarray, snr_left: np.ndarray, snr_right: np.ndarray,
                row_left: np.ndarray, row_right: np.ndarray, *, beta: float, band_cutoff: float | None,
                max_shift_px: float | None, iterations: int, sigma_floor_px: float, focal_px: float,
                baseline_m: float, quant_noise_dn: float, min_snr: float, min_quality: float
                ) -> tuple[np.ndarray, ...]:
    """A block's ranges in one compiled call.

    The live case of :meth:`iscd.decode.ranging.stereo.StereoRanger.measure`: identity rectification,
    ``"iscd-fast"`` with row weights, no core refill: both cameras' :func:`project_patches`,
    the per-block noise (median over the frames of the ring MAD, at least ``quant_noise_dn``),
    the weaker camera's matched-filter SNR, :func:`correlate_1d_compiled` of the profiles and
    the range with its standard deviation (:func:`iscd.decode.ranging.range.range_from_disparity`,
    :func:`~iscd.decode.ranging.range.range_sigma`; ``sigma_floor_px`` added in quadrature).

    Parameters
    ----------
    left, right : ndarray
        (n, H, W) frames, DN.
    x0l, x0r, y0 : int
        The patches' top-left corners (x0l, y0) and (x0r, y0), px.
    bg_left, bg_right : ndarray
        (h, w) backgrounds of the patches, DN.
    ring : ndarray
        As :func:`project_patches`.
    snr_left, snr_right : ndarray
        (h, w) matched-filter weights, as :func:`project_patches`.
    row_left, row_right : ndarray
        (h,) projection weights, as :func:`project_patches`.
    beta, band_cutoff, max_shift_px, iterations
        Keyword-only; as :func:`correlate_1d_compiled` (cycles/px, px).
    sigma_floor_px : float
        Keyword-only. Added in quadrature to the disparity sigma, px.
    focal_px : float
        Keyword-only. f / rho, px.
    baseline_m : float
        Keyword-only. Stereo baseline b, m.
    quant_noise_dn : float
        Keyword-only. Lowest noise per pixel, DN.
    min_snr, min_quality : float
        Keyword-only. Frames below either are not valid.

    Returns
    -------
    z, disparity, sigma : ndarray
        (n,) range, m; disparity, px; range sigma, m. z and sigma NaN where not valid (frames
        below ``min_snr`` or ``min_quality``, no peak, d <= 0).
    quality : ndarray
        (n,) correlation peak height.
    valid : ndarray of bool
        (n,).
    snr : ndarray
        (n,) the weaker camera's matched-filter SNR.

    References
    ----------
    Dissertation, eq. (2.2) (the range).
    """
    L = np.require(left, requirements=["C", "W"])
    R = np.require(right, dtype=L.dtype, requirements=["C", "W"])
    n = L.shape[0]
    rest = range_block_args(
        int(np.shape(bg_left)[1]), ring, snr_left, snr_right, row_left, row_right, beta=beta,
        band_cutoff=band_cutoff, max_shift_px=max_shift_px, iterations=iterations,
        sigma_floor_px=sigma_floor_px, focal_px=focal_px, baseline_m=baseline_m,
        quant_noise_dn=quant_noise_dn, min_snr=min_snr, min_quality=min_quality)
    out = [np.empty(n) for _ in range(4)]
    valid = np.empty(n, np.bool_)
    snr = np.empty(n)
    _range_block(L, R, int(x0l), int(x0r), int(y0), _w(bg_left, np.float32), _w(bg_right, np.float32),
                 *rest, out[0], out[1], out[2], out[3], valid, snr)
    z, d, sig, q = out
    return z, d, sig, q, valid, snr


def range_block_args(w: int, ring: np.ndarray, snr_left: np.ndarray, snr_right: np.ndarray,
                     row_left: np.ndarray, row_right: np.ndarray, *, beta: float,
                     band_cutoff: float | None, max_shift_px: float | None, iterations: int,
                     sigma_floor_px: float, focal_px: float, baseline_m: float, quant_noise_dn: float,
                     min_snr: float, min_quality: float) -> tuple:
    """The arguments of the compiled block ranging from ``ring`` to ``min_quality`` (what
    :func:`range_block` passes it besides the frames, the patches' corners and backgrounds and
    the outputs), as the kernel's types: made once per patch geometry by a caller that ranges
    block after block with it (:meth:`iscd.decode.ranging.stereo.StereoRanger.measure`).

    Parameters
    ----------
    w : int
        Patch width, px.
    ring, snr_left, snr_right, row_left, row_right
        As :func:`range_block`.
    beta, band_cutoff, max_shift_px, iterations, sigma_floor_px, focal_px, baseline_m,
    quant_noise_dn, min_snr, min_quality
        Keyword-only; as :func:`range_block`.

    Returns
    -------
    tuple
        The kernel's arguments, in its order.
    """
    key = (int(w), band_cutoff)
    spec = _SPECTRAL_W.get(key)
    if spec is None:  # writable copies (the cached ones are read-only: another Numba type)
        spec = _SPECTRAL_W[key] = tuple(np.array(a, dtype=np.float64) for a in _spectral(int(w), band_cutoff))
    omega, mult, band, w2, w2m = spec
    cos_t, sin_t = _tables(int(w), omega.size)
    return (_w(ring, np.int64), _w(snr_left, np.float64), _w(snr_right, np.float64),
            _w(row_left, np.float64), _w(row_right, np.float64), cos_t, sin_t,
            omega, mult, band, w2, w2m, float(beta),
            -1.0 if max_shift_px is None else float(max_shift_px), int(iterations), _TINY,
            float(sigma_floor_px), float(focal_px) * float(baseline_m), float(quant_noise_dn),
            float(min_snr), float(min_quality))


def _warm_b(dtype: type) -> tuple:
    fr = np.zeros((2, 8, 8), dtype)
    return (fr, fr, 1, 1, 1, np.zeros((4, 4), np.float32), np.zeros((4, 4), np.float32), np.zeros((4, 4), dtype))


def _warm_r(dtype: type) -> tuple:
    fr = np.zeros((2, 8, 8), dtype)
    w, nk = 4, 3
    t = np.ones((nk, w))
    v = np.ones(nk)
    bg = np.zeros((4, 4), np.float32)
    return (fr, fr, 1, 1, 1, bg, bg, np.arange(4, dtype=np.int64), np.zeros(16), np.zeros(16),
            np.zeros(4), np.zeros(4), t, t, v, v, v, v, v, 0.5, 2.0, 2, 1e-12, 0.006, 100.0,
            0.5, 3.0, 0.5, np.empty(2), np.empty(2), np.empty(2), np.empty(2), np.empty(2, np.bool_),
            np.empty(2))


def _warm_l(dtype: type) -> tuple:
    fr = np.zeros((2, 8, 8), dtype)
    w, nk = 4, 3
    bg = np.zeros((4, 4), np.float32)
    return (fr, fr, np.array([1, 1, 1, 2], np.int64), np.array([0.5, 2.0, 1e-12, 0.006, 100.0, 0.5, 3.0, 0.5]),
            np.arange(4, dtype=np.int64), np.zeros((2, 16)), np.zeros((2, 4)), np.ones((nk, w)), np.ones((nk, w)),
            np.ones((5, nk)), bg, bg, np.empty((4, 4), np.float32), np.empty((4, 4), np.float32),
            np.empty((5, 2)), np.empty(2, np.bool_))


for _dt in (np.uint8, np.uint16):
    register_warm(_block_minima, lambda _dt=_dt: _warm_b(_dt))
    register_warm(_range_block, lambda _dt=_dt: _warm_r(_dt))
    register_warm(_range_live, lambda _dt=_dt: _warm_l(_dt))
