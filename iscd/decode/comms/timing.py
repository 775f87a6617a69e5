"""Symbol timing: header search, symbol phase and clock drift, frame <-> symbol geometry.

Time is measured in *frame units* on the camera's frame index: frame n exposes the window
``[n, n + e]``, ``e = exposure_s * fps`` (<= 1). The LED's symbols of a packet are
``[u0 + k p, u0 + (k + 1) p)`` for packet symbol k (k = 0 is the first header symbol):
``u0`` is the packet's phase against the frames and ``p`` the symbol period in frames
(``fps / symbol_rate_hz`` = 2 nominally; the LED clock's drift makes it ``p = 2 / (1 +
drift)``). Since e <= 1 < p, a window touches at most two symbols: it lies in symbol
``k_n`` for the fraction ``alpha_n`` of its length and in ``k_n + 1`` for the rest
(:func:`frame_map`). A frame with alpha = 1 is *clean*; with two frames per symbol every
symbol has at least one clean frame (SPEC section 3).

Header search (:func:`coarse_header_search`): the luminance of each LED is normalized to
[0, 1] (its 2nd and 98th percentiles), averaged over LEDs and cameras, and correlated
(normalized, NaN-aware, sliding) with the Barker-13 header rendered at frame resolution
at several sub-frame phases -- the integrated '+' fraction of each window. Peaks above a
correlation threshold whose amplitude is plausible are candidates.

Fine phase (:func:`fine_header`): a grid search of u0 (default 0.02 frame = 20 us steps over
+-0.6 frame, refined by a parabola) of the least-squares fit ``L_i = g_i D_n(u0) + c_i``
per LED and camera over the frames inside the header, D_n the exact '+' fraction.

Tracking (:func:`refine_clock`): Gauss-Newton on (u0, p) of the residuals of the straddling
frames ``L - h(alpha l_a + (1 - alpha) l_b)`` against the channel model's response h
(:mod:`iscd.decode.comms.channel`), for symbols whose levels are known (header, training) or
decided (data, decision-directed), with a Gaussian prior on p and Huber weights. Only a
straddling frame carries timing information: its value moves with the boundary position.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from iscd.core.airinterface import BARKER13, HEADER_SYMBOLS
from iscd.core.jit import njit, register_warm
from iscd.decode.comms.channel import ChannelModel, ChannelTrack

HEADER_BITS = (BARKER13 > 0).astype(np.float64)


def _clip(x: float, lo: float, hi: float) -> float:
    """``np.clip`` of one number (bounds lo <= hi, not zero): x itself when inside (NaN
    included), else the bound -- without numpy's per-call cost."""
    return lo if x < lo else hi if x > hi else x


@dataclass(frozen=True)
class SymbolClock:
    """Packet symbol k covers frame-unit time ``[u0 + k p, u0 + (k+1) p)``."""

    u0: float
    p: float

    def boundary(self, k: np.ndarray | float) -> np.ndarray:
        """Start of packet symbol k: ``u0 + k p``, frames.

        Parameters
        ----------
        k : ndarray or float
            Packet symbol index (fractional allowed), symbols.

        Returns
        -------
        ndarray of float64
            Frame-unit time, frames, the shape of ``k``.
        """
        return self.u0 + np.asarray(k, dtype=np.float64) * self.p

    def drift_ppm(self, nominal_p: float) -> float:
        """LED clock rate error against the camera, ppm (positive = LED fast).

        Parameters
        ----------
        nominal_p : float
            Nominal symbol period fps / symbol rate, frames.

        Returns
        -------
        float
            ``(nominal_p / p - 1) 1e6``, ppm.
        """
        return (nominal_p / self.p - 1.0) * 1e6

    def shifted(self, k: float) -> "SymbolClock":
        """The clock of a packet starting k symbols later.

        Parameters
        ----------
        k : float
            Shift, symbols.

        Returns
        -------
        SymbolClock
            ``u0 + k p``, the same period.
        """
        return SymbolClock(self.u0 + k * self.p, self.p)


def frame_map(frames: np.ndarray, clock: SymbolClock, e: float) -> tuple[np.ndarray, np.ndarray]:
    """Symbol k_n containing the start of frame n's window and the fraction alpha_n of the
    window inside it (1 = clean; the rest lies in k_n + 1).

    Parameters
    ----------
    frames : ndarray
        Frame indices n, frames.
    clock : SymbolClock
        The packet's symbol clock, frames.
    e : float
        Exposure window length, frames (exposure_s * fps, <= 1).

    Returns
    -------
    k : ndarray of int64
        Packet symbol of each window's start, the shape of ``frames``.
    alpha : ndarray of float64
        Fraction of each window in symbol k, 0 .. 1.
    """
    n = np.asarray(frames, dtype=np.float64)
    k = np.floor((n - clock.u0) / clock.p).astype(np.int64)
    end = clock.u0 + (k + 1) * clock.p
    alpha = np.clip((end - n) / e, 0.0, 1.0)
    return k, alpha


@njit(inline="always")
def _map_one(fr: int, u0: float, p: float, e: float) -> tuple[int, float]:
    """:func:`frame_map` of one frame (the same float64 operations)."""
    n = float(fr)
    k = int(np.floor((n - u0) / p))
    end = u0 + float(k + 1) * p
    return k, min(max((end - n) / e, 0.0), 1.0)


@njit(warm=lambda: (0, 4, 0.3, 2.0, 1.0), error_model="numpy")
def _frame_map_range(lo: int, hi: int, u0: float, p: float, e: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`frame_map` of frames lo .. hi - 1 (compiled, identical)."""
    n = max(hi - lo, 0)
    k = np.empty(n, np.int64)
    alpha = np.empty(n)
    for j in range(n):
        k[j], alpha[j] = _map_one(lo + j, u0, p, e)
    return k, alpha


def frame_map_range(lo: int, hi: int, clock: SymbolClock, e: float) -> tuple[np.ndarray, np.ndarray]:
    """``frame_map(np.arange(lo, hi), clock, e)`` in one compiled call.

    Parameters
    ----------
    lo, hi : int
        Frames lo .. hi - 1.
    clock : SymbolClock
        The packet's symbol clock, frames.
    e : float
        Exposure window length, frames.

    Returns
    -------
    k : ndarray of int64
        Packet symbol of each window's start.
    alpha : ndarray of float64
        Fraction of each window in symbol k, 0 .. 1.
    """
    return _frame_map_range(int(lo), int(hi), float(clock.u0), float(clock.p), float(e))


def clean_frame(k: np.ndarray, clock: SymbolClock, e: float) -> np.ndarray:
    """Index of the frame closest to the middle of symbol k (the cleanest one).

    Parameters
    ----------
    k : ndarray
        Packet symbol indices, symbols.
    clock : SymbolClock
        The packet's symbol clock, frames.
    e : float
        Exposure window length, frames.

    Returns
    -------
    ndarray of int64
        Frame indices whose window is centred nearest the symbol's middle, the shape of ``k``.
    """
    mid = clock.u0 + (np.asarray(k, dtype=np.float64) + 0.5) * clock.p
    return np.rint(mid - e / 2).astype(np.int64)


def _header_cum(u: np.ndarray, p: float) -> np.ndarray:
    """Integral of the header's '+' indicator from its start to u (frame units)."""
    knots = np.arange(HEADER_SYMBOLS + 1) * p
    vals = np.concatenate([[0.0], np.cumsum(HEADER_BITS) * p])
    return np.interp(u, knots, vals, left=0.0, right=vals[-1])


def header_fraction(offset: np.ndarray, p: float, e: float) -> np.ndarray:
    """Fraction of the window ``[o, o + e]`` (o = frame start - header start, frames) in '+'
    chips, for windows inside the header; the exact straddle integral of Barker-13.

    Parameters
    ----------
    offset : ndarray
        Window starts o relative to the header start, frames.
    p : float
        Symbol period, frames.
    e : float
        Exposure window length, frames.

    Returns
    -------
    ndarray of float64
        '+' fraction of each window, 0 .. 1, the shape of ``offset``.
    """
    o = np.asarray(offset, dtype=np.float64)
    return (_header_cum(o + e, p) - _header_cum(o, p)) / e


@dataclass(frozen=True)
class HeaderCandidate:
    """A header found by correlation: start u0 (frames), correlation rho, amplitude slope
    (normalized luminance units, ~1 for a real header)."""

    u0: float
    rho: float
    slope: float


def luminance_range(L: np.ndarray, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """2nd and 98th percentiles (C, N) of each camera's and LED's luminance L (C, n, N),
    from every ``step``-th frame; NaN for LEDs with fewer than 8 values or no spread.

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance, DN (NaN = missing).
    step : int
        Use every ``step``-th frame, frames.

    Returns
    -------
    lo, hi : ndarray of float64
        Each (C, N), DN.
    """
    C, n, N = L.shape
    sub = L[:, ::max(1, step), :]
    flat = sub.transpose(1, 0, 2).reshape(sub.shape[1], C * N)
    lo = np.full(C * N, np.nan)
    hi = np.full(C * N, np.nan)
    ok = np.isfinite(flat).sum(0) >= 8
    if ok.any():
        cols = flat[:, ok]
        pct = np.percentile if np.isfinite(cols).all() else np.nanpercentile
        lo[ok], hi[ok] = pct(cols, [2.0, 98.0], axis=0)
    flat_led = ~(hi - lo > 1e-6 * np.maximum(np.abs(hi), 1.0))
    lo[flat_led] = np.nan
    hi[flat_led] = np.nan
    return lo.reshape(C, N), hi.reshape(C, N)


def normalized_mean(L: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Mean over cameras and LEDs of ``(L - lo) / (hi - lo)``: (C, n, N) -> (n,), NaN where
    nothing is valid (LEDs with NaN range are ignored).

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance, DN (NaN = missing).
    lo, hi : ndarray
        (C, N) luminance range (:func:`luminance_range`), DN.

    Returns
    -------
    ndarray of float64
        (n,) normalized luminance, ~0 .. 1.
    """
    z = (L - lo[:, None, :]) / (hi - lo)[:, None, :]
    cnt = np.isfinite(z).sum(axis=(0, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        y = np.nansum(z, axis=(0, 2)) / cnt
    y[cnt == 0] = np.nan
    return y


def normalize_luminance(L: np.ndarray) -> np.ndarray:
    """Per camera and LED, map the 2nd..98th percentile range to 0..1; (C, n, N) -> (n,)
    mean over LEDs and cameras (NaN where nothing is valid). Flat LEDs are ignored.

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance, DN (NaN = missing).

    Returns
    -------
    ndarray of float64
        (n,) normalized luminance, ~0 .. 1.
    """
    lo, hi = luminance_range(L)
    return normalized_mean(L, lo, hi)


def coarse_header_search(y: np.ndarray, p: float, e: float, n_phases: int = 8,
                         min_rho: float = 0.7, min_slope: float = 0.3,
                         min_valid: float = 0.7) -> list[HeaderCandidate]:
    """Barker-13 candidates in the normalized luminance y (n,), best first.

    For each start frame n0 and phase phi in [0, 1) (steps 1/n_phases), the Pearson
    correlation of y over the frames inside the header with the header's '+' fraction
    (NaN frames skipped; at least ``min_valid`` of them present). Non-maximum
    suppression keeps the best candidate within 1.5 symbols.

    Parameters
    ----------
    y : ndarray
        (n,) normalized luminance (:func:`normalized_mean`), ~0 .. 1 (NaN = missing).
    p : float
        Symbol period, frames.
    e : float
        Exposure window length, frames.
    n_phases : int
        Sub-frame phases tried per frame.
    min_rho : float
        Least correlation of a candidate.
    min_slope : float
        Least amplitude slope, normalized luminance units (~1 for a real header).
    min_valid : float
        Least fraction of the header's frames present, 0 .. 1.

    Returns
    -------
    list of HeaderCandidate
        Header starts u0 (frames, indices into ``y``), by decreasing correlation; empty when
        ``y`` is shorter than a header.
    """
    y = np.asarray(y, dtype=np.float64)
    J = int(np.floor(HEADER_SYMBOLS * p - e))  # window frames 1..J after n0
    if J < 8 or y.size < J + 2:
        return []
    mask = np.isfinite(y)
    yf = np.where(mask, y, 0.0)
    mf = mask.astype(np.float64)
    phases = np.arange(n_phases) / n_phases
    j = np.arange(1, J + 1)
    T = header_fraction(j[:, None] - phases[None, :], p, e)  # (J, P)
    Y = sliding_window_view(yf[1:], J)  # row n0 covers frames n0+1 .. n0+J
    Mw = sliding_window_view(mf[1:], J)
    n_eff = Mw.sum(1)
    Sy = Y.sum(1)
    Syy = (Y * Y).sum(1)
    St = Mw @ T
    Stt = Mw @ (T * T)
    Syt = Y @ T
    ne = np.maximum(n_eff, 1.0)[:, None]
    cov = Syt - Sy[:, None] * St / ne
    vy = np.maximum(Syy - Sy * Sy / ne[:, 0], 0.0)[:, None]
    vt = np.maximum(Stt - St * St / ne, 1e-12)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = cov / np.sqrt(vy * vt)
    rho[~np.isfinite(rho)] = -1.0
    rho[n_eff < min_valid * J] = -1.0
    best = rho.argmax(1)
    r = rho[np.arange(rho.shape[0]), best]
    slope = (cov / vt)[np.arange(rho.shape[0]), best]
    u = np.arange(rho.shape[0]) + phases[best]
    order = np.argsort(-r)
    order = order[(r[order] >= min_rho) & (slope[order] >= min_slope)]
    out: list[HeaderCandidate] = []
    taken = np.zeros(r.size, bool)
    rad = int(np.ceil(1.5 * p))
    for i in order:
        if taken[i]:
            continue
        taken[max(0, i - rad): i + rad + 1] = True
        out.append(HeaderCandidate(float(u[i]), float(r[i]), float(slope[i])))
    return out


def fine_header(L: np.ndarray, u_guess: float, p: float, e: float, half_width: float = 0.6,
                step: float = 0.02) -> tuple[float, float]:
    """Header start u0 (frames) by grid search around ``u_guess``; returns (u0, mean R^2).

    Each LED/camera column is fitted ``L = g D + c`` over the frames inside the header for
    every grid u0; the sum of the columns' R^2 is maximized (equivalent to least squares per
    column, scale-free across columns), then refined by a parabola.

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance of the buffer, DN (NaN = missing).
    u_guess : float
        Approximate header start (:func:`coarse_header_search`), frames.
    p : float
        Symbol period, frames.
    e : float
        Exposure window length, frames.
    half_width : float
        Half-width of the searched grid, frames.
    step : float
        Grid step, frames.

    Returns
    -------
    u0 : float
        Header start, frames (``u_guess`` when too few frames or columns are usable).
    r2 : float
        Mean R^2 of the columns at the best grid point, 0 .. 1 (0 when not computable).
    """
    C, n, N = L.shape
    grid = u_guess + np.arange(-half_width, half_width + step / 2, step)
    n_lo = int(np.ceil(grid[-1]))
    n_hi = int(np.floor(grid[0] + HEADER_SYMBOLS * p - e))  # inclusive
    n_lo, n_hi = max(n_lo, 0), min(n_hi, n - 1)
    if n_hi - n_lo < 6:
        return float(u_guess), 0.0
    frames = np.arange(n_lo, n_hi + 1)
    V = L[:, frames, :].transpose(1, 0, 2).reshape(frames.size, C * N)
    ok = np.isfinite(V)
    cols = ok.sum(0) >= max(6, frames.size // 2)
    if not cols.any():
        return float(u_guess), 0.0
    V = V[:, cols]
    ok = ok[:, cols]
    mean = np.nanmean(V, axis=0)
    Vc = np.where(ok, V - mean, 0.0)
    vv = (Vc * Vc).sum(0)
    vv = np.where(vv > 1e-12, vv, np.inf)
    X = header_fraction(frames[None, :] - grid[:, None], p, e)  # (G, J)
    Xc = X - X.mean(1, keepdims=True)
    vx = np.maximum((Xc * Xc).sum(1), 1e-12)
    cov = Xc @ Vc  # (G, cols)
    score = ((cov * cov) / (vx[:, None] * vv[None, :])).sum(1) / cols.sum()
    g = int(score.argmax())
    u = float(grid[g])
    if 0 < g < grid.size - 1:
        a, b, c = score[g - 1], score[g], score[g + 1]
        den = a - 2 * b + c
        if den < 0:
            u += float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) * step
    return u, float(score[g])



def _response(track: ChannelTrack, k: np.ndarray, q: np.ndarray, dl: np.ndarray, e: float,
              timing_sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Response, slope and variance (C, n, N) of straddling frames with fractional levels
    q (n, N) between symbols k (n,) and k + 1 whose levels differ by dl (n, N): each frame
    from the model of its symbol k (linear interpolation between the centroids); the
    variance widened by ``timing_sigma`` frames of boundary error and by the interpolation
    error where the response bends (saturation)."""
    mu_t, var_t, err_t = track.tables  # (J, C, N, M), (J, C, N, M - 1)
    J, C, N, M = mu_t.shape
    seg = track.segment(k)[:, None]  # (n, 1)
    q0 = np.clip(np.floor(q), 0, M - 2).astype(np.intp)
    f = (q - q0)[None]
    led = np.arange(N)[None, :]
    # advanced indices around a slice: the gathered axes (n, N) come first
    a = np.moveaxis(mu_t[seg, :, led, q0], -1, 0)  # (C, n, N)
    slope = np.moveaxis(mu_t[seg, :, led, q0 + 1], -1, 0) - a
    va = np.moveaxis(var_t[seg, :, led, q0], -1, 0)
    var = va + f * (np.moveaxis(var_t[seg, :, led, q0 + 1], -1, 0) - va)
    gain = np.moveaxis((mu_t[:, :, :, -1] - mu_t[:, :, :, 0])[seg, :, led], -1, 0) / max(M - 1, 1)
    var = var + (timing_sigma / e * gain * dl[None]) ** 2
    seg_err = np.clip(q, 0, M - 2).astype(np.intp)
    var = var + np.square(np.moveaxis(err_t[seg, :, led, seg_err], -1, 0))
    return a + f * slope, slope, var


@njit(error_model="numpy")
def _segment_of(starts: np.ndarray, k: int) -> int:
    """``searchsorted(starts, k, "right") - 1``, clipped: the channel model of symbol k."""
    J = starts.shape[0]
    seg = J - 1
    for jj in range(J):
        if starts[jj] > k:
            seg = jj - 1
            break
    return min(max(seg, 0), J - 1)


@njit(error_model="numpy")
def _response_at(mu_t: np.ndarray, var_t: np.ndarray, err_t: np.ndarray, seg: int, c: int, i: int,
                 q: float, dl: float, ts_e: float, straddle: bool) -> tuple[float, float, float]:
    """Response, slope (per unit of q) and variance of camera c, LED i at fractional level
    q in channel model ``seg`` (element by element :func:`_response`); a ``straddle``-ing
    frame's variance is widened by the boundary uncertainty and the interpolation error."""
    M = mu_t.shape[3]
    q0 = int(min(max(np.floor(q), 0.0), M - 2.0))
    f = q - q0
    a = mu_t[seg, c, i, q0]
    slope = mu_t[seg, c, i, q0 + 1] - a
    va = var_t[seg, c, i, q0]
    var = va + f * (var_t[seg, c, i, q0 + 1] - va)
    if straddle:
        gain = (mu_t[seg, c, i, M - 1] - mu_t[seg, c, i, 0]) / max(M - 1, 1)
        tv = ts_e * gain * dl
        var = var + tv * tv
        ee = err_t[seg, c, i, int(min(max(q, 0.0), M - 2.0))]
        var = var + ee * ee
    return a + f * slope, slope, var


def _warm_clock() -> tuple:
    C, n, N, M = 2, 12, 2, 3
    tab = np.ones((1, C, N, M))
    return (np.ones((C, n + 2, N))[:, :n], 0, n, 0.3, 2.0, 1.0, np.zeros((6, N), np.int64), 0, 3.0,
            np.zeros(1, np.int64), tab, tab, np.zeros((1, C, N, M - 1)), 0.02, 3.0)


@njit(warm=_warm_clock, error_model="numpy")
def _clock_sums(L: np.ndarray, n_lo: int, n_hi: int, u0: float, p: float, e: float,
                lev: np.ndarray, k_first: int, kc: float, starts: np.ndarray, mu_t: np.ndarray,
                var_t: np.ndarray, err_t: np.ndarray, timing_sigma: float, huber: float
                ) -> tuple[int, float, float, float, float, float, int]:
    """One Gauss-Newton step's normal equations of :func:`refine_clock` on frames
    n_lo .. n_hi - 1 of L (C, n, N) with the clock (u0, p) (frames): the number of
    straddling frames between two labelled symbols, H = [[h00, h01], [h01, h11]], b = (b0,
    b1) and the observations used. Element by element what :func:`refine_clock_reference`
    and :func:`_response` compute (the response h interpolated in the model of the
    frame's first symbol, Huber weights); the sums run in frame order instead of numpy's
    pairwise order (agreement ~1e-13 relative)."""
    C = L.shape[0]
    S, N = lev.shape
    J = mu_t.shape[0]
    M = mu_t.shape[3]
    n_sel = 0
    used = 0
    h00 = 0.0
    h01 = 0.0
    h11 = 0.0
    b0 = 0.0
    b1 = 0.0
    ts_e = timing_sigma / e
    # per frame, the terms of every LED and camera first (loops without a carried
    # dependency: they vectorize), then the sums in the element-by-element order (LED,
    # camera); _response_at's arithmetic spelled out, its gain once per model
    gain = np.empty((J, C, N))
    for sg in range(J):
        for c in range(C):
            for i in range(N):
                gain[sg, c, i] = (mu_t[sg, c, i, M - 1] - mu_t[sg, c, i, 0]) / max(M - 1, 1)
    mu_f = np.ascontiguousarray(mu_t).reshape(J, C, N * M)  # flat per model and camera
    var_f = np.ascontiguousarray(var_t).reshape(J, C, N * M)
    err_f = np.ascontiguousarray(err_t).reshape(J, C, N * (M - 1))
    t00 = np.empty((C, N))
    t01 = np.empty((C, N))
    t11 = np.empty((C, N))
    tb0 = np.empty((C, N))
    tb1 = np.empty((C, N))
    pos = np.empty((C, N), np.bool_)
    ok = np.empty((C, N), np.bool_)
    fq = np.empty(N)  # per LED: interpolation fraction, level difference, the gathered
    dlf = np.empty(N)  # centroid, slope, variances and interpolation error
    q0s = np.empty(N, np.int64)
    e0s = np.empty(N, np.int64)
    vld = np.empty(N, np.bool_)
    ga = np.empty(N)
    gs = np.empty(N)
    gva = np.empty(N)
    gvb = np.empty(N)
    gee = np.empty(N)
    for fr in range(n_lo, n_hi):
        n = float(fr)
        k = int(np.floor((n - u0) / p))
        end = u0 + (k + 1) * p
        alpha = min(max((end - n) / e, 0.0), 1.0)
        if not (alpha > 0.0 and alpha < 1.0 and k >= k_first and k + 1 < k_first + S):
            continue
        n_sel += 1
        seg = _segment_of(starts, k)
        dk = float(k + 1) - kc
        lev_a = lev[k - k_first]
        lev_b = lev[k + 1 - k_first]
        for i in range(N):  # per LED: q and where it falls (vectorizes)
            la = lev_a[i]
            lb = lev_b[i]
            vld[i] = (la >= 0) & (lb >= 0) & (la != lb)
            dlf[i] = la - lb
            q = alpha * la + (1 - alpha) * lb
            q0 = int(min(max(np.floor(q), 0.0), M - 2.0))
            q0s[i] = q0
            e0s[i] = int(min(max(q, 0.0), M - 2.0))
            fq[i] = q - q0
        for c in range(C):
            Lc = L[c, fr]
            mu_c = mu_f[seg, c]
            var_c = var_f[seg, c]
            err_c = err_f[seg, c]
            gain_c = gain[seg, c]
            okc = ok[c]
            for i in range(N):  # the lookups (gathers: scalar)
                j = i * M + q0s[i]
                a_ = mu_c[j]
                ga[i] = a_
                gs[i] = mu_c[j + 1] - a_
                gva[i] = var_c[j]
                gvb[i] = var_c[j + 1]
                gee[i] = err_c[i * (M - 1) + e0s[i]]
                okc[i] = vld[i] & np.isfinite(Lc[i])
            c00 = t00[c]
            c01 = t01[c]
            c11 = t11[c]
            cb0 = tb0[c]
            cb1 = tb1[c]
            cpos = pos[c]
            for i in range(N):  # the arithmetic (vectorizes)
                f = fq[i]
                va = gva[i]
                var = va + f * (gvb[i] - va)
                dl = dlf[i]
                tv = ts_e * gain_c[i] * dl
                var = var + tv * tv
                ee = gee[i]
                var = var + ee * ee
                slope = gs[i]
                r = Lc[i] - (ga[i] + f * slope)
                g = -slope * (dl / e)
                w = 1.0 / var
                z = abs(r) * np.sqrt(w)
                w = w * min(1.0, huber / max(z, 1e-12))
                wg = w * g
                # a skipped observation adds +0.0: exact, a sum from +0.0 is never -0.0
                use = okc[i]
                cpos[i] = use & (w > 0)
                c00[i] = wg * g if use else 0.0
                c01[i] = wg * g * dk if use else 0.0
                c11[i] = wg * g * dk * dk if use else 0.0
                cb0[i] = wg * r if use else 0.0
                cb1[i] = wg * r * dk if use else 0.0
        for i in range(N):
            for c in range(C):
                used += 1 if pos[c, i] else 0
                h00 += t00[c, i]
                h01 += t01[c, i]
                h11 += t11[c, i]
                b0 += tb0[c, i]
                b1 += tb1[c, i]
    return n_sel, h00, h01, h11, b0, b1, used


def _warm_clock_c() -> tuple:
    """:func:`_warm_clock` with a C-contiguous buffer (what the packet assembler passes)."""
    args = _warm_clock()
    return (np.ascontiguousarray(args[0]),) + args[1:]


register_warm(_clock_sums, _warm_clock_c)


@njit(error_model="numpy")
def _clock_cost(L: np.ndarray, n_lo: int, n_hi: int, u0: float, p: float, e: float,
                lev: np.ndarray, k_first: int, starts: np.ndarray, mu_t: np.ndarray,
                var_t: np.ndarray, err_t: np.ndarray, timing_sigma: float, huber: float,
                log_var: bool) -> float:
    """Robust cost of the clock (u0, p) on frames n_lo .. n_hi - 1: every frame whose window
    lies in labelled symbols, clean (the centroid of its level) or straddling (the response
    of :func:`_clock_sums`), Huber's rho of the normalized residual; with ``log_var`` plus
    the log of each residual's variance (a likelihood: without it a clock that makes frames
    straddle by a hair, their variance widened by the timing term, costs less than one that
    keeps them clean). Element by element :func:`clock_cost_reference` (sums in frame order)."""
    C = L.shape[0]
    S, N = lev.shape
    ts_e = timing_sigma / e
    tot = 0.0
    for fr in range(n_lo, n_hi):
        n = float(fr)
        k = int(np.floor((n - u0) / p))
        end = u0 + (k + 1) * p
        alpha = min(max((end - n) / e, 0.0), 1.0)
        clean = alpha >= 1.0
        if not (k >= k_first and (k < k_first + S if clean else k + 1 < k_first + S)):
            continue
        seg = _segment_of(starts, k)
        for i in range(N):
            la = lev[k - k_first, i]
            lb = la if clean else lev[k + 1 - k_first, i]
            if la < 0 or lb < 0:
                continue
            q = alpha * la + (1 - alpha) * lb
            for c in range(C):
                obs = L[c, fr, i]
                if not np.isfinite(obs):
                    continue
                mu, _, var = _response_at(mu_t, var_t, err_t, seg, c, i, q, la - lb, ts_e, not clean)
                z = abs(obs - mu) / np.sqrt(var)
                tot += z * z if z <= huber else 2.0 * huber * z - huber * huber
                if log_var:
                    tot += np.log(var)
    return tot


def clock_cost_reference(L: np.ndarray, n_lo: int, n_hi: int, u0: float, p: float, e: float,
                         lev: np.ndarray, k_first: int, track: ChannelTrack, timing_sigma: float,
                         huber: float, log_var: bool = False) -> float:
    """Pure-numpy reference of :func:`_clock_cost` (the clock's robust cost on all labelled
    frames, clean and straddling).

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance of the buffer, DN (NaN = missing).
    n_lo, n_hi : int
        Frames ``n_lo .. n_hi - 1`` are used, frames.
    u0 : float
        Start of packet symbol 0, frames.
    p : float
        Symbol period, frames.
    e : float
        Exposure window length, frames.
    lev : ndarray
        (S, N) 0-based levels of packet symbols ``k_first .. k_first + S - 1`` (-1 = unknown).
    k_first : int
        Packet symbol of ``lev[0]``, symbols.
    track : ChannelTrack
        The channel along the packet.
    timing_sigma : float
        Symbol boundary uncertainty that widens the straddle variances, frames.
    huber : float
        Huber threshold of the normalized residual, noise RMS.

    log_var : bool
        Add each residual's log variance (as :func:`_clock_cost`).

    Returns
    -------
    float
        Sum of Huber's rho of the normalized residuals (with ``log_var``: plus their log
        variances, DN^2).
    """
    S, N = lev.shape
    frames = np.arange(n_lo, n_hi)
    k, alpha = frame_map(frames, SymbolClock(u0, p), e)
    clean = alpha >= 1.0
    ok = (k >= k_first) & np.where(clean, k < k_first + S, k + 1 < k_first + S)
    frames, k, alpha, clean = frames[ok], k[ok], alpha[ok], clean[ok]
    if frames.size == 0:
        return 0.0
    la = lev[k - k_first]
    lb = np.where(clean[:, None], la, lev[np.minimum(k + 1, k_first + S - 1) - k_first])
    valid = (la >= 0) & (lb >= 0)
    q = alpha[:, None] * la + (1 - alpha[:, None]) * lb
    mu, _, var = _response(track, k, q, la - lb, e, timing_sigma)
    mu_t, var_t, _ = track.tables
    M = mu_t.shape[3]
    seg = track.segment(k)[:, None]
    led = np.arange(N)[None, :]
    q0 = np.clip(np.floor(q), 0, M - 2).astype(np.intp)
    f = (q - q0)[None]
    va = np.moveaxis(var_t[seg, :, led, q0], -1, 0)
    var_clean = va + f * (np.moveaxis(var_t[seg, :, led, q0 + 1], -1, 0) - va)
    var = np.where(clean[None, :, None], var_clean, var)
    obs = L[:, frames, :]
    z = np.abs(obs - mu) / np.sqrt(var)
    rho = np.where(z <= huber, z * z, 2.0 * huber * z - huber * huber)
    if log_var:
        rho = rho + np.log(var)
    use = valid[None] & np.isfinite(obs)
    return float(np.where(use, rho, 0.0).sum())


def _warm_cost() -> tuple:
    a = _warm_clock_c()
    return a[:8] + a[9:] + (False,)


register_warm(_clock_cost, _warm_cost)


PERIOD_SEARCH_FRAMES = 0.05
"""With exposures shorter than the frame period (a dark gap of more than
:data:`GAP_MIN_FRAMES` between two windows) the period is searched on a grid first when
its prior uncertainty (3 sigma) moves the span's far end by more than this, frames. A
boundary may then sit in the gap at the start of a packet and drift into the windows
later; no frame straddles under the nominal period, and a Gauss-Newton fit that only
sees the frames straddling under its current estimate never moves (a randomized approach
scene lost its first packet so). Without a gap every boundary crosses some window and
the fit sees it: no search (and the default rig's results are what they were)."""

GAP_MIN_FRAMES = 0.01
"""Dark time between exposures (frames) below which there is no gap to search across."""


ENDS_STEP_FRAMES = 0.1
"""Grid step of :func:`_search_ends` (then refined twice, at a quarter of it), frames."""

ENDS_MIN_GAP_FRAMES = 0.1
"""Least dark gap between exposures (1 - e, frames) for which ``search_ends`` searches: in a
narrower gap a boundary is never far from a straddling frame."""

ENDS_MAX_LEDS = 4
"""LEDs of an array the ends search reads (spread over the array; the clock is common)."""


def _ends_leds(N: int) -> np.ndarray:
    """Indices of at most :data:`ENDS_MAX_LEDS` LEDs spread over N."""
    return np.unique(np.round(np.linspace(0, N - 1, min(N, ENDS_MAX_LEDS))).astype(np.int64))


@njit(error_model="numpy")
def _search_ends(L: np.ndarray, n_lo: int, n_hi: int, a0: float, b0: float, S: int, reach: float,
                 step: float, e: float, lev: np.ndarray, k_first: int, starts: np.ndarray,
                 mu_t: np.ndarray, var_t: np.ndarray, err_t: np.ndarray, timing_sigma: float,
                 huber: float, p_prior: float, p_sigma: float) -> tuple[float, float]:
    """The clock (u0, p) whose boundaries at the span's first and last symbol, a0 + da and
    b0 + db, minimize :func:`_clock_cost` plus the period's prior, over da, db in
    -reach .. reach on a grid of ``step`` frames, then twice around the best at a quarter of
    the step; ties keep the smaller move (the start clock wins a flat cost)."""
    best_c = np.inf
    best_a = 0.0
    best_b = 0.0
    cen_a = 0.0
    cen_b = 0.0
    r = reach
    st = step
    for _ in range(3):
        m = int(np.ceil(r / st))
        for i in range(-m, m + 1):
            da = cen_a + i * st
            for j in range(-m, m + 1):
                db = cen_b + j * st
                u0 = a0 + da
                q = (b0 + db - u0) / S
                c = _clock_cost(L, n_lo, n_hi, u0, q, e, lev, k_first, starts, mu_t, var_t, err_t,
                                timing_sigma, huber, False) + ((q - p_prior) / p_sigma) ** 2
                if c < best_c - 1e-9 or (c <= best_c + 1e-9 and abs(da) + abs(db) < abs(best_a) + abs(best_b)):
                    best_c = c
                    best_a = da
                    best_b = db
        cen_a = best_a
        cen_b = best_b
        r = st
        st = st / 4.0
    u0 = a0 + best_a
    return u0, (b0 + best_b - u0) / S


def _search_period(cost: Callable[[float, float], float], uc: float, kc: float, p: float,
                   p_prior: float, p_sigma: float, half_span: float) -> float:
    """The period on a grid over p_prior +- 3 p_sigma (steps that move the span's ends by
    0.03 frames) minimizing ``cost(u0, p)`` (the clock through ``uc`` at symbol ``kc``) plus
    the prior; ``p`` itself is a candidate, and wins ties."""
    step = 0.03 / max(half_span, 1.0)
    n = int(min(np.ceil(3 * p_sigma / step), 60))
    grid = p_prior + step * np.arange(-n, n + 1)
    best_p = p
    best = cost(uc - kc * p, p) + ((p - p_prior) / p_sigma) ** 2
    for q in grid:
        c = cost(uc - kc * q, q) + ((q - p_prior) / p_sigma) ** 2
        if c < best:
            best, best_p = c, float(q)
    return best_p


def refine_clock(L: np.ndarray, clock: SymbolClock, e: float, lev: np.ndarray, k_first: int,
                 model: ChannelModel | ChannelTrack, p_prior: float, p_sigma: float, iters: int = 3,
                 huber: float = 3.0, timing_sigma: float = 0.02,
                 fit_p: bool = True, search_ends: bool = False) -> tuple[SymbolClock, int]:
    """Gauss-Newton refinement of the symbol clock on labelled symbols.

    A straddling frame uses the model of its first symbol. With exposures shorter than the
    frame period the period is first searched on a grid (:data:`PERIOD_SEARCH_FRAMES`), or
    with ``search_ends`` both ends of the span together (:func:`_search_ends`): where the
    symbol boundaries sit in the dark gap between exposures no frame straddles and the
    clock is free across the gap; an LED clock drifting 200 ppm carries them out of it
    within a packet, and a clock held at the gap's edge then reads straddling frames as
    clean ones (a randomized 40 km/h scene lost a packet so: 49 of 600 symbols wrong).
    The normal equations come from the compiled :func:`_clock_sums`;
    :func:`refine_clock_reference` is the specification.

    Parameters
    ----------
    L : ndarray
        (C, n, N) buffer luminance, DN (NaN = missing).
    clock : SymbolClock
        The clock to start from, frames.
    e : float
        Exposure window length, frames.
    lev : ndarray
        (S, N) 0-based levels of packet symbols ``k_first .. k_first + S - 1`` (-1 = unknown).
    k_first : int
        Packet symbol of ``lev[0]``, symbols.
    model : ChannelModel or ChannelTrack
        The channel, one for the span or a track along the packet.
    p_prior : float
        Prior mean of the symbol period, frames.
    p_sigma : float
        Its RMS, frames.
    iters : int
        Most Gauss-Newton steps.
    huber : float
        Huber threshold of the normalized residual, noise RMS.
    timing_sigma : float
        Symbol boundary uncertainty that widens the straddle variances, frames.
    fit_p : bool
        Fit the period too (else the phase only).
    search_ends : bool
        With ``fit_p`` and an exposure gap of at least :data:`ENDS_MIN_GAP_FRAMES`: search the
        boundaries at the span's two ends over the gap first (a grid of
        :data:`ENDS_STEP_FRAMES`, on at most :data:`ENDS_MAX_LEDS` LEDs; for a packet's
        final clock, and for every clock update of a packet whose period is not yet known:
        a header that leaves the clock at the gap's far edge puts the end of a longer span
        beyond the search's reach, gap + 0.1 frames).

    Returns
    -------
    clock : SymbolClock
        The refined clock, frames.
    used : int
        Number of informative straddling observations used (0: clock unchanged).
    """
    track = model if isinstance(model, ChannelTrack) else ChannelTrack.single(model)
    C, n, N = L.shape
    S = lev.shape[0]
    kc = k_first + S / 2.0  # parametrize around the span's centre
    uc, p = clock.u0 + kc * clock.p, clock.p
    n_lo = int(max(0, np.floor(clock.boundary(k_first)) - 1))
    n_hi = int(min(n, np.ceil(clock.boundary(k_first + S)) + 1))
    mu_t, var_t, err_t = track.tables
    starts = np.asarray(track.starts, dtype=np.int64)
    Lc = L if L.dtype == np.float64 else L.astype(np.float64)
    levc = np.ascontiguousarray(lev, dtype=np.int64)
    used = 0
    if fit_p and search_ends and e <= 1.0 - ENDS_MIN_GAP_FRAMES and S > 0:
        reach = (1.0 - e) + ENDS_STEP_FRAMES  # the gap: where no straddle pins the clock
        a, b = clock.boundary(k_first), clock.boundary(k_first + S)
        sel = _ends_leds(N)
        u_a, p = _search_ends(np.ascontiguousarray(Lc[:, :, sel]), n_lo, max(n_lo, n_hi), float(a), float(b),
                              int(S), float(reach), ENDS_STEP_FRAMES, float(e), np.ascontiguousarray(levc[:, sel]),
                              int(k_first), starts, np.ascontiguousarray(mu_t[:, :, sel]),
                              np.ascontiguousarray(var_t[:, :, sel]), np.ascontiguousarray(err_t[:, :, sel]),
                              float(timing_sigma), float(huber), float(p_prior), float(p_sigma))
        uc = u_a + (kc - k_first) * p
    elif fit_p and e < 1.0 - GAP_MIN_FRAMES and 3 * p_sigma * S / 2 > PERIOD_SEARCH_FRAMES:
        lo, hi = n_lo, max(n_lo, n_hi)
        p = _search_period(lambda u0, q: _clock_cost(Lc, lo, hi, u0, q, float(e), levc, int(k_first),
                                                     starts, mu_t, var_t, err_t, float(timing_sigma),
                                                     float(huber), False),
                           uc, kc, p, p_prior, p_sigma, S / 2.0)
    for _ in range(iters):
        n_sel, h00, h01, h11, b0, b1, n_used = _clock_sums(
            Lc, n_lo, max(n_lo, n_hi), uc - kc * p, p, float(e), levc, int(k_first), float(kc),
            starts, mu_t, var_t, err_t, float(timing_sigma), float(huber))
        if n_sel == 0:
            break
        used = n_used
        if h00 <= 0:
            break
        if fit_p:
            H = np.array([[h00 + 1e-9, h01], [h01, h11 + 1.0 / p_sigma ** 2]])
            rhs = -np.array([b0, b1 + (p - p_prior) / p_sigma ** 2])
            try:
                d_u, d_p = np.linalg.solve(H, rhs)
            except np.linalg.LinAlgError:
                break
        else:
            d_u, d_p = -b0 / h00, 0.0
        d_u = float(_clip(d_u, -0.25, 0.25))
        d_p = float(_clip(d_p, -3 * p_sigma, 3 * p_sigma))
        uc += d_u
        p += d_p
        if abs(d_u) < 1e-3 and abs(d_p) * S < 1e-3:  # 1 us
            break
    return SymbolClock(uc - kc * p, p), used


def period_sigma(L: np.ndarray, clock: SymbolClock, e: float, lev: np.ndarray, k_first: int,
                 model: ChannelModel | ChannelTrack, p_sigma: float, huber: float = 3.0,
                 timing_sigma: float = 0.02) -> float:
    """How well a packet's frames pin the symbol period: its posterior RMS at ``clock``.

    The Laplace approximation of :func:`refine_clock`'s fit: the inverse of its
    Gauss-Newton normal matrix (phase and period, the period's prior ``p_sigma`` included),
    at the fitted clock. Only frames that straddle a symbol boundary carry timing; where a
    packet's boundaries stay in the dark gap between exposures (an exposure shorter than
    the frame period) none does, and the period is known no better than its prior: a next
    packet must not take it as known to a few ppm (a randomized 100 km/h scene, seed
    2068419781: a first packet in the gap fitted 0 ppm for a true 199 ppm, the next packet,
    locked to it at 20 ppm, lost 32 symbols where its boundaries left the gap).

    Parameters
    ----------
    L : ndarray
        (C, n, N) buffer luminance, DN (NaN = missing).
    clock : SymbolClock
        The fitted clock, frames.
    e : float
        Exposure window length, frames.
    lev : ndarray
        (S, N) 0-based levels of packet symbols ``k_first .. k_first + S - 1`` (-1 = unknown).
    k_first : int
        Packet symbol of ``lev[0]``, symbols.
    model : ChannelModel or ChannelTrack
        The channel, one for the span or a track along the packet.
    p_sigma : float
        The period's prior RMS, frames.
    huber, timing_sigma : float
        As :func:`refine_clock` (noise RMS; frames).

    Returns
    -------
    float
        Posterior RMS of the period, frames (at most ``p_sigma``).
    """
    track = model if isinstance(model, ChannelTrack) else ChannelTrack.single(model)
    C, n, N = L.shape
    S = lev.shape[0]
    kc = k_first + S / 2.0
    n_lo = int(max(0, np.floor(clock.boundary(k_first)) - 1))
    n_hi = int(min(n, np.ceil(clock.boundary(k_first + S)) + 1))
    mu_t, var_t, err_t = track.tables
    Lc = L if L.dtype == np.float64 else L.astype(np.float64)
    n_sel, h00, h01, h11, _, _, _ = _clock_sums(
        Lc, n_lo, max(n_lo, n_hi), clock.u0, clock.p, float(e), np.ascontiguousarray(lev, dtype=np.int64),
        int(k_first), float(kc), np.asarray(track.starts, dtype=np.int64), mu_t, var_t, err_t,
        float(timing_sigma), float(huber))
    prior = 1.0 / p_sigma ** 2
    det = h00 * (h11 + prior) - h01 * h01
    if n_sel == 0 or not h00 > 0 or not det > 0:
        return float(p_sigma)
    sig = float(np.sqrt(h00 / det))
    if e <= 1.0 - ENDS_MIN_GAP_FRAMES and S > 0:  # the curvature is blind to a flat side
        sig = max(sig, _flat_period(Lc, clock, e, lev, k_first, track, timing_sigma, huber))
    return float(min(p_sigma, sig))


FLAT_COST = 4.0
"""Cost rise (Huber rho plus log variance: twice a negative log-likelihood) below which
:func:`period_sigma` counts a moved clock as fitting as well as the fitted one."""


def _flat_period(L: np.ndarray, clock: SymbolClock, e: float, lev: np.ndarray, k_first: int,
                 track: ChannelTrack, timing_sigma: float, huber: float) -> float:
    """Largest period change that moves one end of the span by up to the exposure gap
    (1 - e frames; the other end held) and raises :func:`_clock_cost` by less than
    :data:`FLAT_COST`, frames/symbol (0: none). Where a fitted clock sits at the gap's edge
    its curvature measures only the steep side; the other side may be flat for the whole
    gap. The cost is a likelihood (:func:`_clock_cost` with ``log_var``): without the log
    variances a clock that makes frames straddle by a hair beats the true one (the timing
    term widens their variance), so a fit at a window's edge looked pinned. Same frames for
    every clock (those inside the span's symbols under all of them), on the
    :func:`_ends_leds` of an array."""
    S, N = lev.shape
    a, b = clock.boundary(k_first), clock.boundary(k_first + S)
    n_lo = int(max(0, np.floor(a) + 2))
    n_hi = int(min(L.shape[1], np.ceil(b) - 2))
    if n_hi <= n_lo:
        return 0.0
    sel = _ends_leds(N)
    mu_t, var_t, err_t = track.tables
    Ls = np.ascontiguousarray(L[:, :, sel])
    ls = np.ascontiguousarray(lev[:, sel], dtype=np.int64)
    starts = np.asarray(track.starts, dtype=np.int64)
    tabs = (np.ascontiguousarray(mu_t[:, :, sel]), np.ascontiguousarray(var_t[:, :, sel]),
            np.ascontiguousarray(err_t[:, :, sel]))

    def cost(u0: float, q: float) -> float:
        return _clock_cost(Ls, n_lo, n_hi, u0, q, float(e), ls, int(k_first), starts, *tabs,
                           float(timing_sigma), float(huber), True)

    c0 = cost(clock.u0, clock.p)
    g = 1.0 - e
    wide = 0.0
    for d in (-g, -g / 2, g / 2, g):
        q = clock.p + d / S
        # the end moved by d (the start held), or the start moved by -d (the end held)
        for u0 in (a - k_first * q, b - (k_first + S) * q):
            if cost(u0, q) - c0 < FLAT_COST:
                wide = max(wide, abs(d) / S)
    return wide


def refine_clock_reference(L: np.ndarray, clock: SymbolClock, e: float, lev: np.ndarray, k_first: int,
                 model: ChannelModel | ChannelTrack, p_prior: float, p_sigma: float, iters: int = 3,
                 huber: float = 3.0, timing_sigma: float = 0.02,
                 fit_p: bool = True, search_ends: bool = False) -> tuple[SymbolClock, int]:
    """Pure-numpy reference of :func:`refine_clock` (the compiled kernel's specification).

    Gauss-Newton refinement of the symbol clock on labelled symbols. A straddling frame uses
    the model of its first symbol.

    Parameters
    ----------
    L : ndarray
        (C, n, N) buffer luminance, DN (NaN = missing).
    clock : SymbolClock
        The clock to start from, frames.
    e : float
        Exposure window length, frames.
    lev : ndarray
        (S, N) 0-based levels of packet symbols ``k_first .. k_first + S - 1`` (-1 = unknown).
    k_first : int
        Packet symbol of ``lev[0]``, symbols.
    model : ChannelModel or ChannelTrack
        The channel, one for the span or a track along the packet.
    p_prior : float
        Prior mean of the symbol period, frames.
    p_sigma : float
        Its RMS, frames.
    iters : int
        Most Gauss-Newton steps.
    huber : float
        Huber threshold of the normalized residual, noise RMS.
    timing_sigma : float
        Symbol boundary uncertainty that widens the straddle variances, frames.
    fit_p : bool
        Fit the period too (else the phase only).
    search_ends : bool
        With ``fit_p`` and an exposure gap of at least :data:`ENDS_MIN_GAP_FRAMES`: search the
        boundaries at the span's two ends over the gap first (a grid of
        :data:`ENDS_STEP_FRAMES`, on at most :data:`ENDS_MAX_LEDS` LEDs; for a packet's
        final clock, and for every clock update of a packet whose period is not yet known:
        a header that leaves the clock at the gap's far edge puts the end of a longer span
        beyond the search's reach, gap + 0.1 frames).

    Returns
    -------
    clock : SymbolClock
        The refined clock, frames.
    used : int
        Number of informative straddling observations used (0: clock unchanged).
    """
    track = model if isinstance(model, ChannelTrack) else ChannelTrack.single(model)
    C, n, N = L.shape
    S = lev.shape[0]
    kc = k_first + S / 2.0  # parametrize around the span's centre
    uc, p = clock.u0 + kc * clock.p, clock.p
    n_lo = int(max(0, np.floor(clock.boundary(k_first)) - 1))
    n_hi = int(min(n, np.ceil(clock.boundary(k_first + S)) + 1))
    frames = np.arange(n_lo, n_hi)
    used = 0
    if fit_p and search_ends and e <= 1.0 - ENDS_MIN_GAP_FRAMES and S > 0:
        reach = (1.0 - e) + ENDS_STEP_FRAMES
        a, b = float(clock.boundary(k_first)), float(clock.boundary(k_first + S))
        sel = _ends_leds(N)
        sub = ChannelTrack(track.starts, tuple(ChannelModel(mu=m.mu[:, sel], var=m.var[:, sel], kind=m.kind,
                                                            nu=m.nu) for m in track.models))
        Ls, levs = L[:, :, sel], lev[:, sel]
        best, cen, r, st = (np.inf, 0.0, 0.0), (0.0, 0.0), reach, ENDS_STEP_FRAMES
        for _ in range(3):  # the grid of _search_ends, then twice around its best
            m = int(np.ceil(r / st))
            for i in range(-m, m + 1):
                for j in range(-m, m + 1):
                    da, db = cen[0] + i * st, cen[1] + j * st
                    q = (b + db - a - da) / S
                    c = clock_cost_reference(Ls, n_lo, n_hi, a + da, q, e, levs, k_first, sub, timing_sigma,
                                             huber) + ((q - p_prior) / p_sigma) ** 2
                    if c < best[0] - 1e-9 or (c <= best[0] + 1e-9 and abs(da) + abs(db) < abs(best[1]) + abs(best[2])):
                        best = (c, da, db)
            cen, r, st = (best[1], best[2]), st, st / 4.0
        p = (b + best[2] - a - best[1]) / S
        uc = a + best[1] + (kc - k_first) * p
    elif fit_p and e < 1.0 - GAP_MIN_FRAMES and 3 * p_sigma * S / 2 > PERIOD_SEARCH_FRAMES:
        p = _search_period(lambda u0, q: clock_cost_reference(L, n_lo, n_hi, u0, q, e, lev, k_first, track,
                                                              timing_sigma, huber),
                           uc, kc, p, p_prior, p_sigma, S / 2.0)
    for _ in range(iters):
        ck = SymbolClock(uc - kc * p, p)
        k, alpha = frame_map(frames, ck, e)
        sel = (alpha > 0) & (alpha < 1) & (k >= k_first) & (k + 1 < k_first + S)
        if not sel.any():
            break
        fr, k, alpha = frames[sel], k[sel], alpha[sel]
        la = lev[k - k_first]
        lb = lev[k + 1 - k_first]
        obs = L[:, fr, :]
        valid = (la >= 0) & (lb >= 0) & (la != lb)
        q = alpha[:, None] * la + (1 - alpha[:, None]) * lb
        mu, slope, var = _response(track, k, q, la - lb, e, timing_sigma)
        r = obs - mu
        g = -slope * ((la - lb) / e)[None]  # d r / d boundary
        w = np.where(valid[None] & np.isfinite(obs), 1.0 / var, 0.0)
        z = np.abs(np.nan_to_num(r)) * np.sqrt(w)
        w = w * np.minimum(1.0, huber / np.maximum(z, 1e-12))
        r = np.nan_to_num(r)
        dk = (k + 1 - kc).astype(np.float64)[None, :, None]
        wg = w * g
        h00 = float((wg * g).sum())
        h01 = float((wg * g * dk).sum())
        h11 = float((wg * g * dk * dk).sum())
        b0 = float((wg * r).sum())
        b1 = float((wg * r * dk).sum())
        used = int((w > 0).sum())
        if h00 <= 0:
            break
        if fit_p:
            H = np.array([[h00 + 1e-9, h01], [h01, h11 + 1.0 / p_sigma ** 2]])
            rhs = -np.array([b0, b1 + (p - p_prior) / p_sigma ** 2])
            try:
                d_u, d_p = np.linalg.solve(H, rhs)
            except np.linalg.LinAlgError:
                break
        else:
            d_u, d_p = -b0 / h00, 0.0
        d_u = float(np.clip(d_u, -0.25, 0.25))
        d_p = float(np.clip(d_p, -3 * p_sigma, 3 * p_sigma))
        uc += d_u
        p += d_p
        if abs(d_u) < 1e-3 and abs(d_p) * S < 1e-3:  # 1 us
            break
    return SymbolClock(uc - kc * p, p), used
