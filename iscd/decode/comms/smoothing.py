"""The channel of one packet smoothed over the whole packet from its decisions (two-sided).

Every channel estimate of :func:`iscd.decode.comms.demod.demodulate_packet` is a window: the
final pass fits each stretch of 32 symbols on the 96 decided symbols centred on it. Where a
spot's core clips as the car closes in, one camera's upper levels fall by a quarter along a
packet while its lower levels hold (randomized 100 km/h approaches, 64 -> 27 m: level 8 from
65 to 49 DN, levels 7 and 8 ending 3 DN apart at 1 DN noise), and a right camera's upper
levels can step by 5-8 DN within forty symbols. A window of 96 symbols then lags: with the
*true* levels as labels the receiver's own estimator still left 3-12 wrong symbols on the four
packets looked at (windows of 24-48 symbols, 2-8), where this smoother left 0-3.

Model (the same as the sequential tracking's, :mod:`iscd.decode.comms.sequential`): per
camera the M level centroids ``x_k`` of symbol k are a random walk whose steps are correlated
between levels, ``Q[s, t] = (kappa span)^2 rho^|s - t|`` per symbol; a clean frame of symbol
k at level s is ``y = x_k[s] + noise`` of variance ``r[s]``. Given every clean frame of the
packet and its label (the header and training known, the data from a decision pass), the
posterior mean of all ``x_k`` at once -- what a Kalman filter run forwards and a
Rauch-Tung-Striebel smoother backwards give -- is the minimum of

    sum_j (y_j - x_{k_j}[s_j])^2 / r[s_j] + sum_k (x_k - x_{k-1})^T Q^-1 (x_k - x_{k-1}),

a block-tridiagonal least-squares problem solved here as one banded Cholesky system
(``S M`` unknowns, half-bandwidth ``2 M - 1``: ~1 ms for a one-LED PWM-8 packet).
The noise ``r[s]`` is taken from the differences of successive clean frames of the same
level (half their robust mean square: a smoother fitted through the frames would leave
residuals smaller than the noise), floored at ``var_floor_dn``. Frames more than
:data:`OUTLIER_SIGMAS` off the first fit (a wrong label, a glitch) are left out of a second.

Pure numerical functions: no I/O, no threads. Units: luminance DN, symbols.

References
----------
H. E. Rauch, F. Tung, C. T. Striebel, "Maximum likelihood estimates of linear dynamic
systems", AIAA Journal 3 (8), 1965 (the smoother); dissertation eq. (4.2) (the per-level
costs the decisions use).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.linalg import solveh_banded

from iscd.decode.comms.channel import ChannelModel
from iscd.decode.comms.sequential import KAPPA, RHO

STRETCH_WINDOW = 24
"""``channel_window_symbols`` the smoothed channel is decided with: stretches of a third of it,
8 symbols, each with the mean of its symbols' smoothed centroids (as the oracle's true channel)."""

OUTLIER_SIGMAS = 4.0
"""A clean frame this many noise RMS off the first fit is left out of the second."""

PRIOR_WEIGHT = 1e-6
"""Weight (1/DN^2) pulling every centroid towards the level mean of its camera: only keeps
the system definite where a level has no frame at all."""


def noise_variance(y: np.ndarray, k: np.ndarray, lab: np.ndarray, M: int, floor_dn: float) -> np.ndarray:
    """Per level the noise variance of clean frames, DN^2, from successive frames of that level.

    Parameters
    ----------
    y : numpy.ndarray
        (n,) clean-frame luminance of one camera, DN, in time order (NaN = missing).
    k : numpy.ndarray
        (n,) the symbol of each frame (two frames of one symbol are not a pair: they share
        its slow errors).
    lab : numpy.ndarray
        (n,) their 0-based levels.
    M : int
        Levels.
    floor_dn : float
        Smallest noise RMS, DN.

    Returns
    -------
    numpy.ndarray
        (M,) variances, DN^2: half the median squared difference of a level's frames in
        successive symbols of that level, over the median of chi-square with one degree of
        freedom (0.455); a level with fewer than three pairs takes the median of the others.
    """
    out = np.full(M, np.nan)
    ok = np.isfinite(y)
    for s in range(M):
        sel = ok & (lab == s)
        v, ks = y[sel], k[sel]
        d = np.diff(v)[np.diff(ks) > 0]  # successive symbols of that level (not one symbol's frames)
        if d.size >= 3:
            out[s] = 0.5 * float(np.median(d ** 2)) / 0.4549
    fill = np.nanmedian(out) if np.isfinite(out).any() else 1.0
    out = np.where(np.isfinite(out), out, fill)
    return np.maximum(out, floor_dn ** 2)


def smooth_centroids(y: np.ndarray, k: np.ndarray, lab: np.ndarray, S: int, M: int, r_var: np.ndarray,
                     step_cov: np.ndarray, use: np.ndarray | None = None) -> np.ndarray:
    """Posterior mean of every symbol's level centroids under the random walk (module docstring).

    Parameters
    ----------
    y : numpy.ndarray
        (n,) clean-frame luminance of one camera, DN (NaN = missing).
    k : numpy.ndarray
        (n,) the symbol of each frame, 0 .. S-1.
    lab : numpy.ndarray
        (n,) its 0-based level, or (n, M) its weight at each level (soft labels, rows
        summing to 1: each frame then counts for every level in proportion).
    S : int
        Symbols.
    M : int
        Levels.
    r_var : numpy.ndarray
        (M,) noise variance per level, DN^2.
    step_cov : numpy.ndarray
        (M, M) covariance of one symbol's random-walk step, DN^2.
    use : numpy.ndarray of bool, optional
        (n,) which frames count (default every finite one).

    Returns
    -------
    numpy.ndarray
        (S, M) centroids, DN.
    """
    y = np.asarray(y, dtype=np.float64)
    ok = np.isfinite(y) if use is None else (np.asarray(use, dtype=bool) & np.isfinite(y))
    lab = np.asarray(lab)
    gam = np.eye(M)[lab.astype(np.int64)] if lab.ndim == 1 else np.asarray(lab, dtype=np.float64)
    kk, gg, yy = np.asarray(k, dtype=np.int64)[ok], gam[ok], y[ok]
    A = np.linalg.inv(step_cov)
    n_un = S * M
    u = 2 * M - 1
    ab = np.zeros((u + 1, n_un))  # upper banded form: ab[u + i - j, j] = H[i, j], i <= j
    # the random walk: x_k - x_{k-1} for k = 1 .. S-1 adds A to blocks (k-1, k-1) and (k, k)
    # and -A to (k-1, k)
    nb = np.full(S, 2.0)
    nb[0] = nb[-1] = 1.0
    if S == 1:
        nb[0] = 0.0
    iu, ju = np.triu_indices(M)
    blocks = np.arange(S)[:, None]
    np.add.at(ab, (np.broadcast_to(u + iu - ju, (S, iu.size)), blocks * M + ju),
              nb[:, None] * A[iu, ju])  # diagonal blocks (their upper triangles)
    if S > 1:  # off-diagonal blocks (rows of k-1, columns of k): always above the diagonal
        ia, ja = (g.ravel() for g in np.meshgrid(np.arange(M), np.arange(M), indexing="ij"))
        rows = blocks[:-1] * M + ia
        cols = (blocks[:-1] + 1) * M + ja
        ab[u + rows - cols, cols] -= A[ia, ja]
    # the weak prior towards the level mean, and the frames
    diag = np.full(n_un, PRIOR_WEIGHT)
    rhs = np.zeros(n_un)
    wsum = gg.sum(axis=0)
    level_mean = np.where(wsum > 0, (gg * yy[:, None]).sum(axis=0) / np.maximum(wsum, 1e-300), np.nan)
    if not np.isfinite(level_mean).any():
        level_mean[:] = 0.0
    good = np.isfinite(level_mean)
    level_mean = np.interp(np.arange(M), np.flatnonzero(good), level_mean[good])
    rhs += PRIOR_WEIGHT * np.tile(level_mean, S)
    idx = (kk[:, None] * M + np.arange(M)).ravel()
    w = (gg / r_var).ravel()
    np.add.at(diag, idx, w)
    np.add.at(rhs, idx, w * np.repeat(yy, M))
    ab[u] += diag
    x = solveh_banded(ab, rhs, lower=False, check_finite=False)
    return x.reshape(S, M)


def step_covariance(span_dn: float, M: int, kappa: float = KAPPA, rho: float = RHO) -> np.ndarray:
    """The random walk's step: ``Q[s, t] = (kappa span)^2 rho^|s - t|`` (:mod:`~iscd.decode.comms.sequential`).

    Parameters
    ----------
    span_dn : float
        The camera's level-M minus level-1 light, DN (at least 1 is used).
    M : int
        Levels.
    kappa : float
        RMS step per symbol, share of the span.
    rho : float
        Correlation of neighbouring levels' steps.

    Returns
    -------
    numpy.ndarray
        (M, M) covariance, DN^2 per symbol.
    """
    d = np.abs(np.subtract.outer(np.arange(M), np.arange(M)))
    return (kappa * max(span_dn, 1.0)) ** 2 * rho ** d


def smoothed_models(y: np.ndarray, k: np.ndarray, lab: np.ndarray, S: int, M: int, floor_dn: float,
                    kappa: float = KAPPA, rho: float = RHO) -> tuple[np.ndarray, np.ndarray]:
    """Every symbol's centroids and the noise per camera of one LED's packet.

    Parameters
    ----------
    y : numpy.ndarray
        (C, n) clean-frame luminance per camera, DN, time order (NaN = missing).
    k : numpy.ndarray
        (n,) the symbol of each frame, 0 .. S-1.
    lab : numpy.ndarray
        (n,) its 0-based level (labels: known or decided).
    S, M : int
        Symbols, levels.
    floor_dn : float
        Smallest noise RMS, DN.
    kappa, rho : float
        The random walk (:func:`step_covariance`).

    Returns
    -------
    mu : numpy.ndarray
        (C, S, M) centroids, DN.
    var : numpy.ndarray
        (C, M) noise variances, DN^2.
    """
    C = y.shape[0]
    mu = np.zeros((C, S, M))
    var = np.ones((C, M))
    for c in range(C):
        yc = y[c]
        if not np.isfinite(yc).any():
            var[c] = 1e12  # a camera without data does not count
            continue
        r = noise_variance(yc, k, lab, M, floor_dn)
        means = [np.nanmedian(yc[lab == s]) for s in (0, M - 1) if np.isfinite(yc[lab == s]).any()]
        span = float(means[-1] - means[0]) if len(means) == 2 else 1.0
        Q = step_covariance(span, M, kappa, rho)
        x = smooth_centroids(yc, k, lab, S, M, r, Q)
        res = yc - x[k, lab]
        keep = np.abs(res) <= OUTLIER_SIGMAS * np.sqrt(r[lab])
        if not keep[np.isfinite(res)].all():
            x = smooth_centroids(yc, k, lab, S, M, r, Q, use=keep)
        mu[c], var[c] = x, r
    return mu, var


def channel_of(mu: np.ndarray, var: np.ndarray, kind: str, nu: float
               ) -> Callable[[object, int, int], ChannelModel]:
    """A ``channel(clock, a, b)`` for :func:`~iscd.decode.comms.demod.demodulate_packet`: the
    mean of the smoothed centroids over packet symbols [a, b) of one LED.

    Parameters
    ----------
    mu : numpy.ndarray
        (C, S, M) centroids per symbol, DN.
    var : numpy.ndarray
        (C, M) noise variances, DN^2.
    kind : str
        The decision's noise model (``"gauss"`` or ``"t"``).
    nu : float
        Student-t degrees of freedom.

    Returns
    -------
    callable
        ``channel(clock, a, b) -> ChannelModel`` (``clock`` unused), (C, 1, M) centroids and
        variances; symbols beyond the smoothed ones take the last.
    """
    S = mu.shape[1]

    def channel(clock: object, a: int, b: int) -> ChannelModel:
        lo = int(np.clip(a, 0, S - 1))
        hi = int(np.clip(b, lo + 1, S))
        return ChannelModel(mu=mu[:, lo:hi].mean(axis=1)[:, None, :].copy(), var=var[:, None, :].copy(),
                            kind=kind, nu=nu)
    return channel


def em_models(y: np.ndarray, k: np.ndarray, lab: np.ndarray, known: np.ndarray, S: int, M: int,
              floor_dn: float, iterations: int = 5, kappa: float = KAPPA, rho: float = RHO
              ) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`smoothed_models`, then rounds of expectation-maximization with each data
    symbol's level uncertain.

    Each round, a data symbol's posterior over the levels (uniform prior; all its clean frames
    of every camera, Gaussian with the smoothed centroids and the noise) weighs its frames in
    every level's centroid of the next smoothing. Hard labels bias a squeezed pair of levels
    (a level-8 symbol decided 7 pulls 7 up and leaves 8 to its brightest frames, which decides
    the next one 7 again); the posterior does not. The noise stays the first fit's. Two
    differences from the first fit, left as measured: the rounds take every frame again (the
    first fit's frames more than :data:`OUTLIER_SIGMAS` off are not left out, so a glitch in a
    known symbol pulls its level's centroid), and their random walk's span is that of the
    first fit's centroids (level M minus level 1, averaged over the packet), not the medians
    of the level-1 and level-M frames.

    Parameters
    ----------
    y : numpy.ndarray
        (C, n) clean-frame luminance per camera, DN, time order (NaN = missing).
    k : numpy.ndarray
        (n,) the symbol of each frame, 0 .. S-1.
    lab : numpy.ndarray
        (n,) its 0-based level: known, or a decision (the first smoothing's labels).
    known : numpy.ndarray of bool
        (S,) symbols whose level is known (header, training, the symbols after the packet):
        kept hard.
    S, M : int
        Symbols, levels.
    floor_dn : float
        Smallest noise RMS, DN.
    iterations : int
        Rounds.
    kappa, rho : float
        The random walk (:func:`step_covariance`).

    Returns
    -------
    mu : numpy.ndarray
        (C, S, M) centroids, DN.
    var : numpy.ndarray
        (C, M) noise variances, DN^2.
    """
    mu, var = smoothed_models(y, k, lab, S, M, floor_dn, kappa, rho)
    C = y.shape[0]
    spans = np.maximum(mu[:, :, -1].mean(axis=1) - mu[:, :, 0].mean(axis=1), 1.0)
    Qs = [step_covariance(float(sp), M, kappa, rho) for sp in spans]
    for _ in range(iterations):
        ll = np.zeros((S, M))
        for c in range(C):
            yc = y[c]
            ok = np.isfinite(yc)
            r = var[c]
            t = -0.5 * ((yc[ok, None] - mu[c][k[ok]]) ** 2 / r + np.log(r))
            np.add.at(ll, k[ok], t)
        ll -= ll.max(axis=1, keepdims=True)
        post = np.exp(ll)
        post /= post.sum(axis=1, keepdims=True)
        ks = np.flatnonzero(known)
        post[ks] = np.eye(M)[_labels_per_symbol(k, lab, S)[ks]]
        g = post[k]
        for c in range(C):
            if var[c, 0] >= 1e11:
                continue
            mu[c] = smooth_centroids(y[c], k, g, S, M, var[c], Qs[c])
    return mu, var


def _labels_per_symbol(k: np.ndarray, lab: np.ndarray, S: int) -> np.ndarray:
    """Per symbol the label of its frames (0 where a symbol has none)."""
    out = np.zeros(S, dtype=np.int64)
    out[np.asarray(k, dtype=np.int64)] = np.asarray(lab, dtype=np.int64)
    return out
