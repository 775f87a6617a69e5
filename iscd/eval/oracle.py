"""Oracle decoding of a simulated recording: where the receiver's symbol errors come from.

The receiver (:class:`iscd.decode.stream.StreamDecoder`) runs on the rendered frames as in
``iscd eval``; then every transmitted packet is decoded again with parts of the receiver
replaced by the truth (:class:`iscd.sim.truth.Truth`), one stage after the other, so that
the symbol error rate (SER) splits into what each stage costs:

===========================  ===================================================================
stage                        what changes against the row above
===========================  ===================================================================
``receiver``                 nothing: the packets the decoder emits
``+true positions``          luminance measured at the true LED centres (truth ``u``/``v`` per
                             frame) with the receiver's own Gaussian window (its sigma, block by
                             block), on the frames the receiver decoded; then the receiver's
                             :class:`~iscd.decode.comms.packets.PacketAssembler` as is
                             -> what following the LEDs costs
``+true timing``             and the true symbol clock of the packet (truth ``symbol_t_s``; no
                             fine phase, no clock fit): :func:`demodulate_packet` ``clock=``
                             -> what the symbol timing costs
``+true channel``            and the channel from the truth: per stretch of 8 symbols the
                             receiver's channel estimate (:func:`estimate_iscd`) from the clean
                             frames of a short window centred on it labelled with the *true*
                             levels (it follows the light as the spot grows):
                             :func:`demodulate_packet` ``channel=`` -> what the channel
                             estimate costs; what is left is decision / noise floor
===========================  ===================================================================

Reference rows (not in the split): ``+true labels`` (``+true timing`` with the receiver's
own channel estimate -- its windows, stretches and light matching -- fitted on the *true*
levels instead of its decisions: ``demodulate_packet(labels=)``; against ``+true timing``
it shows what decision feedback costs, against ``+true channel`` what the estimator and its
windows cost); ``+true channel (one per packet)`` (true levels, one
channel for the whole packet, as the dissertation estimates it: shows how stale a channel
gets as the car closes in); ``genie luminance`` (a background-subtracted sum of the pixels
within the spot's radius ``R = f_px D / (2 Z)`` plus the PSF, at the true centres, the
background per pixel from the nearest frames in which every LED is dark; true timing, the
receiver's channel) and ``genie luminance +true channel``.

Per packet and stage the errors are also counted in ``bins`` equal stretches along the
data symbols (:func:`profile_bins`, in the air interface's data order: symbol time major),
so errors that grow along a packet show.

The split is over the packets every chain stage delivered a demodulation for (the
"common" packets): ``SER(receiver) = following + timing + channel + floor`` exactly (each
term a difference of SERs on the same symbols; a negative term means the truth made that
stage worse, e.g. a true clock that the channel estimate was not fitted to).

Units: positions px, times s (the symbol clock in frame units as in
:mod:`iscd.decode.comms.timing`), luminance DN (genie: DN summed over the window's pixels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from iscd.core.airinterface import AirInterface
from iscd.core.config import Config
from iscd.eval.metrics import match_packets
from iscd.eval.sweeps import (CommsResult, ReceiverMode, _blocks, _decoder_cfg, _num, _score,
                              frames_for_packets)
from iscd.decode.stream import StreamDecoder
from iscd.decode.comms.channel import ChannelModel, IscdChannelSettings, estimate_iscd
from iscd.decode.comms.demod import PacketResult, clean_samples, demodulate_packet, known_levels
from iscd.decode.tracking.luminance import gather_patches, gauss_mean
from iscd.decode.tracking.registered_background import MAX_SHIFT_PX
from iscd.decode.comms.packets import PacketAssembler
from iscd.decode.comms.settings import ReceiverConfig, receiver_config
from iscd.decode.comms.timing import SymbolClock
from iscd.sim.optics import PIXEL_VAR
from iscd.sim.scene import Scene
from iscd.sim.truth import Truth

CHAIN = ("receiver", "+true positions", "+true timing", "+true channel")
"""The stages of the split, each with one more part of the receiver replaced by the truth."""
REFERENCE = ("+true labels", "+true channel (one per packet)", "genie luminance", "genie luminance +true channel")
"""Reference decoders beside the chain (not in the split)."""
STAGES = CHAIN + REFERENCE
SPLIT = (("following", "receiver", "+true positions"), ("timing", "+true positions", "+true timing"),
         ("channel", "+true timing", "+true channel"))
"""(cost, stage without, stage with) of each replaced part."""
FLOOR = "decision/noise"
GENIE_WINDOWS = (32, 96, None)
"""True-level windows (symbols; None = the whole packet) of the ``+true channel`` estimate,
on 8-symbol stretches; per packet the one with the fewest errors counts (a short window
follows a growing spot but estimates from few samples: one LED has ~6 clean frames per
level in 32 symbols)."""
GENIE_STRETCH_WINDOW = 24
"""``channel_window_symbols`` given to the demodulator with the true channel: its stretches
are then a third of it, 8 symbols."""
WINDOW_TOLERANCE = 2e-3
"""Relative difference between the receiver's luminance and the oracle's reconstruction of
its window (at the receiver's own centres) above which a result notes it."""
DARK_NEIGHBOURS = 4
"""Dark frames (nearest in time) whose per-pixel median is the genie's background."""


# ----------------------------------------------------------------------------- pure parts

def profile_bins(F: int, N: int, bins: int) -> np.ndarray:
    """Bin of every data symbol of a packet along the packet.

    Data symbol ``j = t N + i`` (symbol time t, LED i; SPEC section 3) goes to bin
    ``j bins // (F N)``, so every data symbol is in exactly one bin and the bins hold
    F N / bins symbols each (+-1), in transmission order.

    Parameters
    ----------
    F : int
        Data symbol times per packet.
    N : int
        LEDs.
    bins : int
        Stretches along the packet.

    Returns
    -------
    numpy.ndarray
        (F, N) int64 bin indices 0 .. bins - 1.
    """
    if F < 1 or N < 1 or bins < 1:
        raise ValueError(f"profile_bins: F, N and bins must be >= 1, got {F}, {N}, {bins}")
    j = np.arange(F * N, dtype=np.int64)
    return (j * bins // (F * N)).reshape(F, N)


def error_profile(sent: np.ndarray, got: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Symbol errors and symbols per stretch along a packet's data.

    Parameters
    ----------
    sent, got : numpy.ndarray
        (F, N) levels 1..M of the data symbols, sent and decided.
    bins : int
        Stretches (:func:`profile_bins` says which symbol is in which).

    Returns
    -------
    errors, symbols : numpy.ndarray
        (bins,) int64 each.
    """
    s, g = np.asarray(sent), np.asarray(got)
    if s.shape != g.shape or s.ndim != 2:
        raise ValueError(f"sent {s.shape} and got {g.shape}: expected the same (F, N) shape")
    b = profile_bins(s.shape[0], s.shape[1], bins).ravel()
    err = np.bincount(b, weights=(s != g).ravel(), minlength=bins).astype(np.int64)
    return err, np.bincount(b, minlength=bins).astype(np.int64)


def true_clock(symbol_t_s: np.ndarray, fps: float, frame0: int = 0) -> SymbolClock:
    """The true symbol clock of a packet.

    The least-squares line ``u0 + k p`` through ``t_k fps - frame0`` (exact for a constant
    clock drift; frame n exposes from ``n / fps``).

    Parameters
    ----------
    symbol_t_s : numpy.ndarray
        (S,) true start times of the packet's symbols 0, 1, ..., s (camera clock).
    fps : float
        Frame rate, 1/s.
    frame0 : int
        The demodulation buffer's first frame.

    Returns
    -------
    SymbolClock
        ``u0`` and ``p`` in frame units relative to ``frame0`` (:mod:`iscd.decode.comms.timing`).
    """
    t = np.asarray(symbol_t_s, dtype=np.float64).reshape(-1)
    if t.size < 2:
        raise ValueError("true_clock: need the start times of at least two symbols")
    k = np.arange(t.size, dtype=np.float64)
    u = t * fps - frame0
    p, u0 = np.polyfit(k, u, 1)
    return SymbolClock(float(u0), float(p))


def true_centres(truth: Truth, side: int) -> np.ndarray:
    """True LED centres in every frame of ``truth``.

    Parameters
    ----------
    truth : Truth
        The recording's truth.
    side : int
        0 = left camera, 1 = right.

    Returns
    -------
    numpy.ndarray
        (F, N, 2) centres (x, y), px.
    """
    u, v = (truth.u_left, truth.v_left) if side == 0 else (truth.u_right, truth.v_right)
    return np.stack([u, v], axis=-1)


def spot_radius_px(cfg: Config, z_m: np.ndarray, side: int) -> np.ndarray:
    """Radius of the genie luminance window.

    The LED disc ``R = f_px D / (2 Z)`` plus twice the camera's blur (PSF sigma, the right
    camera's defocus, the pixel), at most half the LED pitch in the image (an array's
    neighbours), at least 1 px.

    Parameters
    ----------
    cfg : Config
        The scene's config (camera, optics, transmitter).
    z_m : numpy.ndarray
        (F,) distance per frame, m.
    side : int
        0 = left camera, 1 = right.

    Returns
    -------
    numpy.ndarray
        (F,) radius, px.
    """
    f_px = cfg.camera.focal_px
    z = np.asarray(z_m, dtype=np.float64)
    op = cfg.optics
    blur = math.sqrt(op.psf_sigma_px ** 2 + (op.right_defocus_px ** 2 if side == 1 else 0.0) + PIXEL_VAR)
    r = f_px * cfg.transmitter.led_diameter_m / (2.0 * z) + 2.0 * blur
    if cfg.transmitter.n_leds > 1:
        r = np.minimum(r, 0.5 * f_px * cfg.transmitter.pitch_m / z)
    return np.maximum(r, 1.0)


def genie_sum(frames: np.ndarray, centres: np.ndarray, radius_px: np.ndarray, background: np.ndarray
              ) -> np.ndarray:
    """Background-subtracted sum of the pixels within a radius of each LED centre.

    Parameters
    ----------
    frames : numpy.ndarray
        (F, H, W) images, DN.
    centres : numpy.ndarray
        (F, N, 2) LED centres (x, y), px.
    radius_px : numpy.ndarray
        (F,) window radius per frame, px (a pixel counts when its centre is inside).
    background : numpy.ndarray
        (F, H, W) per-pixel background of each frame, DN, on the same pixel grid.

    Returns
    -------
    numpy.ndarray
        (F, N) float64, DN summed over the window's pixels.
    """
    r = np.asarray(radius_px, dtype=np.float64).reshape(-1)
    half = int(np.ceil(r.max())) + 1
    p = gather_patches(frames, centres, half)
    q = gather_patches(background, centres, half)
    c = np.asarray(centres, dtype=np.float32)
    dx = p.xs - c[..., 0:1]  # (F, N, K)
    dy = p.ys - c[..., 1:2]
    inside = (dy[..., :, None] ** 2 + dx[..., None, :] ** 2) <= (r.astype(np.float32)[:, None, None, None] ** 2)
    return ((p.pix - q.pix) * inside).sum(axis=(-1, -2), dtype=np.float64)


def nearest_dark(dark: np.ndarray, frames: np.ndarray, k: int = DARK_NEIGHBOURS) -> np.ndarray:
    """The dark frames nearest in time to each frame.

    Parameters
    ----------
    dark : numpy.ndarray
        (D,) sorted frame numbers of frames in which every LED is dark.
    frames : numpy.ndarray
        (F,) frame numbers.
    k : int
        How many.

    Returns
    -------
    numpy.ndarray
        (F, min(k, D)) indices into ``dark``.
    """
    d = np.asarray(dark, dtype=np.float64)
    if d.size == 0:
        raise ValueError("nearest_dark: no dark frames")
    k = min(k, d.size)
    return np.argsort(np.abs(np.asarray(frames, dtype=np.float64)[:, None] - d[None, :]), axis=1,
                      kind="stable")[:, :k]


def genie_channel(L: np.ndarray, e: float, levels: np.ndarray, M: int, cfg: ReceiverConfig,
                  window: int | None = 32) -> Callable[[SymbolClock, int, int], ChannelModel]:
    """A channel from the truth for :func:`demodulate_packet`'s ``channel=``.

    For packet symbols [a, b): the receiver's estimate (:func:`estimate_iscd` with the
    receiver's settings) from the clean frames of the ``window`` symbols centred on [a, b),
    labelled with the true levels.

    Parameters
    ----------
    L : numpy.ndarray
        (C, n, N) the demodulation buffer's luminance, DN (NaN = missing).
    e : float
        Exposure, frames.
    levels : numpy.ndarray
        (P, N) true 0-based levels of the packet's symbols (header, training, data).
    M : int
        Levels.
    cfg : ReceiverConfig
        The receiver's settings (noise model, variance floor).
    window : int or None
        Symbols of the window; None = the whole packet (one channel).

    Returns
    -------
    callable
        ``channel(clock, a, b) -> ChannelModel``.
    """
    st = IscdChannelSettings(var_floor_dn=cfg.var_floor_dn)
    lev = np.asarray(levels, dtype=np.int64)
    P = lev.shape[0]

    def channel(clock: SymbolClock, a: int, b: int) -> ChannelModel:
        if window is None or window >= P:
            lo, hi = 0, P
        else:
            W = max(int(window), b - a)
            lo = int(np.clip(round((a + b - W) / 2), 0, P - W))
            hi = lo + W
        y, lv = clean_samples(L, clock, e, lev[lo:hi], lo)
        return estimate_iscd(y, lv, M, st, cfg.noise_model, cfg.t_nu)
    return channel


# ----------------------------------------------------------------------------- results

@dataclass
class StageScore:
    """One stage's decoding of one packet: ``found`` (the stage delivered a demodulation),
    ``crc_ok``, symbol ``errors`` of ``symbols`` data symbols, and per bin along the data
    ``profile_errors`` / ``profile_symbols`` (bins,)."""

    found: bool
    crc_ok: bool = False
    errors: int = 0
    symbols: int = 0
    profile_errors: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    profile_symbols: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def as_dict(self) -> dict[str, Any]:
        return {"found": self.found, "crc_ok": self.crc_ok, "errors": self.errors, "symbols": self.symbols,
                "profile_errors": self.profile_errors.tolist()}


@dataclass
class PacketOracle:
    """Every stage's decoding of transmitted packet ``index`` (``z_start_m`` /
    ``z_end_m``: the distance at its first and last frame, m)."""

    index: int
    z_start_m: float
    z_end_m: float
    stages: dict[str, StageScore] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"index": self.index, "z_start_m": self.z_start_m, "z_end_m": self.z_end_m,
                "stages": {k: v.as_dict() for k, v in self.stages.items()}}


@dataclass
class OracleResult:
    """The oracle decodings of one simulated recording (module docstring).

    ``receiver`` is the receiver scored as ``iscd eval`` scores it (packets found,
    delivered, SER); ``packets`` the per-packet stage scores of the whole transmitted
    packets; ``bins`` the profile bins; ``notes`` what was not possible."""

    receiver: CommsResult
    packets: list[PacketOracle]
    bins: int
    stages: tuple[str, ...] = STAGES
    notes: list[str] = field(default_factory=list)
    luminance: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    """(2, frames, N) per camera and frame (NaN = not measured), for plots: ``receiver``
    (what the decoder measured), ``true positions`` (its window at the true centres),
    ``genie`` (DN summed over the spot); not in :meth:`as_dict`, not kept by :func:`pool`."""

    def common(self) -> list[PacketOracle]:
        """The packets that every stage of the chain demodulated (the split's packets)."""
        return [p for p in self.packets if all(p.stages.get(s, StageScore(False)).found for s in CHAIN)]

    def _sel(self, stage: str, packets: Sequence[PacketOracle] | None) -> list[StageScore]:
        pk = self.common() if packets is None else packets
        return [p.stages[stage] for p in pk if stage in p.stages and p.stages[stage].found]

    def ser(self, stage: str, packets: Sequence[PacketOracle] | None = None) -> float:
        """SER of ``stage`` over ``packets`` (default :meth:`common`) it demodulated; NaN
        without any."""
        sc = self._sel(stage, packets)
        n = sum(s.symbols for s in sc)
        return sum(s.errors for s in sc) / n if n else float("nan")

    def counts(self, stage: str, packets: Sequence[PacketOracle] | None = None) -> tuple[int, int]:
        """(errors, symbols) of ``stage`` over ``packets`` (default :meth:`common`)."""
        sc = self._sel(stage, packets)
        return sum(s.errors for s in sc), sum(s.symbols for s in sc)

    def profile(self, stage: str, packets: Sequence[PacketOracle] | None = None) -> np.ndarray:
        """(bins,) SER per stretch along the data (NaN where nothing was demodulated)."""
        sc = self._sel(stage, packets)
        if not sc:
            return np.full(self.bins, np.nan)
        e = np.sum([s.profile_errors for s in sc], axis=0)
        n = np.sum([s.profile_symbols for s in sc], axis=0)
        return np.where(n > 0, e / np.maximum(n, 1), np.nan)

    def split(self) -> dict[str, float]:
        """What each replaced part costs in SER on the common packets: ``following``,
        ``timing``, ``channel`` (differences of consecutive chain stages) and the
        ``decision/noise`` floor (the last stage's SER); they sum to ``receiver``."""
        out = {"receiver": self.ser("receiver")}
        for name, a, b in SPLIT:
            out[name] = self.ser(a) - self.ser(b)
        out[FLOOR] = self.ser(CHAIN[-1])
        return out

    def as_dict(self) -> dict[str, Any]:
        common = self.common()
        return {"receiver": self.receiver.as_dict(), "bins": self.bins, "notes": self.notes,
                "common_packets": [p.index for p in common],
                "ser": {s: _num(self.ser(s)) for s in self.stages},
                "ser_found": {s: _num(self.ser(s, self.packets)) for s in self.stages},
                "found": {s: sum(p.stages[s].found for p in self.packets if s in p.stages) for s in self.stages},
                "crc_ok": {s: sum(p.stages[s].crc_ok for p in self.packets if s in p.stages) for s in self.stages},
                "split": {k: _num(v) for k, v in self.split().items()},
                "profile": {s: [_num(x) for x in self.profile(s)] for s in self.stages},
                "packets": [p.as_dict() for p in self.packets]}


# ----------------------------------------------------------------------------- the run

def above_background(frames: np.ndarray, bg: np.ndarray) -> np.ndarray:
    """The light above a per-pixel background.

    Parameters
    ----------
    frames : numpy.ndarray
        (F, H, W) frames, DN.
    bg : numpy.ndarray
        (H, W) background, DN (+inf where none was taken yet: those pixels are left as they are).

    Returns
    -------
    numpy.ndarray
        (F, H, W) float32, DN.
    """
    b = np.where(np.isfinite(bg), bg, 0.0).astype(np.float32)
    return frames.astype(np.float32) - b[None]


def above_registered(frames: np.ndarray, bg: np.ndarray, shifts: np.ndarray, margin: int,
                     residual: np.ndarray | None = None) -> np.ndarray:
    """The light above a background map held in the scene's frame
    (:class:`~iscd.decode.tracking.registered_background.RegisteredBackground`), read at each
    frame's image shift: ``frames[f, y, x] - bg[y - sy + margin, x - sx + margin]``; with
    ``residual``, the map moved on by each frame's residual shift r to first order, ``bg -
    grad(bg) . r`` (the central differences where the point and its four neighbours are seen,
    else 0: :func:`~iscd.decode.tracking.registered_background.map_gradient`).

    Parameters
    ----------
    frames : numpy.ndarray
        (F, H, W) frames, DN.
    bg : numpy.ndarray
        (H + 2 margin, W + 2 margin) the map, DN (+inf where nothing was seen: left as is).
    shifts : numpy.ndarray
        (F, 2) int image shift (x, y) of each frame, px.
    margin : int
        The map's margin, px.
    residual : numpy.ndarray, optional
        (F, 2) residual shift (x, y) of each frame beyond the whole pixels, px
        (:attr:`~iscd.decode.tracking.registered_background.RegisteredBackground.residual`).

    Returns
    -------
    numpy.ndarray
        (F, H, W) float32, DN.
    """
    F, H, W = frames.shape
    b = np.where(np.isfinite(bg), bg, 0.0).astype(np.float32)
    out = frames.astype(np.float32)
    gx = gy = None
    if residual is not None and np.any(np.asarray(residual) != 0):
        fin = np.isfinite(bg)
        ok = np.zeros(bg.shape, bool)
        ok[1:-1, 1:-1] = (fin[1:-1, 1:-1] & fin[1:-1, :-2] & fin[1:-1, 2:] & fin[:-2, 1:-1] & fin[2:, 1:-1])
        b64 = np.where(fin, bg, 0.0).astype(np.float64)
        gx = np.zeros(bg.shape)
        gy = np.zeros(bg.shape)
        gx[1:-1, 1:-1] = 0.5 * (b64[1:-1, 2:] - b64[1:-1, :-2])
        gy[1:-1, 1:-1] = 0.5 * (b64[2:, 1:-1] - b64[:-2, 1:-1])
        gx[~ok] = 0.0
        gy[~ok] = 0.0
    for f in range(F):
        sx, sy = int(shifts[f][0]), int(shifts[f][1])
        win = (slice(margin - sy, margin - sy + H), slice(margin - sx, margin - sx + W))
        out[f] -= b[win]
        if gx is not None and gy is not None:
            rx, ry = float(residual[f][0]), float(residual[f][1])  # type: ignore[index]
            if rx or ry:
                out[f] += (gx[win] * rx + gy[win] * ry).astype(np.float32)
    return out


class _RecordingDecoder(StreamDecoder):
    """The pipeline's decoder, unchanged, that also hands each decoded block's frames (the
    light above its per-pixel background where it subtracts one),
    luminance and Gaussian window (px, per camera, as :meth:`_luminance` computed it) to
    ``hook(ids, left, right, lum_l, lum_r, sigmas)``."""

    def __init__(self, cfg: Config, hook: Callable[..., None],
                 trace_steps: list[tuple[Any, ...]] | None = None) -> None:
        self._hook = hook
        self._trace_steps = trace_steps
        """with a list: every assembler is a :class:`~iscd.eval.lumtrace.TracingAssembler`
        that appends its input to it"""
        self._last_growth: list[float] = [1.0, 1.0]
        self.window_error = 0.0
        """largest relative difference between the receiver's luminance and the oracle's
        window at the receiver's own followed centres (first frame of each block): ~1e-6
        unless the pipeline's window formula changed"""
        super().__init__(cfg)

    def _make_assembler(self) -> PacketAssembler:
        if self._trace_steps is None:
            return super()._make_assembler()
        from iscd.eval.lumtrace import TracingAssembler

        return TracingAssembler(self.tx, fps=self.fps, exposure_s=self.cfg.camera.exposure_s, cfg=self.rx_cfg,
                                steps=self._trace_steps)

    def _growth(self, starts: list[np.ndarray]) -> list[float]:
        g = super()._growth(starts)
        self._last_growth = list(g)
        return g

    def _luminance(self, frame_ids: np.ndarray, left: np.ndarray, right: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        lum_l, lum_r = super()._luminance(frame_ids, left, right)
        tr = self.track
        assert tr is not None
        # the window of StreamDecoder._luminance
        sig = [float(np.clip(s * g, 0.6, max(s, self.MAX_SIGMA_PX))) for s, g in zip(tr.roi_sigma, self._last_growth)]
        # the receiver's images: the light above its per-pixel background where it has one
        # (one LED by default, [tracking] background_one_led), as its window saw them
        imgs = (left, right)
        if self._registered is not None and self.image_shifts[0] is not None and self.image_shifts[1] is not None:
            # one LED: the light above the map held in the scene's frame, at each frame's shift
            imgs = tuple(above_registered(img, r.bg, sh, MAX_SHIFT_PX, r.residual if r.subpixel else None)
                         for img, r, sh in zip(imgs, self._registered, self.image_shifts))
        elif self.background_on and self._backgrounds is not None:
            imgs = tuple(above_background(img, b.bg) for img, b in zip(imgs, self._backgrounds))
        if self.last_centres is not None:  # check: that window at the followed centres is the receiver's
            for img, c, lum, sg in zip(imgs, self.last_centres, (lum_l, lum_r), sig):
                again = gauss_mean(img[:1], c[:1], sg, radius=int(np.ceil(3.5 * sg)) + 1)
                scale = max(float(np.nanmax(np.abs(lum[:1]))), 1.0)
                self.window_error = max(self.window_error, float(np.nanmax(np.abs(again - lum[:1]))) / scale)
        self._hook(np.asarray(frame_ids, dtype=np.int64), imgs[0], imgs[1], lum_l, lum_r, sig)
        return lum_l, lum_r


def _score_levels(sent: np.ndarray, got: np.ndarray, crc_ok: bool, bins: int) -> StageScore:
    e, n = error_profile(sent, got, bins)
    return StageScore(True, bool(crc_ok), int(e.sum()), int(n.sum()), e, n)


def _assembler_scores(packets: list[Any], truth: Truth, air: AirInterface, tol_s: float,
                      want: dict[int, int], bins: int) -> dict[int, StageScore]:
    """Stage scores per transmitted packet index of decoded packets (``t_s``, ``levels``
    (F, N) or flat, ``crc_ok``), matched to the truth's packets as the eval scores them;
    ``want``: packet index -> row of the truth's packet arrays."""
    F, N = air.data_symbols, air.n_leds
    out: dict[int, StageScore] = {}
    t = [float(getattr(p, "t_s", None) if not isinstance(p, dict) else p["t_s"]) for p in packets]
    match = match_packets(t, truth.packet_t_s, tol_s)
    for p, j in zip(packets, match):
        if j < 0:
            continue
        idx = int(truth.packet_index[j])
        if idx not in want or idx in out:
            continue
        start = int(truth.packet_start_symbol[j]) + air.data_offset
        sent = truth.levels_of(start, start + F)
        lev = p["levels"] if isinstance(p, dict) else p.levels
        crc = p["crc_ok"] if isinstance(p, dict) else p.crc_ok
        out[idx] = _score_levels(sent, np.asarray(lev, dtype=np.int64).reshape(F, N), crc, bins)
    return out


FrameReader = Callable[[int, np.ndarray, np.ndarray], None]
"""``read(k, left, right)``: frame k of each camera into the (H, W) uint8 arrays given
(as :meth:`iscd.sim.scene.Scene.render_pair_into`)."""


def whole_packets(truth: Truth, packet_symbols: int, fps: float, exposure_s: float) -> int:
    """Packets, from the first one, that lie wholly within a truth's frames.

    Parameters
    ----------
    truth : Truth
        The recording's truth.
    packet_symbols : int
        Symbols of a packet (header + training + data).
    fps : float
        Frame rate, 1/s.
    exposure_s : float
        Exposure, s.

    Returns
    -------
    int
        Packets whose last symbol ends before the last frame's exposure does.
    """
    t_end = float(truth.t_s[-1]) + exposure_s
    n = 0
    for k0 in truth.packet_start_symbol:
        i = int(k0) + packet_symbols - int(truth.symbol_index[0])
        if k0 < 0 or i >= truth.symbol_t_s.size or truth.symbol_t_s[i] > t_end:
            break
        n += 1
    return n


def oracle_of_recording(directory: str | Path, *, mode: ReceiverMode | None = None, block: int = 32,
                        bins: int = 8, genie: bool = True,
                        progress: Callable[[int], None] | None = None) -> OracleResult:
    """:func:`run_oracle` on a recording with its truth, every whole packet of it.

    Parameters
    ----------
    directory : str or Path
        Holds ``left.iscr``, ``right.iscr``, ``truth.npz`` + ``truth.json``
        (:class:`~iscd.sim.truth.Truth`) and ``config.toml``, as ``iscd simulate`` writes
        them (any renderer may write the same files); frames numbered from 0.
    mode, block, bins, genie, progress
        As :func:`run_oracle`.

    Returns
    -------
    OracleResult
    """
    from iscd.core.config import load
    from iscd.recording import open_recording

    d = Path(directory)
    cfg = load(d / "config.toml")
    truth = Truth.load(d)
    left, right = open_recording(d / "left.iscr"), open_recording(d / "right.iscr")
    try:
        def read(k: int, out_l: np.ndarray, out_r: np.ndarray) -> None:
            out_l[...] = left[k]
            out_r[...] = right[k]
        air = AirInterface.from_config(cfg.transmitter)
        n = whole_packets(truth, air.packet_symbols, cfg.camera.fps, cfg.camera.exposure_s)
        if n < 1:
            raise ValueError(f"{d}: no whole packet in the recording")
        return run_oracle(cfg, n, mode=mode, block=block, bins=bins, genie=genie, progress=progress,
                          reader=read, truth=truth)
    finally:
        left.close()
        right.close()


def run_oracle(cfg: Config, packets: int = 2, *, mode: ReceiverMode | None = None, block: int = 32,
               bins: int = 8, genie: bool = True,
               genie_windows: Sequence[int | None] = GENIE_WINDOWS,
               progress: Callable[[int], None] | None = None,
               reader: FrameReader | None = None, truth: Truth | None = None,
               trace_to: str | Path | None = None, trace_label: str = "") -> OracleResult:
    """Decode a simulated recording with the receiver and with the oracle stages.

    Renders ``packets`` whole packets of ``cfg``'s scene (as
    :func:`iscd.eval.sweeps.run_comms`) and the next packet's header and training (a
    transmitter keeps sending: a car's receiver sees the header after the last packet
    scored, which :data:`~iscd.decode.comms.demod.ANCHOR_RETRY` reads for a failed packet),
    decodes them with the receiver and again with the stages of the module docstring.

    Parameters
    ----------
    cfg : Config
        The scene (and the ``[receiver]``, ``[tracking]`` sections).
    packets : int
        Whole packets to render and score.
    mode : ReceiverMode, optional
        Cameras and decision rule (default both cameras, the project's rule).
    block : int
        Frames per block pushed to the decoder.
    bins : int
        Stretches per packet of the error profiles.
    genie : bool
        Also the genie-luminance reference rows (reads the all-dark frames once more for
        the background).
    genie_windows : sequence of int or None
        True-level channel windows tried per packet, symbols (None = the packet); the
        one with the fewest errors counts.
    progress : callable, optional
        ``progress(n)`` after every block of n frames.
    reader : callable, optional
        ``reader(k, left, right)`` writes frame k of each camera (uint8 (H, W)) -- a
        recording made elsewhere (:func:`oracle_of_recording`) instead of rendering;
        ``cfg`` must then be the config it was made with.
    truth : Truth, optional
        That recording's truth (frames 0 .. len(truth) - 1).
    trace_to : path, optional
        Also write the receiver's luminance trace there (:mod:`iscd.eval.lumtrace`: what its
        packet assembler was fed, the sent packets and the receiver's scores), labelled
        ``trace_label``.

    Returns
    -------
    OracleResult
        Receiver scores, per-packet stage scores and profiles, the luminance decoded.
    """
    if packets < 1:
        raise ValueError(f"packets: expected >= 1, got {packets}")
    mode = mode or ReceiverMode("both", "both")
    dcfg = _decoder_cfg(cfg, mode)
    rx = receiver_config(dcfg)
    cams = rx.camera_indices
    scene = Scene(cfg)
    air = AirInterface.from_config(cfg.transmitter)
    tx = cfg.transmitter
    if truth is None:
        n_frames = frames_for_packets(scene, air, packets, after_symbols=known_levels(air).shape[0])
        truth = scene.truth(np.arange(n_frames))
    else:
        n_frames = len(truth)
        if not np.array_equal(truth.frames, np.arange(n_frames)):
            raise ValueError("truth: frames must be numbered 0 .. n - 1")
    read = reader or scene.render_pair_into
    N, F, M = tx.n_leds, air.data_symbols, tx.levels
    fps, e = cfg.camera.fps, cfg.camera.exposure_s * cfg.camera.fps
    notes: list[str] = []

    # luminance per camera and frame: the receiver's, at the true centres, the genie's
    L_rx = np.full((2, n_frames, N), np.nan)
    L_tp = np.full((2, n_frames, N), np.nan)
    L_g = np.full((2, n_frames, N), np.nan)
    centres = [true_centres(truth, 0), true_centres(truth, 1)]
    decoded: list[np.ndarray] = []

    def hook(ids: np.ndarray, left: np.ndarray, right: np.ndarray, lum_l: np.ndarray, lum_r: np.ndarray,
             sig: list[float]) -> None:
        rows = ids  # truth rows: frames 0 .. n_frames - 1
        decoded.append(ids)
        for c, (img, lum) in enumerate(((left, lum_l), (right, lum_r))):
            L_rx[c, rows] = lum
            L_tp[c, rows] = gauss_mean(img, centres[c][rows], sig[c], radius=int(np.ceil(3.5 * sig[c])) + 1)

    # genie background: the frames in which every LED is dark, cropped around the array
    dark = np.flatnonzero(truth.on_fraction.max(axis=1) <= 0.0) if genie else np.zeros(0, np.int64)
    if genie and dark.size == 0:
        notes.append("genie luminance: no all-dark frame to take the background from")
        genie = False
    radius = [spot_radius_px(cfg, truth.z_m, c) for c in (0, 1)]
    H, W = scene.height, scene.width
    boxes, dark_crops = [], [[], []]
    if genie:
        for c in (0, 1):
            m = float(np.ceil(radius[c].max())) + 4
            xy = centres[c].reshape(-1, 2)
            x0, y0 = int(max(0, np.floor(xy[:, 0].min() - m))), int(max(0, np.floor(xy[:, 1].min() - m)))
            x1, y1 = int(min(W, np.ceil(xy[:, 0].max() + m) + 1)), int(min(H, np.ceil(xy[:, 1].max() + m) + 1))
            boxes.append((x0, y0, x1, y1))
        dl = np.empty((H, W), np.uint8)
        dr = np.empty_like(dl)
        for k in dark:
            read(int(k), dl, dr)
            for c, img in enumerate((dl, dr)):
                x0, y0, x1, y1 = boxes[c]
                dark_crops[c].append(img[y0:y1, x0:x1].copy())
    crops = [np.stack(dc) if dc else None for dc in dark_crops]

    trace_steps: list[tuple[Any, ...]] | None = [] if trace_to is not None else None
    dec = _RecordingDecoder(dcfg, hook, trace_steps)
    records: list[dict] = []
    Lb = np.empty((block, H, W), np.uint8)
    Rb = np.empty_like(Lb)
    for ids in _blocks(n_frames, block):
        n = ids.size
        for i, k in enumerate(ids):
            read(int(k), Lb[i], Rb[i])
        if genie:
            near = nearest_dark(dark, ids)  # (n, k)
            for c, img in enumerate((Lb[:n], Rb[:n])):
                x0, y0, x1, y1 = boxes[c]
                sub = img[:, y0:y1, x0:x1]
                bg = np.median(crops[c][near].astype(np.float32), axis=1)  # (n, h, w)
                cc = centres[c][ids] - np.array([x0, y0], np.float64)
                L_g[c, ids] = genie_sum(sub, cc, radius[c][ids], bg)
        records += [r for r in dec.push(ids, ids / scene.fps, Lb[:n], Rb[:n]) if r["type"] == "packet"]
        if progress is not None:
            progress(n)
    records += [r for r in dec.finish() if r["type"] == "packet"]
    dec.close()
    if dec.window_error > WINDOW_TOLERANCE:
        notes.append(f"+true positions: the oracle's luminance window differs from the receiver's by up to "
                     f"{100 * dec.window_error:.2g} % (has StreamDecoder._luminance changed?)")

    tol = 0.5 / tx.symbol_rate_hz
    packet_s = air.period_symbols / tx.symbol_rate_hz
    res = CommsResult(mode=mode, levels=M, n_leds=N, data_symbols=F, packet_s=packet_s,
                      payload_bytes=air.payload_bytes, packets_sent=packets)
    _score(res, records, truth, air, packets, tol)

    want = {int(truth.packet_index[j]): j for j in range(truth.packet_index.size)
            if int(truth.packet_index[j]) < packets}
    scores: dict[str, dict[int, StageScore]] = {
        "receiver": _assembler_scores(records, truth, air, tol, want, bins)}
    if trace_to is not None and trace_steps is not None:
        _write_trace(trace_to, trace_label, dec, rx, cfg, truth, air, want, scores["receiver"], trace_steps)

    # +true positions: the receiver's assembler on the true-position luminance of the same frames
    # (one LED: with the true centres, for its sub-pixel phase attempt, as the receiver has its
    # followed ones)
    asm = PacketAssembler(tx, fps=fps, exposure_s=cfg.camera.exposure_s, cfg=rx)
    got: list[Any] = []
    if decoded:
        ids_all = np.concatenate(decoded)
        _, first = np.unique(ids_all, return_index=True)  # a frame decoded twice counts once
        ids_all = ids_all[np.sort(first)]
        for s in range(0, ids_all.size, block):
            i = ids_all[s:s + block]
            got += asm.push(i, i / fps, L_tp[0, i], L_tp[1, i], (centres[0][i], centres[1][i]) if N == 1 else None)
        got += asm.flush()
    scores["+true positions"] = _assembler_scores(got, truth, air, tol, want, bins)

    # per packet with the true clock: demodulate_packet with truth substituted
    Ptot = air.packet_symbols
    p_nom = fps / tx.symbol_rate_hz
    p_sig = rx.drift_max_ppm * 1e-6 * p_nom
    rx_genie = replace(rx, channel_window_symbols=GENIE_STRETCH_WINDOW)
    rx_static = replace(rx, channel_window_symbols=0)
    for name in CHAIN[2:] + REFERENCE:
        scores[name] = {}
    for idx, j in want.items():
        k0 = int(truth.packet_start_symbol[j])
        t_sym = truth.symbol_t_s[k0 - truth.symbol_index[0]: k0 - truth.symbol_index[0] + Ptot + 1]
        clk = true_clock(t_sym, fps)
        lo = max(0, int(np.floor(clk.u0)) - 8)
        hi = min(n_frames, int(np.ceil(clk.boundary(Ptot))) + 8)
        clock = SymbolClock(clk.u0 - lo, clk.p)
        true_lev = truth.levels_of(k0, k0 + Ptot).astype(np.int64) - 1
        sent = true_lev[air.data_offset:] + 1
        runs: list[tuple[str, np.ndarray, ReceiverConfig, Sequence[Any]]] = [
            ("+true timing", L_tp, rx, ("receiver",)),
            ("+true labels", L_tp, rx, ("labels",)),
            ("+true channel", L_tp, rx_genie, tuple(genie_windows)),
            ("+true channel (one per packet)", L_tp, rx_static, (None,))]
        if genie:
            runs += [("genie luminance", L_g, rx, ("receiver",)),
                     ("genie luminance +true channel", L_g, rx_genie, tuple(genie_windows))]
        for name, Lsrc, rcfg, windows in runs:
            buf = np.ascontiguousarray(Lsrc[list(cams), lo:hi])
            for w in windows:  # the best of the true channels counts
                ch = None if w in ("receiver", "labels") else genie_channel(buf, e, true_lev, M, rx, w)
                r = demodulate_packet(buf, clock.u0, air, e, p_nom, clock.p, p_sig, rcfg, clock=clock,
                                      channel=ch, grid=asm.grid, labels=true_lev if w == "labels" else None)
                if isinstance(r, PacketResult):
                    sc = _score_levels(sent, r.levels.astype(np.int64), r.crc_ok, bins)
                    if idx not in scores[name] or sc.errors < scores[name][idx].errors:
                        scores[name][idx] = sc
    if not genie:
        notes.append("genie luminance rows not computed")
    out: list[PacketOracle] = []
    for idx, j in sorted(want.items()):
        fr = np.flatnonzero((truth.symbol_mid >= truth.packet_start_symbol[j]) &
                            (truth.symbol_mid < truth.packet_start_symbol[j] + Ptot))
        po = PacketOracle(idx, float(truth.z_m[fr[0]]) if fr.size else float("nan"),
                          float(truth.z_m[fr[-1]]) if fr.size else float("nan"))
        for name in STAGES:
            if name in scores:
                po.stages[name] = scores[name].get(idx, StageScore(False))
        out.append(po)
    lum = {"receiver": L_rx, "true positions": L_tp, **({"genie": L_g} if genie else {})}
    return OracleResult(res, out, bins, STAGES if genie else STAGES[:-2], notes, lum)


def _write_trace(path: str | Path, label: str, dec: StreamDecoder, rx: ReceiverConfig, cfg: Config, truth: Truth,
                 air: AirInterface, want: dict[int, int], scores: dict[int, StageScore],
                 steps: list[tuple[Any, ...]]) -> None:
    """:func:`run_oracle`'s ``trace_to``: the receiver's luminance trace with the truth's sent
    packets (header start, data levels) and the receiver's own scores."""
    from iscd.eval.lumtrace import PacketScore, SentPacket, Trace, save

    F = air.data_symbols
    sent = []
    for idx, j in sorted(want.items()):
        k = int(truth.packet_start_symbol[j]) + air.data_offset
        sent.append(SentPacket(idx, float(truth.packet_t_s[j]), truth.levels_of(k, k + F).astype(np.int64)))
    got = {idx: scores.get(idx, StageScore(False)) for idx in want}
    captured = [PacketScore(idx, sc.found, sc.crc_ok, sc.errors) for idx, sc in sorted(got.items())]
    save(Trace(label or Path(path).stem, dec.tx, rx, float(cfg.camera.fps), float(cfg.camera.exposure_s), sent,
               steps, captured), path)


def pool(results: Sequence[OracleResult]) -> OracleResult:
    """Several recordings (seeds) of one case as one result.

    Parameters
    ----------
    results : sequence of OracleResult
        One per recording.

    Returns
    -------
    OracleResult
        The receiver's counts summed, the packets side by side (SERs, split and profiles
        are then over all of them), the stages every result has; no luminance.
    """
    if not results:
        raise ValueError("pool: no results")
    r0 = results[0].receiver
    rec = CommsResult(mode=r0.mode, levels=r0.levels, n_leds=r0.n_leds, data_symbols=r0.data_symbols,
                      packet_s=r0.packet_s, payload_bytes=r0.payload_bytes)
    for r in results:
        c = r.receiver
        for k in ("packets_sent", "found", "crc_ok", "exact", "undetected", "spurious", "spurious_crc_ok",
                  "symbols", "symbol_errors", "bits", "bit_errors"):
            setattr(rec, k, getattr(rec, k) + getattr(c, k))
        rec.margin_p01 += c.margin_p01
        rec.seconds += c.seconds
    stages = tuple(s for s in STAGES if all(s in r.stages for r in results))
    notes = sorted({n for r in results for n in r.notes})
    return OracleResult(rec, [p for r in results for p in r.packets], results[0].bins, stages, notes)
