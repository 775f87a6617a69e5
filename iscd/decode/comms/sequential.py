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


BEAM = 8
"""Survivors kept (per-survivor processing): each is one sequence of decisions with its own
centroids and their covariance, and each symbol every survivor is extended by every level,
keeping the ``BEAM`` sequences of least summed cost. With one survivor a single symbol that
the noise decides wrong updates the wrong centroid and the next ones follow it (a slip);
a few survivors keep the sequence that decided it right until the symbols after it tell
the two apart. On the two dumped packets it was built on (randomized 100 km/h approaches,
the second packets' upper levels squeezing; docs/receiver.md) one survivor left 32 and 3
wrong symbols, four and sixteen left 1 and 0 alike; 8 lies between, not tuned."""


def _warm() -> tuple:
    y = np.ones((2, 6, 1))
    kr = np.arange(6, dtype=np.int64)
    mu = np.tile(np.arange(4.0), (2, 1, 1))
    return (y, kr, 6, mu, np.ones((2, 1, 4)), KAPPA, RHO, P0, BEAM)


@njit(warm=_warm, error_model="numpy")
def sequential_levels(y: np.ndarray, kr: np.ndarray, S: int, mu: np.ndarray, var: np.ndarray,
                      kappa: float, rho: float, p0: float, beam: int) -> np.ndarray:
    """Levels (S, N) int64 of S symbols decided one at a time, the centroids Kalman-filtered,
    the ``beam`` most likely decision sequences kept (per-survivor processing).

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
    beam : int
        :data:`BEAM`, survivors kept (1: each symbol's best level, decided for good).

    Returns
    -------
    ndarray of int64
        (S, N) 0-based levels of the sequence of least summed cost; -1 where a symbol has
        no finite clean frame.

    References
    ----------
    R. Raheli, A. Polydoros, C.-K. Tzou, "Per-survivor processing: a general approach to
    MLSE in uncertain environments", IEEE Trans. Commun. 43 (1995) (the survivors, each
    with its own channel estimate).
    """
    C, n, N = y.shape
    M = mu.shape[2]
    B = max(1, beam)
    first = np.zeros(S + 1, np.int64)  # each symbol's frames: first[k] .. first[k + 1]
    j = 0
    for k in range(S):
        first[k] = j
        while j < n and kr[j] == k:
            j += 1
    first[S] = j
    lv = np.full((S, N), -1, np.int64)
    Q = np.zeros((C, M, M))
    m = np.zeros((B, C, M))
    m2 = np.zeros((B, C, M))
    P = np.zeros((B, C, M, M))
    P2 = np.zeros((B, C, M, M))
    cost = np.zeros(B)
    cost2 = np.zeros(B)
    dec = np.full((S, B), -1, np.int64)
    back = np.zeros((S, B), np.int64)
    cand = np.zeros(B * M)
    ybar = np.zeros(C)
    cnt = np.zeros(C)
    K = np.zeros(M)
    row = np.zeros(M)
    for i in range(N):  # the LEDs' channels are independent
        for c in range(C):
            span = max(mu[c, i, M - 1] - mu[c, i, 0], 1.0)
            q = (kappa * span) ** 2
            for s in range(M):
                m[0, c, s] = mu[c, i, s]
                for t in range(M):
                    Q[c, s, t] = q * rho ** abs(s - t)
                    P[0, c, s, t] = 0.0
                P[0, c, s, s] = p0 * var[c, i, s]
        nb = 1
        cost[0] = 0.0
        for k in range(S):
            for b in range(nb):
                for c in range(C):
                    for s in range(M):
                        for t in range(M):
                            P[b, c, s, t] += Q[c, s, t]
            any_obs = False
            for c in range(C):
                ybar[c] = 0.0
                cnt[c] = 0.0
                for f in range(first[k], first[k + 1]):
                    v = y[c, f, i]
                    if np.isfinite(v):
                        ybar[c] += v
                        cnt[c] += 1.0
                if cnt[c] > 0 and np.isfinite(m[0, c, 0]):
                    ybar[c] /= cnt[c]
                    any_obs = True
                else:
                    cnt[c] = 0.0
            if not any_obs:
                for b in range(nb):
                    dec[k, b] = -1
                    back[k, b] = b
                continue
            for b in range(nb):
                for s in range(M):
                    tot = cost[b] if B > 1 else 0.0  # (one survivor: exactly each symbol's best)
                    for c in range(C):
                        if cnt[c] > 0:
                            v = var[c, i, s] / cnt[c] + P[b, c, s, s]
                            d = ybar[c] - m[b, c, s]
                            tot += d * d / v + np.log(v)
                    cand[b * M + s] = tot
            order = np.argsort(cand[:nb * M], kind="mergesort")  # stable: ties to the lower level
            nn = min(B, nb * M)
            for jj in range(nn):
                b = order[jj] // M
                best = order[jj] % M
                cost2[jj] = cand[order[jj]]
                dec[k, jj] = best
                back[k, jj] = b
                for c in range(C):
                    for s in range(M):
                        m2[jj, c, s] = m[b, c, s]
                        for t in range(M):
                            P2[jj, c, s, t] = P[b, c, s, t]
                    if cnt[c] == 0:
                        continue
                    den = P2[jj, c, best, best] + var[c, i, best] / cnt[c]
                    r = ybar[c] - m2[jj, c, best]
                    for s in range(M):
                        K[s] = P2[jj, c, s, best] / den
                        row[s] = P2[jj, c, best, s]
                    for s in range(M):
                        m2[jj, c, s] += K[s] * r
                        for t in range(M):
                            P2[jj, c, s, t] -= K[s] * row[t]
            m, m2 = m2, m
            P, P2 = P2, P
            cost, cost2 = cost2, cost
            nb = nn
        jb = 0
        for b in range(1, nb):
            if cost[b] < cost[jb]:
                jb = b
        for k in range(S - 1, -1, -1):
            lv[k, i] = dec[k, jb]
            jb = back[k, jb]
    return lv


def sequential_levels_reference(y: np.ndarray, kr: np.ndarray, S: int, mu: np.ndarray, var: np.ndarray,
                                kappa: float = KAPPA, rho: float = RHO, p0: float = P0,
                                beam: int = BEAM) -> np.ndarray:
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
    beam : int
        :data:`BEAM`, survivors kept.

    Returns
    -------
    ndarray of int64
        (S, N) 0-based levels; -1 where a symbol has no finite clean frame.
    """
    C, n, N = y.shape
    M = mu.shape[2]
    B = max(1, int(beam))
    lag = np.abs(np.subtract.outer(np.arange(M), np.arange(M)))
    idx = np.arange(M)
    starts = np.searchsorted(kr, np.arange(S + 1))
    lv = np.full((S, N), -1, np.int64)
    for i in range(N):
        m0 = np.array(mu[:, i], dtype=np.float64)  # (C, M)
        span = np.maximum(m0[:, -1] - m0[:, 0], 1.0)  # (C,)
        Q = (kappa * span)[:, None, None] ** 2 * rho ** lag  # (C, M, M)
        P0m = np.zeros((C, M, M))
        P0m[:, idx, idx] = p0 * var[:, i]
        # survivors: (summed cost, centroids (C, M), covariances (C, M, M), decisions)
        surv: list[tuple[float, np.ndarray, np.ndarray, list[int]]] = [(0.0, m0, P0m, [])]
        usable = np.isfinite(m0[:, 0])
        for k in range(S):
            yk = y[:, starts[k]:starts[k + 1], i]  # (C, f)
            fin = np.isfinite(yk)
            cnt = np.where(usable, fin.sum(axis=1), 0).astype(np.float64)
            ybar = np.where(fin, yk, 0.0).sum(axis=1) / np.maximum(cnt, 1.0)
            cams = np.flatnonzero(cnt > 0)
            grown = [(c_, m_, P_ + Q, h_) for c_, m_, P_, h_ in surv]
            if cams.size == 0:
                surv = [(c_, m_, P_, h_ + [-1]) for c_, m_, P_, h_ in grown]
                continue
            cands = []
            for b, (c_, m_, P_, h_) in enumerate(grown):
                v = var[cams, i] / cnt[cams, None] + P_[cams][:, idx, idx]  # (c, M)
                lvl = ((ybar[cams, None] - m_[cams]) ** 2 / v + np.log(v)).sum(axis=0)
                tot = (c_ if B > 1 else 0.0) + lvl
                cands += [(float(tot[s]), b, s) for s in range(M)]
            cands.sort(key=lambda x: x[0])  # stable: ties to the earlier survivor, the lower level
            new = []
            for tot, b, best in cands[:B]:
                _, m_, P_, h_ = grown[b]
                m_ = m_.copy()
                P_ = P_.copy()
                for c in cams:
                    Kg = P_[c, :, best] / (P_[c, best, best] + var[c, i, best] / cnt[c])
                    m_[c] += Kg * (ybar[c] - m_[c, best])
                    P_[c] = P_[c] - np.outer(Kg, P_[c, best])
                new.append((tot, m_, P_, h_ + [best]))
            surv = new
        best_seq = min(surv, key=lambda x: x[0])[3]
        lv[:, i] = best_seq
    return lv
