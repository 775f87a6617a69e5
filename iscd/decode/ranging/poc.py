"""Phase-only correlation (POC) of patch pairs and its sub-pixel peak, dissertation eqs. 3.5-3.9.

All functions work on a batch: ``left`` and ``right`` are (n, h, w) arrays (one pair per
row of the batch) and results are (n,) arrays. Shift convention everywhere in
:mod:`iscd.decode.ranging`: ``shift = position in the left patch - position in the right patch``
(px), so that an LED's disparity is ``(x0_left - x0_right) + shift_x`` for patches cut at
columns ``x0_left``/``x0_right`` (``d = x_l - x_r``, eq. 2.2). The POC surface then peaks
at ``+shift`` (the cross-power spectrum is ``F_l conj(F_r)``, eq. 3.5).

Two sub-pixel estimators live here:

- :func:`sinc_fit` -- the dissertation's: the POC peak is modelled as ``A sinc(x - gamma)``
  (eq. 3.9, the approximation of the Dirichlet kernel 3.8) along the peak row (and,
  separately, the peak column), and ``gamma`` is found by least squares on a grid of
  candidate offsets with a chosen resolution (0.01 px in the dissertation), ``A`` in
  closed form for each candidate.
- :func:`continuous_peak` -- the project's: the correlation surface of a (possibly
  weighted) cross-power spectrum is a trigonometric polynomial, so its maximum can be found
  exactly by Newton's method on the analytic surface (no grid, no model mismatch: for a
  pure shift and any non-negative even spectral weight the maximum is at the shift). It also
  returns a per-estimate standard deviation from the residual phases (a sandwich estimate).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

Kernel = Literal["sinc", "dirichlet"]

_TINY = 1e-12


def as_batch(patches: ArrayLike, name: str = "patches") -> NDArray[np.float64]:
    """``patches`` as a float64 (n, h, w) array; a single (h, w) patch becomes n = 1.

    Parameters
    ----------
    patches : array_like
        (n, h, w) or (h, w) patches, DN.
    name : str
        The argument's name in error messages.

    Returns
    -------
    ndarray of float64
        (n, h, w).
    """
    g = np.asarray(patches, dtype=np.float64)
    if g.ndim == 2:
        g = g[None]
    if g.ndim != 3 or g.shape[1] < 2 or g.shape[2] < 2:
        raise ValueError(f"{name}: expected shape (n, h, w) with h, w >= 2, got {np.shape(patches)}")
    return g


def check_pair(left: ArrayLike, right: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Validate a batch of patch pairs: same shape (n, h, w), finite values.

    Parameters
    ----------
    left, right : array_like
        (n, h, w) or (h, w) patches, DN.

    Returns
    -------
    left, right : ndarray of float64
        Each (n, h, w).
    """
    lf, rt = as_batch(left, "left"), as_batch(right, "right")
    if lf.shape != rt.shape:
        raise ValueError(f"left and right patches differ in shape: {lf.shape} vs {rt.shape}")
    if not (np.isfinite(lf).all() and np.isfinite(rt).all()):
        raise ValueError("patches contain NaN or infinite values")
    return lf, rt


def cross_power(f_left: NDArray[np.complex128], f_right: NDArray[np.complex128],
                beta: float = 1.0) -> NDArray[np.complex128]:
    """Cross-power spectrum ``X / |X|^beta`` with ``X = F_l conj(F_r)`` (eq. 3.5 for beta = 1).

    ``beta = 1`` is phase-only (POC, unit magnitude), ``beta = 0`` plain cross-correlation;
    in between is the "PHAT-beta" weighting. Bins with ``X = 0`` stay 0.

    Parameters
    ----------
    f_left, f_right : ndarray of complex128
        DFTs of the left and right patches, same shape.
    beta : float
        Magnitude weighting exponent, 0-1.

    Returns
    -------
    ndarray of complex128
        The weighted cross-power spectrum, the shape of the inputs.

    References
    ----------
    Dissertation, eq. (3.5).
    """
    x = f_left * np.conj(f_right)
    if beta == 0.0:
        return x
    mag = np.abs(x)
    scale = np.where(mag > _TINY, np.maximum(mag, _TINY) ** (-beta), 0.0)
    return x * scale


def poc_surface(left: ArrayLike, right: ArrayLike) -> NDArray[np.float64]:
    """The POC function (eq. 3.6): real inverse DFT of the normalized cross-power spectrum.

    Unshifted (index 0 = zero shift; negative shifts wrap to the end). A perfect integer shift
    gives a Kronecker delta of height 1 at ``+shift``.

    Parameters
    ----------
    left, right : array_like
        (n, h, w) or (h, w) patch pairs, DN.

    Returns
    -------
    ndarray of float64
        (n, h, w) correlation surfaces, indexed by shift in px.

    References
    ----------
    Dissertation, eqs. (3.5), (3.6).
    """
    lf, rt = check_pair(left, right)
    c = cross_power(np.fft.fft2(lf), np.fft.fft2(rt))
    return np.fft.ifft2(c).real


def integer_peak(surface: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Signed (row, column) of the maximum of each (h, w) surface (eq. 3.7).

    Indices above h/2 (w/2) wrap to negative shifts.

    Parameters
    ----------
    surface : ndarray of float64
        (n, h, w) correlation surfaces (:func:`poc_surface`).

    Returns
    -------
    iy, ix : ndarray of int64
        Each (n,), samples (px of the surface).

    References
    ----------
    Dissertation, eq. (3.7).
    """
    n, h, w = surface.shape
    flat = np.argmax(surface.reshape(n, -1), axis=1)
    iy, ix = np.divmod(flat, w)
    iy = np.where(iy >= (h + 1) // 2, iy - h, iy)
    ix = np.where(ix >= (w + 1) // 2, ix - w, ix)
    return iy.astype(np.int64), ix.astype(np.int64)


def peak_kernel(u: NDArray[np.float64], size: int, kernel: Kernel = "sinc") -> NDArray[np.float64]:
    """The POC peak shape at offset ``u`` samples.

    ``sinc(u)`` (eq. 3.9) or the Dirichlet kernel ``sin(pi u) / (size sin(pi u / size))``
    (eq. 3.8).

    Parameters
    ----------
    u : ndarray of float64
        Offsets from the peak, samples.
    size : int
        Transform length, samples (Dirichlet kernel only).
    kernel : {"sinc", "dirichlet"}
        Peak model.

    Returns
    -------
    ndarray of float64
        The model at ``u``, the shape of ``u``.

    References
    ----------
    Dissertation, eqs. (3.8), (3.9).
    """
    if kernel == "sinc":
        return np.sinc(u)
    if kernel == "dirichlet":
        den = size * np.sin(np.pi * u / size)
        small = np.abs(den) < 1e-9
        return np.where(small, 1.0, np.sin(np.pi * u) / np.where(small, 1.0, den))
    raise ValueError(f"kernel: expected 'sinc' or 'dirichlet', got {kernel!r}")


@lru_cache(maxsize=32)
def _model_table(radius: int, step: float, span: float, size: int,
                 kernel: Kernel) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    cand = np.arange(-span, span + step / 2, step)           # candidate offsets, samples
    j = np.arange(-radius, radius + 1, dtype=np.float64)      # sample offsets from the peak
    m = peak_kernel(j[None, :] - cand[:, None], size, kernel)  # (n_cand, 2r+1)
    norm2 = np.sum(m * m, axis=1)
    for a in (cand, m, norm2):
        a.setflags(write=False)
    return cand, m, norm2


def _line_samples(surface: NDArray[np.float64], iy: NDArray[np.int64], ix: NDArray[np.int64],
                  radius: int, axis: int) -> NDArray[np.float64]:
    n, h, w = surface.shape
    j = np.arange(-radius, radius + 1)
    rows = np.arange(n)[:, None]
    if axis == 1:    # along x, on the peak row
        return surface[rows, (iy % h)[:, None], (ix[:, None] + j[None, :]) % w]
    return surface[rows, (iy[:, None] + j[None, :]) % h, (ix % w)[:, None]]


def sinc_fit(surface: NDArray[np.float64], iy: NDArray[np.int64], ix: NDArray[np.int64],
             radius: int = 2, step: float = 0.01, span: float = 1.0,
             kernel: Kernel = "sinc") -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Least-squares sinc-model fit of the POC peak (eqs. 3.8, 3.9), on a grid.

    Along the peak row, the ``2*radius+1`` samples ``c(ix+j)`` are fitted by
    ``A * S(j - gamma)`` for every candidate ``gamma`` in ``[-span, span]`` with spacing
    ``step`` (samples; the estimate's resolution), ``A`` by linear least squares, and the
    candidate with the least squared error (and A > 0) wins; likewise along the peak column.
    ``S`` is ``sinc`` (3.9) or the Dirichlet kernel (3.8).

    Parameters
    ----------
    surface : ndarray of float64
        (n, h, w) POC surfaces.
    iy, ix : ndarray of int64
        (n,) integer peaks (:func:`integer_peak`), samples.
    radius : int
        Samples each side of the peak in the fit.
    step : float
        Grid spacing of the candidates, samples.
    span : float
        Candidates in ``[-span, span]``, samples.
    kernel : {"sinc", "dirichlet"}
        Peak model (:func:`peak_kernel`).

    Returns
    -------
    dy, dx : ndarray of float64
        (n,) sub-pixel peak position ``(iy + gamma_y, ix + gamma_x)``, samples.
    amplitude : ndarray of float64
        (n,) fitted peak height ``A`` of the x fit.

    References
    ----------
    Dissertation, eqs. (3.8), (3.9).
    """
    _, h, w = surface.shape
    out = []
    amp = None
    for axis, size in ((0, h), (1, w)):
        cand, m, norm2 = _model_table(int(radius), float(step), float(span), int(size), kernel)
        s = _line_samples(surface, iy, ix, radius, axis)          # (n, 2r+1)
        proj = s @ m.T                                            # (n, n_cand) = <c, model>
        score = np.where(proj > 0, proj * proj / norm2, -np.inf)  # = |c|^2 - min residual
        best = np.argmax(score, axis=1)
        out.append(cand[best])
        if axis == 1:
            amp = proj[np.arange(len(best)), best] / norm2[best]
    return iy + out[0], ix + out[1], amp  # type: ignore[return-value]


@dataclass(frozen=True)
class PeakResult:
    """Sub-pixel correlation peak of a batch: all fields (n,), positions in samples."""

    dy: NDArray[np.float64]
    dx: NDArray[np.float64]
    height: NDArray[np.float64]
    """peak value / sum of spectral weights: 1 for a perfect match, ~0 for no match."""
    sigma_y: NDArray[np.float64]
    sigma_x: NDArray[np.float64]
    """standard deviations of dy, dx from the residual phases (sandwich estimate)."""


def _freqs(n: int) -> NDArray[np.float64]:
    """Angular frequency (rad/sample) of the DFT bins; the Nyquist bin of an even size is 0
    (it is dropped by :func:`continuous_peak`, whose surface must be real and symmetric)."""
    k = np.fft.fftfreq(n) * n
    if n % 2 == 0:
        k[n // 2] = 0.0
    return 2.0 * np.pi * k / n


@lru_cache(maxsize=32)
def _powers(h: int, w: int) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.complex128],
                                      NDArray[np.complex128], NDArray[np.float64], NDArray[np.float64]]:
    """Bin frequencies wy (h,), wx (w,); derivative weights [1, i w, (i w)^2] per axis
    ((h, 3), (w, 3)); and the real moment weights [1, w, w^2] ((h, 3), (w, 3)). Read-only."""
    wy, wx = _freqs(h), _freqs(w)
    py = np.stack([np.ones(h), 1j * wy, -(wy ** 2)], axis=1)
    px = np.stack([np.ones(w), 1j * wx, -(wx ** 2)], axis=1)
    qy = np.stack([np.ones(h), wy, wy ** 2], axis=1)
    qx = np.stack([np.ones(w), wx, wx ** 2], axis=1)
    for a in (wy, wx, py, px, qy, qx):
        a.setflags(write=False)
    return wy, wx, py, px, qy, qx


def _parabolic_start(surf: NDArray[np.float64], y: NDArray[np.float64],
                     x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Refine integer peak positions by a 3-point parabola per axis on the correlation
    surface (a start for Newton's method, within a few hundredths of a sample)."""
    n, h, w = surf.shape
    iy = np.round(y).astype(np.int64)
    ix = np.round(x).astype(np.int64)
    k = np.arange(n)
    c0 = surf[k, iy % h, ix % w]
    out = []
    for lo, hi, base in ((surf[k, (iy - 1) % h, ix % w], surf[k, (iy + 1) % h, ix % w], y),
                         (surf[k, iy % h, (ix - 1) % w], surf[k, iy % h, (ix + 1) % w], x)):
        den = lo - 2 * c0 + hi
        off = np.where(den < -_TINY, 0.5 * (lo - hi) / np.where(den < -_TINY, den, 1.0), 0.0)
        out.append(base + np.clip(off, -0.5, 0.5))
    return out[0], out[1]


def continuous_peak(spectrum: NDArray[np.complex128], iy: ArrayLike, ix: ArrayLike,
                    iterations: int = 6, surface: NDArray[np.float64] | None = None,
                    width: int | None = None, stats: bool = True) -> PeakResult:
    """Maximum of the band-limited correlation surface of a cross-power ``spectrum``.

    ``spectrum`` is (n, h, w) from ``fft2``, or (n, h, w//2 + 1) from ``rfft2`` when the
    patch ``width`` w is given (half the work: each bin then stands for itself and its
    conjugate). ``c(y, x) = Re sum_k R(k) exp(i(w_y y + w_x x))`` is the trigonometric
    interpolant of the inverse DFT (the exact continuous form of eq. 3.6; for
    R = exp(-i w.delta) it is the Dirichlet kernel 3.8 centred at ``delta``). Starting from the
    integer peak ``(iy, ix)`` refined by a parabola, Newton steps on the analytic gradient and
    Hessian (steps clipped to 0.5 samples) find the maximum. Nyquist bins of even sizes are
    ignored so that the surface is real-symmetric. With ``iterations = 0`` the statistics are
    evaluated at the given (possibly fractional) ``(iy, ix)``.

    The standard deviations come from the linearized estimator: with residual phases
    ``e(k) = arg(R(k) exp(i w.delta))`` the gradient noise is
    ``G = 2 sum_k |R|^2 w w^T sin^2 e`` (conjugate bins are not independent, hence 2) and the
    Hessian ``H = -sum_k |R| w w^T cos e``; ``cov = H^-1 G H^-1``.

    Parameters
    ----------
    spectrum : ndarray of complex128
        (n, h, w) from ``fft2``, or (n, h, w//2 + 1) from ``rfft2`` with ``width``.
    iy, ix : array_like
        (n,) start positions (integer peaks), samples.
    iterations : int
        Newton steps.
    surface : ndarray of float64, optional
        The inverse DFT of ``spectrum`` if the caller has it (saves one transform for the
        parabolic start).
    width : int, optional
        Patch width w, px, when ``spectrum`` is a half spectrum.
    stats : bool
        False skips the height and standard deviations (NaN), for intermediate passes.

    Returns
    -------
    PeakResult
        dy, dx, samples; peak height; sigma_y, sigma_x, samples. All (n,).

    References
    ----------
    Dissertation, eqs. (3.6), (3.8).
    """
    n, h, wk = spectrum.shape
    half = width is not None and wk == width // 2 + 1 and width != wk
    w = int(width) if half else wk
    wy, wx, py, px, qy, qx = _powers(h, w)
    r = spectrum.copy()
    if h % 2 == 0:
        r[:, h // 2, :] = 0.0
    if w % 2 == 0:
        r[:, :, w // 2] = 0.0
    mult = np.ones(wk)
    if half:                       # columns 1 .. ceil(w/2)-1 stand for two bins each
        mult[1:(w + 1) // 2] = 2.0
        wx, px, qx = wx[:wk], px[:wk], qx[:wk]
        r *= mult
    y = np.array(iy, dtype=np.float64).reshape(n)
    x = np.array(ix, dtype=np.float64).reshape(n)
    if iterations > 0:
        if surface is None:
            surface = np.fft.irfft2(spectrum, s=(h, w)) if half else np.fft.ifft2(spectrum).real
        y, x = _parabolic_start(surface, y, x)
    # separable evaluation: c(y, x) = Re(ey^T R ex); the derivatives weight ex / ey by
    # (i w)^p. One batched matrix product per iteration gives all of them.
    for _ in range(iterations):
        ex = np.exp(1j * wx[None, :] * x[:, None])                   # (n, w)
        ey = np.exp(1j * wy[None, :] * y[:, None])                   # (n, h)
        t = np.matmul(r, ex[:, :, None] * px[None])                  # (n, h, 3)
        m = np.matmul(ey[:, None, :] * py.T[None], t).real           # (n, 3, 3): d^a/dy^a d^b/dx^b
        gy, gx = m[:, 1, 0], m[:, 0, 1]
        hyy, hxx, hxy = m[:, 2, 0], m[:, 0, 2], m[:, 1, 1]
        det = hyy * hxx - hxy * hxy
        ok = (det > _TINY) & (hxx < 0)                # a maximum: negative-definite Hessian
        safe = np.where(ok, det, 1.0)
        sy = np.clip(np.where(ok, -(hxx * gy - hxy * gx) / safe, np.sign(gy) * 0.25), -0.5, 0.5)
        sx = np.clip(np.where(ok, -(hyy * gx - hxy * gy) / safe, np.sign(gx) * 0.25), -0.5, 0.5)
        y = y + sy
        x = x + sx
        if np.abs(sy).max() < 1e-6 and np.abs(sx).max() < 1e-6:
            break
    if not stats:
        nan = np.full(n, np.nan)
        return PeakResult(dy=y, dx=x, height=nan, sigma_y=nan, sigma_x=nan)
    ey = np.exp(1j * wy[None, :] * y[:, None])
    ex = np.exp(1j * wx[None, :] * x[:, None])
    rot = r * ey[:, :, None] * ex[:, None, :]         # R(k) exp(i w.delta): residual phases
    c = rot.real                                      # |R| cos e (x multiplicity)
    s2 = rot.imag ** 2 / mult                         # |R|^2 sin^2 e (x multiplicity)
    total = np.maximum(np.abs(r).sum(axis=(1, 2)), _TINY)
    # sums over the bins of a(k) w_y^p w_x^q as (py^T A px): rows p, columns q
    mc = np.matmul(qy.T[None], np.matmul(c, qx[None]))              # (n, 3, 3)
    ms = np.matmul(qy.T[None], np.matmul(s2, qx[None]))
    height = mc[:, 0, 0] / total
    hyy, hxx, hxy = -mc[:, 2, 0], -mc[:, 0, 2], -mc[:, 1, 1]
    gyy, gxx, gxy = 2.0 * ms[:, 2, 0], 2.0 * ms[:, 0, 2], 2.0 * ms[:, 1, 1]
    det = hyy * hxx - hxy * hxy
    good = det > _TINY
    det = np.where(good, det, 1.0)
    # H^-1 = [[hxx, -hxy], [-hxy, hyy]] / det ;  cov = H^-1 G H^-1
    iyy, ixx, ixy = hxx / det, hyy / det, -hxy / det
    var_y = iyy * iyy * gyy + 2 * iyy * ixy * gxy + ixy * ixy * gxx
    var_x = ixy * ixy * gyy + 2 * ixy * ixx * gxy + ixx * ixx * gxx
    sig_y = np.where(good, np.sqrt(np.maximum(var_y, 0.0)), np.inf)
    sig_x = np.where(good, np.sqrt(np.maximum(var_x, 0.0)), np.inf)
    return PeakResult(dy=y, dx=x, height=height, sigma_y=sig_y, sigma_x=sig_x)
