"""Spot optics: a uniformly bright disk blurred by the lens PSF, plus a glare halo.

An LED of diameter D at distance Z is a disk of radius R = f_px D / (2 Z) px. Its image is

    I(r) = L [ (1 - g) P(r; R, s) + g H(r; R, s_g) ]                               [DN]

* P(r; R, s) = disk (*) Gaussian(s): the share of a 2-D Gaussian of sigma s centred at
  distance r from the disk centre that falls inside the disk, i.e. the non-central
  chi-square CDF ``ncx2.cdf(R^2/s^2, df=2, nc=r^2/s^2)`` (scipy.special.chndtr) (= 1 - Marcum Q1(r/s, R/s)).
  s^2 = psf_sigma_px^2 (+ right_defocus_px^2 for the right camera) + 1/12, the 1/12 px^2
  approximating the integration over the square pixel (box of 1 px) by its variance.
  P = 1 in the middle of a resolved disk, so L is the grey level of a resolved, fully-on LED.
* H: the glare halo, g = glare_fraction of the light, disk (*) Gaussian(glare_sigma_px),
  approximated by a Gaussian of variance s_g^2 = glare_sigma_px^2 + R^2/4 + 1/12 (same
  second moment) carrying the flux g L pi R^2. Separable, so it is rendered by two small
  matrix products for all sources at once.

The core P is evaluated from a precomputed table indexed by r^2 at the pixel centres of a
small window around each source; the windows are summed with ``np.bincount`` (crosstalk of
neighbouring LEDs comes out naturally). Everything here is in px and DN, pure numpy.

Other spot models (``optics.psf_model``, ``optics.diffuser_falloff``, ``optics.glare_model``)
stay sums of the same exact pieces, so they tabulate the same way and render through the
same compiled kernels:

* a Moffat PSF (1 + r^2/alpha^2)^-beta is a scale mixture of Gaussians (precision
  ~ Gamma(beta - 1, scale 2/alpha^2)); it is discretized into ``MOFFAT_COMPONENTS``
  equal-weight Gaussians at the quantile mid-points (:func:`moffat_components`);
* a diffuser disk brighter in the centre, b(rho) = 1 - k (rho/R)^2, is a stack of nested
  uniform disks (:func:`diffuser_disks`), normalized to the uniform disk's flux;
* so the core is P(r) = sum_d sum_c w_d w_c ncx2.cdf((c_d R)^2/s_c^2, 2, r^2/s_c^2)
  (:class:`SpotProfile`, :func:`profile_at`);
* a power-law glare halo (1 + r^2/r0^2)^-gamma is again a Gaussian scale mixture, rendered
  as ``GLARE_COMPONENTS`` separable Gaussians (:func:`glare_components`).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from scipy.special import chndtr, gammaincinv

PIXEL_VAR = 1.0 / 12.0
"""Variance (px^2) of a 1-px box: the pixel-area integration as extra Gaussian blur."""


def disk_blur_profile(r: np.ndarray, radius_px: float, sigma_px: float) -> np.ndarray:
    """P(r): a unit disk of radius R blurred by a Gaussian of sigma s, at radius r (px).

    The non-central chi-square CDF ``chndtr(R^2/s^2, 2, r^2/s^2)`` (= scipy.stats.ncx2.cdf).

    Parameters
    ----------
    r : ndarray
        Distances from the disk centre, px.
    radius_px : float
        Disk radius R, px.
    sigma_px : float
        Gaussian sigma s, px (> 0).

    Returns
    -------
    ndarray of float64
        P, 0..1, the shape of ``r``.
    """
    s2 = sigma_px * sigma_px
    return chndtr(radius_px * radius_px / s2, 2.0, np.asarray(r, dtype=np.float64) ** 2 / s2)


MOFFAT_COMPONENTS = 8
"""Gaussians in the discretized Moffat PSF."""
DIFFUSER_DISKS = 4
"""Nested uniform disks of a non-uniform diffuser."""
GLARE_COMPONENTS = 4
"""Gaussians in the discretized power-law glare halo."""


@dataclass(frozen=True)
class SpotProfile:
    """A radially symmetric spot model: a stack of nested uniform disks (weights w_d,
    radii c_d R) blurred by a mixture of Gaussians (weights w_c, sigmas s_c in px, pixel
    and defocus blur included). Hashable (a table-cache key). The default, one disk and one
    Gaussian, is the disk (*) Gaussian of :func:`disk_blur_profile`."""

    psf: tuple[tuple[float, float], ...]  # (w_c, s_c px)
    disks: tuple[tuple[float, float], ...] = ((1.0, 1.0),)  # (w_d, c_d)

    @property
    def is_gaussian_disk(self) -> bool:
        return len(self.psf) == 1 and self.psf[0][0] == 1.0 and self.disks == ((1.0, 1.0),)

    @property
    def sigma_min(self) -> float:
        return min(sc for _, sc in self.psf)

    @property
    def sigma_max(self) -> float:
        return max(sc for _, sc in self.psf)


def gaussian_profile(sigma_px: float) -> SpotProfile:
    """The default spot: a uniform disk blurred by one Gaussian of sigma ``sigma_px``.

    Parameters
    ----------
    sigma_px : float
        Total blur sigma (PSF, pixel area, defocus), px.

    Returns
    -------
    SpotProfile
    """
    return SpotProfile(((1.0, float(sigma_px)),))


def moffat_components(fwhm_sigma_px: float, beta: float, extra_var_px2: float,
                      n: int = MOFFAT_COMPONENTS) -> tuple[tuple[float, float], ...]:
    """A Moffat PSF (1 + r^2/alpha^2)^-beta with the FWHM of a Gaussian of sigma
    ``fwhm_sigma_px`` (alpha = sigma sqrt(2 ln 2) / sqrt(2^(1/beta) - 1)) as ``n``
    equal-weight Gaussians: precisions tau_j = Gamma(beta - 1, 2/alpha^2) quantiles at
    (j + 0.5)/n, variances 1/tau_j + ``extra_var_px2`` (pixel, defocus). ((w, sigma), ...).

    Parameters
    ----------
    fwhm_sigma_px : float
        Sigma of the Gaussian with the same FWHM, px.
    beta : float
        Moffat exponent (> 1).
    extra_var_px2 : float
        Variance added to every component (pixel area, defocus), px^2.
    n : int
        Number of Gaussians.

    Returns
    -------
    tuple of (float, float)
        ``n`` pairs (weight, sigma in px).
    """
    alpha = fwhm_sigma_px * math.sqrt(2 * math.log(2)) / math.sqrt(2 ** (1 / beta) - 1)
    p = (np.arange(n) + 0.5) / n
    tau = gammaincinv(beta - 1.0, p) * (2.0 / alpha ** 2)
    return tuple((1.0 / n, float(math.sqrt(1.0 / t + extra_var_px2))) for t in tau)


def diffuser_disks(falloff: float, n: int = DIFFUSER_DISKS) -> tuple[tuple[float, float], ...]:
    """b(rho) = 1 - k (rho/R)^2 as ``n`` nested uniform disks (radii j/n R, the brightness
    of each annulus at its mid-radius), weights normalized so that the flux is the uniform
    disk's (mean surface brightness 1, centre 1/(1 - k/2)). ((w_d, c_d), ...).

    Parameters
    ----------
    falloff : float
        k, the brightness drop from centre to edge (<= 0: a uniform disk).
    n : int
        Number of disks.

    Returns
    -------
    tuple of (float, float)
        Pairs (weight w_d, radius c_d as a fraction of R); ``((1.0, 1.0),)`` when uniform.
    """
    if falloff <= 0:
        return ((1.0, 1.0),)
    c = (np.arange(n) + 1.0) / n
    b = 1.0 - falloff * ((np.arange(n) + 0.5) / n) ** 2  # annulus j brightness
    w = b - np.r_[b[1:], 0.0]  # nested disk j carries b_j - b_{j+1}
    w /= float((w * c * c).sum())
    return tuple((float(wi), float(ci)) for wi, ci in zip(w, c))


def profile_at(r: np.ndarray, radius_px: float, prof: SpotProfile) -> np.ndarray:
    """P(r) of ``prof`` for a disk of radius R px (1 in a resolved uniform disk).

    Parameters
    ----------
    r : ndarray
        Distances from the spot centre, px.
    radius_px : float
        Disk radius R, px.
    prof : SpotProfile
        The spot model.

    Returns
    -------
    ndarray of float64
        P, the shape of ``r``.
    """
    if prof.is_gaussian_disk:
        return disk_blur_profile(r, radius_px, prof.psf[0][1])
    out = np.zeros(np.shape(r))
    for wd, cd in prof.disks:
        for wc, sc in prof.psf:
            out += (wd * wc) * disk_blur_profile(r, cd * radius_px, sc)
    return out


def glare_components(r0_px: float, gamma: float, n: int = GLARE_COMPONENTS,
                     max_sigma_px: float | None = None) -> tuple[tuple[float, float], ...]:
    """A power-law halo (1 + r^2/r0^2)^-gamma (gamma > 1) as ``n`` equal-weight Gaussians
    (precision quantiles of Gamma(gamma - 1, 2/r0^2)); sigmas capped at ``max_sigma_px``
    (default 4 r0: the farthest wing is pulled in so the render window stays small).
    ((w, sigma px), ...): add the disk's and the pixel's variance per component.

    Parameters
    ----------
    r0_px : float
        Core radius r0, px.
    gamma : float
        Power-law exponent (> 1).
    n : int
        Number of Gaussians.
    max_sigma_px : float, optional
        Cap on the sigmas, px (default 4 r0).

    Returns
    -------
    tuple of (float, float)
        ``n`` pairs (weight, sigma in px).
    """
    cap = 4.0 * r0_px if max_sigma_px is None else max_sigma_px
    p = (np.arange(n) + 0.5) / n
    tau = gammaincinv(gamma - 1.0, p) * (2.0 / r0_px ** 2)
    return tuple((1.0 / n, float(min(math.sqrt(1.0 / t), cap))) for t in tau)


REL_CUT = 2e-5
"""The core profile is cut where P < REL_CUT (0.012 DN for a 600 DN spot)."""


@dataclass(frozen=True)
class SpotTable:
    """The core profile P(r) of one (R, s) tabulated on r^2 for fast lookup.

    Bin i covers r^2 in [i, i+1) * step and holds P at the bin's middle, so a lookup is
    ``table[int(r^2 / step)]``; 0 beyond r_cut. ``half`` is the half-size of the square
    window (2*half + 1 px) that holds r <= r_cut.
    """

    radius_px: float
    sigma_px: float
    r_cut: float
    half: int
    step: float
    table: np.ndarray  # float32


def make_table(radius_px: float, sigma_px: float, rel_cut: float = REL_CUT,
               n_entries: int = 8192, profile: SpotProfile | None = None) -> SpotTable:
    """Tabulate P for disk radius R (px) and blur s (px), cut where P < rel_cut; with
    ``profile`` (not the plain Gaussian disk), P of that spot model (``sigma_px`` is then
    only recorded).

    Parameters
    ----------
    radius_px : float
        Disk radius R, px.
    sigma_px : float
        Gaussian blur s, px (at least 1e-3 is used).
    rel_cut : float
        P below which the profile is cut to 0.
    n_entries : int
        Table bins (in r^2).
    profile : SpotProfile, optional
        A spot model other than the Gaussian disk.

    Returns
    -------
    SpotTable
    """
    if profile is not None and not profile.is_gaussian_disk:
        return _make_profile_table(radius_px, profile, rel_cut, n_entries)
    s = max(sigma_px, 1e-3)
    reach = int(math.ceil(radius_px + 6.5 * s)) + 2
    step = 2.0 * reach * reach / (n_entries - 1)
    r_tab = np.sqrt((np.arange(n_entries) + 0.5) * step)
    # P is smooth on the scale of s: evaluate it on a fine r grid (h <= s/40) and
    # interpolate (error ~ h^2 P''/8 < 1e-4), 5-10x faster than chndtr at every bin
    r_end = min(float(r_tab[-1]), radius_px + 7.0 * s)  # beyond: P < 1e-10, taken as 0
    r_grid = np.linspace(0.0, r_end, max(256, int(40 * r_end / s) + 2))
    tab = np.interp(r_tab, r_grid, disk_blur_profile(r_grid, radius_px, s), right=0.0)
    above = np.nonzero(tab >= rel_cut)[0]
    r_cut = max(float(r_tab[above[-1]]) if above.size else 0.5, 0.5)
    tab[r_tab > r_cut] = 0.0
    half = int(math.ceil(r_cut))
    return SpotTable(radius_px, s, r_cut, half, step, tab.astype(np.float32))


def _make_profile_table(radius_px: float, prof: SpotProfile, rel_cut: float,
                        n_entries: int) -> SpotTable:
    """:func:`make_table` of a mixture profile (the same binning and cut)."""
    s_lo, s_hi = max(prof.sigma_min, 1e-3), max(prof.sigma_max, 1e-3)
    reach = int(math.ceil(radius_px + 6.5 * s_hi)) + 2
    step = 2.0 * reach * reach / (n_entries - 1)
    r_tab = np.sqrt((np.arange(n_entries) + 0.5) * step)
    r_end = min(float(r_tab[-1]), radius_px + 7.0 * s_hi)
    r_grid = np.linspace(0.0, r_end, max(256, min(int(40 * r_end / s_lo) + 2, 20000)))
    tab = np.interp(r_tab, r_grid, profile_at(r_grid, radius_px, prof), right=0.0)
    above = np.nonzero(tab >= rel_cut)[0]
    r_cut = max(float(r_tab[above[-1]]) if above.size else 0.5, 0.5)
    tab[r_tab > r_cut] = 0.0
    half = int(math.ceil(r_cut))
    return SpotTable(radius_px, prof.sigma_min, r_cut, half, step, tab.astype(np.float32))


ZERO_TABLE = SpotTable(0.0, 0.0, 0.0, 0, 1.0, np.zeros(1, np.float32))
"""A table of no core light (1x1 window of 0): for glare-only source sets."""


class TableCache:
    """Spot tables keyed by (radius bucket, sigma): radii are quantized to ``rel_step``
    relative steps (geometric grid, error <= rel_step/2); callers scale the amplitude by
    (R_true / R_table)^2 so that the flux stays exact. LRU with ``size`` entries."""

    def __init__(self, rel_step: float = 0.01, size: int = 512) -> None:
        self.log_step = math.log1p(rel_step)
        self.size = size
        self._d: OrderedDict[tuple, SpotTable] = OrderedDict()

    def get(self, radius_px: float, sigma_px: float,
            profile: SpotProfile | None = None) -> SpotTable:
        """The table of radius ``radius_px`` (quantized) and blur ``sigma_px``, or of spot
        model ``profile`` when it is not the plain Gaussian disk.

        Parameters
        ----------
        radius_px : float
            Disk radius R, px.
        sigma_px : float
            Gaussian blur s, px.
        profile : SpotProfile, optional
            A spot model other than the Gaussian disk.

        Returns
        -------
        SpotTable
            Tabulated at the quantized radius (its ``radius_px``).
        """
        b = int(round(math.log(max(radius_px, 1e-6)) / self.log_step))
        plain = profile is None or profile.is_gaussian_disk
        key = (b, round(sigma_px, 9)) if plain else (b, profile)
        t = self._d.get(key)
        if t is None:
            t = make_table(math.exp(b * self.log_step), sigma_px,
                           profile=None if plain else profile)
            self._d[key] = t
            if len(self._d) > self.size:
                self._d.popitem(last=False)
        else:
            self._d.move_to_end(key)
        return t


@dataclass
class Canvas:
    """A window of the image: pixel (y0 + i, x0 + j) is data[i, j] (float32 or float64)."""

    x0: int
    y0: int
    data: np.ndarray


def source_box(u: np.ndarray, v: np.ndarray, half: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) half-open pixel box holding windows of ``half`` around all (u, v).

    Parameters
    ----------
    u, v : ndarray
        (n,) source centres, px (n >= 1).
    half : int
        Half-size of each source's window, px.

    Returns
    -------
    x0, y0, x1, y1 : int
        Box, px (x1, y1 exclusive).
    """
    x0 = int(np.floor(u.min() + 0.5)) - half - 1
    y0 = int(np.floor(v.min() + 0.5)) - half - 1
    x1 = int(np.floor(u.max() + 0.5)) + half + 2
    y1 = int(np.floor(v.max() + 0.5)) + half + 2
    return x0, y0, x1, y1


@dataclass
class Footprint:
    """Where n sources of one spot table land in a canvas (geometry only, reusable for
    any amplitudes while the sources do not move).

    flat: (n*k*k,) indices into the flattened canvas; kern: (n, k*k) core profile P there;
    gy (H, m), gx (W, q): glare Gaussians (unit area) of the source rows/columns, with
    ``grid`` = (m, q) when the n = m*q sources form a row-major grid (shared row v and
    column u, e.g. an LED array), else m = q = n.
    """

    x0: int
    y0: int
    shape: tuple[int, int]
    flat: np.ndarray
    kern: np.ndarray
    gy: np.ndarray | None
    gx: np.ndarray | None
    grid: tuple[int, int] | None


def footprint(x0: int, y0: int, shape: tuple[int, int], u: np.ndarray, v: np.ndarray,
              tab: SpotTable, glare_sigma_px: float = 0.0,
              grid: tuple[int, int] | None = None) -> Footprint:
    """Precompute the pixels of sources at (u, v) px in the canvas at (x0, y0) of ``shape``.

    Every source's (2*half+1)^2 window must lie inside the canvas (see :func:`source_box`).

    Parameters
    ----------
    x0, y0 : int
        Image px of the canvas's pixel (0, 0).
    shape : tuple of int
        (H, W) of the canvas, px.
    u, v : ndarray
        (n,) source centres, image px.
    tab : SpotTable
        The core profile of every source.
    glare_sigma_px : float
        Glare Gaussian sigma, px (0: no glare).
    grid : tuple of int, optional
        (m, q) when the n = m q sources form a row-major grid (shared rows and columns).

    Returns
    -------
    Footprint
    """
    H, W = shape
    h = tab.half
    k = 2 * h + 1
    sc = math.sqrt(1.0 / tab.step)  # r^2 in table bins
    ix = np.floor(u + 0.5).astype(np.int64) - h  # window origin, image coords
    iy = np.floor(v + 0.5).astype(np.int64) - h
    ar = np.arange(k, dtype=np.float64)
    dx = ((ix - u)[:, None] + ar[None, :]) * sc
    dy = ((iy - v)[:, None] + ar[None, :]) * sc
    dx = (dx * dx).astype(np.float32)
    dy = (dy * dy).astype(np.float32)
    r2 = dy[:, :, None] + dx[:, None, :]  # (n, k, k), in table bins
    kern = tab.table.take(r2.astype(np.intp)).reshape(u.size, k * k)
    off = (np.arange(k)[:, None] * W + np.arange(k)[None, :]).ravel()
    base = (iy - y0) * W + (ix - x0)
    flat = (base[:, None] + off[None, :]).ravel()
    gy = gx = None
    if glare_sigma_px > 0:
        if grid is not None:
            m, q = grid
            vv = v.reshape(m, q)[:, 0]
            uu = u.reshape(m, q)[0, :]
        else:
            vv, uu = v, u
        y = y0 + np.arange(H, dtype=np.float64)
        x = x0 + np.arange(W, dtype=np.float64)
        c = 1.0 / (math.sqrt(2 * math.pi) * glare_sigma_px)
        gy = _gauss(y[:, None], vv[None, :], glare_sigma_px) * c
        gx = _gauss(x[:, None], uu[None, :], glare_sigma_px) * c
    return Footprint(x0, y0, (H, W), flat, kern, gy, gx, grid)


def render(fp: Footprint, amp: np.ndarray, flux: np.ndarray | None = None,
           out: np.ndarray | None = None) -> np.ndarray:
    """Sources of footprint ``fp`` with core peak scales ``amp`` (n,) DN and glare fluxes
    ``flux`` (n,) DN px^2, as a float64 (H, W) canvas (added into ``out`` if given).

    Parameters
    ----------
    fp : Footprint
        Where the sources land.
    amp : ndarray
        (n,) core peak scales, DN.
    flux : ndarray, optional
        (n,) glare fluxes, DN px^2 (None: no glare).
    out : ndarray, optional
        (H, W) float64 canvas to add into (in place).

    Returns
    -------
    ndarray of float64
        (H, W) canvas, DN (``out`` if given).
    """
    H, W = fp.shape
    w = fp.kern * amp.astype(np.float32)[:, None]
    acc = np.bincount(fp.flat, w.ravel(), minlength=H * W).reshape(H, W)
    if out is not None:
        out += acc
        acc = out
    if fp.gy is not None and flux is not None:
        if fp.grid is not None:
            acc += fp.gy @ (flux.reshape(fp.grid) @ fp.gx.T)
        else:
            acc += (fp.gy * flux[None, :]) @ fp.gx.T
    return acc


def add_cores(canvas: Canvas, u: np.ndarray, v: np.ndarray, amp: np.ndarray,
              tab: SpotTable) -> None:
    """Add amp_i * P(|x - (u_i, v_i)|) of every source into ``canvas`` (in place).

    Parameters
    ----------
    canvas : Canvas
        The image window, DN.
    u, v : ndarray
        (n,) source centres, image px.
    amp : ndarray
        (n,) core peak scales, DN.
    tab : SpotTable
        The core profile P.
    """
    if u.size == 0:
        return
    fp = footprint(canvas.x0, canvas.y0, canvas.data.shape, u, v, tab)
    canvas.data += render(fp, amp)


def add_glare(canvas: Canvas, u: np.ndarray, v: np.ndarray, flux: np.ndarray,
              sigma_px: float) -> None:
    """Add Gaussian halos (total ``flux`` DN px^2 each, sigma px) at (u, v) into ``canvas``.

    Separable: canvas += (Gy * flux) @ Gx^T with Gy[y, i] = N(y - v_i; s), Gx likewise.

    Parameters
    ----------
    canvas : Canvas
        The image window, DN.
    u, v : ndarray
        (n,) halo centres, image px.
    flux : ndarray
        (n,) total flux of each halo, DN px^2.
    sigma_px : float
        Halo sigma s, px.
    """
    if u.size == 0:
        return
    H, W = canvas.data.shape
    y = canvas.y0 + np.arange(H, dtype=np.float64)
    x = canvas.x0 + np.arange(W, dtype=np.float64)
    c = 1.0 / (math.sqrt(2 * math.pi) * sigma_px)
    gy = _gauss(y[:, None], v[None, :], sigma_px) * (c * flux)[None, :]
    gx = _gauss(x[:, None], u[None, :], sigma_px) * c
    canvas.data += gy @ gx.T


def _gauss(x: np.ndarray, mu: np.ndarray, s: float) -> np.ndarray:
    """exp(-(x - mu)^2 / (2 s^2)), exactly 0 beyond 8.9 s (no denormals downstream)."""
    a = (x - mu) * (1.0 / s)
    a *= a
    a *= -0.5
    e = np.exp(a)
    e[a < -40.0] = 0.0
    return e


def spot_size_px(radius_px: float, sigma_px: float, level: float = 0.1) -> float:
    """Full width (px) of the continuous core profile at ``level`` of its peak.

    Parameters
    ----------
    radius_px : float
        Disk radius R, px.
    sigma_px : float
        Gaussian blur s, px.
    level : float
        Fraction of the peak, 0..1.

    Returns
    -------
    float
        Full width, px.
    """
    s = max(sigma_px, 1e-3)
    rr = np.linspace(0.0, radius_px + 8 * s, 4001)
    p = disk_blur_profile(rr, radius_px, s)
    return 2.0 * float(np.interp(-level * p[0], -p, rr))
