"""Symbol decisions from the frames of both cameras (dissertation 3.12 / 4.3 and beyond).

Every frame whose exposure window touches a symbol contributes a cost per candidate level
(:meth:`iscd.decode.comms.channel.ChannelModel.cost`, the negative log-likelihood up to a
constant; NaN frames contribute nothing):

* a *clean* frame (window inside the symbol) directly: ``cost(L | h(s))``;
* a *straddling* frame between symbols a and b (fraction alpha in a), when the other
  symbol's level is known (header, training) or tentatively decided: as a function of the
  candidate level, ``cost(L | h(alpha a + (1 - alpha) b))`` with the response ``h``
  interpolated between the centroids and the variance widened by the timing uncertainty
  (``timing_sigma`` frames of boundary error). This is interference cancellation with
  decision feedback; iterated (:func:`decide_span` called again with the new decisions as
  context) it approaches the joint (sequence) decision, and it adds roughly the energy of
  the second frame per symbol to the clean one (about +2 dB at 2 frames per symbol).

The decision is the level of least summed cost over cameras and frames; the *margin* is
the cost gap to the runner-up (for the Gaussian model twice the log-likelihood ratio).
With the dissertation's Euclidean model and clean frames only this is exactly rule 3.12.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from iscd.core.jit import njit
from iscd.decode.comms.channel import ChannelModel
from iscd.decode.comms.timing import SymbolClock, frame_map, frame_map_range


@dataclass
class SpanDecision:
    """Decisions for packet symbols ``k_a .. k_a + S - 1``: 0-based levels (S, N), margins
    (S, N), the number of camera-frame observations that touched each symbol (S, N) and the
    runner-up levels (S, N, 0-based; the level whose cost is ``margin`` above the decision's,
    the same level where there is no other)."""

    k_a: int
    levels: np.ndarray
    margin: np.ndarray
    n_obs: np.ndarray
    runner_up: np.ndarray


def _scatter_add(out: np.ndarray, idx: np.ndarray, vals: np.ndarray) -> None:
    """out[idx[j]] += vals[j] for sorted idx (reduceat over runs; much faster than add.at)."""
    if idx.size == 0:
        return
    if idx.size == 1 or bool((idx[1:] != idx[:-1]).all()):
        out[idx] += vals
        return
    starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
    out[idx[starts]] += np.add.reduceat(vals, starts, axis=0)


def _ctx(ctx: np.ndarray, k_first: int, k: np.ndarray) -> np.ndarray:
    """Context levels (len(k), N) of packet symbols k; -1 outside the context."""
    S, N = ctx.shape
    j = k - k_first
    inside = (j >= 0) & (j < S)
    out = np.full((k.size, N), -1, dtype=np.int64)
    out[inside] = ctx[j[inside]]
    return out


def _straddle_cost(model: ChannelModel, obs: np.ndarray, alpha: np.ndarray, fixed: np.ndarray,
                   cand: np.ndarray, fixed_first: bool, e: float, timing_sigma: float) -> np.ndarray:
    """Cost (n, N, T) of candidate levels ``cand`` (n, N, T) of one side of straddling frames
    obs (C, n, N) whose other side has level ``fixed`` (n, N) (-1: unknown -> zero cost)."""
    a = alpha.astype(np.float32)[:, None, None]
    f = np.maximum(fixed, 0).astype(np.float32)[:, :, None]
    cf = cand.astype(np.float32)
    q = a * f + (1 - a) * cf if fixed_first else a * cf + (1 - a) * f
    mu, var = model.lookup(q, led_axis=-2)  # (C, n, N, T)
    if model.kind != "euclid" and timing_sigma > 0:
        # boundary uncertainty: the straddle's value moves with the level difference
        gain = ((model.mu[:, :, -1] - model.mu[:, :, 0]) / max(model.levels - 1, 1)
                * (timing_sigma / e)).astype(np.float32)  # (C, N)
        var += np.square(gain[:, None, :, None] * (f - cf)[None])
        # where the response bends between levels (saturation) the interpolation is poor
        var += np.square(model.interp_error_at(q, led_axis=-2))
    c = model.cost(obs[..., None], mu, var)
    c[fixed < 0] = 0.0
    return c


@dataclass
class CleanCosts:
    """Per-symbol costs (S, N, M) of packet symbols ``k_a .. k_b - 1`` from their clean
    frames, observation counts (S, N), and the frame geometry of the span."""

    k_a: int
    k_b: int
    costs: np.ndarray
    n_obs: np.ndarray
    k: np.ndarray
    alpha: np.ndarray
    Lf: np.ndarray  # (C, n_fr, N) luminance of the span's frames
    valid_obs: np.ndarray  # (n_fr, N) cameras with a value


def clean_costs_reference(L: np.ndarray, clock: SymbolClock, e: float, k_a: int, k_b: int,
                model: ChannelModel) -> CleanCosts:
    """Pure-numpy reference of :func:`clean_costs` (the compiled kernel's specification).

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance of the buffer's frames, DN (NaN = missing).
    clock : SymbolClock
        The packet's symbol clock, frames.
    e : float
        Exposure window length, frames (exposure_s * fps).
    k_a, k_b : int
        Packet symbols ``k_a <= k < k_b`` to cost, symbols.
    model : ChannelModel
        The channel.

    Returns
    -------
    CleanCosts
        Costs (S, N, M) and observation counts (S, N), S = k_b - k_a, with the span's frame
        geometry.

    References
    ----------
    Dissertation, eqs. (3.12), (4.3) (Euclidean model).
    """
    C, n, N = L.shape
    M = model.levels
    S = k_b - k_a
    costs = np.zeros((S, N, M), np.float32)
    n_obs = np.zeros((S, N), dtype=np.int64)
    lo = int(max(0, np.floor(clock.boundary(k_a)) - 1))
    hi = int(min(n, np.ceil(clock.boundary(k_b)) + 1))
    frames = np.arange(lo, hi)
    k, alpha = frame_map(frames, clock, e)
    Lf = L[:, frames, :]
    valid_obs = np.isfinite(Lf).sum(0)
    clean = (alpha >= 1.0) & (k >= k_a) & (k < k_b)
    if clean.any():
        _scatter_add(costs, k[clean] - k_a, model.level_cost(Lf[:, clean, :]))
        _scatter_add(n_obs, k[clean] - k_a, valid_obs[clean])
    return CleanCosts(k_a, k_b, costs, n_obs, k, alpha, Lf, valid_obs)


def decide_span_reference(L: np.ndarray, clock: SymbolClock, e: float, k_a: int, k_b: int,
                model: ChannelModel, ctx: np.ndarray | None = None, k_first: int = 0,
                straddle: bool = True, timing_sigma: float = 0.02,
                candidates: int = 4, pre: CleanCosts | None = None,
                edge_levels: tuple[int, ...] = ()) -> SpanDecision:
    """Decide packet symbols ``k_a <= k < k_b`` from the buffer L (C, n, N).

    Pure-numpy reference of :func:`decide_span`. With straddling frames, only the
    ``candidates`` best levels of the clean frames compete (symbols without a clean frame
    always get all M).

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance of the buffer's frames, DN (NaN = missing).
    clock : SymbolClock
        The packet's symbol clock, frames.
    e : float
        Exposure window length, frames (exposure_s * fps).
    k_a, k_b : int
        Packet symbols to decide, symbols.
    model : ChannelModel
        The channel.
    ctx : ndarray, optional
        (S, N) 0-based levels of packet symbols ``k_first ..`` used as the neighbours of
        straddling frames (-1 unknown); None: clean frames only.
    k_first : int
        Packet symbol of ``ctx[0]``, symbols.
    straddle : bool
        False: clean frames only.
    timing_sigma : float
        Symbol boundary uncertainty that widens the straddle variances, frames.
    candidates : int
        Levels per symbol that compete with straddling frames (0 = all M).
    pre : CleanCosts, optional
        The span's :func:`clean_costs` when already computed (same clock and model).
    edge_levels : tuple of int
        The plausible 0-based levels of the symbol right after the context (its straddling
        frame with the last context symbol then counts with the best of them).

    Returns
    -------
    SpanDecision
        0-based levels, margins (cost gap to the runner-up) and observation counts, each
        (k_b - k_a, N).

    References
    ----------
    Dissertation, eqs. (3.12), (4.3) (Euclidean model, clean frames only).
    """
    cc = pre if pre is not None else clean_costs_reference(L, clock, e, k_a, k_b, model)
    if not (straddle and ctx is not None):
        return _finish(k_a, cc.costs, cc.n_obs)
    M = model.levels
    S, N = cc.n_obs.shape
    k, alpha, Lf, valid_obs = cc.k, cc.alpha, cc.Lf, cc.valid_obs
    T = M if candidates <= 0 or candidates >= M else candidates
    if T < M:
        cand = np.argpartition(cc.costs, T - 1, axis=-1)[..., :T]
    else:
        cand = np.broadcast_to(np.arange(M), (S, N, M))
    no_clean = cc.n_obs == 0
    c_cand = np.take_along_axis(cc.costs, cand, axis=-1)
    extra = np.zeros((S, N, T), np.float32)
    full_costs = cc.costs.copy() if (T < M and no_clean.any()) else None
    n_obs = cc.n_obs.copy()
    st = (alpha > 0) & (alpha < 1)
    for fixed_first in (True, False):
        # fixed_first: candidate = right symbol (k+1), left one from the context
        ks = k + 1 if fixed_first else k
        sel = st & (ks >= k_a) & (ks < k_b)
        if not sel.any():
            continue
        fixed = _ctx(ctx, k_first, k[sel] if fixed_first else k[sel] + 1)
        rows = fixed.max(1) >= 0
        if not rows.any():
            continue
        idx = np.flatnonzero(sel)[rows]
        fixed = fixed[rows]
        j = ks[idx] - k_a
        c = _straddle_cost(model, Lf[:, idx, :], alpha[idx], fixed, cand[j], fixed_first, e,
                           timing_sigma)
        _scatter_add(extra, j, c)
        _scatter_add(n_obs, j, np.where(fixed >= 0, valid_obs[idx], 0))
        if full_costs is not None and no_clean[j].any():  # seen only in straddles: all M
            full = np.broadcast_to(np.arange(M), (idx.size, N, M))
            cf = _straddle_cost(model, Lf[:, idx, :], alpha[idx], fixed, full, fixed_first, e,
                                timing_sigma)
            cf[~no_clean[j]] = 0.0
            _scatter_add(full_costs, j, cf)
    if edge_levels:
        # the frame straddling the last context symbol and the one after it (idle, the next
        # header or darkness): the best of the plausible levels of that unknown symbol
        k_end = k_first + ctx.shape[0]
        sel = st & (k + 1 == k_end) & (k >= k_a) & (k < k_b)
        if sel.any():
            idx = np.flatnonzero(sel)
            j = k[idx] - k_a
            c = np.minimum.reduce([
                _straddle_cost(model, Lf[:, idx, :], alpha[idx], np.full((idx.size, N), lv),
                               cand[j], False, e, timing_sigma) for lv in edge_levels])
            _scatter_add(extra, j, c)
            _scatter_add(n_obs, j, valid_obs[idx])
    dc = _finish(k_a, c_cand + extra, n_obs)
    dc.levels = np.take_along_axis(cand, dc.levels[..., None], axis=-1)[..., 0]
    dc.runner_up = np.take_along_axis(cand, dc.runner_up[..., None], axis=-1)[..., 0]
    if full_costs is not None:
        # symbols without a clean frame: decided over all M from the straddle costs
        df = _finish(k_a, full_costs, n_obs)
        dc.levels = np.where(no_clean, df.levels, dc.levels)
        dc.margin = np.where(no_clean, df.margin, dc.margin)
        dc.runner_up = np.where(no_clean, df.runner_up, dc.runner_up)
    return dc


def _finish(k_a: int, costs: np.ndarray, n_obs: np.ndarray) -> SpanDecision:
    """Argmin and margin (cost gap best -> runner-up) over the last axis."""
    levels = costs.argmin(-1)
    if costs.shape[-1] > 1:
        two = np.partition(costs, 1, axis=-1)
        margin = (two[..., 1] - two[..., 0]).astype(np.float64)
        # the runner-up: the first level of least cost once the decision is set aside
        rest = costs.copy()
        np.put_along_axis(rest, levels[..., None], np.inf, axis=-1)
        runner_up = rest.argmin(-1)
    else:
        margin = np.full(levels.shape, np.inf)
        runner_up = levels.copy()
    return SpanDecision(k_a=k_a, levels=levels, margin=margin, n_obs=n_obs, runner_up=runner_up)


# ---- compiled kernels ------------------------------------------------------------------
# :func:`clean_costs` and :func:`decide_span` below do what the ``*_reference`` functions
# above do, in one compiled pass each instead of some hundred small numpy calls. Every
# arithmetic step is the reference's, in the same precision (float32 costs, float64
# margins) and order; the one difference is the float32 logarithm of a straddle's
# variance (numpy's vectorized float32 log vs the correctly rounded one: <= 1 ulp), so
# costs and margins agree to ~1e-6 relative and decisions are the same
# (tests/test_rx_kernels.py).

KIND_CODE = {"gauss": 0, "t": 1, "euclid": 2}
"""Noise model -> the integer the kernels take."""


_LOG_C = (1.0, 1.0 / 3, 1.0 / 5, 1.0 / 7, 1.0 / 9, 1.0 / 11, 1.0 / 13, 1.0 / 15, 1.0 / 17,
          1.0 / 19, 1.0 / 21)


@njit(inline="always")
def _log_inplace(x: np.ndarray, xi: np.ndarray, mb: np.ndarray, ex: np.ndarray, n: int) -> None:
    """x[:n] = log(x[:n]) (float64, error ~2e-16 relative: a float32 cast of it is the
    correctly rounded float32 logarithm), in branch-free loops that vectorize (libm's log
    does not): x = 2^e m from the bits (xi: x viewed as int64; mb, ex: scratch of n int64
    and int32), log m = 2 atanh((m - 1) / (m + 1)) by its series for m in [sqrt(1/2),
    sqrt(2)). Zero, subnormal, infinite and NaN inputs go to libm afterwards."""
    mf = mb.view(np.float64)
    for k in range(n):
        b = xi[k]
        ex[k] = np.int32((b >> 52) & 0x7FF) - np.int32(1023)
        mb[k] = (b & 0x000FFFFFFFFFFFFF) | 0x3FF0000000000000
    bad = 0
    for k in range(n):
        m = mf[k]
        big = m > 1.4142135623730951
        m = m * 0.5 if big else m
        e = np.float64(ex[k]) + (1.0 if big else 0.0)
        s = (m - 1.0) / (m + 1.0)
        z = s * s
        p = _LOG_C[10]
        p = p * z + _LOG_C[9]
        p = p * z + _LOG_C[8]
        p = p * z + _LOG_C[7]
        p = p * z + _LOG_C[6]
        p = p * z + _LOG_C[5]
        p = p * z + _LOG_C[4]
        p = p * z + _LOG_C[3]
        p = p * z + _LOG_C[2]
        p = p * z + _LOG_C[1]
        p = p * z + _LOG_C[0]
        bad += 1 if (ex[k] == -1023 or ex[k] == 1024) else 0
        x[k] = e * 0.6931471805599453 + 2.0 * s * p
    if bad:  # zero, subnormal, inf, NaN: libm (the input rebuilt from its bits)
        for k in range(n):
            if ex[k] == -1023 or ex[k] == 1024:
                xi[k] = (np.int64(ex[k] + 1023) << 52) | (mb[k] & 0x000FFFFFFFFFFFFF)
                x[k] = np.log(x[k])
    return None


def _warm_clean() -> tuple:
    C, n, N, M = 2, 6, 2, 4
    L = np.full((C, n, N), 10.0)
    mu = np.ones((C, N, M), np.float32)
    return (L, np.arange(n, dtype=np.int64) // 2, np.ones(n), 0, 3, mu, mu, mu, 1,
            np.float32(0.1), np.float32(9.0))


@njit(warm=_warm_clean, error_model="numpy")
def _clean_kernel(Lf: np.ndarray, k: np.ndarray, alpha: np.ndarray, k_a: int, S: int,
                  mu: np.ndarray, ivar: np.ndarray, logvar: np.ndarray, kind: int,
                  inv_nu: np.float32, nu1: np.float32
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clean-frame costs (S, N, M) float32, observation counts (S, N) and the cameras
    with a value per frame (n_fr, N) of frames Lf (C, n_fr, N) (DN, NaN = missing) whose
    symbol k (relative k - k_a in [0, S)) holds them whole (alpha = 1); mu, ivar, logvar
    (C, N, M) float32 tables (:meth:`ChannelModel.level_cost`); kind 0 gauss, 1 t, 2 euclid;
    inv_nu = 1 / nu, nu1 = nu + 1.

    Per frame, the N x M costs of each camera in branch-free loops over contiguous
    buffers (they vectorize); the Student-t log1p in float64 (:func:`_log_inplace`,
    log1p(v) = log(1 + v) v / ((1 + v) - 1)): correctly rounded float32, where numpy's
    float32 log1p may be 1 ulp off."""
    C, nfr, N = Lf.shape
    M = mu.shape[2]
    NM = N * M
    costs = np.zeros((S, N, M), np.float32)
    n_obs = np.zeros((S, N), np.int64)
    valid = np.zeros((nfr, N), np.int64)
    v = np.empty((C, NM), np.float32)
    w = np.empty(NM, np.float64)
    lg = np.empty(NM, np.float64)
    lgi = lg.view(np.int64)
    mb = np.empty(NM, np.int64)
    ex = np.empty(NM, np.int32)
    for t in range(nfr):
        for i in range(N):
            cnt = 0
            for c in range(C):
                if np.isfinite(Lf[c, t, i]):
                    cnt += 1
            valid[t, i] = cnt
        j = k[t] - k_a
        if alpha[t] < 1.0 or j < 0 or j >= S:
            continue
        for i in range(N):
            n_obs[j, i] += valid[t, i]
        for c in range(C):
            L_c = Lf[c, t]
            mu_c = mu[c].ravel()
            iv_c = ivar[c].ravel()
            lv_c = logvar[c].ravel()
            v_c = v[c]
            for i in range(N):
                x32 = np.float32(L_c[i])
                for s in range(M):
                    d = x32 - mu_c[i * M + s]
                    v_c[i * M + s] = d * d
            if kind == 0:
                for e_ in range(NM):
                    r = v_c[e_] * iv_c[e_]
                    v_c[e_] = r + lv_c[e_]
            elif kind == 1:
                for e_ in range(NM):
                    r = v_c[e_] * iv_c[e_]
                    r = r * inv_nu
                    w[e_] = np.float64(r)
                    lg[e_] = 1.0 + np.float64(r)
                _log_inplace(lg, lgi, mb, ex, NM)
                for e_ in range(NM):
                    vv = w[e_]
                    uu = 1.0 + vv
                    r = lg[e_] * (vv / (uu - 1.0)) if uu != 1.0 else vv
                    r = r if vv < np.inf else vv
                    rr = np.float32(r) * nu1
                    v_c[e_] = rr + lv_c[e_]
            for i in range(N):
                if np.isnan(L_c[i]):
                    for s in range(M):
                        v_c[i * M + s] = np.float32(0.0)
        crow = costs[j].ravel()
        if C == 1:
            for e_ in range(NM):
                crow[e_] += v[0, e_]
        else:
            for e_ in range(NM):
                tot = v[0, e_]
                for c in range(1, C):
                    tot = tot + v[c, e_]
                crow[e_] += tot
    return costs, n_obs, valid


def _warm_straddle() -> tuple:
    C, n, N, M, T = 2, 6, 2, 4, 2
    L = np.full((C, n, N), 10.0)
    G = (M - 1) * 32 + 1
    fine = np.ones((C, N * G), np.float32)
    err = np.zeros((C, N * (M - 1)), np.float32)
    cand = np.zeros((3, N, T), np.int64)
    return (L, np.arange(n, dtype=np.int64) // 2, np.full(n, 0.5), np.ones((n, N), np.int64),
            np.zeros((3, N), np.int64), 0, 0, cand, np.zeros((3, N), np.bool_), False,
            np.zeros(0, np.int64), fine, fine, err, np.ones((C, N), np.float32), True, M, 1,
            np.float32(0.1), np.float32(9.0))


@njit
def _straddle_one(Lf: np.ndarray, t: int, i: int, a: np.float32, f32: np.float32, cf32: np.float32,
                  fixed_first: bool, mu_t: np.ndarray, var_t: np.ndarray, err_t: np.ndarray,
                  gain: np.ndarray, timing: bool, M: int, kind: int, inv_nu: np.float32,
                  nu1: np.float32) -> np.float32:
    """Cost (summed over cameras) of one straddling frame t, LED i: candidate level cf32
    on one side, fixed level f32 on the other (:func:`_straddle_cost`, element by element)."""
    C = Lf.shape[0]
    G = (M - 1) * 32 + 1
    one = np.float32(1.0)
    if fixed_first:
        q = a * f32 + (one - a) * cf32
    else:
        q = a * cf32 + (one - a) * f32
    x = min(max(q, np.float32(0.0)), np.float32(M - 1))
    x = x * np.float32(32.0)
    x = x + np.float32(0.5)
    idx = i * G + int(x)
    seg = i * (M - 1) + int(min(max(q, np.float32(0.0)), np.float32(M - 2)))
    total = np.float32(0.0)
    for c in range(C):
        obs = Lf[c, t, i]
        if np.isnan(obs):
            v = np.float32(0.0)
        else:
            m = mu_t[c, idx]
            var = var_t[c, idx]
            if timing:
                gd = gain[c, i] * (f32 - cf32)
                var = var + gd * gd
                ee = err_t[c, seg]
                var = var + ee * ee
            d = np.float32(obs) - m
            v = d * d
            if kind != 2:
                iv = one / var
                lv = np.float32(np.log(np.float64(var)))
                if kind == 1:
                    v = v * iv
                    v = v * inv_nu
                    v = np.log1p(v)
                    v = v * nu1
                    v = v + lv
                else:
                    v = v * iv
                    v = v + lv
        if c == 0:
            total = v
        else:
            total = total + v
    return total


@njit(warm=_warm_straddle, error_model="numpy")
def _straddle_kernel(Lf: np.ndarray, k: np.ndarray, alpha: np.ndarray, valid: np.ndarray,
                     ctx: np.ndarray, k_first: int, k_a: int, cand: np.ndarray,
                     no_clean: np.ndarray, want_full: bool, edge: np.ndarray,
                     mu_t: np.ndarray, var_t: np.ndarray, err_t: np.ndarray, gain: np.ndarray,
                     timing: bool, M: int, kind: int, inv_nu: np.float32, nu1: np.float32
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Straddling-frame costs of the candidates cand (S, N, T) of symbols k_a .. k_a + S - 1
    (:func:`decide_span_reference`'s three passes: candidate on the right, on the left of
    a context symbol, and the edge after the context): extra costs (S, N, T) float32,
    added observation counts (S, N) and, with ``want_full``, the costs of all M levels
    (S, N, M) of symbols without a clean frame (``no_clean``). Each pass's costs are summed
    per symbol first and then added, as the reference's ``_scatter_add`` does.

    The candidates' costs of a frame (passes 1 and 2) are computed for all N x T at once:
    a gather loop (table lookups, residuals, variances), then branch-free loops over the
    contiguous buffers (reciprocal, the vectorized :func:`_log_inplace`, the noise model)
    -- the same float32 operations in the same order as :func:`_straddle_one`, which the
    rare full-M and edge costs still use."""
    C, nfr, N = Lf.shape
    S, _, T = cand.shape
    Sc = ctx.shape[0]
    G = (M - 1) * 32 + 1
    NT = N * T
    CN = C * NT
    one = np.float32(1.0)
    extra = np.zeros((S, N, T), np.float32)
    tmp = np.zeros((S, N, T), np.float32)
    dn = np.zeros((S, N), np.int64)
    full = np.zeros((S, N, M), np.float32)
    tmpf = np.zeros((S, N, M), np.float32)
    d2 = np.empty(CN, np.float32)  # squared residuals, camera-major
    vb = np.empty(CN, np.float32)  # variances
    lg = np.empty(CN, np.float64)  # log variances (float64 until cast)
    lgi = lg.view(np.int64)
    w = np.empty(CN, np.float64)  # log1p scratch
    lv32 = np.empty(CN, np.float32)
    mb = np.empty(CN, np.int64)
    ex = np.empty(CN, np.int32)
    cost = np.empty(CN, np.float32)
    qidx = np.empty(M * M, np.int64)
    qseg = np.empty(M * M, np.int64)
    pidx = np.empty(NT, np.int64)
    pseg = np.empty(NT, np.int64)
    pdl = np.empty(NT, np.float32)
    keep = np.empty(NT, np.bool_)
    for pss in range(3):
        touched = False
        for t in range(nfr):
            al = alpha[t]
            if not (al > 0.0 and al < 1.0):
                continue
            kt = k[t]
            if pss == 0:  # candidate = right symbol k + 1, left one from the context
                j = kt + 1 - k_a
                jc = kt - k_first
            elif pss == 1:  # candidate = left symbol k, right one from the context
                j = kt - k_a
                jc = kt + 1 - k_first
            else:  # edge: the symbol after the context (edge levels), candidate = k
                if edge.size == 0 or kt + 1 != k_first + Sc:
                    continue
                j = kt - k_a
                jc = -1
            if j < 0 or j >= S:
                continue
            if pss < 2 and (jc < 0 or jc >= Sc):
                continue
            a = np.float32(al)
            touched = True
            if pss == 2:
                for i in range(N):
                    for u in range(T):
                        best = np.float32(0.0)
                        for ww in range(edge.size):
                            v = _straddle_one(Lf, t, i, a, np.float32(edge[ww]),
                                              np.float32(cand[j, i, u]), False, mu_t, var_t,
                                              err_t, gain, timing, M, kind, inv_nu, nu1)
                            best = v if ww == 0 else min(best, v)
                        tmp[j, i, u] += best
                    dn[j, i] += valid[t, i]
                continue
            ctxrow = ctx[jc]
            crow = cand[j].ravel()
            # q = a f + (1 - a) c (fixed first) or a c + (1 - a) f: the same two products
            wf = a if pss == 0 else one - a
            wc = one - a if pss == 0 else a
            # table lookups of every (fixed, candidate) pair: q depends on the pair only
            for f in range(M):
                f32 = np.float32(f)
                for cl in range(M):
                    cf32 = np.float32(cl)
                    q = wf * f32 + wc * cf32
                    x = min(max(q, np.float32(0.0)), np.float32(M - 1))
                    x = x * np.float32(32.0)
                    x = x + np.float32(0.5)
                    qidx[f * M + cl] = int(x)
                    qseg[f * M + cl] = int(min(max(q, np.float32(0.0)), np.float32(M - 2)))
            for i in range(N):
                fx = ctxrow[i]
                fi = fx if fx > 0 else 0
                for u in range(T):
                    pr = fi * M + crow[i * T + u]
                    pidx[i * T + u] = i * G + qidx[pr]
                    pseg[i * T + u] = i * (M - 1) + qseg[pr]
                    pdl[i * T + u] = np.float32(fi) - np.float32(crow[i * T + u])
            for c in range(C):
                mu_c = mu_t[c]
                var_c = var_t[c]
                err_c = err_t[c]
                gain_c = gain[c]
                L_c = Lf[c, t]
                d2_c = d2[c * NT:(c + 1) * NT]
                vb_c = vb[c * NT:(c + 1) * NT]
                for i in range(N):
                    obs = np.float32(L_c[i])
                    g_i = gain_c[i]
                    for u in range(T):
                        iu = i * T + u
                        m = mu_c[pidx[iu]]
                        var = var_c[pidx[iu]]
                        if timing:
                            gd = g_i * pdl[iu]
                            var = var + gd * gd
                            ee = err_c[pseg[iu]]
                            var = var + ee * ee
                        d = obs - m
                        d2_c[iu] = d * d
                        vb_c[iu] = var
            if kind == 2:
                for e_ in range(CN):
                    cost[e_] = d2[e_]
            else:
                for e_ in range(CN):
                    lg[e_] = np.float64(vb[e_])
                _log_inplace(lg, lgi, mb, ex, CN)
                if kind == 0:
                    for e_ in range(CN):
                        v = d2[e_] * (one / vb[e_])
                        cost[e_] = v + np.float32(lg[e_])
                else:
                    for e_ in range(CN):
                        lv32[e_] = np.float32(lg[e_])
                        v = d2[e_] * (one / vb[e_])
                        v = v * inv_nu
                        w[e_] = np.float64(v)
                    # log1p(v) = log(1 + v) v / ((1 + v) - 1) (Goldberg), in float64
                    for e_ in range(CN):
                        lg[e_] = 1.0 + w[e_]
                    _log_inplace(lg, lgi, mb, ex, CN)
                    for e_ in range(CN):
                        vv = w[e_]
                        uu = 1.0 + vv
                        r = lg[e_] * (vv / (uu - 1.0)) if uu != 1.0 else vv
                        r = r if vv < np.inf else vv
                        v = np.float32(r) * nu1
                        cost[e_] = v + lv32[e_]
            trow = tmp[j].ravel()
            for i in range(N):
                kp = ctxrow[i] >= 0
                for u in range(T):
                    keep[i * T + u] = kp
                if kp:
                    dn[j, i] += valid[t, i]
            # a NaN observation (the only source of a NaN cost) costs nothing
            for iu in range(NT):
                v = cost[iu]
                total = v if v == v else np.float32(0.0)
                for c in range(1, C):
                    v = cost[c * NT + iu]
                    total = total + (v if v == v else np.float32(0.0))
                trow[iu] += total if keep[iu] else np.float32(0.0)
            if want_full:
                for i in range(N):
                    fx = ctxrow[i]
                    if fx < 0 or not no_clean[j, i]:
                        continue
                    f32 = np.float32(fx)
                    for s in range(M):
                        tmpf[j, i, s] += _straddle_one(Lf, t, i, a, f32, np.float32(s), pss == 0,
                                                       mu_t, var_t, err_t, gain, timing, M,
                                                       kind, inv_nu, nu1)
        if touched:
            for j in range(S):
                for i in range(N):
                    for u in range(T):
                        extra[j, i, u] += tmp[j, i, u]
                        tmp[j, i, u] = 0.0
                    if want_full and pss < 2:
                        for s in range(M):
                            full[j, i, s] += tmpf[j, i, s]
                            tmpf[j, i, s] = 0.0
    return extra, dn, full


@njit(inline="always")
def _finish_row(row: np.ndarray, K: int) -> tuple[int, float, int]:
    """Argmin (the first of equal minima), margin (runner-up minus best, float32 then
    float64; inf when K = 1) and the runner-up (the first of the least once the argmin is
    set aside; the argmin when K = 1) of row[:K] float32."""
    b = 0
    bv = row[0]
    for u in range(1, K):  # selects, not branches (the same comparisons)
        lt = row[u] < bv
        b = u if lt else b
        bv = row[u] if lt else bv
    mar = np.inf
    r = b
    if K > 1:
        m2 = np.float32(np.inf)
        first = True
        for u in range(K):
            x = row[u]
            take = (u != b) & (first | (x < m2))
            m2 = x if take else m2
            r = u if take else r
            first = first & (u == b)
        mar = np.float64(m2 - bv)
    return b, mar, r


@njit(warm=lambda: (np.zeros((2, 2, 3), np.float32),))
def _finish_kernel(costs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Argmin (first of equal minima), margin (runner-up minus best, float64) and runner-up
    over the last axis of costs (S, N, T) float32 (:func:`_finish`)."""
    S, N, T = costs.shape
    lev = np.zeros((S, N), np.int64)
    mar = np.full((S, N), np.inf)
    run = np.zeros((S, N), np.int64)
    for j in range(S):
        for i in range(N):
            lev[j, i], mar[j, i], run[j, i] = _finish_row(costs[j, i], T)
    return lev, mar, run


@njit(warm=lambda: (np.zeros((2, 2, 3), np.float32),))
def clean_levels(costs: np.ndarray) -> np.ndarray:
    """The levels (S, N) of least cost (the first of equal minima) of costs (S, N, M)
    float32: :func:`decide_span`'s decisions without straddling frames, no margins."""
    S, N, M = costs.shape
    lev = np.zeros((S, N), np.int64)
    for j in range(S):
        for i in range(N):
            row = costs[j, i]
            b = 0
            bv = row[0]
            for u in range(1, M):  # selects, not branches (the same comparisons)
                lt = row[u] < bv
                b = u if lt else b
                bv = row[u] if lt else bv
            lev[j, i] = b
    return lev


def _warm_cands() -> tuple:
    for M, T in ((8, 4), (16, 4), (4, 4)):  # numpy's selection probed ahead of the stream
        _argpartition_sorts(M, T)
    return (np.arange(24, dtype=np.float32).reshape(2, 2, 6), 4)


@njit(warm=_warm_cands)
def _candidates_kernel(costs: np.ndarray, T: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The T levels of least cost (S, N, T), ascending, of each row of costs (S, N, M)
    float32 whose M costs are distinct (each cost's rank counted, in branch-free loops over
    the rows that vectorize); rows with equal or NaN costs are flagged (S, N) (and counted)
    for numpy's selection, whose order among equal costs is its own."""
    S, N, M = costs.shape
    R = S * N
    flat = costs.reshape(R, M)
    ct = np.empty((M, R), np.float32)  # level-major: the loops below run over rows
    for r in range(R):
        for u in range(M):
            ct[u, r] = flat[r, u]
    rank = np.zeros((M, R), np.int32)
    ties = np.zeros(R, np.int32)
    for u in range(M):
        x = ct[u]
        rk = rank[u]
        for r in range(R):
            ties[r] += np.int32(M + 1) if np.isnan(x[r]) else np.int32(0)  # a NaN: never M in total
        for v in range(M):
            y = ct[v]
            for r in range(R):
                rk[r] += np.int32(1) if y[r] < x[r] else np.int32(0)
                ties[r] += np.int32(1) if y[r] == x[r] else np.int32(0)  # M when all distinct
    out = np.zeros((R, T + 1), np.int64)  # column T: where the ranks >= T go
    for u in range(M):
        rk = rank[u]
        for r in range(R):
            out[r, min(rk[r], T)] = u
    cand = np.ascontiguousarray(out[:, :T]).reshape(S, N, T)
    tie = np.empty((S, N), np.bool_)
    tf = tie.reshape(R)
    n_tie = 0
    for r in range(R):
        t = ties[r] != M
        tf[r] = t
        n_tie += 1 if t else 0
    return cand, tie, n_tie


_SORTS: dict[tuple[int, int], bool] = {}


def _argpartition_sorts(M: int, T: int) -> bool:
    """Whether ``np.argpartition(costs, T - 1, axis=-1)[..., :T]`` lists the T least of M
    distinct float32 costs in ascending order (numpy's vectorized selection sorts short
    rows: x86 with AVX-512 or AVX2); probed once per (M, T) on random rows. Else
    :func:`select_candidates` always asks numpy."""
    key = (int(M), int(T))
    if key not in _SORTS:
        x = np.random.default_rng(12345).random((4096, M)).astype(np.float32)
        x = x[(np.diff(np.sort(x, axis=-1), axis=-1) > 0).all(-1)]
        a = np.argpartition(x, T - 1, axis=-1)[..., :T]
        _SORTS[key] = bool(np.array_equal(a, np.argsort(x, axis=-1, kind="stable")[..., :T]))
    return _SORTS[key]


def select_candidates(costs: np.ndarray, T: int) -> np.ndarray:
    """``np.argpartition(costs, T - 1, axis=-1)[..., :T]`` (C-contiguous int64), exactly:
    compiled for rows of distinct costs where numpy's selection sorts them
    (:func:`_argpartition_sorts`), numpy's own for the other rows.

    Parameters
    ----------
    costs : ndarray
        (S, N, M) float32 costs.
    T : int
        Candidates per row, 1 <= T < M.

    Returns
    -------
    ndarray of int64
        (S, N, T) level indices.
    """
    M = costs.shape[-1]
    if costs.dtype != np.float32 or costs.ndim != 3 or not _argpartition_sorts(M, T):
        return np.ascontiguousarray(np.argpartition(costs, T - 1, axis=-1)[..., :T], dtype=np.int64)
    cand, tie, n_tie = _candidates_kernel(costs, int(T))
    if n_tie:
        cand[tie] = np.argpartition(costs[tie], T - 1, axis=-1)[..., :T]
    return cand


def _warm_finish_span() -> tuple:
    c = np.zeros((2, 2, 3), np.float32)
    i = np.zeros((2, 2), np.int64)
    return (c, np.zeros((2, 2, 2), np.int64), c[..., :2].copy(), c, i, i, i == 0, True)


@njit(warm=_warm_finish_span)
def _finish_span(costs: np.ndarray, cand: np.ndarray, extra: np.ndarray, full: np.ndarray,
                 n_obs: np.ndarray, dn: np.ndarray, no_clean: np.ndarray, want_full: bool
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`decide_span`'s last step in one pass: per symbol and LED the candidates'
    costs ``costs[cand] + extra`` -> the best candidate's level, the margin and the
    runner-up's level (:func:`_finish_kernel`'s rule), over all M levels (``costs + full``)
    for symbols without a clean frame when ``want_full``; the observation counts n_obs + dn."""
    S, N, T = cand.shape
    M = costs.shape[2]
    lev = np.zeros((S, N), np.int64)
    mar = np.full((S, N), np.inf)
    run = np.zeros((S, N), np.int64)
    tot = np.empty(max(T, M), np.float32)
    for j in range(S):
        for i in range(N):
            if want_full and no_clean[j, i]:
                for s in range(M):
                    tot[s] = costs[j, i, s] + full[j, i, s]
                lev[j, i], mar[j, i], run[j, i] = _finish_row(tot, M)
            else:
                for u in range(T):
                    tot[u] = costs[j, i, cand[j, i, u]] + extra[j, i, u]
                b, mar[j, i], r = _finish_row(tot, T)
                lev[j, i] = cand[j, i, b]
                run[j, i] = cand[j, i, r]
    return lev, mar, n_obs + dn, run


def _kind_args(model: ChannelModel) -> tuple[int, np.float32, np.float32]:
    return (KIND_CODE[model.kind], np.float32(1.0 / model.nu), np.float32(model.nu + 1.0))


def clean_costs(L: np.ndarray, clock: SymbolClock, e: float, k_a: int, k_b: int,
                model: ChannelModel) -> CleanCosts:
    """Clean-frame costs of packet symbols ``k_a <= k < k_b`` from the buffer L (C, n, N)
    (compiled; :func:`clean_costs_reference` is the specification).

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance of the buffer's frames, DN (NaN = missing).
    clock : SymbolClock
        The packet's symbol clock, frames.
    e : float
        Exposure window length, frames (exposure_s * fps).
    k_a, k_b : int
        Packet symbols to cost, symbols.
    model : ChannelModel
        The channel.

    Returns
    -------
    CleanCosts
        Costs (S, N, M) and observation counts (S, N), S = k_b - k_a, with the span's frame
        geometry.

    References
    ----------
    Dissertation, eqs. (3.12), (4.3) (Euclidean model).
    """
    C, n, N = L.shape
    lo = int(max(0, np.floor(clock.boundary(k_a)) - 1))
    hi = int(min(n, np.ceil(clock.boundary(k_b)) + 1))
    k, alpha = frame_map_range(lo, hi, clock, e)
    Lf = np.ascontiguousarray(L[:, lo:max(lo, hi), :], dtype=np.float64)
    mu, ivar, logvar = model._tables
    costs, n_obs, valid = _clean_kernel(Lf, k, alpha, k_a, k_b - k_a, mu, ivar, logvar,
                                        *_kind_args(model))
    return CleanCosts(k_a, k_b, costs, n_obs, k, alpha, Lf, valid)


def decide_span(L: np.ndarray, clock: SymbolClock, e: float, k_a: int, k_b: int,
                model: ChannelModel, ctx: np.ndarray | None = None, k_first: int = 0,
                straddle: bool = True, timing_sigma: float = 0.02,
                candidates: int = 4, pre: CleanCosts | None = None,
                edge_levels: tuple[int, ...] = ()) -> SpanDecision:
    """Decide packet symbols ``k_a <= k < k_b`` from the buffer L (C, n, N).

    With straddling frames, only the ``candidates`` best levels of the clean frames compete
    (symbols without a clean frame always get all M).

    Compiled (:func:`_clean_kernel`, :func:`_straddle_kernel`, :func:`_finish_kernel`);
    :func:`decide_span_reference` is the specification.

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance of the buffer's frames, DN (NaN = missing).
    clock : SymbolClock
        The packet's symbol clock, frames.
    e : float
        Exposure window length, frames (exposure_s * fps).
    k_a, k_b : int
        Packet symbols to decide, symbols.
    model : ChannelModel
        The channel.
    ctx : ndarray, optional
        (S, N) 0-based levels of packet symbols ``k_first ..`` used as the neighbours of
        straddling frames (-1 unknown); None: clean frames only.
    k_first : int
        Packet symbol of ``ctx[0]``, symbols.
    straddle : bool
        False: clean frames only.
    timing_sigma : float
        Symbol boundary uncertainty that widens the straddle variances, frames.
    candidates : int
        Levels per symbol that compete with straddling frames (0 = all M).
    pre : CleanCosts, optional
        The span's :func:`clean_costs` when already computed (same clock and model).
    edge_levels : tuple of int
        The plausible 0-based levels of the symbol right after the context (its straddling
        frame with the last context symbol then counts with the best of them).

    Returns
    -------
    SpanDecision
        0-based levels, margins (cost gap to the runner-up) and observation counts, each
        (k_b - k_a, N).

    References
    ----------
    Dissertation, eqs. (3.12), (4.3) (Euclidean model, clean frames only).
    """
    cc = pre if pre is not None else clean_costs(L, clock, e, k_a, k_b, model)
    if not (straddle and ctx is not None):
        lev, mar, run = _finish_kernel(cc.costs)
        return SpanDecision(k_a, lev, mar, cc.n_obs, run)
    M = model.levels
    S, N = cc.n_obs.shape
    T = M if candidates <= 0 or candidates >= M else candidates
    if T < M:  # numpy's selection (equal costs pick the same candidates)
        cand = select_candidates(cc.costs, T)
    else:
        cand = np.ascontiguousarray(np.broadcast_to(np.arange(M), (S, N, M)))
    no_clean = cc.n_obs == 0
    want_full = bool(T < M and no_clean.any())
    timing = model.kind != "euclid" and timing_sigma > 0
    gain = model._straddle_gain(float(timing_sigma / e))
    mu_t, var_t = model._fine
    Lf = cc.Lf if cc.Lf.dtype == np.float64 and cc.Lf.flags.c_contiguous else \
        np.ascontiguousarray(cc.Lf, dtype=np.float64)
    valid = cc.valid_obs if cc.valid_obs.dtype == np.int64 and cc.valid_obs.flags.c_contiguous \
        else np.ascontiguousarray(cc.valid_obs, dtype=np.int64)
    ctx = ctx if ctx.dtype == np.int64 and ctx.flags.c_contiguous else np.ascontiguousarray(ctx, dtype=np.int64)
    extra, dn, full = _straddle_kernel(Lf, cc.k, cc.alpha, valid, ctx, int(k_first), int(k_a), cand,
                                       no_clean, want_full, _edge_array(edge_levels), mu_t, var_t,
                                       model._interp_error32, gain, timing, M, *_kind_args(model))
    lev, mar, n_obs, run = _finish_span(cc.costs, cand, extra, full, cc.n_obs, dn, no_clean, want_full)
    return SpanDecision(k_a, lev, mar, n_obs, run)


_EDGES: dict[tuple[int, ...], np.ndarray] = {}


def _edge_array(edge_levels: tuple[int, ...]) -> np.ndarray:
    """``edge_levels`` as an int64 array (cached: a handful of distinct tuples)."""
    key = tuple(int(v) for v in edge_levels)
    a = _EDGES.get(key)
    if a is None:
        a = _EDGES[key] = np.asarray(key, dtype=np.int64)
    return a
