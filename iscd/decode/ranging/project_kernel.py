"""The live ranging's per-pixel work as compiled kernels (identity rectification).

:meth:`iscd.decode.ranging.stereo.StereoRanger.measure` cuts each camera's patch out of a block of
frames, keeps a running per-pixel minimum of it (the background), takes each frame's
pedestal (median of the patch's outer ring after the background) and noise (1.4826 MAD),
a matched-filter signal and the row-weighted projection onto x that the ``"iscd-fast"``
estimator matches (:mod:`iscd.decode.ranging.projected`). Its numpy reference does this with a
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


@njit(fastmath=_FAST)
def _project(fr, x0: int, y0: int, bg: np.ndarray, ring: np.ndarray, snr_w: np.ndarray,
             row_w: np.ndarray, ped: np.ndarray, mad: np.ndarray, snr_sum: np.ndarray,
             prof: np.ndarray) -> None:
    n, H, W = fr.shape
    h, w = bg.shape
    k = ring.size
    vals = np.empty(k)
    dev = np.empty(k)
    # the ring's pixels as (row, column) once, and whether they are all inside the image
    r_a = np.empty(k, np.int64)
    r_b = np.empty(k, np.int64)
    r_bg = np.empty(k)
    inside = True
    for i in range(k):
        a, b = ring[i] // w, ring[i] % w
        r_a[i] = a
        r_b[i] = b
        r_bg[i] = bg[a, b]
        if not (0 <= y0 + a < H and 0 <= x0 + b < W):
            inside = False
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
    # the columns of the patch inside the image
    xa = max(0, -x0)
    xb = min(w, W - x0)
    for f in range(n):
        frf = fr[f]
        if inside:
            for i in range(k):
                vals[i] = float(frf[y0 + r_a[i], x0 + r_b[i]]) - r_bg[i]
        else:
            for i in range(k):
                y, x = y0 + r_a[i], x0 + r_b[i]
                v = float(frf[y, x]) if 0 <= y < H and 0 <= x < W else 0.0
                vals[i] = v - r_bg[i]
        p = np.median(vals)  # selection, not a sort (exact: the same order statistic)
        for i in range(k):
            dev[i] = abs(vals[i] - p)
        ped[f] = p
        mad[f] = 1.4826 * np.median(dev)
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
                row = frf[y, x0 + xa:x0 + xb]  # hoisted slices: the inner loop vectorizes
                sw = snr_w[a * w + xa:a * w + xb]
                pp = pf[xa:xb]
                for b in range(xb - xa):
                    v = float(row[b])
                    pp[b] += ra * v
                    s += sw[b] * v
        snr_sum[f] = s - bg_snr - p * sw_tot
        for b in range(w):
            pf[b] -= bg_prof[b] + p * rw_tot


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
def _range_block(L, R, x0l: int, x0r: int, y0: int, bg_l: np.ndarray, bg_r: np.ndarray,
                 ring: np.ndarray, snr_l: np.ndarray, snr_r: np.ndarray, row_l: np.ndarray,
                 row_r: np.ndarray, cos_t: np.ndarray, sin_t: np.ndarray, omega: np.ndarray,
                 mult: np.ndarray, band: np.ndarray, w2: np.ndarray, w2m: np.ndarray, beta: float,
                 max_shift: float, iterations: int, tiny: float, floor_px: float, fb: float,
                 quant_noise: float, min_snr: float, min_quality: float,
                 z: np.ndarray, disp: np.ndarray, sigma_m: np.ndarray, quality: np.ndarray,
                 valid: np.ndarray, snr: np.ndarray) -> None:
    """See :func:`range_block`. Not fastmath here: the result arithmetic is numpy's, in
    numpy's order (the inner kernels keep their own flags)."""
    n = L.shape[0]
    w = bg_l.shape[1]
    ped_l, mad_l, sig_l, prof_l = np.empty(n), np.empty(n), np.empty(n), np.empty((n, w))
    ped_r, mad_r, sig_r, prof_r = np.empty(n), np.empty(n), np.empty(n), np.empty((n, w))
    _project(L, x0l, y0, bg_l, ring, snr_l, row_l, ped_l, mad_l, sig_l, prof_l)
    _project(R, x0r, y0, bg_r, ring, snr_r, row_r, ped_r, mad_r, sig_r, prof_r)
    noise_l = max(np.sort(mad_l)[n // 2], quant_noise)
    noise_r = max(np.sort(mad_r)[n // 2], quant_noise)
    dx, height, sig = np.empty(n), np.empty(n), np.empty(n)
    _correlate(prof_l, prof_r, cos_t, sin_t, omega, mult, band, w2, w2m, beta, max_shift,
               iterations, tiny, dx, height, sig)
    off = float(x0l - x0r)
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
    w = int(np.shape(bg_left)[1])
    key = (w, band_cutoff)
    spec = _SPECTRAL_W.get(key)
    if spec is None:  # writable copies (the cached ones are read-only: another Numba type)
        spec = _SPECTRAL_W[key] = tuple(np.array(a, dtype=np.float64) for a in _spectral(w, band_cutoff))
    omega, mult, band, w2, w2m = spec
    cos_t, sin_t = _tables(w, omega.size)
    out = [np.empty(n) for _ in range(4)]
    valid = np.empty(n, np.bool_)
    snr = np.empty(n)
    _range_block(L, R, int(x0l), int(x0r), int(y0), _w(bg_left, np.float32), _w(bg_right, np.float32),
                 _w(ring, np.int64), _w(snr_left, np.float64), _w(snr_right, np.float64),
                 _w(row_left, np.float64), _w(row_right, np.float64), cos_t, sin_t,
                 omega, mult, band, w2, w2m, float(beta),
                 -1.0 if max_shift_px is None else float(max_shift_px), int(iterations), _TINY,
                 float(sigma_floor_px), float(focal_px) * float(baseline_m), float(quant_noise_dn),
                 float(min_snr), float(min_quality), out[0], out[1], out[2], out[3], valid, snr)
    z, d, sig, q = out
    return z, d, sig, q, valid, snr


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


for _dt in (np.uint8, np.uint16):
    register_warm(_block_minima, lambda _dt=_dt: _warm_b(_dt))
    register_warm(_range_block, lambda _dt=_dt: _warm_r(_dt))
