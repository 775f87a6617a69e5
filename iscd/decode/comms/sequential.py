"""Symbol-by-symbol channel tracking: a Kalman filter on the level centroids (one packet's data).

The tracking pass of :func:`iscd.decode.comms.demod.demodulate_packet` decides a packet in
steps, each with a model fitted on the decided symbols before it and its light matched to
the step's own frames by one gain per camera. A level whose light changes faster than that
model follows is decided as its neighbour: on a randomized 100 km/h approach (63.7 -> 27 m)
one camera's levels 5-7 fell by a tenth within thirty symbols as the spot's core clipped,
while its levels 1-2 rose; level 7 was then decided as 6, dropped out of the next fit,
its centroid was filled from level 6's and the two never parted again (docs/receiver.md,
"Sequential tracking").

:func:`sequential_levels` decides one symbol at a time and updates the centroids after each
decision with a Kalman filter, per camera and LED:

* state: the M level centroids (DN), a random walk whose steps are correlated between
  levels, ``Q[s, t] = (kappa * span)^2 * rho^|s - t|`` per symbol (span: the starting
  model's level-M minus level-1 light): neighbouring levels drift together, so a level not
  sent for a while moves with the ones that were;
* observation: the decided level's centroid plus the model's noise (variance ``var``);
* decision: the level of least summed Gaussian cost over the cameras, each with its
  predictive variance ``var + P[s, s]``: a level whose centroid is uncertain (not seen
  lately) weighs its camera less, and a camera whose levels squeeze together is outvoted
  by one that still tells them apart.

Pure numerical function: no I/O, no threads; compiled (:func:`iscd.core.jit.njit`).

References
----------
R. E. Kalman, "A new approach to linear filtering and prediction problems", 1960 (the
filter); dissertation eq. (4.2) (the per-level Gaussian costs it decides with).
"""

from __future__ import annotations

import numpy as np

from iscd.core.jit import njit

KAPPA = 0.005
"""Process noise per symbol: RMS random-walk step of a centroid, share of the camera's span."""

RHO = 0.9
"""Correlation of two neighbouring levels' random-walk steps (``rho^|s - t|``)."""

P0 = 0.1
"""Starting centroid variance, share of the noise variance (the training's estimate)."""


def _warm() -> tuple:
    y = np.ones((2, 6, 1))
    kr = np.arange(6, dtype=np.int64)
    mu = np.tile(np.arange(4.0), (2, 1, 1))
    return (y, kr, 6, mu, np.ones((2, 1, 4)), KAPPA, RHO, P0)


@njit(warm=_warm, error_model="numpy")
def sequential_levels(y: np.ndarray, kr: np.ndarray, S: int, mu: np.ndarray, var: np.ndarray,
                      kappa: float, rho: float, p0: float) -> np.ndarray:
    """Levels (S, N) int64 of S symbols decided one at a time, the centroids Kalman-filtered.

    Parameters
    ----------
    y : ndarray
        (C, n, N) clean-frame luminance, DN (NaN = missing), frame order.
    kr : ndarray of int64
        (n,) the symbol (0 .. S-1) of each frame, non-decreasing.
    S : int
        Symbols to decide.
    mu : ndarray
        (C, N, M) starting centroids, DN (the header and training's model). Not modified.
    var : ndarray
        (C, N, M) noise variance of one clean frame, DN^2 (held fixed).
    kappa : float
        :data:`KAPPA`.
    rho : float
        :data:`RHO`.
    p0 : float
        :data:`P0`.

    Returns
    -------
    ndarray of int64
        (S, N) 0-based levels; -1 where a symbol has no finite clean frame.
    """
    C, n, N = y.shape
    M = mu.shape[2]
    m = mu.copy()
    Q = np.zeros((C, N, M, M))
    P = np.zeros((C, N, M, M))
    for c in range(C):
        for i in range(N):
            span = max(mu[c, i, M - 1] - mu[c, i, 0], 1.0)
            q = (kappa * span) ** 2
            for s in range(M):
                P[c, i, s, s] = p0 * var[c, i, s]
                for t in range(M):
                    Q[c, i, s, t] = q * rho ** abs(s - t)
    lv = np.full((S, N), -1, np.int64)
    ybar = np.zeros(C)
    cnt = np.zeros(C)
    K = np.zeros(M)
    row = np.zeros(M)
    j = 0
    for k in range(S):
        j1 = j
        while j1 < n and kr[j1] == k:
            j1 += 1
        for i in range(N):
            any_obs = False
            for c in range(C):
                for s in range(M):
                    for t in range(M):
                        P[c, i, s, t] += Q[c, i, s, t]
                ybar[c] = 0.0
                cnt[c] = 0.0
                for f in range(j, j1):
                    v = y[c, f, i]
                    if np.isfinite(v):
                        ybar[c] += v
                        cnt[c] += 1.0
                if cnt[c] > 0 and np.isfinite(m[c, i, 0]):
                    ybar[c] /= cnt[c]
                    any_obs = True
                else:
                    cnt[c] = 0.0
            if not any_obs:
                continue
            best = 0
            best_cost = np.inf
            for s in range(M):
                tot = 0.0
                for c in range(C):
                    if cnt[c] > 0:
                        v = var[c, i, s] / cnt[c] + P[c, i, s, s]
                        d = ybar[c] - m[c, i, s]
                        tot += d * d / v + np.log(v)
                if tot < best_cost:
                    best_cost = tot
                    best = s
            lv[k, i] = best
            for c in range(C):
                if cnt[c] == 0:
                    continue
                den = P[c, i, best, best] + var[c, i, best] / cnt[c]
                r = ybar[c] - m[c, i, best]
                for s in range(M):
                    K[s] = P[c, i, s, best] / den
                    row[s] = P[c, i, best, s]
                for s in range(M):
                    m[c, i, s] += K[s] * r
                    for t in range(M):
                        P[c, i, s, t] -= K[s] * row[t]
        j = j1
    return lv


def sequential_levels_reference(y: np.ndarray, kr: np.ndarray, S: int, mu: np.ndarray, var: np.ndarray,
                                kappa: float = KAPPA, rho: float = RHO, p0: float = P0) -> np.ndarray:
    """Pure-numpy reference of :func:`sequential_levels` (the specification the compiled
    kernel is tested against: ``tests/test_rx_sequential.py``).

    Parameters
    ----------
    y : ndarray
        (C, n, N) clean-frame luminance, DN (NaN = missing), frame order.
    kr : ndarray of int64
        (n,) the symbol (0 .. S-1) of each frame, non-decreasing.
    S : int
        Symbols to decide.
    mu : ndarray
        (C, N, M) starting centroids, DN. Not modified.
    var : ndarray
        (C, N, M) noise variance of one clean frame, DN^2.
    kappa, rho, p0 : float
        :data:`KAPPA`, :data:`RHO`, :data:`P0`.

    Returns
    -------
    ndarray of int64
        (S, N) 0-based levels; -1 where a symbol has no finite clean frame.
    """
    C, n, N = y.shape
    M = mu.shape[2]
    m = np.array(mu, dtype=np.float64)
    lag = np.abs(np.subtract.outer(np.arange(M), np.arange(M)))
    span = np.maximum(m[..., -1] - m[..., 0], 1.0)  # (C, N)
    Q = (kappa * span)[..., None, None] ** 2 * rho ** lag  # (C, N, M, M)
    P = np.zeros((C, N, M, M))
    idx = np.arange(M)
    P[..., idx, idx] = p0 * var
    lv = np.full((S, N), -1, np.int64)
    starts = np.searchsorted(kr, np.arange(S + 1))
    for k in range(S):
        yk = y[:, starts[k]:starts[k + 1], :]  # (C, f, N)
        fin = np.isfinite(yk)
        cnt = fin.sum(axis=1).astype(np.float64)  # (C, N)
        ybar = np.where(fin, yk, 0.0).sum(axis=1) / np.maximum(cnt, 1.0)
        cnt = np.where(np.isfinite(m[..., 0]), cnt, 0.0)
        P += Q
        for i in range(N):
            cams = np.flatnonzero(cnt[:, i] > 0)
            if cams.size == 0:
                continue
            v = var[cams, i] / cnt[cams, i, None] + P[cams, i][:, idx, idx]  # (c, M)
            cost = ((ybar[cams, i, None] - m[cams, i]) ** 2 / v + np.log(v)).sum(axis=0)
            b = int(np.argmin(cost))
            lv[k, i] = b
            for c in cams:
                Pc = P[c, i]
                K = Pc[:, b] / (Pc[b, b] + var[c, i, b] / cnt[c, i])
                m[c, i] += K * (ybar[c, i] - m[c, i, b])
                P[c, i] = Pc - np.outer(K, Pc[b])
    return lv
