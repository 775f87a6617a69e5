"""The live ranging's per-pixel work as compiled kernels (identity rectification).

:meth:`iscd.stereo_range.StereoRanger.measure` cuts each camera's patch out of a block of
frames, keeps a running per-pixel minimum of it (the background), takes each frame's
pedestal (median of the patch's outer ring after the background) and noise (1.4826 MAD),
a matched-filter signal and the row-weighted projection onto x that the ``"iscd-fast"``
estimator matches (:mod:`iscd.ranging.projected`). Its numpy reference does this with a
dozen (n, h, w) temporaries; here two passes over each patch's pixels, read straight out
of the frames (pixels outside the image count as 0, as the reference's zero padding):

* :func:`patch_minimum` -- the block's per-pixel minimum of the patch (h, w);
* :func:`project_patches` -- per frame the pedestal and MAD of the ring residual, the
  matched-filter sum and the profile (n, w).

The ring medians are exact (the residuals are differences of integers); the sums are in
float64 where the reference sums partly in float32 (agreement ~1e-6 relative,
``tests/test_frame_kernels.py``).
"""

from __future__ import annotations

import numpy as np

from iscd.jit import njit, register_warm


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
    """(h, w) float32 per-pixel minimum over the block ``frames`` (n, H, W) of the patch
    whose top-left pixel is (x0, y0) px (0 outside the image)."""
    fr = np.require(frames, requirements=["C", "W"])
    out = np.zeros((h, w), fr.dtype)
    _patch_minimum(fr, int(x0), int(y0), out)
    return out.astype(np.float32)


@njit(fastmath=_FAST)
def _project(fr, x0: int, y0: int, bg: np.ndarray, ring: np.ndarray, snr_w: np.ndarray,
             row_w: np.ndarray, ped: np.ndarray, mad: np.ndarray, snr_sum: np.ndarray,
             prof: np.ndarray) -> None:
    n, H, W = fr.shape
    h, w = bg.shape
    k = ring.size
    vals = np.empty(k)
    dev = np.empty(k)
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
        for b in range(w):
            bg_prof[b] += row_w[a] * bg[a, b]
            bg_snr += snr_w[a * w + b] * bg[a, b]
    for f in range(n):
        for i in range(k):
            a, b = ring[i] // w, ring[i] % w
            y, x = y0 + a, x0 + b
            v = float(fr[f, y, x]) if 0 <= y < H and 0 <= x < W else 0.0
            vals[i] = v - bg[a, b]
        p = np.median(vals)  # selection, not a sort (exact: the same order statistic)
        for i in range(k):
            dev[i] = abs(vals[i] - p)
        ped[f] = p
        mad[f] = 1.4826 * np.median(dev)
        s = 0.0
        for b in range(w):
            prof[f, b] = 0.0
        for a in range(h):
            y = y0 + a
            if y < 0 or y >= H:
                continue
            ra = row_w[a]
            xa = max(0, -x0)
            xb = min(w, W - x0)
            row = fr[f, y]
            for b in range(xa, xb):
                v = float(row[x0 + b])
                prof[f, b] += ra * v
                s += snr_w[a * w + b] * v
        snr_sum[f] = s - bg_snr - p * sw_tot
        for b in range(w):
            prof[f, b] -= bg_prof[b] + p * rw_tot


def project_patches(frames: np.ndarray, x0: int, y0: int, background: np.ndarray, ring: np.ndarray,
                    snr_weights: np.ndarray, row_weights: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per frame of ``frames`` (n, H, W), for the (h, w) patch at (x0, y0) px with its
    ``background`` (h, w) grey levels: the pedestal (median of the ring residual, ``ring``
    flat indices), its 1.4826 MAD, the matched-filter signal ``snr_weights . (patch - bg -
    pedestal)`` and the profile ``row_weights @ (patch - bg - pedestal)`` (n, w).
    Returns (pedestal (n,), mad (n,), signal (n,), profile (n, w)), grey levels."""
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
def _correlate(left: np.ndarray, right: np.ndarray, cos_t: np.ndarray, sin_t: np.ndarray,
               omega: np.ndarray, mult: np.ndarray, band: np.ndarray, w2: np.ndarray, w2m: np.ndarray,
               beta: float, max_shift: float, iterations: int, tiny: float,
               dx: np.ndarray, height: np.ndarray, sigma: np.ndarray) -> None:
    n, w = left.shape
    nk = omega.size
    xr = np.empty(nk)
    xi = np.empty(nk)
    surf = np.empty(w)
    for f in range(n):
        # cross-power spectrum X = F_l conj(F_r), weighted |X|^-beta, band-limited
        for k in range(nk):
            lr = 0.0
            li = 0.0
            rr = 0.0
            ri = 0.0
            ck = cos_t[k]
            sk = sin_t[k]
            lf = left[f]
            rf = right[f]
            for j in range(w):
                lr += lf[j] * ck[j]
                li -= lf[j] * sk[j]
                rr += rf[j] * ck[j]
                ri -= rf[j] * sk[j]
            a = lr * rr + li * ri
            b = li * rr - lr * ri
            if beta != 0.0:
                g = (np.sqrt(a * a + b * b) + tiny) ** (-beta)
                a *= g
                b *= g
            xr[k] = a * band[k]
            xi[k] = b * band[k]
        # its inverse transform (the correlation at integer lags) and the integer peak
        best = -np.inf
        i0 = 0
        for j in range(w):
            s = 0.0
            for k in range(nk):
                s += mult[k] * (xr[k] * cos_t[k, j] - xi[k] * sin_t[k, j])
            surf[j] = s / w
            lag = j if j < (w + 1) // 2 else j - w
            if max_shift >= 0 and abs(lag) > max_shift:
                continue
            if surf[j] > best:
                best = surf[j]
                i0 = j
        lo = surf[(i0 - 1) % w]
        c0 = surf[i0]
        hi = surf[(i0 + 1) % w]
        den = lo - 2.0 * c0 + hi
        off = 0.5 * (lo - hi) / den if den < -tiny else 0.0
        pos = (i0 - w if i0 >= (w + 1) // 2 else i0) + min(max(off, -0.5), 0.5)
        # Newton steps on the trigonometric interpolant
        for _ in range(iterations):
            a = 0.0
            b = 0.0
            for k in range(nk):
                re, im = _rotated(xr[k], xi[k], mult[k], omega[k], pos)
                a += im * omega[k]
                b += re * w2[k]
            step = -a / b if b > tiny else 0.0
            pos += min(max(step, -0.5), 0.5)
        tot = 0.0
        hr = 0.0
        hess = 0.0
        var = 0.0
        for k in range(nk):
            re, im = _rotated(xr[k], xi[k], mult[k], omega[k], pos)
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
    """The compiled :func:`iscd.ranging.projected.correlate_1d` (same arguments and
    result): the transforms as sums over cached cos/sin tables (w is a few tens of px),
    the peak search and the Newton steps in the same loop, per profile pair (n, w)."""
    from iscd.ranging.projected import _TINY, Peak1D, _spectral

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
