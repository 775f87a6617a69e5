"""Light of an array's neighbours in each LED's luminance: estimated and cancelled.

Where the point-spread function (blur, glare, a diffuser's halo) is wider than the LED
pitch, part of each neighbour's light falls in an LED's luminance window. The contract:

* The model is linear and the same for every LED of a camera: LED ``i`` of camera ``c``
  reads ``y_i = x_i + sum_d a[c, d] x_{n_d(i)}``, ``x`` the light of the LED alone and
  ``n_d(i)`` its neighbour in direction ``d`` (:data:`DIRECTIONS`: up, down, left, right;
  none past the array's edge). ``a`` is a fraction (DN per DN), a few per cent where it
  matters.
* Why it costs symbols: the packet's training sends LED ``i`` the level ``(k + i) mod M``
  (:mod:`iscd.core.airinterface`), so the LEDs above and below an LED send its own level
  and those beside it one level off; the centroids fitted on the training then hold the
  neighbours' light of a correlated pattern, the data's neighbours are random -- a bias and
  a data-dependent spread the channel model (:mod:`iscd.decode.comms.channel`) cannot
  hold. With 4 x 0.025 of the light beside each LED, an f/4 camera's per-LED noise was
  4.2 DN RMS against 0.9 DN once the neighbours' levels were accounted for.
* Estimated from a packet's decided data (:func:`estimate_crosstalk`: the regression of
  each clean sample's deviation from its LED's level mean on the neighbours' level means,
  pooled over the array; a few per cent wrong decisions barely move it), then cancelled in
  every frame (:func:`cancel_crosstalk`: ``y - sum_d a_d y_{n_d}``, first order in ``a``;
  the neighbours' own crosstalk is ``a^2``). An offset added to every LED passes through
  as a per-LED offset that the channel model fits anyway.

Pure numpy functions (nothing here is per frame: :func:`iscd.decode.comms.demod.demodulate_packet`
calls them once for a packet that failed its CRC).
"""

from __future__ import annotations

import numpy as np

DIRECTIONS: tuple[tuple[int, int], ...] = ((-1, 0), (1, 0), (0, -1), (0, 1))
"""Neighbour offsets (row, column): up, down, left, right."""

MIN_CROSSTALK = 0.005
"""Smallest estimated fraction (largest over a camera's directions) worth cancelling: below
it the neighbours' light is within the noise of the estimate."""


def grid_neighbours(rows: int, cols: int) -> np.ndarray:
    """Index of each LED's neighbour in every direction of :data:`DIRECTIONS`.

    Parameters
    ----------
    rows, cols : int
        The array's shape; LED ``i`` sits at row ``i // cols``, column ``i % cols``.

    Returns
    -------
    ndarray of int64
        (4, rows * cols) neighbour indices, -1 past the array's edge.
    """
    if rows < 1 or cols < 1:
        raise ValueError(f"grid: expected at least 1 x 1 LEDs, got {rows} x {cols}")
    r, c = np.divmod(np.arange(rows * cols), cols)
    out = np.full((len(DIRECTIONS), rows * cols), -1, np.int64)
    for d, (dr, dc) in enumerate(DIRECTIONS):
        rr, cc = r + dr, c + dc
        ok = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
        out[d, ok] = rr[ok] * cols + cc[ok]
    return out


def _neighbour_values(x: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """(D, ..., N) the values of each LED's neighbours in x (..., N); 0 past the edge."""
    out = np.zeros((nb.shape[0],) + x.shape)
    for d in range(nb.shape[0]):
        ok = nb[d] >= 0
        out[d][..., ok] = x[..., nb[d][ok]]
    return out


def estimate_crosstalk(y: np.ndarray, lev: np.ndarray, M: int, nb: np.ndarray) -> np.ndarray:
    """Fraction of each neighbour's light in an LED's luminance, per camera and direction.

    Parameters
    ----------
    y : ndarray
        (C, n, N) clean-frame luminance of decided symbols, DN (NaN = missing).
    lev : ndarray
        (n, N) their 0-based levels (-1 = unknown), decided or known; use random data, not
        the training (there the neighbours' levels follow the LED's own).
    M : int
        Number of levels.
    nb : ndarray
        (D, N) neighbour indices (:func:`grid_neighbours`).

    Returns
    -------
    ndarray
        (C, D) fractions a (DN per DN; 0 for a camera without enough samples).
    """
    C, n, N = y.shape
    D = nb.shape[0]
    out = np.zeros((C, D))
    if n == 0 or lev.shape != (n, N):
        return out
    for c in range(C):
        yc = y[c]
        dev = np.full(yc.shape, np.nan)  # deviation from the LED's mean at its level
        lm = np.full(yc.shape, np.nan)  # the LED's mean at its level (its light, noise-free)
        for s in range(M):
            m = (lev == s) & np.isfinite(yc)
            cnt = m.sum(axis=0)
            mean = np.where(m, yc, 0.0).sum(axis=0) / np.maximum(cnt, 1)
            dev = np.where(m, yc - mean[None, :], dev)
            lm = np.where(m, mean[None, :], lm)
        with np.errstate(all="ignore"):
            centre = np.nanmean(lm, axis=0)
        light = np.where(np.isfinite(lm), lm - centre[None, :], np.nan)  # (n, N) around each LED's mean
        X = _neighbour_values(light, nb)  # (D, n, N); NaN where a neighbour's level is unknown
        X = X.reshape(D, -1).T
        t = dev.reshape(-1)
        ok = np.isfinite(t) & np.isfinite(X).all(axis=1)
        if ok.sum() < 4 * D:
            continue
        coef, *_ = np.linalg.lstsq(X[ok], t[ok], rcond=None)
        out[c] = coef
    return out


def cancel_crosstalk(L: np.ndarray, coef: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """Luminance with the neighbours' light taken out, to first order.

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance, DN (NaN = missing: a missing neighbour cancels nothing).
    coef : ndarray
        (C, D) fractions (:func:`estimate_crosstalk`).
    nb : ndarray
        (D, N) neighbour indices (:func:`grid_neighbours`).

    Returns
    -------
    ndarray
        (C, n, N) float64 ``L - sum_d coef[c, d] L[c, :, nb[d]]`` (C-contiguous).
    """
    if coef.shape != (L.shape[0], nb.shape[0]) or nb.shape[1] != L.shape[2]:
        raise ValueError(f"cancel_crosstalk: coef {coef.shape} / neighbours {nb.shape} do not fit "
                         f"luminance {L.shape}")
    sh = _neighbour_values(np.nan_to_num(np.asarray(L, dtype=np.float64), nan=0.0), nb)  # (D, C, n, N)
    return np.ascontiguousarray(L - np.einsum("cd,dcnk->cnk", coef, sh))
