"""One packet, from a luminance buffer and a header candidate to decided levels and CRC.

:func:`demodulate_packet` is pure (no state between packets except what the caller passes
in: the expected symbol period and its uncertainty). Steps, for packet symbols
``0 .. 13 + K + F - 1`` (header, training, data):

1. Fine header phase (:func:`iscd.decode.comms.timing.fine_header`).
2. Clean frames of header and training -> channel model (:mod:`iscd.decode.comms.channel`);
   reject the candidate unless the training sequence is there (rank correlation of the
   training frames with the known training levels) and the header has contrast -- a false
   header (data that happens to look like Barker-13, noise) never becomes a packet.
3. Clock refinement on the known symbols (:func:`iscd.decode.comms.timing.refine_clock`).
4. Tracking pass: data decided in chunks; after each chunk the clock (phase and period,
   i.e. drift) is re-fitted on all symbols so far, decision-directed.
5. Final pass: channel re-estimated from all decided symbols (decision-directed, iscd
   rule), clock re-fitted on the whole packet, then ``ic_iterations`` decision passes with
   straddling frames cancelled against the neighbours' decisions.
6. Levels -> Gray demapping -> CRC-32 (:meth:`iscd.core.airinterface.AirInterface.decode_data`).

The dissertation's rule (``rule = "dissertation" | "left" | "right"``) uses the same timing
(the dissertation does not say how it finds it) but its own channel factors from the
training only (3.11 / 4.2) and the clean-frame Euclidean decision (3.12 / 4.3).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from iscd.core.airinterface import CRC_BYTES, HEADER_SYMBOLS, AirInterface
from iscd.core.airinterface_v2 import AirInterfaceV2
from iscd.core.jit import njit, register_warm
from iscd.decode.comms.channel import (ChannelModel, ChannelTrack, IscdChannelSettings, _iscd_camera,
                                   _select_kth, estimate_dissertation, estimate_iscd)
from iscd.decode.comms.crosstalk import MIN_CROSSTALK, cancel_crosstalk, estimate_crosstalk, grid_neighbours
from iscd.decode.comms.decide import CleanCosts, SpanDecision, clean_costs, clean_levels, decide_span
from iscd.decode.comms.phy import INCOMPLETE, erasure_masks, read_phy_header
from iscd.decode.comms.sequential import BEAM, KAPPA, P0, RHO, sequential_levels
from iscd.decode.comms.settings import ReceiverConfig
from iscd.decode.comms.timing import (SymbolClock, _clip, _map_one, clean_frame, fine_header, period_sigma,
                                      refine_clock)


@dataclass
class PacketResult:
    """A demodulated packet (frame positions relative to the buffer passed in).

    u0: header start, frames; p: symbol period, frames; first_frame: the clean frame of
    the first header symbol; levels: (F, N) decided data levels 1..M; raw: the decoded
    payload bytes -- untrusted unless crc_ok; margins: (F, N) decision margins.
    """

    u0: float
    p: float
    first_frame: int
    levels: np.ndarray
    raw: bytes
    crc_ok: bool
    drift_ppm: float
    header_r2: float
    training_rho: float
    contrast: float
    margins: np.ndarray = field(repr=False)
    erasures: int = 0
    channel: str = "static"
    """``tracked`` (re-estimated along the packet), ``static`` (one channel per packet) or
    ``anchored`` (tracked backwards from the next packet's header, :func:`demodulate_anchored`)"""
    reason: str = ""
    """why a packet that failed its CRC could not be decoded (:func:`failure_reason`);
    empty when the CRC passed"""
    air: AirInterface | AirInterfaceV2 | None = field(default=None, repr=False)
    """the packet's geometry: the receiver's v1, or the v2 one its PHY header described"""
    corrected: int = 0
    """v2: bytes the Reed-Solomon code corrected"""
    failed_codewords: int = 0
    """v2: codewords beyond the code's reach (the packet is then failed)"""
    erased: int = 0
    """v2: bytes decoded as erasures (low-confidence symbols)"""
    p_sigma: float = float("nan")
    """how well the packet's frames pinned the period ``p``: its posterior RMS, frames
    (:func:`~iscd.decode.comms.timing.period_sigma`; NaN where the clock was not fitted)"""
    runner_up: np.ndarray | None = field(default=None, repr=False)
    """(F, N) levels 1..M second to ``levels`` in each decision (the level ``margins`` above
    it; :func:`~iscd.decode.comms.listdecode.list_decode` tries them)"""
    sequential: "PacketResult | None" = field(default=None, repr=False)
    """the failed attempt with the channel tracked symbol by symbol (:data:`SEQUENTIAL_RETRY`):
    not reported, but list-decoded after the others (:class:`~iscd.decode.comms.packets.PacketAssembler`).
    On that attempt's own result: its survivors' own decisions, where its final pass changed
    some (:func:`_survivors_own`; list-decoded after it)"""
    clock_fixed: bool = False
    """one LED: delivered demodulated again with the clock its failed attempts ended on held
    fixed (:class:`~iscd.decode.comms.packets.PacketAssembler`), after every other attempt failed"""
    phase_corrected: bool = False
    """one LED: delivered with the sub-pixel phase of its followed centres taken out of the
    luminance (:mod:`~iscd.decode.comms.pixelphase`), after every other attempt failed"""
    channel_smoothed: bool = False
    """one LED: delivered with its channel smoothed over the whole packet from a failed
    attempt's decisions (:mod:`~iscd.decode.comms.smoothing`), after every other attempt failed"""
    list_flips: int = 0
    """symbols that CRC-aided list decoding (:mod:`~iscd.decode.comms.listdecode`) changed from
    this attempt's decisions for the CRC to pass (0: as decided)"""

    @property
    def version(self) -> int:
        """Air interface version: 2 when a PHY header was read, else 1."""
        return 2 if isinstance(self.air, AirInterfaceV2) else 1

    def v2_fields(self) -> dict[str, int | str]:
        """``version``, ``fec``, ``corrected``, ``payload_len``, ``erased_bytes``,
        ``failed_codewords`` of a v2 packet (empty for v1: its records stay as they were)."""
        if not isinstance(self.air, AirInterfaceV2):
            return {}
        return {"version": 2, "fec": self.air.fec, "corrected": int(self.corrected),
                "payload_len": int(self.air.payload_len), "erased_bytes": int(self.erased),
                "failed_codewords": int(self.failed_codewords)}

    def quality(self) -> dict[str, float]:
        """Summary metrics (the receiver has no truth): margins and sync quality (and the
        v2 fields, :meth:`v2_fields`)."""
        mn, p01, med, weak = margin_summary(self.margins)
        return {**self.v2_fields(), "margin_min": mn, "margin_p01": p01, "margin_median": med, "weak_symbols": weak,
                "erasures": int(self.erasures), "drift_ppm": float(self.drift_ppm),
                "channel_tracked": self.channel in ("tracked", "anchored"),
                **({"channel_anchored": True} if self.channel == "anchored" else {}),
                **({"list_flips": int(self.list_flips)} if self.list_flips else {}),
                **({"clock_fixed": True} if self.clock_fixed else {}),
                **({"phase_corrected": True} if self.phase_corrected else {}),
                **({"channel_smoothed": True} if self.channel_smoothed else {}),
                "header_r2": float(self.header_r2), "training_rho": float(self.training_rho),
                "contrast": float(self.contrast),
                **({"reason": self.reason} if not self.crc_ok and self.reason else {})}


def margin_summary(m: np.ndarray) -> tuple[float, float, float, int]:
    """``m.min()``, ``np.percentile(m, 1)``, ``np.median(m)`` (0.0 each when m is empty) and
    ``(m < 4).sum()`` of decision margins, exactly: for finite non-negative float64 margins
    the order statistics come from :func:`_order_stats` (a histogram of the values' leading
    bits, then selection within the few buckets that hold them) and numpy's interpolation
    rule is applied to them; otherwise numpy's own functions.

    Parameters
    ----------
    m : ndarray
        Decision margins, any shape.

    Returns
    -------
    tuple
        (min, 1st percentile, median, count below 4).
    """
    n = m.size
    if n == 0:
        return 0.0, 0.0, 0.0, int((m < 4.0).sum())
    if m.dtype == np.float64:
        q = np.true_divide(1, 100)
        v = (n - 1) * q  # numpy's virtual index, method "linear"
        if v >= n - 1:
            ip, i_prev, i_next = -1, n - 1, n - 1
        elif v < 0:
            ip, i_prev, i_next = 0, 0, 0
        else:
            ip = int(np.floor(v))
            i_prev, i_next = ip, ip + 1
        gamma = float(v - ip)
        ks = np.array([i_prev, i_next, (n - 1) // 2, n // 2], dtype=np.int64)
        vals, ok, mn, weak = _order_stats(np.ascontiguousarray(m).reshape(-1), ks)
        if ok:
            a, b = vals[0], vals[1]
            diff = b - a
            p01 = b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma
            med = vals[2] if n % 2 else (vals[2] + vals[3]) / 2
            return float(mn), float(p01), float(med), int(weak)
    return (float(m.min()), float(np.percentile(m, 1)), float(np.median(m)), int((m < 4.0).sum()))


@njit(warm=lambda: (np.arange(5.0), np.array([0, 1, 2, 2], np.int64)), error_model="numpy")
def _order_stats(x: np.ndarray, ks: np.ndarray) -> tuple[np.ndarray, bool, float, int]:
    """The ks-th smallest values of x (1-D float64), its minimum and how many are below 4,
    when every value is finite and non-negative (else ok = False): a histogram of the
    values' top 16 bits (monotonic in the value), then selection among the values of the
    buckets that hold the wanted ranks only."""
    n = x.size
    K = ks.size
    vals = np.zeros(K)
    bits = x.view(np.int64)
    NB = 1 << 15
    hist = np.zeros(NB, np.int64)
    lo_b = NB
    hi_b = -1
    mn = np.inf
    weak = 0
    bad = False
    for j in range(n):
        b = bits[j]
        bad = bad or b < 0 or b >= 0x7FF0000000000000  # sign bit (negative, -0), inf, NaN
        hb = (b >> 48) & (NB - 1)
        hist[hb] += 1
        lo_b = min(lo_b, hb)
        hi_b = max(hi_b, hb)
        v = x[j]
        mn = v if v < mn else mn
        weak += 1 if v < 4.0 else 0
    if bad:
        return vals, False, 0.0, 0
    tb = np.empty(K, np.int64)  # each rank's bucket and its rank within the bucket
    rk = np.empty(K, np.int64)
    for s in range(K):
        acc = 0
        for hb in range(lo_b, hi_b + 1):
            if acc + hist[hb] > ks[s]:
                tb[s] = hb
                rk[s] = ks[s] - acc
                break
            acc += hist[hb]
    off = np.zeros(K + 1, np.int64)  # buffer of each distinct bucket (first use of it)
    first = np.empty(K, np.int64)
    for s in range(K):
        first[s] = s
        for t in range(s):
            if tb[t] == tb[s]:
                first[s] = first[t]
                break
        off[s + 1] = off[s] + (hist[tb[s]] if first[s] == s else 0)
    buf = np.empty(off[K])
    fill = off[:K].copy()
    for j in range(n):
        hb = bits[j] >> 48
        for s in range(K):
            if first[s] == s and hb == tb[s]:
                buf[fill[s]] = x[j]
                fill[s] += 1
    for s in range(K):
        f = first[s]
        vals[s] = _select_kth(buf, off[f], off[f] + hist[tb[s]], off[f] + rk[s])
    return vals, True, mn, weak


@dataclass
class Rejection:
    """Why a header candidate did not become a packet."""

    u0: float
    reason: str
    need_frames: float | None = None
    """with ``incomplete``: the buffer rows the packet needs when its PHY header told its
    length (None: not known)"""

    @property
    def incomplete(self) -> bool:
        """The packet's frames are not all in the buffer yet (not a verdict)."""
        return self.reason == "incomplete"


SEPARATION_MIN = 6.0
"""Adjacent levels whose centroids lie fewer noise RMS apart than this are called
indistinguishable by :func:`failure_reason`: with Gaussian noise a symbol between them is
wrong with probability 2 Q(6 / 2) = 0.27 %, one or more errors in a few hundred symbols."""

WEAK_MARGIN = 4.0
"""A decision margin below this is a weak symbol (as :meth:`PacketResult.quality` counts)."""


def level_separation(model: ChannelModel) -> np.ndarray:
    """(C, N, M - 1) distance of adjacent level centroids in noise RMS units.

    ``(mu_s+1 - mu_s) / sqrt((var_s + var_s+1) / 2)`` per camera and LED.

    Parameters
    ----------
    model : ChannelModel
        Centroids (C, N, M), DN, and variances, DN^2.

    Returns
    -------
    ndarray of float64
        (C, N, M - 1) separations, noise RMS.
    """
    sd = np.sqrt(0.5 * (model.var[..., 1:] + model.var[..., :-1]))
    return (model.mu[..., 1:] - model.mu[..., :-1]) / np.maximum(sd, 1e-9)


def failure_reason(models: list[ChannelModel], margins: np.ndarray) -> str:
    """Why a packet failed its CRC, from the receiver's own channel estimates: one line.

    * ``"saturated"`` -- in every camera some LED's upper levels (above M / 2) lie closer
      than :data:`SEPARATION_MIN` noise RMS *and* their centroids are squeezed together,
      less than :data:`CLIP_SQUEEZE` of the lower levels' spacing in DN: its spot clips
      (too close, or too bright for both apertures) and its levels live only in the wings;
    * ``"low light"`` -- in every camera some LED's adjacent levels lie closer than
      :data:`SEPARATION_MIN` noise RMS without that squeeze: evenly spaced levels too few
      DN apart for the noise (too far, too dim; one LED at 100 m: 4 DN apart in an f/4
      camera with 0.5-1 DN of noise, the upper levels' shot noise the larger);
    * ``"weak decisions"`` -- the levels are apart but many decisions are weak (noise,
      motion, timing);
    * otherwise ``"few symbol errors"`` -- a handful of wrong symbols (v1 has no FEC).

    The worst stretch of the packet counts.

    Parameters
    ----------
    models : list of ChannelModel
        The channel of each stretch of the packet.
    margins : ndarray
        The packet's decision margins (cost gap to the runner-up), any shape; below
        :data:`WEAK_MARGIN` is weak.

    Returns
    -------
    str
        The reason, starting with one of the four labels above, with the count of weak
        decisions.
    """
    n_weak = int((margins < WEAK_MARGIN).sum()) if margins.size else 0
    detail = f"{n_weak} of {margins.size} decisions weak"
    noisy = [m for m in models if m.kind != "euclid"]  # (the dissertation's rule has no variances)
    if not noisy:
        return f"weak decisions: {detail}" if n_weak > 0.02 * max(margins.size, 1) else f"few symbol errors: {detail}"
    M1 = noisy[0].mu.shape[-1] - 1
    half = M1 // 2
    clipped = np.zeros((noisy[0].mu.shape[0], M1 - half), dtype=bool)  # (C, upper gaps): in any LED, stretch
    overlap = np.zeros(noisy[0].mu.shape[0], dtype=bool)  # (C,)
    for m in noisy:
        sep = level_separation(m)  # (C, N, M - 1), noise RMS
        gap = np.diff(m.mu, axis=-1)  # DN
        lower = np.median(gap[..., :half], axis=-1, keepdims=True) if half else np.full(gap.shape[:-1] + (1,), np.inf)
        close = sep < SEPARATION_MIN
        clipped |= (close[..., half:] & (gap[..., half:] < CLIP_SQUEEZE * lower)).any(axis=1)
        overlap |= close.any(axis=(1, 2))
    if clipped.any(axis=-1).all():
        lo = int(np.argmax(clipped.any(axis=0))) + half + 1
        return f"saturated: levels {lo}-{M1 + 1} overlap in every camera (too close or too bright); {detail}"
    if overlap.all():
        return f"low light: adjacent levels overlap in every camera (too far or too dim); {detail}"
    if margins.size and n_weak > 0.02 * margins.size:
        return f"weak decisions: {detail}"
    return f"few symbol errors: {detail}"


CLIP_SQUEEZE = 0.5
"""Upper levels whose centroids lie closer than this share of the lower levels' median
spacing (DN) are squeezed by clipping (:func:`failure_reason`); PWM light is linear in the
level, so an unclipped LED's levels are evenly spaced in DN whatever the noise."""


def known_levels(air: AirInterface | AirInterfaceV2) -> np.ndarray:
    """0-based levels (13 + K, N) of header and training (v2: (13 + H + K, N), the PHY
    header included).

    Parameters
    ----------
    air : AirInterface or AirInterfaceV2
        The air interface (M, N, K).

    Returns
    -------
    ndarray of int64
        (13 + K, N) levels 0 .. M-1, symbol time major.
    """
    return np.concatenate([air.header(), air.training()]).astype(np.int64) - 1


def clean_samples(L: np.ndarray, clock: SymbolClock, e: float, lev: np.ndarray, k_first: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Clean-frame luminance (C, n_s, N) of packet symbols ``k_first ..`` and their levels.

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance of the buffer's frames, DN.
    clock : SymbolClock
        The packet's symbol clock, frames.
    e : float
        Exposure window length, frames (exposure_s * fps).
    lev : ndarray
        (S, N) 0-based levels of packet symbols ``k_first .. k_first + S - 1``.
    k_first : int
        Packet symbol of ``lev[0]``, symbols.

    Returns
    -------
    y : ndarray
        (C, n_s, N) luminance of the clean frames of those symbols, DN.
    lev : ndarray
        (n_s, N) the level of each of those frames.
    """
    frames, kr = _clean_index(L.shape[1], float(clock.u0), float(clock.p), float(e), int(k_first),
                              int(lev.shape[0]))
    return L[:, frames, :], lev[kr]


def clean_index(n: int, clock: SymbolClock, e: float, S: int) -> tuple[np.ndarray, np.ndarray]:
    """The clean frames of packet symbols 0 .. S-1 within a buffer of ``n`` frames and the
    symbol of each (:func:`clean_samples` without the luminance), frame order.

    Parameters
    ----------
    n : int
        Frames in the buffer.
    clock : SymbolClock
        The packet's symbol clock, frames.
    e : float
        Exposure window length, frames.
    S : int
        Symbols.

    Returns
    -------
    frames : ndarray of int64
        Buffer rows.
    k : ndarray of int64
        Their symbols, 0 .. S-1.
    """
    return _clean_index(int(n), float(clock.u0), float(clock.p), float(e), 0, int(S))


@njit(warm=lambda: (10, 0.3, 2.0, 1.0, 0, 3), error_model="numpy")
def _clean_index(n: int, u0: float, p: float, e: float, k_first: int, S: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The clean frames (of n buffer frames) of packet symbols k_first .. k_first + S - 1
    and their symbols relative to k_first, in frame order (:func:`clean_samples`: the same
    float64 operations as ``clock.boundary`` and :func:`frame_map`)."""
    lo = int(max(0.0, np.floor(u0 + float(k_first) * p)))
    hi = int(min(float(n), np.ceil(u0 + float(k_first + S) * p) + 1))
    m = max(hi - lo, 0)
    frames = np.empty(m, np.int64)
    kr = np.empty(m, np.int64)
    j = 0
    for fr in range(lo, hi):
        k, alpha = _map_one(fr, u0, p, e)
        if alpha >= 1.0 and k >= k_first and k < k_first + S:
            frames[j] = fr
            kr[j] = k - k_first
            j += 1
    return frames[:j], kr[:j]


@njit(inline="always")
def _gather_y(L: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """float64 (C, len(frames), N) copy of L[:, frames, :]."""
    C, _, N = L.shape
    m = frames.size
    y = np.empty((C, m, N))
    for c in range(C):
        for j in range(m):
            fr = frames[j]
            for i in range(N):
                y[c, j, i] = L[c, fr, i]
    return y


def _warm_fit() -> tuple:
    L = np.ones((2, 14, 3))[:, :12]
    return (L, 0.3, 2.0, 1.0, np.zeros((6, 3), np.int64), 0, 3, 4.0, 3.0, 10.0, 10.0, 0.3, 6.0)


@njit(warm=_warm_fit, error_model="numpy")
def _fit_kernel(L: np.ndarray, u0: float, p: float, e: float, lev: np.ndarray, k_first: int, M: int,
                led_prior: float, level_prior: float, var_prior: float, led_var_prior: float,
                var_floor_dn: float, outlier_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_fit` in one call: the clean samples of packet symbols k_first .. k_first + S - 1
    (lev (S, N) int64, :func:`clean_samples`), then :func:`estimate_iscd` per camera
    (centroids and variances (C, N, M))."""
    C, n, N = L.shape
    frames, kr = _clean_index(n, u0, p, e, k_first, lev.shape[0])
    y = _gather_y(L, frames)
    lv = np.empty((frames.size, N), np.int64)
    for j in range(frames.size):
        for i in range(N):
            lv[j, i] = lev[kr[j], i]
    mu = np.zeros((C, N, M))
    var = np.full((C, N, M), 1e12)
    for c in range(C):
        ok, mu_c, var_c = _iscd_camera(y[c], lv, M, led_prior, level_prior, var_prior,
                                       led_var_prior, var_floor_dn, outlier_sigma)
        if ok:
            mu[c] = mu_c
            var[c] = var_c
    return mu, var


def _warm_fit_c() -> tuple:
    """:func:`_warm_fit` with a C-contiguous buffer (one camera, or a full buffer)."""
    a = _warm_fit()
    return (np.ascontiguousarray(a[0]),) + a[1:]


register_warm(_fit_kernel, _warm_fit_c)


def _warm_gain_samples() -> tuple:
    return (np.ones((2, 14, 3))[:, :12], 0.3, 2.0, 1.0, 0, 3, 1024)


@njit(warm=_warm_gain_samples, error_model="numpy")
def _gain_samples(L: np.ndarray, u0: float, p: float, e: float, k_a: int, S: int, most: int
                  ) -> tuple[np.ndarray, int, np.ndarray]:
    """:func:`_match_gain`'s samples: the clean frames of packet symbols k_a .. k_a + S - 1
    (float64 (C, n, N)), every k-th when there are more than ``most`` per camera; the
    number before thinning, and per camera whether any is finite."""
    C, n, N = L.shape
    frames, _ = _clean_index(n, u0, p, e, k_a, S)
    m = frames.size
    if m * N > most:
        step = int(np.ceil(m * N / most))
        frames = frames[::step].copy()
    y = _gather_y(L, frames)
    has = np.zeros(C, np.bool_)
    for c in range(C):
        for j in range(frames.size):
            for i in range(N):
                if np.isfinite(y[c, j, i]):
                    has[c] = True
                    break
            if has[c]:
                break
    return y, m, has


def _warm_gain_samples_c() -> tuple:
    a = _warm_gain_samples()
    return (np.ascontiguousarray(a[0]),) + a[1:]


register_warm(_gain_samples, _warm_gain_samples_c)


def _camera_tops(L: np.ndarray) -> np.ndarray:
    """Per camera of L (C, n, N): ``nanmax`` when any value is finite, else NaN (numpy's
    vectorized ``fmax`` over the camera's values; the finite test only when that is +inf)."""
    out = np.full(L.shape[0], np.nan)
    for c in range(L.shape[0]):
        Lc = L[c]
        if Lc.size == 0:
            continue
        m = float(np.fmax.reduce(Lc, axis=None))  # NaN-skipping maximum, infinities included
        if math.isfinite(m) or (m == math.inf and bool(np.isfinite(Lc).any())):
            out[c] = m
    return out


def rankdata(a: np.ndarray) -> np.ndarray:
    """Ranks (1..n, ties averaged) along axis 0 of a 2-D array, like scipy's rankdata.

    Parameters
    ----------
    a : ndarray
        (n, m) values.

    Returns
    -------
    ndarray of float64
        (n, m) ranks of each column.
    """
    n, m = a.shape
    order = np.argsort(a, axis=0, kind="stable")
    srt = np.take_along_axis(a, order, axis=0)
    new = np.ones((n, m), bool)
    new[1:] = srt[1:] != srt[:-1]
    grp = np.cumsum(new, axis=0) - 1 + (np.arange(m) * n)[None, :]  # global group ids
    pos = np.broadcast_to(np.arange(1, n + 1, dtype=np.float64)[:, None], (n, m))
    mean = np.bincount(grp.ravel(), pos.ravel(), minlength=n * m) / np.maximum(
        np.bincount(grp.ravel(), minlength=n * m), 1)
    ranks = np.empty((n, m))
    np.put_along_axis(ranks, order, mean[grp], axis=0)
    return ranks


def training_rank_correlation(y: np.ndarray, lev: np.ndarray) -> float:
    """Mean over LEDs and cameras of the Spearman correlation of clean training samples.

    Parameters
    ----------
    y : ndarray
        (C, n, N) clean-frame luminance of training symbols, DN (NaN = missing; columns with
        fewer than 4 values are skipped).
    lev : ndarray
        (n, N) their levels.

    Returns
    -------
    float
        Mean rank correlation, -1 .. 1; NaN when not computable (n < 4 or no usable column).
    """
    C, n, N = y.shape
    if n < 4:
        return float("nan")
    vals = []
    lr = rankdata(lev.astype(np.float64))
    lr = lr - lr.mean(0)
    for c in range(C):
        yc = y[c]
        ok = np.isfinite(yc).sum(0) >= 4
        if not ok.any():
            continue
        yo = yc[:, ok]
        fin = np.isfinite(yo)
        if fin.all():  # (the medians only fill gaps)
            yf = yo
        else:
            med = np.nanmedian(np.where(fin, yo, np.nan), axis=0)
            yf = np.where(fin, yo, med)
        yr = rankdata(yf)
        yr = yr - yr.mean(0)
        lo = lr[:, ok]
        den = np.sqrt((yr * yr).sum(0) * (lo * lo).sum(0))
        r = np.where(den > 0, (yr * lo).sum(0) / np.where(den > 0, den, 1.0), 0.0)
        vals.append(r)
    if not vals:
        return float("nan")
    return float(np.mean(np.concatenate(vals)))


def header_contrast(model: ChannelModel) -> float:
    """Median over LEDs of the best camera's (level M - level 1) / noise RMS.

    Parameters
    ----------
    model : ChannelModel
        Centroids (C, N, M), DN, and variances, DN^2.

    Returns
    -------
    float
        The contrast, noise RMS.
    """
    sd = np.sqrt(0.5 * (model.var[:, :, -1] + model.var[:, :, 0]))
    c = (model.mu[:, :, -1] - model.mu[:, :, 0]) / sd
    return float(np.median(c.max(0)))



@njit(warm=lambda: (np.ones((4, 3), np.uint8), 8, 3, 4), error_model="numpy")
def _pack_levels(levels: np.ndarray, M: int, k: int, n_bytes: int) -> np.ndarray:
    """The first n_bytes bytes of the Gray-coded bits (k per symbol, most significant
    first, symbol time major) of levels (F, N) 1..M (clipped): what
    :meth:`AirInterface.decode_data` packs, in one pass."""
    flat = levels.reshape(-1)
    out = np.zeros(n_bytes, np.uint8)
    acc = np.int64(0)  # pending bits, the oldest highest
    n_acc = 0
    o = 0
    for j in range(flat.size):
        l = min(max(np.int64(flat[j]), 1), M) - 1
        acc = ((acc << k) | (l ^ (l >> 1))) & 0xFFFF
        n_acc += k
        while n_acc >= 8:
            if o == n_bytes:
                return out
            n_acc -= 8
            out[o] = np.uint8((acc >> n_acc) & 0xFF)
            o += 1
    if o < n_bytes and n_acc > 0:  # the last bits, zero-padded (packbits)
        out[o] = np.uint8((acc << (8 - n_acc)) & 0xFF)
    return out


def decode_data(air: AirInterface, levels: np.ndarray) -> tuple[bytes, bool]:
    """:meth:`AirInterface.decode_data` (payload bytes and CRC verdict of decided levels
    (F, N) 1..M), compiled for the uint8 levels of :func:`demodulate_packet`.

    Parameters
    ----------
    air : AirInterface
        The air interface (M, N, F).
    levels : ndarray
        (F, N) decided data levels 1..M.

    Returns
    -------
    bytes, bool
        The payload (untrusted unless the CRC passed) and whether it did.
    """
    if levels.dtype != np.uint8 or levels.shape != (air.data_symbols, air.n_leds):
        return air.decode_data(levels)
    P = air.payload_bytes
    framed = _pack_levels(np.ascontiguousarray(levels), int(air.levels), int(air.bits_per_symbol),
                          P + CRC_BYTES).tobytes()
    body, crc = framed[:P], framed[P:]
    return body, zlib.crc32(body) == int.from_bytes(crc, "big")


def _segment_symbols(window: int) -> int:
    """Length of the stretches that share one channel model: a third of the window."""
    return max(8, window // 3)


def _tracking_step(window: int, n_leds: int) -> int:
    """Symbols the tracking pass decides with one model (fitted on the window's past half,
    its light matched to the step's own frames).

    For an array, half a final-pass stretch (at least 8): the model predicts ahead of the
    frames it was fitted on and the light match (:func:`_match_gain`) moves each camera's
    span, not one LED's offset, so the step bounds how far an LED's offset can move unseen:
    in a randomized 8x8 approach at 40 km/h (35 -> 25 m) an LED's level-1 light rose 30 DN,
    1.5 level spacings, within about 60 symbols; with steps of 64 the tracking slipped it one
    level up for the rest of the packet (the model then learns its own decisions), with steps
    of 16 it followed. For one LED the camera's span is the LED's own, the match follows it
    within the step, and the longer step (two stretches) is steadier: on randomized 100 km/h
    scenes steps of 16 cost single symbols that 64 did not (docs/receiver.md, "Tracking
    step")."""
    if n_leds == 1:
        return 2 * _segment_symbols(window)
    return _short_step(window)


def _short_step(window: int) -> int:
    """An array's tracking step (:func:`_tracking_step`): half a final-pass stretch, at
    least 8 symbols. One LED's packet that fails with its own step is tried once more with
    this one (:func:`demodulate_packet`)."""
    return max(8, _segment_symbols(window) // 2)


def _segments(k0: int, P: int, size: int) -> list[tuple[int, int]]:
    """Consecutive stretches [a, b) of at most ``size`` symbols covering k0 .. P - 1."""
    return [(a, min(P, a + size)) for a in range(k0, P, size)]


def _centred(a: int, b: int, W: int, P: int) -> tuple[int, int]:
    """Symbols [lo, hi) of a window of W symbols centred on [a, b), kept inside [0, P)."""
    if W <= 0 or W >= P:
        return 0, P
    lo = int(min(max(round((a + b - W) / 2), 0), P - W))  # (np.clip of Python ints)
    return lo, lo + W


def _fit(L: np.ndarray, clock: SymbolClock, e: float, lev: np.ndarray, lo: int, hi: int, M: int,
         st: IscdChannelSettings, cfg: ReceiverConfig) -> ChannelModel:
    """The iscd channel model from the labelled clean frames of packet symbols [lo, hi)."""
    lv = lev[lo:hi]
    if lv.dtype != np.int64 or not lv.flags.c_contiguous:
        lv = np.ascontiguousarray(lv, dtype=np.int64)
    mu, var = _fit_kernel(L, float(clock.u0), float(clock.p), float(e), lv, int(lo), int(M),
                          float(st.led_prior), float(st.level_prior), float(st.var_prior),
                          float(st.led_var_prior), float(st.var_floor_dn), float(st.outlier_sigma))
    return ChannelModel(mu=mu, var=var, kind=cfg.noise_model, nu=cfg.t_nu)



GAINS = np.exp(np.linspace(np.log(0.8), np.log(1.25), 11))
"""Relative gains tried by :func:`_match_gain` (4.5 % steps, refined by a parabola)."""

GAIN_SAMPLES = 1024
"""Most clean samples per camera :func:`_match_gain` fits (one number: plenty)."""


def _warm_gain() -> tuple:
    one = np.ones((2, 3), np.float32)
    return (np.ones((4, 3)), one[0], one, GAINS.astype(np.float32), np.float32(5.0), one, one)


@njit(warm=_warm_gain, error_model="numpy")
def _gain_costs(yc: np.ndarray, base: np.ndarray, span: np.ndarray, gains: np.ndarray,
                top: np.float32, var: np.ndarray, logvar: np.ndarray) -> np.ndarray:
    """Summed best-level Gaussian costs (G,) float64 of the samples yc (n, N) DN (NaN =
    missing: no cost) for each relative gain: centroids ``min(base + g span, top)`` with
    base (N,), span, var, logvar (M, N) float32 (:func:`_match_gain_reference`, element by
    element in float32; the sums in sample order, numpy's are pairwise: ~1e-15).

    Per gain, the centroids (M, N) once; per sample row, the best level of all N LEDs in
    branch-free loops over the LED axis (they vectorize), then the sum in sample order."""
    n, N = yc.shape
    M = span.shape[0]
    out = np.zeros(gains.size)
    mg = np.empty((M, N), np.float32)
    best = np.empty(N, np.float32)
    x32 = np.empty(N, np.float32)
    for g in range(gains.size):
        gg = gains[g]
        for s in range(M):
            srow = span[s]
            mrow = mg[s]
            for i in range(N):
                a = base[i] + gg * srow[i]
                mrow[i] = top if top < a else a
        tot = 0.0
        for t in range(n):
            yrow = yc[t]
            for i in range(N):
                x32[i] = np.float32(yrow[i])
            for s in range(M):
                mrow = mg[s]
                vrow = var[s]
                lrow = logvar[s]
                if s == 0:
                    for i in range(N):
                        d = x32[i] - mrow[i]
                        best[i] = d * d / vrow[i] + lrow[i]
                else:
                    for i in range(N):
                        d = x32[i] - mrow[i]
                        v = d * d / vrow[i] + lrow[i]
                        b = best[i]
                        best[i] = v if v < b else b
            for i in range(N):
                if np.isfinite(yrow[i]):
                    tot += np.float64(best[i])
        out[g] = tot
    return out


def _match_gain(model: ChannelModel, L: np.ndarray, clock: SymbolClock, e: float, lev: np.ndarray,
                k_a: int, k_b: int, tops: list[float] | None = None) -> ChannelModel:
    """``model`` with each camera's light scaled to fit the clean frames of the undecided
    stretch [k_a, k_b): per camera the gain g (centroids ``mu_1 + g (mu_s - mu_1)``, capped at
    the brightest value seen) whose best-level costs, summed over the stretch's symbols and
    LEDs, are least. Decision-free in the sense that every level competes for every
    sample: thousands of samples fix one number, so a stretch with some wrong decisions
    still gives the right gain. Follows an LED that brightens as the car closes in.

    tops: each camera's brightest value in L (DN; computed when not given). The costs come
    from the compiled :func:`_gain_costs`; :func:`_match_gain_reference` is the specification.
    """
    S = max(0, min(k_b, lev.shape[0]) - k_a)  # the symbols of lev[k_a:k_b]
    y, n_all, has = _gain_samples(L, float(clock.u0), float(clock.p), float(e), int(k_a), int(S),
                                  GAIN_SAMPLES)
    if n_all == 0:
        return model
    C = model.n_cams
    gs = np.zeros(C)
    if has.any():
        top = _camera_tops(L) if tops is None else np.asarray(tops, dtype=np.float64)
        var = np.ascontiguousarray(model.var.transpose(0, 2, 1), dtype=np.float32)  # (C, M, N)
        costs = _gain_costs_cams(y, model.mu, _GAINS32, top, var, np.log(var), has)
        for c in range(C):
            if not has[c]:
                continue
            cc = costs[c]
            b = int(np.argmin(cc))
            g = float(GAINS[b])
            if 0 < b < GAINS.size - 1:  # parabola through the best and its neighbours (log gain)
                den = cc[b - 1] - 2 * cc[b] + cc[b + 1]
                if den > 0:
                    g *= float(np.exp(_clip(0.5 * (cc[b - 1] - cc[b + 1]) / den, -0.5, 0.5) * _GAIN_STEP))
            gs[c] = g
        mu = _scale_light(model.mu, gs, top, has)
    else:
        mu = model.mu.copy()
    return ChannelModel(mu=mu, var=model.var, kind=model.kind, nu=model.nu)


_GAINS32 = GAINS.astype(np.float32)
_GAIN_STEP = float(np.log(GAINS[1] / GAINS[0]))


def _warm_gain_cams() -> tuple:
    one = np.ones((2, 3, 4), np.float32)
    return (np.ones((2, 5, 4)), np.ones((2, 4, 3)), _GAINS32, np.full(2, 5.0), one, one, np.ones(2, np.bool_))


@njit(warm=_warm_gain_cams, error_model="numpy")
def _gain_costs_cams(y: np.ndarray, mu: np.ndarray, gains: np.ndarray, tops: np.ndarray, var: np.ndarray,
                     logvar: np.ndarray, has: np.ndarray) -> np.ndarray:
    """:func:`_gain_costs` (G,) of each camera c with ``has[c]`` ((C, G); zeros for the
    others): samples y (C, n, N), centroids mu (C, N, M) float64 (base ``mu_1`` and span
    ``mu_s - mu_1`` cast to float32 as :func:`_match_gain_reference`), caps tops (C,),
    variances and their logs (C, M, N) float32."""
    C, N, M = mu.shape
    out = np.zeros((C, gains.size))
    base = np.empty(N, np.float32)
    span = np.empty((M, N), np.float32)
    for c in range(C):
        if not has[c]:
            continue
        for i in range(N):
            base[i] = np.float32(mu[c, i, 0])
            for s in range(M):
                span[s, i] = np.float32(mu[c, i, s] - mu[c, i, 0])
        out[c] = _gain_costs(y[c], base, span, gains, np.float32(tops[c]), var[c], logvar[c])
    return out


@njit(warm=lambda: (np.ones((2, 4, 3)), np.ones(2), np.full(2, 5.0), np.ones(2, np.bool_)),
      error_model="numpy")
def _scale_light(mu: np.ndarray, gs: np.ndarray, tops: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Centroids (C, N, M) with camera c's light scaled by gs[c] where ``use[c]``:
    ``min(mu_1 + g (mu_s - mu_1), max(top, max mu))`` (:func:`_match_gain`)."""
    C, N, M = mu.shape
    out = mu.copy()
    for c in range(C):
        if not use[c]:
            continue
        m = mu[c, 0, 0]
        for i in range(N):
            for s in range(M):
                m = max(m, mu[c, i, s])
        cap = m if m > tops[c] else tops[c]  # Python's max(top, m)
        g = gs[c]
        for i in range(N):
            m0 = mu[c, i, 0]
            for s in range(M):
                x = m0 + g * (mu[c, i, s] - m0)
                out[c, i, s] = np.nan if (np.isnan(x) or np.isnan(cap)) else min(x, cap)
    return out


def _match_gain_reference(model: ChannelModel, L: np.ndarray, clock: SymbolClock, e: float, lev: np.ndarray,
                k_a: int, k_b: int, tops: list[float] | None = None) -> ChannelModel:
    """Pure-numpy reference of :func:`_match_gain`: ``model`` with each camera's light scaled to fit the clean frames of the undecided
    stretch [k_a, k_b): per camera the gain g (centroids ``mu_1 + g (mu_s - mu_1)``, capped at
    the brightest value seen) whose best-level costs, summed over the stretch's symbols and
    LEDs, are least. Decision-free in the sense that every level competes for every
    sample: thousands of samples fix one number, so a stretch with some wrong decisions
    still gives the right gain. Follows an LED that brightens as the car closes in."""
    y, _ = clean_samples(L, clock, e, lev[k_a:k_b], k_a)
    if y.shape[1] == 0:
        return model
    if y.shape[1] * y.shape[2] > GAIN_SAMPLES:  # every k-th frame is enough
        y = y[:, ::int(np.ceil(y.shape[1] * y.shape[2] / GAIN_SAMPLES))]
    mu = model.mu.copy()
    G = GAINS.astype(np.float32)[None, :, None, None]  # (1, G, 1, 1)
    for c in range(model.n_cams):
        yc = y[c]  # (n, N)
        ok = np.isfinite(yc)
        if not ok.any():
            continue
        top = float(np.nanmax(L[c])) if tops is None else tops[c]
        base = model.mu[c, :, 0].astype(np.float32)  # (N,)
        span = (model.mu[c] - model.mu[c, :, :1]).T.astype(np.float32)  # (M, N)
        # levels first, so that the best level is an elementwise minimum of M arrays
        mu_g = np.minimum(base + G * span[:, None, None, :], np.float32(top))  # (M, G, 1, N)
        r2 = np.square(np.where(ok, yc, 0.0).astype(np.float32)[None, None] - mu_g)  # (M, G, n, N)
        # Gaussian costs (cheap; the gain is one number fitted to thousands of samples)
        var = model.var[c].T.astype(np.float32)[:, None, None, :]  # (M, 1, 1, N)
        r2 /= var
        r2 += np.log(var)
        best = r2[0].copy()  # (G, n, N); a loop of contiguous minima (faster than a reduce)
        for r in r2[1:]:
            np.minimum(best, r, out=best)
        best[:, ~ok] = 0.0
        costs = best.sum(axis=(1, 2), dtype=np.float64)
        b = int(np.argmin(costs))
        g = float(GAINS[b])
        if 0 < b < GAINS.size - 1:  # parabola through the best and its neighbours (log gain)
            den = costs[b - 1] - 2 * costs[b] + costs[b + 1]
            if den > 0:
                step = float(np.log(GAINS[1] / GAINS[0]))
                g *= float(np.exp(np.clip(0.5 * (costs[b - 1] - costs[b + 1]) / den, -0.5, 0.5) * step))
        mu[c] = np.minimum(model.mu[c, :, :1] + g * (model.mu[c] - model.mu[c, :, :1]),
                           max(top, float(model.mu[c].max())))
    return ChannelModel(mu=mu, var=model.var, kind=model.kind, nu=model.nu)


def _fit_segment(L: np.ndarray, clock: SymbolClock, e: float, lev: np.ndarray, a: int, b: int,
                 W: int, M: int, st: IscdChannelSettings, cfg: ReceiverConfig,
                 tops: list[float] | None = None) -> ChannelModel:
    """The channel of stretch [a, b): the model of the W symbols centred on it, its light
    matched to the stretch's own frames (:func:`_match_gain`: a window at the packet's
    ends is off-centre and lags)."""
    P = lev.shape[0]
    return _match_gain(_fit(L, clock, e, lev, *_centred(a, b, W, P), M, st, cfg), L, clock, e, lev, a, b,
                       tops)


def _track(segs: list[tuple[int, int]], models: list[ChannelModel]) -> ChannelTrack:
    """The models of consecutive stretches as a track (the first also holds for the
    header and training)."""
    return ChannelTrack((0,) + tuple(a for a, _ in segs[1:]), tuple(models))

REUSE_UNCHANGED = True
"""The final pass's later iterations reuse a stretch's decision when its inputs (channel
model, clean costs, the levels one symbol either side) are unchanged -- exactly what
deciding again would give (``tests/test_demod_reuse.py``); False decides every time."""

LOCKED_PPM = 30.0
"""A period prior at most this wide (ppm of the nominal period) is locked: the packet's
clock is fitted once over the whole packet, not re-fitted along it (:func:`_locked`)."""


def _locked(p_sigma: float, p_nominal: float) -> bool:
    """Whether a period prior of RMS ``p_sigma`` frames is locked (:data:`LOCKED_PPM`)."""
    return not p_sigma > LOCKED_PPM * 1e-6 * p_nominal  # (NaN: locked)


SHORT_STEP_RETRY = True
"""One LED's packet that every other attempt of :func:`demodulate_packet` failed is tried
once more with an array's tracking step (:func:`_short_step`); False skips that attempt (the
receiver before it: tests compare the two)."""

SEQUENTIAL_RETRY = True
"""One LED's packet that the attempts before it failed is tried once more with the tracking
pass deciding symbol by symbol, its centroids Kalman-filtered (:mod:`iscd.decode.comms.sequential`),
and the final pass's windows halved (the channel of a fast-changing approach); only a CRC
pass counts (its final pass's decisions, or the survivors' own where the final pass changed
some: :func:`_survivors_own`): a failure leaves the report as it was and rides along
(``PacketResult.sequential``) to be list-decoded last, the survivors' own decisions after it. Not run with an oracle's given channel (``channel=``: nothing to
follow). False skips it (tests compare the two)."""

SEQUENTIAL_MAX_LEDS = 1
"""Transmitters of at most this many LEDs get the :data:`SEQUENTIAL_RETRY` attempt: one LED.
On the three randomized 8x8 approaches that still lose a packet (seeds 1678105432,
1502534612, 1967368334: 113, 18 and 6 wrong symbols) the attempt for arrays changed none
of them (session 25), and an array's failed packet is costlier to demodulate again."""

UNLOCKED_RETRY = True
"""A packet whose period was locked on a delivered packet's, and which every other attempt
failed, is demodulated once more with the period free (:func:`demodulate_packet`,
``retry_unlocked``); False skips that attempt (tests compare the two)."""

ChannelOf = Callable[[SymbolClock, int, int], ChannelModel]
"""``channel(clock, a, b)``: a channel model for packet symbols [a, b) (an oracle's)."""


def demodulate_packet(L: np.ndarray, u_guess: float, air: AirInterface, e: float,
                      p_nominal: float, p_prior: float, p_sigma: float, cfg: ReceiverConfig,
                      *, clock: SymbolClock | None = None, channel: ChannelOf | None = None,
                      grid: tuple[int, int] | None = None, retry_unlocked: bool = False,
                      labels: np.ndarray | None = None) -> PacketResult | Rejection:
    """Demodulate the packet whose header starts near frame-unit time ``u_guess``.

    With ``channel_window_symbols`` the channel is first tracked along the packet; if that
    packet fails its CRC it is demodulated again with one channel for the whole packet
    (better at low SNR when nothing changes: every symbol estimates it), then with a
    tracking window :data:`WIDER_WINDOW` times longer, and the CRC decides which is
    delivered -- a valid CRC-32 from any of the three is still only a 2^-30 chance for a
    wrong packet. When all fail, the one with the largest mean decision margin is reported.

    An array (``grid``) whose first attempt fails is first tried again with its neighbours'
    light cancelled (:mod:`iscd.decode.comms.crosstalk`, estimated from that attempt's
    decisions) when the estimate says there is any (:data:`~iscd.decode.comms.crosstalk.MIN_CROSSTALK`);
    the two fallbacks then read the cancelled luminance. One LED's packet that all three
    fail is tried last with an array's shorter tracking step (:data:`SHORT_STEP_RETRY`):
    over ten randomized one-LED seed sets the two steps delivered the same number of
    packets, each losing marginal scenes the other kept (docs/receiver.md, "Tracking
    step"). Only a CRC pass of that attempt counts; its failure changes no report.

    With ``retry_unlocked`` (the caller's period prior came from a delivered packet), a
    packet whose period was locked (``p_sigma`` at most :data:`LOCKED_PPM`) and which every
    attempt above failed is demodulated once more as a first packet is, its period free
    within ``cfg.drift_max_ppm`` (the clock re-fitted along the packet, searching across the
    exposure gap): a delivered packet's period can be a few ppm off while its own spread
    said it was pinned (an 8x8 seed whose first packet came out at 179 ppm for a true 187 ppm
    lost its second packet's last 456 symbols to the lock). Again only a CRC pass counts.
    It costs one unlocked demodulation (0.9 s of CPU for an 8x8 packet, in the worker)
    and runs at most once per delivered packet: the prior after a failed packet is not
    a delivered one's.

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance of the selected cameras, DN (NaN = missing), covering the whole
        packet.
    u_guess : float
        Approximate header start (:func:`iscd.decode.comms.timing.coarse_header_search`), frames.
    air : AirInterface
        The air interface (M, N, K, F, G).
    e : float
        Exposure window length, frames (exposure_s * fps).
    p_nominal : float
        Nominal symbol period fps / symbol rate, frames.
    p_prior : float
        Expected symbol period, frames.
    p_sigma : float
        Its RMS uncertainty, frames.
    cfg : ReceiverConfig
        Receiver settings.
    clock : SymbolClock, optional
        Diagnosis hook (:mod:`iscd.eval.oracle`; the receiver never passes it): fixes the
        symbol clock (no fine phase, no clock fits; ``header_r2`` is NaN).
    channel : callable, optional
        Diagnosis hook: ``channel(clock, a, b)`` replaces every channel estimate of the iscd
        rule (verification, tracking and final pass) for the stretch [a, b) of packet
        symbols.
    grid : (int, int), optional
        (rows, cols) of an LED array whose LED i sits at row i // cols (N = rows * cols > 1):
        enables the crosstalk retry.
    retry_unlocked : bool
        ``p_prior`` is a delivered packet's period: a locked packet that fails is tried
        once more with the period free (above).
    labels : ndarray, optional
        Diagnosis hook (:mod:`iscd.eval.oracle`, ``+true labels``; the receiver never
        passes it): (P, N) 0-based levels of the packet's symbols (the truth) that every
        channel fit of the decision-directed estimate reads in place of the decisions;
        the estimator, its windows and the decisions are the receiver's own. What is then
        left of the errors is not decision feedback.

    Returns
    -------
    PacketResult or Rejection
        The decided levels and payload (``crc_ok``), or why the header candidate did not
        become a packet (``"incomplete"``: its frames are not all in ``L`` yet).

    References
    ----------
    Dissertation, eqs. (3.11), (4.2) and (3.12), (4.3) (the ``dissertation`` rule).
    """
    res = _demodulate(L, u_guess, air, e, p_nominal, p_prior, p_sigma, cfg, clock, channel, labels=labels)
    if isinstance(res, PacketResult) and not res.crc_ok and res.channel == "tracked":
        best = res
        W = cfg.channel_window_symbols
        Lx = _without_crosstalk(L, res, e, grid)
        if Lx is not None:
            alt = _demodulate(Lx, u_guess, air, e, p_nominal, p_prior, p_sigma, cfg, clock, channel, labels=labels)
            if isinstance(alt, PacketResult):
                if alt.crc_ok:
                    return alt
                if _mean_margin(alt) > _mean_margin(best):
                    best = alt
            L = Lx
        others = [0] + ([WIDER_WINDOW * W] if WIDER_WINDOW * W < res.air.packet_symbols else [])
        for w in others:
            alt = _demodulate(L, u_guess, air, e, p_nominal, p_prior, p_sigma,
                              replace(cfg, channel_window_symbols=w), clock, channel, labels=labels)
            if isinstance(alt, PacketResult):
                if alt.crc_ok:
                    return alt
                if _mean_margin(alt) > _mean_margin(best):
                    best = alt
        if SHORT_STEP_RETRY and res.air.n_leds == 1:
            # one LED: the array's shorter tracking step (a CRC pass only; a failure here
            # leaves the report as it was)
            alt = _demodulate(L, u_guess, air, e, p_nominal, p_prior, p_sigma, cfg, clock, channel,
                              tracking_step=_short_step(W), labels=labels)
            if isinstance(alt, PacketResult) and alt.crc_ok:
                return alt
        if SEQUENTIAL_RETRY and res.air.n_leds <= SEQUENTIAL_MAX_LEDS and channel is None:
            # one LED: the channel followed symbol by symbol, the final pass's stretches and
            # windows halved (a CRC pass only; an oracle's given channel has nothing to follow)
            alt = _demodulate(L, u_guess, air, e, p_nominal, p_prior, p_sigma,
                              replace(cfg, channel_window_symbols=max(1, W // 2)), clock, channel,
                              sequential=True, labels=labels)
            if isinstance(alt, PacketResult):
                if alt.crc_ok:
                    return alt
                own = alt.sequential  # the survivors' own decisions, where the final pass changed some
                if own is not None and own.crc_ok:
                    return own
                best = replace(best, sequential=alt)  # (list-decoded last, and its own; the report stays)
        wide = cfg.drift_max_ppm * 1e-6 * p_nominal
        if UNLOCKED_RETRY and retry_unlocked and clock is None and _locked(p_sigma, p_nominal) \
                and not _locked(wide, p_nominal):
            # last, the period as a first packet finds it: the lock is an assumption (the
            # last delivered packet's period), and a CRC failure is evidence against it
            alt = _demodulate(L, u_guess, air, e, p_nominal, p_prior, wide, cfg, clock, channel, labels=labels)
            if isinstance(alt, PacketResult) and alt.crc_ok:
                return alt
        return best
    return res


def demodulate_with_channel(L: np.ndarray, air: AirInterface, e: float, p_nominal: float, clock: SymbolClock,
                            cfg: ReceiverConfig, channel: ChannelOf) -> PacketResult | Rejection:
    """One attempt at a clock held fixed with every channel estimate given.

    The tracking pass and the final pass decide with ``channel(clock, a, b)`` for packet
    symbols [a, b) (stretches a third of ``cfg.channel_window_symbols``); no fallback. The
    smoothed-channel attempt of a failed one-LED packet (:mod:`~iscd.decode.comms.smoothing`)
    reads a packet so.

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance of the selected cameras, DN (NaN = missing), covering the packet.
    air : AirInterface
        The packet's geometry (v1).
    e : float
        Exposure window length, frames.
    p_nominal : float
        Nominal symbol period, frames.
    clock : SymbolClock
        The packet's clock (header start ``u0`` in buffer frames, period ``p``), held fixed.
    cfg : ReceiverConfig
        Receiver settings.
    channel : callable
        ``channel(clock, a, b) -> ChannelModel``.

    Returns
    -------
    PacketResult or Rejection
        As :func:`demodulate_packet`.
    """
    return _demodulate(L, clock.u0, air, e, p_nominal, clock.p, 20e-6 * p_nominal, cfg, clock, channel)


ANCHOR_RETRY = True
"""A packet that every attempt of :func:`demodulate_packet` failed is demodulated once more
when the frames after it are in (the :class:`~iscd.decode.comms.packets.PacketAssembler`
holds it back for them, about 13 + K symbols): :func:`demodulate_anchored`, the channel
tracked backwards from the next packet's header and training."""


def after_levels(air: AirInterface | AirInterfaceV2) -> np.ndarray:
    """0-based levels (G + 13 + K, N) of the symbols after a packet when another one like it
    follows: its G idle symbols (level 1), then the next packet's header and training (v2:
    its PHY header too, :func:`known_levels`).

    Parameters
    ----------
    air : AirInterface or AirInterfaceV2
        The packet's geometry.

    Returns
    -------
    ndarray of int64
        (G + 13 + K, N) levels 0 .. M-1, symbol time major.
    """
    idle = np.zeros((air.idle_symbols, air.n_leds), dtype=np.int64)
    return np.concatenate([idle, known_levels(air)])


def demodulate_anchored(L: np.ndarray, failed: PacketResult, e: float, p_nominal: float,
                        cfg: ReceiverConfig) -> PacketResult | Rejection:
    """A failed packet demodulated once more with the next packet's header and training as
    the anchor of its channel.

    Decision-directed tracking forwards from the training can slip: a stretch of wrong
    decisions that the window then learns carries the model one level off for the rest of
    the packet (a randomized 100 km/h approach, 100 -> 64 m: the packet's second half, 63
    wrong symbols, while the true channel per 96 symbols decodes it). The symbols after the
    packet are known when another packet follows (:func:`after_levels`), so the tracking pass
    here starts from them and runs backwards, each step decided with the model of the
    decided symbols after it; the final pass is the usual one, its windows near the packet's
    end holding the anchor. The clock starts from ``failed``'s (its period as a prior of at
    least 20 ppm RMS) and is re-fitted in the final pass. Only a CRC pass is worth anything
    (the caller keeps ``failed`` otherwise): one more 2^-32 chance for a wrong payload.

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance, DN (NaN = missing), covering the packet and the symbols after it
        (:func:`after_levels`) in the frame positions of ``failed``.
    failed : PacketResult
        The failed packet (its geometry ``air``, clock ``u0``, ``p`` and ``p_sigma``).
    e : float
        Exposure window length, frames (exposure_s * fps).
    p_nominal : float
        Nominal symbol period fps / symbol rate, frames.
    cfg : ReceiverConfig
        Receiver settings (a tracked channel: ``channel_window_symbols`` > 0, else the
        result is as :func:`demodulate_packet`'s static channel would be).

    Returns
    -------
    PacketResult or Rejection
        With ``channel = "anchored"``; a Rejection ``"incomplete"`` when ``L`` ends before
        the anchor's last symbol.
    """
    air = failed.air
    if air is None:
        raise ValueError("demodulate_anchored: the failed packet has no geometry (air)")
    floor = 20e-6 * p_nominal
    p_sigma = max(failed.p_sigma, floor) if np.isfinite(failed.p_sigma) else cfg.drift_max_ppm * 1e-6 * p_nominal
    p = failed.p if np.isfinite(failed.p) else p_nominal
    res = _demodulate(L, failed.u0, air, e, p_nominal, p, p_sigma, cfg, after=after_levels(air))
    if isinstance(res, PacketResult) and res.channel == "tracked":
        res.channel = "anchored"
    return res


WIDER_WINDOW = 2
"""A packet whose tracked channel fails its CRC, and again with one channel for the whole
packet, is tried once more with a window this many times longer (when that is still shorter
than the packet): decision-directed tracking can be derailed mid-packet by a stretch of wrong
decisions that its own window then learns (a randomized 40 km/h scene closing 35 -> 25 m:
90 wrong symbols from the packet's middle on with 96 symbols, none with 192), while one
channel for the whole packet cannot follow the light growing 2x. The CRC decides, as between
the first two (each attempt a 2^-32 chance of passing a wrong packet)."""


def _without_crosstalk(L: np.ndarray, res: PacketResult, e: float, grid: tuple[int, int] | None
                       ) -> np.ndarray | None:
    """``L`` with the array's neighbours' light cancelled, estimated from the data decided
    in ``res`` (:mod:`iscd.decode.comms.crosstalk`); None for one LED, without a grid, or
    when no camera shows :data:`~iscd.decode.comms.crosstalk.MIN_CROSSTALK`."""
    air = res.air
    N = air.n_leds
    if grid is None or N < 2 or grid[0] * grid[1] != N or res.levels.shape != (air.data_symbols, N):
        return None
    nb = grid_neighbours(*grid)
    k0 = air.data_offset
    lev = res.levels.astype(np.int64) - 1
    y, lv = clean_samples(L, SymbolClock(res.u0, res.p), e, lev, k0)
    coef = estimate_crosstalk(y, lv, int(air.levels), nb)
    if not np.nanmax(np.abs(coef)) >= MIN_CROSSTALK:
        return None
    return cancel_crosstalk(L, coef, nb)


def _mean_margin(res: PacketResult) -> float:
    """Mean decision margin of a packet (which of the failed attempts fits best)."""
    return float(np.mean(res.margins)) if res.margins.size else 0.0


def _demodulate(L: np.ndarray, u_guess: float, air: AirInterface, e: float,
                p_nominal: float, p_prior: float, p_sigma: float, cfg: ReceiverConfig,
                fixed_clock: SymbolClock | None = None, channel: ChannelOf | None = None,
                tracking_step: int | None = None, after: np.ndarray | None = None,
                sequential: bool = False, labels: np.ndarray | None = None) -> PacketResult | Rejection:
    """One demodulation attempt (:func:`demodulate_packet`), channel as ``cfg`` says
    (``tracking_step``: the tracking pass's step, symbols, instead of :func:`_tracking_step`'s;
    ``sequential``: the tracking pass decides symbol by symbol, the centroids following each
    decision (:func:`~iscd.decode.comms.sequential.sequential_levels`; a tracked channel);
    ``after``: the 0-based levels (A, N) of the A symbols right after the packet, known --
    :func:`demodulate_anchored`: ``L`` must cover them, the tracked channel's tracking pass
    runs backwards from them and the final pass fits them too; ``labels``: the
    :func:`demodulate_packet` diagnosis hook, the packet's true levels for every channel fit)."""
    C, n, N = L.shape
    st = IscdChannelSettings(var_floor_dn=cfg.var_floor_dn)
    kind = cfg.noise_model
    ts = cfg.timing_sigma_frames

    if fixed_clock is None:
        u0, r2 = fine_header(L, u_guess, p_prior, e)
        clock = SymbolClock(u0, p_prior)
    else:
        clock, u0, r2 = fixed_clock, fixed_clock.u0, float("nan")
    if not isinstance(air, AirInterfaceV2) and cfg.air_v2:  # v2 says what it is after the Barker
        hdr = read_phy_header(L, clock, e)
        if hdr == INCOMPLETE:
            # the frames of a v2 header are not all in, yet the caller has those of a whole v1
            # packet (few LEDs: H > 13 + K + F): decoded as v1, as a v1 receiver always did
            # (a v2 packet is then seen only by a receiver whose v1 packet is not shorter)
            return _demodulate(L, u_guess, air, e, p_nominal, p_prior, p_sigma, replace(cfg, air_v2=False),
                               fixed_clock, channel, tracking_step, labels=labels)
        if hdr is not None:
            air = AirInterfaceV2.from_header(hdr)  # type: ignore[arg-type]
    M = air.levels
    known = known_levels(air)
    n_known = known.shape[0]
    P = air.packet_symbols
    A = 0 if after is None else int(after.shape[0])
    last = clean_frame(np.array([P + A - 1]), clock, e)[0]  # the last symbol's clean frame
    if last + 1 > n:
        return Rejection(u0, "incomplete", last + 4 if isinstance(air, AirInterfaceV2) else None)
    y, lv = clean_samples(L, clock, e, known, 0)
    model = estimate_iscd(y, lv, M, st, kind, cfg.t_nu) if channel is None else channel(clock, 0, n_known)
    rho_t = float("nan")
    if air.training_symbols >= 4:
        yt, lt = clean_samples(L, clock, e, known[HEADER_SYMBOLS:], HEADER_SYMBOLS)
        rho_t = training_rank_correlation(yt, lt)
        # random data's mean rank correlation has RMS ~ 1/sqrt((n - 1) N): demand 4 of
        # them (at most 0.9: a short training cannot reject much, the CRC still does)
        n_eff = max(yt.shape[1] - 1, 1) * N
        need = max(cfg.training_rho, min(0.9, 4.0 / np.sqrt(n_eff)))
        if not rho_t >= need:
            return Rejection(u0, f"training sequence absent (rank correlation {rho_t:.2f})")
    contrast = header_contrast(model)
    if not contrast >= cfg.min_contrast:
        return Rejection(u0, f"header contrast {contrast:.1f} below {cfg.min_contrast}")

    # clock on the known symbols, then the channel again with the refined clock
    if fixed_clock is None:
        clock, _ = refine_clock(L, clock, e, known, 0, model, p_prior, p_sigma, timing_sigma=ts)
    y, lv = clean_samples(L, clock, e, known, 0)
    model = estimate_iscd(y, lv, M, st, kind, cfg.t_nu) if channel is None else channel(clock, 0, n_known)

    # tracking pass: data decided in stretches; with a tracked channel each stretch first
    # with the channel of the latest window, then again with the window that includes its
    # own tentative decisions; the clock re-fitted on everything decided so far every
    # ``chunk_symbols`` (a clock tracked over earlier packets needs no updates within this one)
    W = cfg.channel_window_symbols
    tracked = cfg.decision_directed and not cfg.dissertation and 0 < W < P
    # a period not yet known (a first packet): the clock is re-fitted every chunk, each time
    # searching both ends of the decided span across the exposure gap (timing.refine_clock)
    unlocked = not _locked(p_sigma, p_nominal)
    chunk = cfg.chunk_symbols if unlocked else P
    step = min(chunk, tracking_step or _tracking_step(W, N)) if tracked else chunk
    lev = np.full((P + A, N), -1, dtype=np.int64)
    lev[:n_known] = known
    if A:
        lev[P:] = after
    # what the channel fits read: the decisions (lev, updated in place), or the diagnosis
    # hook's true levels
    fit_lev = lev
    if labels is not None:
        if np.shape(labels) != (P, N):
            raise ValueError(f"labels: expected the packet's ({P}, {N}) levels, got shape {np.shape(labels)}")
        fit_lev = lev.copy()
        fit_lev[:P] = np.asarray(labels, dtype=np.int64)
    # each camera's brightest value in the buffer (the cap of _match_gain), once per packet
    tops = _camera_tops(L).tolist() if tracked else None  # (NaN: an absent camera, never used)
    starts, models = [0], [model]
    next_clock = n_known + chunk
    seq_own: np.ndarray | None = None
    if sequential and tracked and channel is None and not A:
        frames, kr = _clean_index(n, float(clock.u0), float(clock.p), float(e), n_known, P - n_known)
        f64 = np.ascontiguousarray  # (the warmed-up signature: C-contiguous float64)
        seq = sequential_levels(f64(L[:, frames, :], dtype=np.float64), kr, P - n_known,
                                f64(model.mu, dtype=np.float64), f64(model.var, dtype=np.float64), KAPPA, RHO, P0,
                                BEAM)
        for k in range(seq.shape[0]):  # a symbol without a clean frame: its predecessor's level
            gap = seq[k] < 0
            if gap.any():
                seq[k, gap] = seq[k - 1, gap] if k else 0
        lev[n_known:P] = seq
        seq_own = seq.copy()  # the survivors' own decisions (the final pass may change some)
    elif A and tracked and channel is None:
        # the known symbols after the packet anchor the channel: decided backwards from them,
        # each step with the model of the decided symbols after it (the clock as given:
        # the final pass re-fits it on the whole packet and the anchor)
        for k_b in range(P, n_known, -step):
            k_a = max(n_known, k_b - step)
            model = _fit(L, clock, e, fit_lev, k_b, min(P + A, k_b + W // 2), M, st, cfg)
            model = _match_gain(model, L, clock, e, lev, k_a, k_b, tops)
            lev[k_a:k_b] = clean_levels(clean_costs(L, clock, e, k_a, k_b, model).costs)
    else:
        for k_a in range(n_known, P, step):
            k_b = min(P, k_a + step)
            if tracked and channel is not None:
                model = channel(clock, k_a, k_b)
            elif tracked:
                model = _fit(L, clock, e, fit_lev, max(0, k_a - W // 2), k_a, M, st, cfg)
                model = _match_gain(model, L, clock, e, lev, k_a, k_b, tops)
            # (decide_span without straddling frames: the levels are all this pass keeps)
            lev[k_a:k_b] = clean_levels(clean_costs(L, clock, e, k_a, k_b, model).costs)
            if tracked:
                starts.append(k_a)
                models.append(model)
            if (k_b >= next_clock or k_b == P) and fixed_clock is None:
                next_clock += chunk
                clock, _ = refine_clock(L, clock, e, lev[:k_b], 0, ChannelTrack(tuple(starts), tuple(models)),
                                        p_prior, p_sigma, iters=2, timing_sigma=ts, search_ends=unlocked)

    # final pass
    p_post = float("nan")
    if cfg.dissertation:
        # channel factors from the training (3.11); without one, from the header's 1 and M
        k0 = HEADER_SYMBOLS if air.training_symbols else 0
        yt, lt = clean_samples(L, clock, e, known[k0:], k0)
        dmodel = estimate_dissertation(yt, lt, M)
        d = decide_span(L, clock, e, n_known, P, dmodel, None, 0, False, ts)
        lev[n_known:P] = d.levels
        margins, erasures = d.margin, int((d.n_obs == 0).sum())
        runner = d.runner_up
    else:
        segs = _segments(n_known, P, _segment_symbols(W) if tracked else P)
        models = [model]
        if channel is not None:
            models = [channel(clock, a, b) for a, b in segs]
        elif tracked:
            models = [_fit_segment(L, clock, e, fit_lev, a, b, W, M, st, cfg, tops) for a, b in segs]
        elif cfg.decision_directed:
            models = [_fit(L, clock, e, fit_lev, 0, P, M, st, cfg)]
        if cfg.decision_directed and fixed_clock is None:
            clock, _ = refine_clock(L, clock, e, lev, 0, _track(segs, models), p_prior, p_sigma,
                                    timing_sigma=ts, search_ends=True)
            p_post = period_sigma(L, clock, e, lev, 0, _track(segs, models), p_sigma, timing_sigma=ts)
        # after the packet: idle (level 1) if the packets have gaps, else the next header
        # (level M) or, when the transmission stops, darkness (level 1)
        edge = (0,) if air.idle_symbols else (0, M - 1)
        pre: list[CleanCosts | None] = [None] * len(segs)
        # per stretch the decision and the levels it was decided with (its own and one
        # symbol either side: the straddling frames' neighbours); a later pass whose
        # inputs are all unchanged would decide the same, so it reuses it (exact)
        seen: list[tuple[np.ndarray, SpanDecision] | None] = [None] * len(segs)
        before = lev.copy()
        for it in range(cfg.ic_iterations if cfg.straddle else 1):
            if it and tracked and channel is None:  # the channel again where the decisions changed
                changed = np.flatnonzero((lev != before).any(axis=1))
                before = lev.copy()
                for j, (a, b) in enumerate(segs):
                    lo, hi = _centred(a, b, W, P)
                    if changed.size and ((changed >= lo) & (changed < hi)).any():
                        models[j] = _fit_segment(L, clock, e, fit_lev, a, b, W, M, st, cfg, tops)
                        pre[j] = None
            parts = []
            for j, (a, b) in enumerate(segs):
                ctx_lv = lev[max(0, a - 1):min(P, b + 1)]
                hit = seen[j]
                if REUSE_UNCHANGED and pre[j] is not None and hit is not None and np.array_equal(hit[0], ctx_lv):
                    d = hit[1]
                else:
                    ctx_before = ctx_lv.copy()
                    if pre[j] is None:
                        pre[j] = clean_costs(L, clock, e, a, b, models[j])
                    d = decide_span(L, clock, e, a, b, models[j], lev, 0, cfg.straddle, ts,
                                    cfg.straddle_candidates, pre[j], edge)
                    seen[j] = (ctx_before, d)
                lev[a:b] = d.levels
                parts.append(d)
        margins = np.concatenate([d.margin for d in parts])
        runner = np.concatenate([d.runner_up for d in parts])
        erasures = int(sum((d.n_obs == 0).sum() for d in parts))
    levels = (lev[n_known:P] + 1).astype(np.uint8)
    v2 = {}
    if isinstance(air, AirInterfaceV2):  # de-interleave, Reed-Solomon (erasures from the margins), CRC-32
        unobserved = np.concatenate([d.n_obs for d in parts]) == 0 if not cfg.dissertation else d.n_obs == 0
        dres = air.decode_data(levels, erasure_masks(margins.reshape(levels.shape), unobserved.reshape(levels.shape)))
        raw, ok = dres.raw, dres.crc_ok
        v2 = dict(corrected=dres.corrected, failed_codewords=dres.failed_codewords, erased=dres.erased)
    else:
        raw, ok = decode_data(air, levels)
    first = int(clean_frame(np.array([0]), clock, e)[0])
    reason = "" if ok else failure_reason([dmodel] if cfg.dissertation else models, margins)
    if not ok and v2.get("failed_codewords"):
        reason = f"code failed: {v2['failed_codewords']} codewords; {reason}"
    res = PacketResult(u0=clock.u0, p=clock.p, first_frame=first, levels=levels, raw=raw,
                       crc_ok=bool(ok), drift_ppm=clock.drift_ppm(p_nominal),
                       header_r2=r2, training_rho=rho_t, contrast=contrast,
                       margins=margins, erasures=erasures,
                       channel="tracked" if tracked else "static", reason=reason, air=air,
                       p_sigma=p_post, runner_up=(runner + 1).astype(np.uint8), **v2)
    if seq_own is not None and not ok and not v2 and not cfg.dissertation:
        own = _survivors_own(res, seq_own, lev[n_known:P], [c for c in pre if c is not None])
        if own is not None:
            res = replace(res, sequential=own)
    return res


def _survivors_own(res: PacketResult, own: np.ndarray, final: np.ndarray, costs: list[CleanCosts]
                   ) -> PacketResult | None:
    """The sequential attempt's survivors' own decisions ``own`` (F, N) 0-based as a packet,
    where its final pass (``res``, decisions ``final``) changed some of them; None where it
    changed none. Reliabilities from the final pass: where the two agree, its margin and
    runner-up; where they differ, the gap between the two levels' clean-frame costs under
    the final pass's channel (``costs``, its stretches in order), and the final pass's level
    as the runner-up (as :func:`~iscd.decode.comms.listdecode.combine` has it)."""
    dis = own != final
    if not dis.any() or sum(c.costs.shape[0] for c in costs) != own.shape[0]:
        return None
    cc = np.concatenate([c.costs for c in costs], axis=0).astype(np.float64)  # (F, N, M)
    gap = np.abs(np.take_along_axis(cc, own[..., None], -1)[..., 0]
                 - np.take_along_axis(cc, final[..., None], -1)[..., 0])
    levels = (own + 1).astype(np.uint8)
    raw, ok = decode_data(res.air, levels)  # type: ignore[arg-type]
    runner = res.runner_up if res.runner_up is not None else levels
    return replace(res, levels=levels, raw=raw, crc_ok=bool(ok), reason="" if ok else res.reason,
                   margins=np.where(dis, gap, res.margins).astype(res.margins.dtype),
                   runner_up=np.where(dis, final + 1, runner).astype(np.uint8))

