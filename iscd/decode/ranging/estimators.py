"""Sub-pixel shift estimators for stereo LED patches, all behind one interface.

``estimate_shift(left, right, method)`` takes two (n, h, w) batches of patches (pair i is
``left[i]``/``right[i]``, cut at known whole-pixel positions) and returns
``(shift_px (n,), quality (n,))`` where ``shift_px`` is the x position of the content in the
left patch minus its position in the right patch, so an LED's disparity is
``(x0_left - x0_right) + shift_px`` (eq. 2.2's ``x_l - x_r``). :func:`get_estimator` gives
the richer :class:`ShiftEstimate` (x and y shift, quality, standard deviation).

Methods (:data:`METHODS`):

``"dissertation"``
    Keys bicubic magnification alpha = 3, a = -0.5 (eqs. 3.1-3.3), POC (3.5-3.7), LS fit of
    the sinc peak model (3.9) on a grid of 0.01 px. One necessary element from the POC
    literature the dissertation cites for 3.8-3.9 (band-limited POC): the cross-power
    spectrum is restricted to the band the interpolation can carry, |f| < 1/(2 alpha) cycles
    per magnified pixel; the POC peak is then ``sinc((x - gamma)/alpha)`` in magnified
    samples, i.e. eq. 3.9's sinc in input pixels. Without it the phase-only spectrum is
    dominated by the spectral images of the interpolation kernel, whose phases follow the
    pixel grid, and the peak sticks to whole input pixels (``"dissertation-literal"`` keeps
    that form; see docs/ranging.md for its errors).
``"poc"``
    The dissertation's conventional POC: no interpolation, full band, sinc fit (3.9).
``"cv2"``
    ``cv2.phaseCorrelate`` (POC with a 5x5 weighted-centroid peak), one call per pair.
``"skimage"``
    ``skimage.registration.phase_cross_correlation(upsample_factor=100)``, one call per pair.
``"centroid"``
    Intensity centroid of each patch above a background and noise threshold.
``"iscd-fast"``
    The project's fast method, the live pipeline's default (:mod:`iscd.decode.ranging.projected`):
    the same weighting and exact peak on row-weighted 1-D projections of the patches onto x
    (a disparity is horizontal), clipped cores refilled per LED; as accurate as ``"iscd"``
    for one LED at a fraction of the cost.
``"iscd"``
    The project's 2-D method (measured in docs/ranging.md): background removal (dark-symbol
    patches if given, else the patch border's median); saturated cores refilled from a
    log-quadratic fit around each clipped blob (:func:`declip`; falls back to clipping both
    patches at a common level, right camera scaled by its gain); a cross-power spectrum
    weighted ``X/|X|^beta`` (beta = 0: plain cross-correlation) with a Gaussian band limit;
    and the exact maximum of the resulting band-limited correlation surface
    (:func:`iscd.decode.ranging.poc.continuous_peak`), with a per-estimate standard deviation from
    the residual phases plus measured floors. For array patches an optional Gaussian window,
    re-centred on the shift found, keeps neighbours and patch edges out of the match.

Every method's ``sigma_px`` is that residual-phase standard deviation of the iscd
estimator's spectrum evaluated at the method's own shift, so that all methods report an
uncertainty on the same footing; ``quality`` is method-specific (higher = better, see each
class).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import label as ndi_label

from iscd.decode.ranging.bicubic import KEYS_A, upsample
from iscd.decode.ranging.shift import Estimator, ShiftEstimate
from iscd.decode.ranging.poc import (PeakResult, check_pair, continuous_peak, cross_power, integer_peak,
                              sinc_fit)


def border_level(patches: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Median and robust standard deviation (1.4826 MAD) of each patch's outer ring of pixels.

    Parameters
    ----------
    patches : ndarray of float64
        (n, h, w) patches, DN.

    Returns
    -------
    median, sigma : ndarray of float64
        Each (n,), DN.
    """
    ring = np.concatenate([patches[:, 0, :], patches[:, -1, :], patches[:, 1:-1, 0],
                           patches[:, 1:-1, -1]], axis=1)
    med = _median_rows(ring)
    mad = _median_rows(np.abs(ring - med[:, None])) * 1.4826
    return med, mad


def _median_rows(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Median of each row (a sort is cheaper than np.median for these short rows)."""
    s = np.sort(a, axis=1)
    m = s.shape[1]
    return s[:, m // 2] if m % 2 else 0.5 * (s[:, m // 2 - 1] + s[:, m // 2])


@lru_cache(maxsize=32)
def _gauss_band(h: int, w: int, cutoff: float | None) -> NDArray[np.float64] | None:
    """Gaussian spectral weight exp(-f^2 / (2 cutoff^2)), f in cycles/px; None = no limit."""
    if cutoff is None or cutoff <= 0:
        return None
    fy, fx = np.fft.fftfreq(h), np.fft.fftfreq(w)
    band = np.exp(-0.5 * (fy[:, None] ** 2 + fx[None, :] ** 2) / cutoff ** 2)
    band.setflags(write=False)
    return band


def _limit_search(surface: NDArray[np.float64], max_shift: float | None) -> NDArray[np.float64]:
    """Mask the correlation surface outside |shift| <= max_shift (px) so the integer peak
    cannot jump to a neighbouring LED of a periodic array."""
    if max_shift is None:
        return surface
    _, h, w = surface.shape
    ky = np.abs(np.fft.fftfreq(h) * h)
    kx = np.abs(np.fft.fftfreq(w) * w)
    keep = (ky[:, None] <= max_shift) & (kx[None, :] <= max_shift)
    return np.where(keep[None], surface, -np.inf)


def residual_sigma(left: NDArray[np.float64], right: NDArray[np.float64], dx: NDArray[np.float64],
                   dy: NDArray[np.float64], beta: float = 0.5,
                   band_cutoff: float | None = 0.12) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Standard deviations of a shift from the residual phases of the cross-power spectrum.

    The spectrum is the weighted cross-power spectrum of background-removed patches (see
    :func:`continuous_peak`).

    Parameters
    ----------
    left, right : ndarray of float64
        (n, h, w) patch pairs, DN.
    dx, dy : ndarray of float64
        (n,) shifts at which to evaluate, px.
    beta : float
        Spectral weighting ``X / |X|^beta``.
    band_cutoff : float or None
        Gaussian band limit, cycles/px (None: full band).

    Returns
    -------
    sigma_y, sigma_x : ndarray of float64
        Each (n,), px.
    """
    lf = left - border_level(left)[0][:, None, None]
    rt = right - border_level(right)[0][:, None, None]
    h, w = lf.shape[1:]
    x = cross_power(np.fft.rfft2(lf), np.fft.rfft2(rt), beta)
    band = _gauss_band(h, w, band_cutoff)
    if band is not None:
        x = x * band[:, : w // 2 + 1]
    p = continuous_peak(x, np.nan_to_num(dy), np.nan_to_num(dx), iterations=0, width=w)
    return p.sigma_y, p.sigma_x


@lru_cache(maxsize=16)
def _quadratic_design(h: int, w: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Columns 1, x, y, x^2, y^2, xy over an (h, w) patch (centred coordinates), (h*w, 6),
    and their pairwise products (h*w, 36) for the normal equations."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    xx -= (w - 1) / 2.0
    yy -= (h - 1) / 2.0
    a = np.stack([np.ones_like(xx), xx, yy, xx * xx, yy * yy, xx * yy], axis=-1).reshape(-1, 6)
    a2 = (a[:, :, None] * a[:, None, :]).reshape(-1, 36)
    a.setflags(write=False)
    a2.setflags(write=False)
    return a, a2


_IN_PLANE_8 = np.zeros((3, 3, 3), dtype=bool)
_IN_PLANE_8[1] = True


def _dilate_labels(labels: NDArray[np.int32], r: int) -> NDArray[np.int32]:
    """Grey dilation (maximum) of (n, h, w) label images by a (2r+1)^2 square."""
    out = labels
    for _ in range(r):
        m = out.copy()
        np.maximum(m[:, 1:, :], out[:, :-1, :], out=m[:, 1:, :])
        np.maximum(m[:, :-1, :], out[:, 1:, :], out=m[:, :-1, :])
        m2 = m.copy()
        np.maximum(m2[:, :, 1:], m[:, :, :-1], out=m2[:, :, 1:])
        np.maximum(m2[:, :, :-1], m[:, :, 1:], out=m2[:, :, :-1])
        out = m2
    return out


def declip(patches: NDArray[np.float64], saturated: NDArray[np.bool_], top: ArrayLike,
           fit_floor: float = 0.03, ring_px: int = 1, min_pixels: int = 6,
           max_gain: float = 30.0) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Refill saturated spot cores from a Gaussian-like surface fitted around each of them.

    ``patches`` (n, h, w) are background-removed, ``saturated`` marks clipped pixels and
    ``top`` (scalar, (n,) or (n, h, w)) is the highest value a pixel could report after the
    background removal. Each saturated blob (8-connected; an array patch has several) gets
    its own fit: ``log(value)`` of the unsaturated pixels within ``ring_px`` (chessboard
    distance) of the blob and above ``fit_floor * top`` is fitted by a quadratic in (x, y)
    (weighted least squares, weight = value), and the blob's pixels are replaced by the
    fitted surface, clamped to ``[top, max_gain * top]``. Why: a clipped core has a flat top
    whose sharp rim aliases when sampled, so the two cameras' clipped spots are not sampled
    shifts of one function (errors of 0.02-0.05 px); the refilled spots nearly are again.

    Parameters
    ----------
    patches : ndarray of float64
        (n, h, w) background-removed patches, DN.
    saturated : ndarray of bool
        (n, h, w) clipped pixels.
    top : array_like
        Highest value a pixel could report after the background removal, DN (scalar, (n,) or
        (n, h, w)).
    fit_floor : float
        Fraction of ``top`` below which pixels are left out of the fit.
    ring_px : int
        Fit pixels within this chessboard distance of a blob, px.
    min_pixels : int
        Fewest usable pixels for a fit.
    max_gain : float
        Upper clamp of the refilled values, multiples of ``top``.

    Returns
    -------
    patches : ndarray of float64
        (n, h, w) the refilled patches, DN.
    ok : ndarray of bool
        (n,) False for a patch where some blob could not be fitted (fewer than ``min_pixels``
        usable pixels, or not a peak) -- such patches are returned unchanged (the caller falls
        back to common clipping).
    """
    n, h, w = patches.shape
    t = np.asarray(top, dtype=np.float64)
    topv = np.broadcast_to(t[:, None, None] if t.ndim == 1 else t, patches.shape)
    has = saturated.any(axis=(1, 2))
    if not has.any():
        return patches.copy(), np.zeros(n, dtype=bool)
    labels, nb = ndi_label(saturated, structure=_IN_PLANE_8)
    near = _dilate_labels(labels, int(ring_px))                      # blob label of the nearby pixels
    use = (~saturated) & (near > 0) & (patches > fit_floor * topv)
    a, a2 = _quadratic_design(h, w)                                  # (h*w, 6), (h*w, 36)
    flat = np.flatnonzero(use)
    pos = flat % (h * w)
    blob = near.ravel()[flat] - 1
    val = patches.ravel()[flat]
    rows = np.concatenate([val[:, None] * a2[pos],
                           (val * np.log(np.maximum(val, 1e-6)))[:, None] * a[pos]], axis=1)   # (k, 42)
    sums = np.zeros((nb, 42))
    count = np.bincount(blob, minlength=nb)
    if blob.size:
        order = np.argsort(blob, kind="stable")
        bs = blob[order]
        starts = np.flatnonzero(np.r_[True, bs[1:] != bs[:-1]])
        sums[bs[starts]] = np.add.reduceat(rows[order], starts, axis=0)
    ata, atb = sums[:, :36], sums[:, 36:]
    coef = np.linalg.solve(ata.reshape(nb, 6, 6) + 1e-9 * np.eye(6), atb[:, :, None])[..., 0]
    d, e, f = coef[:, 3], coef[:, 4], coef[:, 5]
    blob_ok = (d < 0) & (e < 0) & (4 * d * e - f * f > 0) & (count >= min_pixels)
    sat_flat = np.flatnonzero(saturated)
    sb = labels.ravel()[sat_flat] - 1
    spos = sat_flat % (h * w)
    model = np.exp(np.clip(np.einsum("pi,pi->p", a[spos], coef[sb]), -60.0, 60.0))
    tv = topv.ravel()[sat_flat]
    fill = np.clip(model, tv, max_gain * tv)
    patch_of_blob = np.zeros(nb, dtype=np.int64)
    patch_of_blob[sb] = sat_flat // (h * w)
    bad_patch = np.zeros(n, dtype=bool)
    bad_patch[patch_of_blob[~blob_ok]] = True
    ok = has & ~bad_patch
    out = patches.copy().ravel()
    take = ok[sat_flat // (h * w)]
    out[sat_flat[take]] = fill[take]
    return out.reshape(n, h, w), ok


# ----------------------------------------------------------------------------- the methods


@dataclass
class DissertationPOC:
    """Bicubic (Keys a = -0.5) x alpha, band-limited POC, grid sinc fit (eqs. 3.1-3.9).

    ``alpha = 1`` with ``band_limit = False`` is the conventional POC (``"poc"``);
    ``band_limit = False`` with alpha = 3 is the literal reading (``"dissertation-literal"``).
    ``quality`` is the fitted sinc amplitude (the POC peak height, 1 for a perfect match).
    """

    name: str = "dissertation"
    alpha: int = 3
    keys_a: float = KEYS_A
    band_limit: bool = True
    resolution_px: float = 0.01
    """grid step of the sinc fit, input px (the dissertation's 0.01 px)."""
    fit_radius_px: float = 1.0
    """the fit uses the samples within this distance of the integer peak, input px."""
    max_shift_px: float | None = None

    def estimate(self, left: ArrayLike, right: ArrayLike, **kw: Any) -> ShiftEstimate:
        """Shifts of the patch pairs by the dissertation's method (see the class).

        Bicubic magnification (eqs. 3.1-3.3), POC (3.5-3.7), sinc fit of the peak (3.9).

        Parameters
        ----------
        left, right : array_like
            (n, h, w) or (h, w) patch pairs, DN.
        **kw
            Ignored (the common estimator interface).

        Returns
        -------
        ShiftEstimate
            dx, dy, px; quality the fitted sinc amplitude; residual-phase sigmas, px.

        References
        ----------
        Dissertation, eqs. (3.1)-(3.3), (3.5)-(3.7), (3.9).
        """
        lf, rt = check_pair(left, right)
        a = int(self.alpha)
        if a > 1:
            lu, ru = upsample(lf, a, self.keys_a), upsample(rt, a, self.keys_a)
        else:
            lu, ru = lf, rt
        spec = cross_power(np.fft.fft2(lu), np.fft.fft2(ru))             # eq. 3.5
        width = (1.0, 1.0)
        if self.band_limit and a > 1:
            h, w = lu.shape[1:]
            fy, fx = np.abs(np.fft.fftfreq(h)), np.abs(np.fft.fftfreq(w))
            in_y, in_x = fy < 0.5 / a, fx < 0.5 / a
            spec = spec * (in_y[:, None] & in_x[None, :])[None]
            # the band-limited POC peak (eq. 3.8 over L kept bins of N) is
            # sin(pi L u / N) / (N sin(pi u / N)) ~ sinc(u L / N): a sinc N/L samples wide
            width = (h / in_y.sum(), w / in_x.sum())
        surf = np.fft.ifft2(spec).real                                   # eq. 3.6
        ms = None if self.max_shift_px is None else self.max_shift_px * a
        iy, ix = integer_peak(_limit_search(surf, ms))                   # eq. 3.7
        radius = max(1, int(round(self.fit_radius_px * a)))
        py, px, amp = _scaled_sinc_fit(surf, iy, ix, radius, self.resolution_px * a, width)
        dx, dy = px / a, py / a
        sy, sx = residual_sigma(lf, rt, dx, dy)
        return ShiftEstimate(dx=dx, dy=dy, quality=amp, sigma_px=sx, sigma_y_px=sy)


def _scaled_sinc_fit(surf: NDArray[np.float64], iy: NDArray[np.int64], ix: NDArray[np.int64], radius: int,
                     step: float, width: tuple[float, float]
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """:func:`iscd.decode.ranging.poc.sinc_fit` with the model ``sinc(u / width)`` per axis
    ((y, x) widths; 1 = eq. 3.9 as written, N/L for a POC limited to L of N bins)."""
    if width == (1.0, 1.0):
        return sinc_fit(surf, iy, ix, radius=radius, step=step, span=1.0)
    n, h, w = surf.shape
    j = np.arange(-radius, radius + 1)
    cand = np.arange(-1.0, 1.0 + step / 2, step)
    rows = np.arange(n)[:, None]
    out = []
    amp = np.zeros(n)
    for axis in (0, 1):
        m = np.sinc((j[None, :] - cand[:, None]) / width[axis])
        norm2 = np.sum(m * m, axis=1)
        if axis == 1:
            s = surf[rows, (iy % h)[:, None], (ix[:, None] + j[None, :]) % w]
        else:
            s = surf[rows, (iy[:, None] + j[None, :]) % h, (ix % w)[:, None]]
        proj = s @ m.T
        score = np.where(proj > 0, proj * proj / norm2, -np.inf)
        best = np.argmax(score, axis=1)
        out.append(cand[best])
        if axis == 1:
            amp = proj[np.arange(n), best] / norm2[best]
    return iy + out[0], ix + out[1], amp


@dataclass
class CV2PhaseCorrelate:
    """``cv2.phaseCorrelate`` per pair (no window); ``quality`` = its response (0-1)."""

    name: str = "cv2"

    def estimate(self, left: ArrayLike, right: ArrayLike, **kw: Any) -> ShiftEstimate:
        """Shifts of the patch pairs by ``cv2.phaseCorrelate``, one call per pair.

        Parameters
        ----------
        left, right : array_like
            (n, h, w) or (h, w) patch pairs, DN.
        **kw
            Ignored (the common estimator interface).

        Returns
        -------
        ShiftEstimate
            dx, dy, px; quality the cv2 response (0-1); residual-phase sigmas, px.
        """
        import cv2

        lf, rt = check_pair(left, right)
        n = lf.shape[0]
        dx, dy, q = np.empty(n), np.empty(n), np.empty(n)
        for i in range(n):
            (sx, sy), resp = cv2.phaseCorrelate(lf[i], rt[i])
            dx[i], dy[i], q[i] = -sx, -sy, resp     # cv2 gives right - left
        sy_, sx_ = residual_sigma(lf, rt, dx, dy)
        return ShiftEstimate(dx=dx, dy=dy, quality=q, sigma_px=sx_, sigma_y_px=sy_)


@dataclass
class SkimagePCC:
    """``skimage.registration.phase_cross_correlation`` (upsample_factor 100) per pair;
    ``quality`` = 1 - its normalized RMS error."""

    name: str = "skimage"
    upsample_factor: int = 100

    def estimate(self, left: ArrayLike, right: ArrayLike, **kw: Any) -> ShiftEstimate:
        """Shifts of the patch pairs by ``skimage.registration.phase_cross_correlation``.

        Parameters
        ----------
        left, right : array_like
            (n, h, w) or (h, w) patch pairs, DN.
        **kw
            Ignored (the common estimator interface).

        Returns
        -------
        ShiftEstimate
            dx, dy, px; quality 1 - the normalized RMS error; residual-phase sigmas, px.
        """
        from skimage.registration import phase_cross_correlation

        lf, rt = check_pair(left, right)
        n = lf.shape[0]
        dx, dy, q = np.empty(n), np.empty(n), np.empty(n)
        for i in range(n):
            shift, err, _ = phase_cross_correlation(lf[i], rt[i], upsample_factor=self.upsample_factor)
            dy[i], dx[i], q[i] = shift[0], shift[1], 1.0 - err
        sy_, sx_ = residual_sigma(lf, rt, dx, dy)
        return ShiftEstimate(dx=dx, dy=dy, quality=q, sigma_px=sx_, sigma_y_px=sy_)


@dataclass
class Centroid:
    """Intensity centroid: pixels above the border median + ``k_sigma`` x its robust noise,
    weighted by their excess. ``quality`` = the spot's summed excess / (its pixel count x 255)."""

    name: str = "centroid"
    k_sigma: float = 3.0

    def _centroids(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        med, noise = border_level(p)
        wgt = np.maximum(p - (med + self.k_sigma * noise)[:, None, None], 0.0)
        tot = wgt.sum(axis=(1, 2))
        with np.errstate(invalid="ignore", divide="ignore"):
            cx = (wgt.sum(axis=1) * np.arange(p.shape[2])).sum(axis=1) / tot
            cy = (wgt.sum(axis=2) * np.arange(p.shape[1])).sum(axis=1) / tot
            q = tot / (np.count_nonzero(wgt, axis=(1, 2)) * 255.0)
        return cx, cy, np.nan_to_num(q)

    def estimate(self, left: ArrayLike, right: ArrayLike, **kw: Any) -> ShiftEstimate:
        """Shifts of the patch pairs as the difference of their intensity centroids.

        Parameters
        ----------
        left, right : array_like
            (n, h, w) or (h, w) patch pairs, DN.
        **kw
            Ignored (the common estimator interface).

        Returns
        -------
        ShiftEstimate
            dx, dy, px; quality the lower of the two spots' (see the class); residual-phase sigmas,
            px.
        """
        lf, rt = check_pair(left, right)
        lx, ly, lq = self._centroids(lf)
        rx, ry, rq = self._centroids(rt)
        dx, dy = lx - rx, ly - ry
        sy_, sx_ = residual_sigma(lf, rt, dx, dy)
        return ShiftEstimate(dx=dx, dy=dy, quality=np.minimum(lq, rq), sigma_px=sx_, sigma_y_px=sy_)


@dataclass
class ISCDShift:
    """The project's estimator (see the module docstring).

    ``beta``: spectral whitening exponent (1 = POC, 0 = plain cross-correlation).
    ``saturation_mode``: ``"declip"`` (default), ``"clip"`` or ``"none"`` (see :meth:`prepare`).
    ``band_cutoff``: Gaussian band limit, cycles/px (None = full band).
    ``saturation``: grey level at which the sensor clips (255 for 8-bit).
    ``gain_ratio``: right-camera gain relative to left (``(N_left/N_right)^2`` for f-numbers
    N); None = estimated from the patches when needed.
    ``quality``: the peak of the weighted correlation / the sum of the weights (1 = a
    perfect match of the two patches, near 0 = no common content).
    Pass ``background=(dark_left, dark_right)`` (patches of the same LEDs during a dark
    symbol, same shape) to :meth:`estimate` to subtract a static background.
    """

    name: str = "iscd"
    beta: float = 0.5
    band_cutoff: float | None = 0.12
    saturation: float = 255.0
    gain_ratio: float | None = None
    saturation_mode: str = "declip"
    max_shift_px: float | None = None
    window_sigma_px: float | None = None
    """Gaussian window (sigma, px) centred on the patch's LED, re-centred on the shift found
    (``window_rounds`` times): isolates one LED of an array from its neighbours."""
    window_rounds: int = 1
    iterations: int = 6
    sigma_floor_px: float = 0.006
    """added in quadrature to the residual-phase sigma (sampling/quantization errors that
    the residual phases do not show; measured on synthetic spots, docs/ranging.md)."""
    sigma_saturated_px: float = 0.008
    """added in quadrature when either patch is saturated (the refilled core's shape error;
    the RMS error measured on saturated synthetic spots)."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.beta <= 1.0:
            raise ValueError(f"beta: expected 0 <= beta <= 1, got {self.beta}")
        if self.band_cutoff is not None and self.band_cutoff < 0:
            raise ValueError(f"band_cutoff: expected >= 0 cycles/px or None, got {self.band_cutoff}")
        if self.saturation_mode not in ("declip", "clip", "none"):
            raise ValueError(f"saturation_mode: expected 'declip', 'clip' or 'none', got {self.saturation_mode!r}")
        if self.window_sigma_px is not None and self.window_sigma_px <= 0:
            raise ValueError(f"window_sigma_px: expected > 0 px or None, got {self.window_sigma_px}")
        if self.gain_ratio is not None and not self.gain_ratio > 0:
            raise ValueError(f"gain_ratio: expected > 0 or None, got {self.gain_ratio}")

    def prepare(self, lf: NDArray[np.float64], rt: NDArray[np.float64],
                background: tuple[ArrayLike, ArrayLike] | None = None
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Background removal and saturation handling.

        Background: ``background`` patches (a dark symbol's, or a running minimum; anything
        broadcastable to the patches) if given -- what is left then has its border median
        removed as a pedestal (a running minimum lies below the mean by the noise) --, else
        each patch's border median. Saturation (pixels >= ``saturation``), per ``saturation_mode``:
        ``"declip"`` refills each saturated core from a log-quadratic (Gaussian-like)
        surface fitted to the unsaturated pixels around it (:func:`declip`), falling back
        to ``"clip"`` for a pair where that fit fails; ``"clip"`` scales the right patch to
        left units (``gain_ratio``) and clips both at the lowest level both can report.

        Parameters
        ----------
        lf, rt : ndarray of float64
            (n, h, w) raw left and right patches, DN.
        background : (array_like, array_like), optional
            Left and right background patches, DN.

        Returns
        -------
        left, right : ndarray of float64
            New (n, h, w) arrays, background removed and saturation handled, DN (right in left
            units when clipped).
        """
        sat_l = lf >= self.saturation - 0.5
        sat_r = rt >= self.saturation - 0.5
        n = lf.shape[0]
        if background is not None:
            bl = np.asarray(background[0], dtype=np.float64)
            br = np.asarray(background[1], dtype=np.float64)
            try:
                bl, br = np.broadcast_to(bl, lf.shape), np.broadcast_to(br, rt.shape)
            except ValueError:
                raise ValueError(f"background patches {np.shape(background[0])}, {np.shape(background[1])} "
                                 f"do not fit the patches {lf.shape}") from None
            if not (np.isfinite(bl).all() and np.isfinite(br).all()):
                raise ValueError("background patches contain NaN or infinite values")
            ped = border_level(np.concatenate([lf - bl, rt - br]))[0][:, None, None]
            lvl_l, lvl_r = bl + ped[:n], br + ped[n:]
        else:
            med = border_level(np.concatenate([lf, rt]))[0][:, None, None]
            lvl_l = np.broadcast_to(med[:n], lf.shape)
            lvl_r = np.broadcast_to(med[n:], rt.shape)
        l0, r0 = lf - lvl_l, rt - lvl_r
        any_l, any_r = sat_l.any(axis=(1, 2)), sat_r.any(axis=(1, 2))
        need_clip = any_l | any_r
        if self.saturation_mode == "none" or not need_clip.any():
            return l0, r0
        if self.saturation_mode == "declip":
            both, ok = declip(np.concatenate([l0, r0]), np.concatenate([sat_l, sat_r]),
                              np.concatenate([self.saturation - lvl_l, self.saturation - lvl_r]))
            l1, r1, ok_l, ok_r = both[:n], both[n:], ok[:n], ok[n:]
            good = (ok_l | ~any_l) & (ok_r | ~any_r)
            l0 = np.where(good[:, None, None], l1, l0)
            r0 = np.where(good[:, None, None], r1, r0)
            need_clip = need_clip & ~good
            if not need_clip.any():
                return l0, r0
        g = (np.full(lf.shape[0], self.gain_ratio) if self.gain_ratio is not None
             else self._gain(l0, r0, sat_l, sat_r))
        g = np.where(np.isfinite(g) & (g > 0), g, 1.0)
        top_l = np.min(self.saturation - lvl_l, axis=(1, 2))
        top_r = np.min(self.saturation - lvl_r, axis=(1, 2)) / g
        t = np.where(need_clip, 0.98 * np.minimum(top_l, top_r), np.inf)[:, None, None]
        gg = np.where(need_clip, g, 1.0)[:, None, None]
        return np.minimum(l0, t), np.minimum(r0 / gg, t)

    def _gain(self, l0: NDArray[np.float64], r0: NDArray[np.float64], sat_l: NDArray[np.bool_],
              sat_r: NDArray[np.bool_]) -> NDArray[np.float64]:
        """Right/left gain by matching the sorted pixel values (the same spot, shifted) where
        neither is saturated; 1 when it cannot be estimated."""
        n = l0.shape[0]
        ls = np.sort(np.where(sat_l, np.inf, l0).reshape(n, -1), axis=1)[:, ::-1]
        rs = np.sort(np.where(sat_r, np.inf, r0).reshape(n, -1), axis=1)[:, ::-1]
        lmax = np.max(np.where(np.isfinite(ls), ls, -np.inf), axis=1, keepdims=True)
        rmax = np.max(np.where(np.isfinite(rs), rs, -np.inf), axis=1, keepdims=True)
        ok = np.isfinite(ls) & np.isfinite(rs) & (ls > 0.2 * lmax) & (rs > 0.2 * rmax)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(ok, rs / ls, np.nan)
            g = np.nanmedian(np.where(ok.any(axis=1, keepdims=True), ratio, 1.0), axis=1)
        return g

    def _peak(self, l0: NDArray[np.float64], r0: NDArray[np.float64], stats: bool = True) -> PeakResult:
        """The weighted correlation's sub-pixel peak of prepared patches."""
        n, h, w = l0.shape
        spec = cross_power(np.fft.rfft2(l0), np.fft.rfft2(r0), self.beta)   # half spectrum
        band = _gauss_band(h, w, self.band_cutoff)
        if band is not None:
            spec = spec * band[:, : w // 2 + 1]
        surf = np.fft.irfft2(spec, s=(h, w))
        iy, ix = integer_peak(_limit_search(surf, self.max_shift_px))
        return continuous_peak(spec, iy, ix, self.iterations, surface=surf, width=w, stats=stats)

    def estimate(self, left: ArrayLike, right: ArrayLike, *,
                 background: tuple[ArrayLike, ArrayLike] | None = None, **kw: Any) -> ShiftEstimate:
        """Shifts of the patch pairs by the project's 2-D method (see the class and module doc).

        Parameters
        ----------
        left, right : array_like
            (n, h, w) or (h, w) raw patch pairs, DN.
        background : (array_like, array_like), optional
            Keyword-only. Left and right background patches (:meth:`prepare`), DN.
        **kw
            Ignored (the common estimator interface).

        Returns
        -------
        ShiftEstimate
            dx, dy, px; quality the correlation peak height; sigmas, px, with the floors added.

        References
        ----------
        Dissertation, eqs. (3.5) (here weighted; beta = 1 is POC), (3.6) (continuous form).
        """
        lf, rt = check_pair(left, right)
        l0, r0 = self.prepare(lf, rt, background)
        windowed = self.window_sigma_px is not None and self.window_rounds > 0
        p = self._peak(l0, r0, stats=not windowed)
        if windowed:
            # Gaussian windows centred on the same scene point in both patches: the patch
            # centre in the left one, the centre minus the current shift in the right one, so
            # the windowed pair is still a shifted pair (no pull towards zero shift).
            n, h, w = l0.shape
            yy = np.arange(h, dtype=np.float64)[None, :, None] - (h - 1) / 2.0
            xx = np.arange(w, dtype=np.float64)[None, None, :] - (w - 1) / 2.0
            k = -0.5 / self.window_sigma_px ** 2
            wl = np.exp(k * (yy ** 2 + xx ** 2))
            for i in range(self.window_rounds):
                dx = np.nan_to_num(p.dx)[:, None, None]
                dy = np.nan_to_num(p.dy)[:, None, None]
                wr = np.exp(k * ((yy + dy) ** 2 + (xx + dx) ** 2))
                p = self._peak(l0 * wl, r0 * wr, stats=i == self.window_rounds - 1)
        sat = ((lf >= self.saturation - 0.5).any(axis=(1, 2)) | (rt >= self.saturation - 0.5).any(axis=(1, 2)))
        floor = np.hypot(self.sigma_floor_px, np.where(sat, self.sigma_saturated_px, 0.0))
        sx = np.hypot(p.sigma_x, floor)
        sy = np.hypot(p.sigma_y, floor)
        dead = ~np.isfinite(p.height) | ~np.isfinite(p.dx) | (np.abs(l0).sum(axis=(1, 2)) == 0) | (np.abs(r0).sum(axis=(1, 2)) == 0)
        dx = np.where(dead, np.nan, p.dx)
        dy = np.where(dead, np.nan, p.dy)
        return ShiftEstimate(dx=dx, dy=dy, quality=np.where(dead, 0.0, p.height), sigma_px=sx, sigma_y_px=sy)


METHODS: dict[str, Callable[..., Estimator]] = {
    "dissertation": lambda **kw: DissertationPOC(**{"name": "dissertation", **kw}),
    "dissertation-literal": lambda **kw: DissertationPOC(**{"name": "dissertation-literal",
                                                            "band_limit": False, **kw}),
    "poc": lambda **kw: DissertationPOC(**{"name": "poc", "alpha": 1, "band_limit": False, **kw}),
    "cv2": lambda **kw: CV2PhaseCorrelate(**kw),
    "skimage": lambda **kw: SkimagePCC(**kw),
    "centroid": lambda **kw: Centroid(**kw),
    "iscd": lambda **kw: ISCDShift(**kw),
    "iscd-fast": lambda **kw: _projected(**kw),
}
"""Estimator factories by name; keyword options go to the estimator's dataclass."""


def _projected(**kw: Any) -> Estimator:
    from iscd.decode.ranging.projected import ProjectedShift   # loaded when first asked for

    return ProjectedShift(**kw)


def get_estimator(method: str = "iscd", **options: Any) -> Estimator:
    """The estimator called ``method`` (one of :data:`METHODS`), with ``options``.

    Parameters
    ----------
    method : str
        Estimator name (module doc).
    **options
        Fields of that estimator's class (e.g. ``beta``, ``max_shift_px``).

    Returns
    -------
    Estimator
    """
    try:
        factory = METHODS[method]
    except KeyError:
        raise ValueError(f"unknown shift estimator {method!r} (known: {', '.join(METHODS)})") from None
    try:
        return factory(**options)
    except TypeError as e:
        raise ValueError(f"estimator {method!r}: {e}") from None


def estimate_shift(left: ArrayLike, right: ArrayLike, method: str = "iscd",
                   **options: Any) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Shift and quality of each pair of (n, h, w) patches (see module doc).

    Parameters
    ----------
    left, right : array_like
        (n, h, w) patch pairs, DN.
    method : str
        Estimator name (one of :data:`METHODS`).
    **options
        Estimator options (:func:`get_estimator`).

    Returns
    -------
    shift_px : ndarray of float64
        (n,) x position in the left patch minus that in the right, px.
    quality : ndarray of float64
        (n,) method-specific, higher is better.
    """
    est = get_estimator(method, **options).estimate(left, right)
    return est.dx, est.quality
