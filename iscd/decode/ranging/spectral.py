"""The 1-D spectral pieces shared by the projected method and its compiled kernels: the
rfft bins' frequencies, multiplicities and band weights, the peak record, the row weights.

A module of its own below both :mod:`iscd.decode.ranging.projected` and
:mod:`iscd.decode.ranging.project_kernel`, so that neither imports the other to get them.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

_TINY = 1e-12


@dataclass(frozen=True)
class Peak1D:
    """Sub-pixel maximum of a batch of 1-D correlation functions; all fields (n,)."""

    dx: NDArray[np.float64]
    """position of the maximum, samples (left - right)."""
    height: NDArray[np.float64]
    """correlation at the maximum / sum of the spectral weights (1 = a perfect match)."""
    sigma: NDArray[np.float64]
    """standard deviation of ``dx`` from the residual phases, samples."""


@lru_cache(maxsize=64)
def _spectral(w: int, band_cutoff: float | None) -> tuple[NDArray[np.float64], ...]:
    """For an rfft of length w: angular frequencies (rad/sample); bin multiplicities (1 for
    DC, 2 for the bins that stand for a conjugate pair, 0 for the Nyquist bin of an even w,
    which a real-symmetric surface cannot use); the Gaussian band weight (0 at an even w's
    Nyquist bin); omega^2; omega^2 / multiplicity (for the gradient variance)."""
    k = np.arange(w // 2 + 1, dtype=np.float64)
    omega = 2.0 * np.pi * k / w
    mult = np.full(k.size, 2.0)
    mult[0] = 1.0
    if w % 2 == 0:
        mult[-1] = 0.0
    band = np.ones(k.size) if band_cutoff is None or band_cutoff <= 0 else np.exp(-0.5 * (k / w / band_cutoff) ** 2)
    band = band * (mult > 0)
    w2 = omega * omega
    w2m = w2 / np.where(mult > 0, mult, 1.0)
    out = (omega, mult, band, w2, w2m)
    for a in out:
        a.setflags(write=False)
    return out


def row_weights(h: int, rows_y: ArrayLike, sigma_px: float) -> NDArray[np.float64]:
    """Projection weights: a Gaussian of ``sigma_px`` at each LED row, summed, max 1.

    The matched filter of the spots' vertical profile; empty rows between and around them get
    ~0 weight.

    Parameters
    ----------
    h : int
        Patch height, px.
    rows_y : array_like
        LED rows, patch px.
    sigma_px : float
        Gaussian standard deviation, px.

    Returns
    -------
    ndarray of float64
        (h,) weights.
    """
    ys = np.unique(np.round(np.asarray(rows_y, dtype=np.float64).ravel(), 2))
    y = np.arange(h, dtype=np.float64)[:, None]
    w = np.exp(-0.5 * ((y - ys[None, :]) / max(sigma_px, 0.3)) ** 2).sum(axis=1)
    m = w.max() if w.size else 0.0
    return w / m if m > 0 else np.ones(h)
