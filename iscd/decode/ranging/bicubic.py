"""Bicubic (Keys cubic-convolution) interpolation of LED patches, dissertation eqs. 3.1-3.3.

The dissertation magnifies every LED patch by an integer factor alpha (3) before
phase-only correlation. Output pixel ``x_bic`` samples the input at ``x_bic / alpha``
(eq. 3.1: ``x = floor(x_bic/alpha)``, ``Delta = frac(x_bic/alpha)``) and is the weighted sum
of the 4x4 neighbouring input pixels with the Keys kernel ``S(u)`` (eqs. 3.2, 3.3),
a = -0.5. (OpenCV's ``INTER_CUBIC`` uses a = -0.75 and a pixel-centre mapping, so it is a
different interpolator; :func:`interp_matrix` can build either for comparison.)

Because the kernel is separable, magnifying an (h, w) patch is ``Wy @ G @ Wx.T`` with two
small constant matrices (alpha*h x h and alpha*w x w): a batch of patches is two batched
matrix products, no per-pixel loops. Pixels outside the patch are the nearest edge pixel
(replicated border).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

Mapping = Literal["dissertation", "center"]

KEYS_A = -0.5
"""The Keys constant of the dissertation's kernel (eq. 3.3)."""


def keys_kernel(u: ArrayLike, a: float = KEYS_A) -> NDArray[np.float64]:
    """Keys cubic-convolution kernel S(u) (eq. 3.3 for a = -0.5).

    ``S(u) = (a+2)|u|^3 - (a+3)|u|^2 + 1`` for ``|u| <= 1``,
    ``a|u|^3 - 5a|u|^2 + 8a|u| - 4a`` for ``1 < |u| <= 2``, 0 beyond. With a = -0.5 this is
    ``1 - 2.5u^2 + 1.5|u|^3`` and ``2 - 4|u| + 2.5u^2 - 0.5|u|^3``.

    Parameters
    ----------
    u : array_like
        Offsets from the output sample, input px.
    a : float
        Kernel constant (default :data:`KEYS_A` = -0.5, the dissertation's).

    Returns
    -------
    ndarray of float64
        S(u), the shape of ``u``.

    References
    ----------
    Dissertation, eq. (3.3).
    """
    x = np.abs(np.asarray(u, dtype=np.float64))
    inner = ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0
    outer = ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a
    return np.where(x <= 1.0, inner, np.where(x <= 2.0, outer, 0.0))


def sample_positions(n_in: int, alpha: int, mapping: Mapping = "dissertation") -> NDArray[np.float64]:
    """Input-pixel coordinates sampled by the ``alpha * n_in`` output pixels.

    ``"dissertation"``: ``x_bic / alpha`` (eq. 3.1; output pixel 0 sits on input pixel 0).
    ``"center"``: ``(x_bic + 0.5) / alpha - 0.5`` (pixel-centre convention of cv2.resize).

    Parameters
    ----------
    n_in : int
        Input samples along the axis, px.
    alpha : int
        Magnification (output samples per input px).
    mapping : {"dissertation", "center"}
        Output-to-input coordinate convention (above).

    Returns
    -------
    ndarray of float64
        (alpha * n_in,) input coordinates, input px.

    References
    ----------
    Dissertation, eq. (3.1).
    """
    j = np.arange(alpha * n_in, dtype=np.float64)
    if mapping == "dissertation":
        return j / alpha
    if mapping == "center":
        return (j + 0.5) / alpha - 0.5
    raise ValueError(f"mapping: expected 'dissertation' or 'center', got {mapping!r}")


@lru_cache(maxsize=64)
def _interp_matrix_cached(n_in: int, alpha: int, a: float, mapping: Mapping) -> NDArray[np.float64]:
    p = sample_positions(n_in, alpha, mapping)
    x0 = np.floor(p)
    delta = p - x0                                   # eq. 3.1: fractional part
    h = np.arange(-1, 3)                             # eq. 3.2: the 4 neighbours x-1 .. x+2
    idx = np.clip(x0[:, None].astype(np.int64) + h[None, :], 0, n_in - 1)   # replicated border
    w = keys_kernel(h[None, :] - delta[:, None], a)  # S(h - Delta)
    m = np.zeros((p.size, n_in))
    np.add.at(m, (np.repeat(np.arange(p.size), 4), idx.ravel()), w.ravel())
    m.setflags(write=False)
    return m


def interp_matrix(n_in: int, alpha: int = 3, a: float = KEYS_A,
                  mapping: Mapping = "dissertation") -> NDArray[np.float64]:
    """The (alpha*n_in, n_in) matrix M with ``upsampled = M @ samples`` along one axis.

    Row j holds the kernel weights S(h - Delta) (eq. 3.2) of output sample j. Cached and
    read-only.

    Parameters
    ----------
    n_in : int
        Input samples along the axis, px.
    alpha : int
        Magnification (output samples per input px).
    a : float
        Keys kernel constant (:func:`keys_kernel`).
    mapping : {"dissertation", "center"}
        Coordinate convention (:func:`sample_positions`).

    Returns
    -------
    ndarray of float64
        (alpha * n_in, n_in), read-only.

    References
    ----------
    Dissertation, eqs. (3.1)-(3.3).
    """
    if not isinstance(n_in, (int, np.integer)) or n_in < 1:
        raise ValueError(f"n_in: expected a positive integer, got {n_in!r}")
    if not isinstance(alpha, (int, np.integer)) or alpha < 1:
        raise ValueError(f"alpha: expected a positive integer magnification, got {alpha!r}")
    return _interp_matrix_cached(int(n_in), int(alpha), float(a), mapping)


def upsample(patches: ArrayLike, alpha: int = 3, a: float = KEYS_A,
             mapping: Mapping = "dissertation") -> NDArray[np.float64]:
    """Magnify (n, h, w) or (h, w) patches by ``alpha`` with the Keys kernel (eqs. 3.1-3.3).

    Output pixel (y_bic, x_bic) is the input at (y_bic/alpha, x_bic/alpha) in input px.
    Computed as ``Wy @ G @ Wx.T``: two batched matrix products.

    Parameters
    ----------
    patches : array_like
        (n, h, w) or (h, w) patches, grey levels (DN).
    alpha : int
        Magnification.
    a : float
        Keys kernel constant (:func:`keys_kernel`).
    mapping : {"dissertation", "center"}
        Coordinate convention (:func:`sample_positions`).

    Returns
    -------
    ndarray of float64
        Patches of shape (n, alpha*h, alpha*w) (or (alpha*h, alpha*w)), DN.

    References
    ----------
    Dissertation, eqs. (3.1)-(3.3).
    """
    g = np.asarray(patches, dtype=np.float64)
    if g.ndim not in (2, 3):
        raise ValueError(f"patches: expected shape (h, w) or (n, h, w), got {g.shape}")
    wy = interp_matrix(g.shape[-2], alpha, a, mapping)
    wx = interp_matrix(g.shape[-1], alpha, a, mapping)
    return np.matmul(np.matmul(wy, g), wx.T)
