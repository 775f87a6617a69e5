"""Synthetic LED patches with exactly known sub-pixel positions, for tests and method comparison.

Not a scene simulator (that is :mod:`iscd.sim`): small (n, h, w) batches of patches with
one or many spots whose continuous centres are given, so estimators can be checked against
ground truth. Positions are in patch pixels, pixel (0, 0) covering [-0.5, 0.5)^2.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import erf


def fourier_shift(images: ArrayLike, dx: ArrayLike, dy: ArrayLike = 0.0) -> NDArray[np.float64]:
    """Shift (n, h, w) images by (dx, dy) px (periodic, band-limited): out(x) = in(x - dx).

    The exact sub-pixel shift of a periodic band-limited image (Nyquist bins are zeroed so
    that the result stays real).

    Parameters
    ----------
    images : array_like
        (n, h, w) or (h, w) images.
    dx, dy : array_like
        Shifts, scalar or (n,), px.

    Returns
    -------
    ndarray of float64
        The shifted images, same shape.
    """
    g = np.asarray(images, dtype=np.float64)
    squeeze = g.ndim == 2
    g = g[None] if squeeze else g
    n, h, w = g.shape
    dx = np.broadcast_to(np.asarray(dx, dtype=np.float64), (n,))
    dy = np.broadcast_to(np.asarray(dy, dtype=np.float64), (n,))
    ky, kx = np.fft.fftfreq(h), np.fft.fftfreq(w)
    f = np.fft.fft2(g)
    if h % 2 == 0:
        f[:, h // 2, :] = 0.0
    if w % 2 == 0:
        f[:, :, w // 2] = 0.0
    ramp = np.exp(-2j * np.pi * (ky[None, :, None] * dy[:, None, None] + kx[None, None, :] * dx[:, None, None]))
    out = np.fft.ifft2(f * ramp).real
    return out[0] if squeeze else out


def _cols(a: ArrayLike, n: int) -> NDArray[np.float64]:
    v = np.asarray(a, dtype=np.float64)
    if v.ndim == 0:
        v = np.full((n, 1), float(v))
    elif v.ndim == 1:
        v = v[:, None]
    return np.broadcast_to(v, (n, v.shape[1]))


def gaussian_spots(n: int, size: tuple[int, int], cx: ArrayLike, cy: ArrayLike, sigma_px: float,
                   peak: ArrayLike = 1.0) -> NDArray[np.float64]:
    """Pixel-integrated Gaussian spots, exact (erf): no noise, no clipping.

    Parameters
    ----------
    n : int
        Patches.
    size : (int, int)
        (h, w), px.
    cx, cy : array_like
        (n,) or (n, m) centres (m spots per patch), px.
    sigma_px : float
        Gaussian standard deviation, px.
    peak : array_like
        Value a spot would have at its centre before pixel integration (scalar, (n,) or
        (n, m)).

    Returns
    -------
    ndarray of float64
        (n, h, w).
    """
    h, w = size
    cxs, cys = _cols(cx, n), _cols(cy, n)
    amp = np.broadcast_to(_cols(peak, n), cxs.shape)
    s = sigma_px * np.sqrt(2.0)
    ex = np.arange(w + 1) - 0.5
    ey = np.arange(h + 1) - 0.5
    px = np.diff(erf((ex[None, None, :] - cxs[..., None]) / s), axis=-1) / 2.0   # (n, m, w)
    py = np.diff(erf((ey[None, None, :] - cys[..., None]) / s), axis=-1) / 2.0   # (n, m, h)
    norm = 2.0 * np.pi * sigma_px ** 2
    return np.einsum("nm,nmy,nmx->nyx", amp * norm, py, px)


def disk_spots(n: int, size: tuple[int, int], cx: ArrayLike, cy: ArrayLike, radius_px: float,
               psf_sigma_px: float = 0.6, peak: ArrayLike = 1.0, supersample: int = 8) -> NDArray[np.float64]:
    """Uniform disks of ``radius_px`` blurred by a Gaussian PSF, integrated over pixels.

    The blurred disk is exact: at distance r from the centre it is
    ``peak * P(|X| <= radius)`` for X ~ N(r, sigma^2 I), a non-central chi-square CDF
    (tabulated once per call and interpolated). Pixel integration averages a
    ``supersample`` x ``supersample`` grid of that smooth function per pixel.

    Parameters
    ----------
    n : int
        Patches.
    size : (int, int)
        (h, w), px.
    cx, cy : array_like
        Centres, (n,) or (n, m), px.
    radius_px : float
        Disk radius, px.
    psf_sigma_px : float
        PSF standard deviation, px.
    peak : array_like
        The disk's surface brightness (a large disk's interior value).
    supersample : int
        Sub-samples per pixel side.

    Returns
    -------
    ndarray of float64
        (n, h, w).
    """
    from scipy.stats import ncx2

    if psf_sigma_px < 0.05:
        raise ValueError(f"psf_sigma_px: expected >= 0.05 px, got {psf_sigma_px}")
    h, w = size
    ss = int(supersample)
    cxs, cys = _cols(cx, n), _cols(cy, n)
    amp = np.broadcast_to(_cols(peak, n), cxs.shape)
    s2 = psf_sigma_px ** 2
    rmax = radius_px + 8.0 * psf_sigma_px
    r2_tab = np.linspace(0.0, rmax ** 2, 4096)
    prof = ncx2.cdf(radius_px ** 2 / s2, 2, r2_tab / s2)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    fx = (np.arange(w)[:, None] + off[None, :]).ravel()         # (w*ss,)
    fy = (np.arange(h)[:, None] + off[None, :]).ravel()
    out = np.zeros((n, h, w))
    for j in range(cxs.shape[1]):
        d2 = (fx[None, None, :] - cxs[:, j, None, None]) ** 2 + (fy[None, :, None] - cys[:, j, None, None]) ** 2
        val = np.interp(d2, r2_tab, prof, right=0.0)
        out += amp[:, j, None, None] * val.reshape(n, h, ss, w, ss).mean(axis=(2, 4))
    return out


def sensor(signal: ArrayLike, rng: np.random.Generator, background_dn: float = 0.0,
           read_noise_dn: float = 0.0, electrons_per_dn: float = 0.0,
           full_scale: float = 255.0) -> NDArray[np.float64]:
    """Add background, shot noise (if ``electrons_per_dn`` > 0), read noise, quantize, clip.

    A bright spot with ``peak`` above ``full_scale`` saturates exactly like a real 8-bit
    sensor.

    Parameters
    ----------
    signal : array_like
        Noise-free signal, DN.
    rng : numpy.random.Generator
        Noise source.
    background_dn : float
        Added background, DN.
    read_noise_dn : float
        Read noise standard deviation, DN.
    electrons_per_dn : float
        Conversion gain for shot noise, e-/DN (0: no shot noise).
    full_scale : float
        Clip level, DN.

    Returns
    -------
    ndarray of float64
        Integer-valued, in [0, full_scale] (8-bit by default), DN.
    """
    v = np.asarray(signal, dtype=np.float64) + background_dn
    if electrons_per_dn > 0:
        v = rng.poisson(np.maximum(v, 0.0) * electrons_per_dn) / electrons_per_dn
    if read_noise_dn > 0:
        v = v + rng.normal(0.0, read_noise_dn, v.shape)
    return np.clip(np.round(v), 0.0, full_scale)
