"""Streaming packet assembly: blocks of per-LED luminance in, decoded packets out.

:class:`PacketAssembler` keeps a bounded buffer of the latest frames (about two packets),
searches it for headers (:mod:`iscd.decode.comms.timing`), and as soon as all frames of a
packet are in, demodulates it (:func:`iscd.decode.comms.demod.demodulate_packet`) and returns
a :class:`Packet`. After a packet it expects the next header one packet period later
(tracked symbol period, i.e. drift) and falls back to a search when it is not there. A
recording that starts mid-packet yields nothing until the next header; missing frames
(gaps in the frame ids) become NaN rows whose symbols are decided from the other frame or
camera, or counted as erasures.

A packet whose CRC-32 fails is reported with ``crc_ok = False`` and no payload: its bytes
are kept only as :attr:`Packet.raw` (untrusted, for diagnostics) and never handed out as
valid.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.stats import rankdata

from iscd.core.airinterface import HEADER_SYMBOLS, AirInterface
from iscd.core.airinterface_v2 import AirInterfaceV2, header_symbols
from iscd.core.config import TransmitterConfig
from iscd.core.jit import njit, register_warm
from iscd.core.records import PacketRecord
from iscd.decode.comms import demod, listdecode, pixelphase, smoothing
from iscd.decode.comms.demod import (PacketResult, Rejection, after_levels, demodulate_anchored, demodulate_packet,
                                      known_levels)
from iscd.decode.comms.settings import ReceiverConfig
from iscd.decode.comms.timing import SymbolClock, coarse_header_search, luminance_range, normalized_mean

log = logging.getLogger(__name__)

FIXED_CLOCK_RETRY = True
"""A one-LED packet that every attempt failed is demodulated once more with the clock its
attempts ended on held fixed (:meth:`PacketAssembler._fixed_clock_attempt`), before the
sub-pixel phase attempt."""

SMOOTH_RETRY = True
"""A one-LED packet that every attempt failed (the sub-pixel phase attempt included) is
demodulated once more with its channel smoothed over the whole packet
(:meth:`PacketAssembler._smoothed_attempt`)."""

SMOOTH_ROUNDS = 3
"""Rounds of the smoothed attempt: each labels the next with its decisions."""


def _levels_follow(y: np.ndarray, lev: np.ndarray, rho_min: float = 0.9) -> bool:
    """Whether clean frames (C, n) DN show the known levels ``lev`` (n,): the rank correlation
    of some camera's frames with them at least ``rho_min`` (as a packet's training must)."""
    for yc in y:
        ok = np.isfinite(yc)
        if ok.sum() >= 8 and np.ptp(lev[ok]) > 0:
            if np.corrcoef(rankdata(yc[ok]), rankdata(lev[ok]))[0, 1] >= rho_min:
                return True
    return False


@njit(warm=lambda: (np.arange(3), np.zeros(3), 0), error_model="numpy")
def _consecutive(ids: np.ndarray, ts: np.ndarray, first: int) -> bool:
    """ids == first, first + 1, ... and every timestamp finite."""
    for j in range(ids.size):
        if ids[j] != first + j or not np.isfinite(ts[j]):
            return False
    return True


# a block's timestamps may come as a strided view (a searcher's kept frames): that layout
# compiled (or loaded) at the warm-up too, not in the middle of a stream
register_warm(_consecutive, lambda: (np.arange(3), np.zeros(6)[::2], 0))


@dataclass
class Packet:
    """A decoded packet.

    frame: frame id of the first header symbol's clean frame; t_s: camera time of the
    header start, s; u0_frames: header start in frame ids (fractional); crc_ok: the CRC-32
    verdict; payload: the payload bytes, ONLY when crc_ok (else None); levels: (F, N)
    decided data levels 1..M; raw: decoded bytes whatever the CRC (untrusted);
    quality: margins and sync metrics (:meth:`PacketResult.quality`).
    """

    frame: int
    t_s: float
    u0_frames: float
    crc_ok: bool
    payload: bytes | None
    levels: np.ndarray
    raw: bytes = field(repr=False)
    quality: dict[str, float] = field(default_factory=dict)
    margins: np.ndarray | None = field(default=None, repr=False)
    version: int = 1
    """air interface version (2: a PHY header was read; its fields are in :attr:`quality`)"""
    shape: tuple[int, int] | None = None
    """v2: the array's (rows, cols) as its PHY header said (None for v1)"""

    def record(self, tx: int = 0) -> dict[str, Any]:
        """The SPEC section 7 JSON record (``payload_hex`` is empty when the CRC failed).

        Parameters
        ----------
        tx : int
            Transmitter index.

        Returns
        -------
        dict
            ``type``, ``tx``, ``frame``, ``t_s`` (s), ``crc_ok``, ``payload_hex``, ``levels``
            (the F·N decided data levels 1..M, symbol time major) and the :attr:`quality`
            metrics.

        References
        ----------
        SPEC section 7 (output).
        """
        return PacketRecord(
            tx=tx, frame=int(self.frame), t_s=float(self.t_s), crc_ok=bool(self.crc_ok),
            payload_hex=self.payload.hex() if self.crc_ok and self.payload is not None else "",
            levels=self.levels.reshape(-1).astype(int).tolist(), extra=dict(self.quality)).to_json()


class PacketAssembler:
    """Streaming demodulator of one transmitter (N LEDs) seen by one or two cameras.

    tx: the transmitter (levels, LED count, packet geometry, symbol rate); fps and
    exposure_s: the cameras'. ``push`` blocks of frames as they arrive; it returns the
    packets completed by them.
    """

    RANGE_EVERY = 128
    """Frames between updates of the per-LED luminance range used by the header search."""
    TRIM_MIN = 512
    """Rows dropped at once from the front of the buffer (fewer, larger copies)."""

    def __init__(self, tx: TransmitterConfig, fps: float, exposure_s: float,
                 cfg: ReceiverConfig | None = None, max_gap_frames: int | None = None) -> None:
        self.tx = tx
        self.cfg = cfg or ReceiverConfig()
        self.air = AirInterface.from_config(tx)
        self.fps = float(fps)
        self.e = float(exposure_s * fps)
        if not 0 < self.e <= 1.0 + 1e-9:
            raise ValueError(f"exposure {exposure_s} s must be within the frame period 1/{fps} s")
        self.p_nom = self.fps / tx.symbol_rate_hz
        if self.p_nom < 2 * 0.999:
            raise ValueError(f"{fps} fps is below 2 frames per symbol at {tx.symbol_rate_hz} Hz")
        self.cams = self.cfg.camera_indices
        self.N = self.air.n_leds
        rows, cols = int(getattr(tx, "rows", 0) or 0), int(getattr(tx, "cols", 0) or 0)
        self.grid: tuple[int, int] | None = (rows, cols) if self.N > 1 and rows * cols == self.N else None
        """(rows, cols) of an array (crosstalk cancellation on a failed packet), else None."""
        self.packet_frames = self.air.packet_symbols * self.p_nom
        self.period_frames = self.air.period_symbols * self.p_nom
        self.max_gap = max_gap_frames if max_gap_frames is not None else int(self.packet_frames)
        self.keep = int(np.ceil(2 * self.packet_frames)) + 16
        self._L = np.zeros((len(self.cams), 0, self.N))
        self._t = np.zeros(0)
        self._Lbuf, self._tbuf = self._L, self._t  # the allocations (_L, _t: views from a row on)
        # one LED: its followed centre (x, y) px per camera and frame, for the phase attempt
        # (pixelphase); NaN where the caller gave none
        self._X: np.ndarray | None = np.zeros((len(self.cams), 0, 1, 2)) if self.N == 1 else None
        self._Xbuf = self._X
        self._n = 0  # filled rows
        self._base: int | None = None  # frame id of row 0
        self._search = 0.0  # buffer position (frames) from which headers are still searched
        self._p = self.p_nom
        self._p_sigma = self.cfg.drift_max_ppm * 1e-6 * self.p_nom
        self._prior_delivered = False  # _p, _p_sigma are a CRC-valid packet's (demodulate_packet's retry_unlocked)
        self._expect: float | None = None  # expected next header start (buffer frames)
        self._wait_until = 0.0  # no new search before the buffer has this many rows
        self._last_u: float | None = None  # absolute start (frames) of the last emitted packet
        self._range: tuple[np.ndarray, np.ndarray] | None = None  # luminance 2..98 % per LED
        self._range_at = -1  # buffer rows when _range was computed
        self._flushing = False
        self._geom: AirInterface | AirInterfaceV2 = self.air  # the last packet's geometry
        self._expect_wait = 0.0  # the expected packet is longer: not before this many rows
        self._held: PacketResult | None = None  # a failed packet waiting for the frames after it
        self._held_need = 0.0  # the buffer rows its anchored attempt needs
        self._held_prior: tuple[float, float, bool] = (self.p_nom, self._p_sigma, False)
        """the period prior the held packet was demodulated with (_p, _p_sigma, _prior_delivered)"""
        self.stats = {"frames_in": 0, "frames_missing": 0, "frames_rejected": 0,
                      "packets_ok": 0, "packets_bad": 0, "false_headers": 0, "resyncs": 0,
                      "anchored_tries": 0, "anchored_delivered": 0, "list_tries": 0, "list_delivered": 0,
                      "clock_tries": 0, "clock_delivered": 0, "phase_tries": 0, "phase_delivered": 0,
                      "smooth_tries": 0, "smooth_delivered": 0}

    # ---- buffer ----------------------------------------------------------------------
    def _reserve(self, extra: int) -> None:
        """Room for ``extra`` more rows after the filled ones: the rows move to the front of
        the allocation when it has room for twice them, else to one twice as large."""
        need = self._n + extra
        if need > self._L.shape[1]:
            X = self._Xbuf
            if 2 * need <= self._Lbuf.shape[1]:
                L, t = self._Lbuf, self._tbuf  # (numpy copies overlapping ranges correctly)
            else:
                cap = max(need, 2 * self._Lbuf.shape[1], 1024)
                L = np.full((len(self.cams), cap, self.N), np.nan)
                t = np.zeros(cap)
                self._Lbuf, self._tbuf = L, t
                if X is not None:
                    X = self._Xbuf = np.full((len(self.cams), cap, 1, 2), np.nan)
            L[:, :self._n] = self._L[:, :self._n]
            t[:self._n] = self._t[:self._n]
            self._L, self._t = L, t
            if X is not None and self._X is not None:
                X[:, :self._n] = self._X[:, :self._n]
                self._X = X

    def _trim(self) -> None:
        """Drop rows before max(search position, end) - keep, shifting positions (the
        buffer's start moves: no copy until :meth:`_reserve` runs out of room)."""
        cut = int(min(np.floor(self._search), self._n - self.keep)) - 8
        if self._expect is not None:
            cut = min(cut, int(np.floor(self._expect)) - 8)
        if self._held is not None:
            cut = min(cut, int(np.floor(self._held.u0)) - 8)
        if cut < self.TRIM_MIN:
            return
        self._L = self._L[:, cut:]
        self._t = self._t[cut:]
        if self._X is not None:
            self._X = self._X[:, cut:]
        self._n -= cut
        self._base = (self._base or 0) + cut
        self._search -= cut
        self._wait_until -= cut
        self._expect_wait -= cut
        self._range_at -= cut
        if self._expect is not None:
            self._expect -= cut
        if self._held is not None:
            self._held = replace(self._held, u0=self._held.u0 - cut, first_frame=self._held.first_frame - cut)
            self._held_need -= cut

    def reset(self) -> list[Packet]:
        """Forget buffered frames and the lock (e.g. after a long gap).

        Returns
        -------
        list of Packet
            A failed packet that was waiting for the frames after it
            (:data:`~iscd.decode.comms.demod.ANCHOR_RETRY`), as it is: nothing decoded is
            dropped.
        """
        out: list[Packet] = []
        self._release(out, force=True)
        self._last_u = None
        self._n = 0
        self._base = None
        self._search = 0.0
        self._expect = None
        self._wait_until = 0.0
        self._expect_wait = 0.0
        self._range = None
        return out

    def push(self, frame_ids: np.ndarray, t_s: np.ndarray, L_left: np.ndarray | None,
             L_right: np.ndarray | None = None,
             centres: tuple[np.ndarray | None, np.ndarray | None] | None = None) -> list[Packet]:
        """Append frames (ids increasing; gaps become NaN rows) and return finished packets.

        Frames whose id does not increase are dropped (counted in ``stats["frames_rejected"]``).
        A gap longer than ``max_gap_frames`` resets the receiver.

        Parameters
        ----------
        frame_ids : ndarray
            (n,) trigger counters, frames.
        t_s : ndarray
            (n,) exposure start times, s (NaN: derived from the ids and the fps).
        L_left : ndarray or None
            (n, N) luminance of each LED in the left camera, DN (None: that camera is absent).
        L_right : ndarray or None
            (n, N) luminance of each LED in the right camera, DN (None: that camera is absent).
        centres : tuple of ndarray or None, optional
            One LED: (left, right) its followed centre (n, 1, 2) (x, y) px in each frame, as
            the luminance was measured there (None, or a camera's None: not known). A packet
            that every other attempt failed is tried with the sub-pixel phase taken out
            (:mod:`~iscd.decode.comms.pixelphase`); ignored for an array.

        Returns
        -------
        list of Packet
            The packets completed by these frames, oldest first.

        Raises
        ------
        ValueError
            If ``t_s`` and ``frame_ids`` differ in length, a block has the wrong LED count or
            ``centres`` the wrong frame count.
        """
        ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        ts = np.asarray(t_s, dtype=np.float64).reshape(-1)
        n = ids.size
        early: list[Packet] = []  # a held packet released by a resynchronization
        if self._fast_push(ids, ts, L_left, L_right, centres):
            out = self._process()
            self._trim()
            return out
        if ts.size != n:
            raise ValueError(f"{n} frame ids but {ts.size} timestamps")
        if n and not np.isfinite(ts).all():  # missing timestamps: from the ids and the fps
            ok = np.isfinite(ts)
            if ok.any():
                j = int(np.flatnonzero(ok)[0])
                ref_id, ref_t = ids[j], ts[j]
            elif self._base is not None and self._n:
                ref_id, ref_t = self._base + self._n - 1, self._t[self._n - 1]
            else:
                ref_id, ref_t = ids[0], 0.0
            ts = np.where(ok, ts, ref_t + (ids - ref_id) / self.fps)
        blocks = []
        for c in self.cams:
            src = (L_left, L_right)[c]
            if src is None:
                blocks.append(np.full((n, self.N), np.nan))
                continue
            a = np.asarray(src, dtype=np.float64).reshape(n, -1) if n else np.zeros((0, self.N))
            if a.shape[1] != self.N:
                raise ValueError(f"expected luminance of {self.N} LEDs, got {a.shape[1]}")
            blocks.append(a)
        if n == 0:
            return []
        Lb = np.stack(blocks)  # (C, n, N)
        Xb = self._centre_block(n, centres)
        # keep strictly increasing ids only
        last = None if self._base is None else self._base + self._n - 1
        prev_max = np.maximum.accumulate(np.concatenate([[ids[0] - 1 if last is None else last], ids]))
        keep = ids > prev_max[:-1]
        if not keep.all():
            self.stats["frames_rejected"] += int((~keep).sum())
            ids, ts, Lb = ids[keep], ts[keep], Lb[:, keep]
            Xb = None if Xb is None else Xb[:, keep]
        if ids.size == 0:
            return []
        self.stats["frames_in"] += int(ids.size)
        if self._base is None:
            self._base = int(ids[0])
        elif ids[0] - last - 1 > self.max_gap:
            log.warning("gap of %d frames: receiver resynchronizes", ids[0] - last - 1)
            self.stats["resyncs"] += 1
            early = self.reset()
            self._base = int(ids[0])
        rows = ids - self._base
        span = int(rows[-1]) + 1 - self._n
        self._reserve(span)
        gap_rows = np.ones(span, bool)
        gap_rows[rows - self._n] = False
        self.stats["frames_missing"] += int(gap_rows.sum())
        self._L[:, self._n:self._n + span] = np.nan
        self._L[:, rows] = Lb
        if self._X is not None:
            self._X[:, self._n:self._n + span] = np.nan
            if Xb is not None:
                self._X[:, rows] = Xb
        # timestamps: measured where present, interpolated (frame period) in gaps
        all_rows = np.arange(self._n, self._n + span)
        if gap_rows.any():
            known_r = np.concatenate([np.arange(max(0, self._n - 1), self._n), rows])
            known_t = np.concatenate([self._t[max(0, self._n - 1):self._n], ts])
            if known_r.size >= 2:
                self._t[all_rows] = np.interp(all_rows, known_r, known_t,
                                              left=np.nan, right=np.nan)
                bad = ~np.isfinite(self._t[all_rows])
                if bad.any():
                    ref_r, ref_t = known_r[-1], known_t[-1]
                    self._t[all_rows[bad]] = ref_t + (all_rows[bad] - ref_r) / self.fps
            else:
                self._t[all_rows] = ts[0] + (all_rows - rows[0]) / self.fps
        else:
            self._t[rows] = ts
        self._n += span
        out = self._process()
        self._trim()
        return early + out

    def _centre_block(self, n: int, centres: tuple[np.ndarray | None, np.ndarray | None] | None
                      ) -> np.ndarray | None:
        """(C, n, 1, 2) float64 centres of a pushed block, NaN for a camera without (None when
        this assembler keeps none or none were given)."""
        if self._X is None or centres is None:
            return None
        out = np.full((len(self.cams), n, 1, 2), np.nan)
        for j, c in enumerate(self.cams):
            src = centres[c]
            if src is not None:
                a = np.asarray(src, dtype=np.float64)
                if a.size != 2 * n:
                    raise ValueError(f"expected centres (n, 1, 2) of {n} frames, got shape {a.shape}")
                out[j] = a.reshape(n, 1, 2)
        return out

    def _fast_push(self, ids: np.ndarray, ts: np.ndarray, L_left: np.ndarray | None,
                   L_right: np.ndarray | None, centres: tuple[np.ndarray | None, np.ndarray | None] | None = None
                   ) -> bool:
        """The usual block -- ids following the last one by one, all timestamps, each
        camera's (n, N) luminance -- appended directly (what :meth:`push` does with it,
        without its general bookkeeping); False (nothing done) for any other block."""
        n = ids.size
        if n == 0 or self._base is None or ts.size != n or self.max_gap < 0:
            return False
        srcs = [(L_left, L_right)[c] for c in self.cams]
        if not all(isinstance(a, np.ndarray) and a.shape == (n, self.N) and a.dtype.kind in "fiub"
                   for a in srcs):
            return False
        if not _consecutive(ids, ts, self._base + self._n):
            return False
        Xb = self._centre_block(n, centres)
        self.stats["frames_in"] += n
        self._reserve(n)
        a = self._n
        for j, src in enumerate(srcs):
            self._L[j, a:a + n] = src
        if self._X is not None:
            self._X[:, a:a + n] = np.nan if Xb is None else Xb
        self._t[a:a + n] = ts
        self._n += n
        return True

    # ---- packet search ---------------------------------------------------------------
    def _frame_time(self, u: float) -> float:
        idx = np.arange(self._n)
        return float(np.interp(u, idx, self._t[:self._n]))

    def _emit_once(self, res: PacketResult, out: list[Packet]) -> None:
        """Emit ``res`` unless a packet starting at (nearly) the same frame was emitted
        already: a header found twice is one packet, never two records."""
        u_abs = (self._base or 0) + res.u0
        if self._last_u is not None and abs(u_abs - self._last_u) < HEADER_SYMBOLS * self.p_nom:
            self.stats["duplicates_suppressed"] = self.stats.get("duplicates_suppressed", 0) + 1
            return
        self._last_u = u_abs
        self._release(out, force=True)  # (released already: its anchor precedes this packet)
        if self._holds(res):
            self._held = res
            self._held_prior = (self._p, self._p_sigma, self._prior_delivered)
            self._held_need = res.u0 + after_levels(res.air).shape[0] * res.p + res.air.packet_symbols * res.p + 3
            self._release(out)
            return
        out.append(self._emit(res))

    def _holds(self, res: PacketResult) -> bool:
        """Whether a demodulated packet waits for the frames after it: a real packet (the
        lock's test) that every attempt failed, read by a receiver that tracks the channel
        along a packet (:data:`~iscd.decode.comms.demod.ANCHOR_RETRY`)."""
        cfg = self.cfg
        tracks = cfg.decision_directed and not cfg.dissertation and cfg.channel_window_symbols > 0
        return (demod.ANCHOR_RETRY and tracks and not res.crc_ok and res.channel != "anchored"
                and res.air is not None and res.training_rho >= 0.9 and np.isfinite(res.p))

    def _release(self, out: list[Packet], force: bool = False) -> None:
        """Emit the held failed packet once the frames after it are in: demodulated again
        anchored on the next packet's header and training
        (:func:`~iscd.decode.comms.demod.demodulate_anchored`), delivered if that passes its
        CRC, else as it was. ``force``: now, as it was when those frames are not in (a
        reset, the end of the stream, a packet after it)."""
        res = self._held
        if res is None or (self._n < self._held_need and not force):
            return
        self._held = None
        tries, good = self._anchored_then_listed(res, self._L[:, :self._n], at_end=force and self._flushing)
        if good is None and FIXED_CLOCK_RETRY and self.N == 1:
            good = self._fixed_clock_attempt(res, tries[0])
        if good is None and pixelphase.PHASE_RETRY and self._X is not None:
            good = self._phase_attempt(res, tries[0])
        if good is None and SMOOTH_RETRY and self.N == 1:
            good = self._smoothed_attempt(tries[0])
        if good is not None:
            res = good
            if not force:  # (waiting for the next packet still: lock on the delivered one)
                self._accept(res)
        out.append(self._emit(res))

    def _anchored_then_listed(self, first: PacketResult, L: np.ndarray, at_end: bool = False,
                              counted: bool = True) -> tuple[list[PacketResult], PacketResult | None]:
        """The attempts after a failed one, ``first``, demodulated from the luminance ``L``:
        anchored on the next header when the frames after it are in (or ``at_end``: the end
        of the stream), then CRC-aided list decoding. Returns the attempts (the anchored one
        first) and the delivered one (None when none passed). ``counted``: in the
        ``anchored_*`` stats (the held packet's own; not a later attempt's, which has its own)."""
        tries = [first]
        if self._n >= self._held_need or at_end:
            if counted:
                self.stats["anchored_tries"] += 1
            alt = demodulate_anchored(L, first, self.e, self.p_nom, self.cfg)
            if isinstance(alt, PacketResult):
                if counted:
                    self.stats["anchored_delivered"] += int(alt.crc_ok)
                tries.insert(0, alt)
        good = tries[0] if tries[0].crc_ok else (self._list_decode(tries) if listdecode.LIST_DECODE else None)
        return tries, good

    def _fixed_clock_attempt(self, held: PacketResult, best: PacketResult) -> PacketResult | None:
        """A one-LED packet that every attempt failed, demodulated again with the clock its
        attempts ended on held fixed (``best``'s, then the first attempt's when it differs):
        each attempt tracks the channel along the packet while its clock is still being fitted,
        so decisions made with an early, wrong period stay in the channel it learned even when
        the final fit of the clock is right. Then list-decoded. Only a CRC pass is returned.

        Found on 288314013 (set 85001, 100 km/h, 0.3 px, each vibration model): the first
        packet's period came out 108 ppm off and, locked, was the second packet's prior; the
        second's own clock ended within 0.01 frame of the truth over the packet, yet it kept 4-9
        wrong symbols late in the packet, which the oracle's ``+true timing`` stage (a fixed true
        clock) did not make (docs/eval.md, session 33)."""
        clocks = [best] + ([held] if held is not best and (held.u0, held.p) != (best.u0, best.p) else [])
        failed: list[PacketResult] = []
        for src in clocks:
            if not np.isfinite(src.p) or not np.isfinite(src.u0):
                continue
            self.stats["clock_tries"] += 1
            r = demodulate_packet(self._L[:, :self._n], src.u0, self.air, self.e, self.p_nom, src.p,
                                  20e-6 * self.p_nom, self.cfg, clock=SymbolClock(src.u0, src.p), grid=self.grid)
            if isinstance(r, PacketResult):
                if r.crc_ok:
                    self.stats["clock_delivered"] += 1
                    return replace(r, clock_fixed=True)
                failed.append(r)
        got = self._list_decode(failed[:1]) if failed and listdecode.LIST_DECODE else None
        if got is not None:
            self.stats["clock_delivered"] += 1
            return replace(got, clock_fixed=True)
        return None

    def _phase_attempt(self, held: PacketResult, best: PacketResult) -> PacketResult | None:
        """A one-LED packet that every attempt failed, demodulated again with the sub-pixel
        phase of its followed centres taken out of its luminance
        (:func:`~iscd.decode.comms.pixelphase.phase_corrected`; each level's light in a frame
        from ``best``'s decisions and clock, the header and training known),
        then as :meth:`_release` does: the same prior as ``held`` had, anchored when the
        frames after it are in, list decoding. Only a CRC pass is returned (None otherwise):
        the correction can spoil a packet, so it runs only where nothing else delivered."""
        air = best.air
        if self._X is None or not isinstance(air, AirInterface) or isinstance(air, AirInterfaceV2) \
                or best.levels.shape != (air.data_symbols, 1) or not np.isfinite(best.p):
            return None
        p, p_sigma, unlocked = self._held_prior
        for _ in range(pixelphase.ROUNDS):
            levels = np.concatenate([known_levels(air)[:, 0], best.levels[:, 0].astype(np.int64) - 1])
            Lc = pixelphase.phase_corrected(self._L[:, :self._n], self._X[:, :self._n], levels,
                                            SymbolClock(best.u0, best.p), self.e)
            if Lc is None:
                return None
            self.stats["phase_tries"] += 1
            first = demodulate_packet(Lc, held.u0, self.air, self.e, self.p_nom, p, p_sigma, self.cfg,
                                      grid=self.grid, retry_unlocked=unlocked)
            if not isinstance(first, PacketResult):
                return None
            tries, good = ([first], first) if first.crc_ok else self._anchored_then_listed(first, Lc, counted=False)
            if good is not None:
                self.stats["phase_delivered"] += 1
                return replace(good, phase_corrected=True)
            best = tries[0]  # its decisions label the next round (from the luminance as it was)
            if best.levels.shape != (air.data_symbols, 1) or not np.isfinite(best.p):
                return None
        return None

    def _smoothed_attempt(self, best: PacketResult) -> PacketResult | None:
        """A one-LED packet that every attempt failed, demodulated again with its channel
        smoothed over the whole packet (:mod:`~iscd.decode.comms.smoothing`: every symbol's
        level centroids at once, a random walk given every clean frame, the data weighed by
        their levels' likelihoods), labelled by ``best``'s decisions at ``best``'s clock (held
        fixed) and by the known symbols -- the header and training, and the idle symbols and
        the next header and training after the packet when their frames are in. Decided
        again, the decisions label the next round (:data:`SMOOTH_ROUNDS` at most, until they
        no longer change); the last round is list-decoded. Only a CRC pass is returned."""
        air = best.air
        if not isinstance(air, AirInterface) or isinstance(air, AirInterfaceV2) \
                or best.levels.shape != (air.data_symbols, 1) or not (np.isfinite(best.p) and np.isfinite(best.u0)):
            return None
        L = self._L[:, :self._n]
        clock = SymbolClock(best.u0, best.p)
        P, D = air.packet_symbols, air.data_offset
        after = after_levels(air)[:, 0]
        known_lev = np.concatenate([known_levels(air)[:, 0], np.zeros(air.data_symbols, np.int64), after])
        S = P + after.size
        if clock.boundary(S) + 1 > self._n:  # the frames after the packet are not in
            S = P
        frames, k = demod.clean_index(L.shape[1], clock, self.e, S)
        if S > P and not _levels_follow(L[:, frames[k >= P], 0], known_lev[k[k >= P]]):
            # no packet like it follows (the transmitter stopped, or sends something else)
            S = P
            frames, k = frames[k < P], k[k < P]
        if frames.size == 0:
            return None
        known = np.ones(S, dtype=bool)
        known[D:P] = False
        cfg = replace(self.cfg, channel_window_symbols=smoothing.STRETCH_WINDOW)
        r = best
        for _ in range(SMOOTH_ROUNDS):
            lab = known_lev[:S].copy()
            lab[D:P] = r.levels[:, 0].astype(np.int64) - 1
            mu, var = smoothing.em_models(L[:, frames, 0], k, lab[k], known, S, air.levels, self.cfg.var_floor_dn)
            self.stats["smooth_tries"] += 1
            alt = demod.demodulate_with_channel(L, air, self.e, self.p_nom, clock, cfg,
                                                smoothing.channel_of(mu, var, self.cfg.noise_model, self.cfg.t_nu))
            if not isinstance(alt, PacketResult):
                return None
            if alt.crc_ok:
                self.stats["smooth_delivered"] += 1
                return replace(alt, channel_smoothed=True)
            done = bool((alt.levels == r.levels).all())
            r = alt
            if done:
                break
        got = self._list_decode([r]) if listdecode.LIST_DECODE else None
        if got is not None:
            self.stats["smooth_delivered"] += 1
            return replace(got, channel_smoothed=True)
        return None

    def _list_decode(self, tries: list[PacketResult]) -> PacketResult | None:
        """The last resort for a held packet that every attempt failed: CRC-aided list
        decoding (:func:`~iscd.decode.comms.listdecode.list_decode`) of the anchored and the
        first attempt's decisions combined (:func:`~iscd.decode.comms.listdecode.combine`,
        where they disagree), then of each alone, then of the first attempt's symbol-by-symbol
        tracked one (``PacketResult.sequential``, when it ran; v1 packets only), then of that
        attempt's survivors' own decisions where its final pass changed some (its
        ``sequential``)."""
        def ok(r: PacketResult) -> bool:
            return (r.runner_up is not None and r.margins.shape == r.levels.shape
                    and isinstance(r.air, AirInterface) and not isinstance(r.air, AirInterfaceV2))

        usable = [r for r in tries if ok(r)]
        lists = [(r, (r.levels, r.margins, r.runner_up)) for r in usable]
        if len(usable) == 2 and usable[0].levels.shape == usable[1].levels.shape \
                and (usable[0].levels != usable[1].levels).any():
            lists.insert(0, (usable[0], listdecode.combine(lists[0][1], lists[1][1])))
        seq = tries[-1].sequential
        if seq is not None and ok(seq):
            lists.append((seq, (seq.levels, seq.margins, seq.runner_up)))
        own = seq.sequential if seq is not None else None  # its survivors' own decisions
        if own is not None and ok(own):
            lists.append((own, (own.levels, own.margins, own.runner_up)))
        for r, (levels, margins, runner) in lists:
            self.stats["list_tries"] += 1
            got = listdecode.list_decode(r.air, levels, margins, runner)
            if got is not None:
                fixed, raw, flips, _ = got
                self.stats["list_delivered"] += 1
                return replace(r, levels=fixed, raw=raw, crc_ok=True, reason="",
                               list_flips=int((fixed != r.levels).sum()))
        return None

    def _emit(self, res: PacketResult) -> Packet:
        base = self._base or 0
        q = res.quality()
        pkt = Packet(frame=base + res.first_frame, t_s=self._frame_time(res.u0),
                     u0_frames=base + res.u0, crc_ok=res.crc_ok,
                     payload=res.raw if res.crc_ok else None, levels=res.levels, raw=res.raw,
                     quality=q, margins=res.margins, version=res.version,
                     shape=(res.air.rows, res.air.cols) if isinstance(res.air, AirInterfaceV2) else None)
        self.stats["packets_ok" if res.crc_ok else "packets_bad"] += 1
        return pkt

    def _accept(self, res: PacketResult) -> None:
        """Lock on a demodulated packet: the next header is one period later."""
        real = res.crc_ok or res.training_rho >= 0.9
        # the retry with the period free runs at most once per delivered packet
        self._prior_delivered = bool(res.crc_ok)
        # a clock fit on bad data must not stall the search: the period stays within
        # +-2000 ppm of nominal and the next header is always ahead of this one
        p = float(np.clip(res.p, self.p_nom * (1 - 2e-3), self.p_nom * (1 + 2e-3))) if np.isfinite(res.p) else self.p_nom
        if real:
            air = res.air or self.air  # (a v2 packet: the geometry its header said)
            self._geom = air
            self._p = p
            # the period as well known as this packet's frames pinned it (at least 20 ppm;
            # a packet whose boundaries stayed in the exposure gap pins nothing)
            post = res.p_sigma if np.isfinite(res.p_sigma) else 0.0
            self._p_sigma = float(min(max(20e-6 * self.p_nom, post), self.cfg.drift_max_ppm * 1e-6 * self.p_nom))
            self._expect = res.u0 + air.period_symbols * p
            self._search = res.u0 + air.packet_symbols * p - 2 * p
        else:  # possibly a false header: search again right after it (a real header
            # may start within its span)
            self._expect = None
            self._search = res.u0 + 2.0

    def _need(self, u: float, expected: bool = False) -> float:
        """Buffer rows needed to demodulate a packet starting at u: one of the receiver's
        v1 geometry, or for the ``expected`` next packet one like the last (a v2 packet's
        length is its header's); at the end of the stream just its PHY header (a shorter
        v2 packet may end there: the demodulator says if it is incomplete)."""
        symbols = (self._geom if expected else self.air).packet_symbols
        if self._flushing:  # up to the clean frame of the last symbol (timing.clean_frame)
            if self.cfg.air_v2:
                symbols = min(symbols, HEADER_SYMBOLS + header_symbols(self.N))
            return u + (symbols - 0.5) * self._p - self.e / 2 + 0.5
        return u + symbols * self._p + 3

    def flush(self) -> list[Packet]:
        """End of stream: decode a packet whose last frames arrived just now (normally
        held back by a safety margin of 3 frames); incomplete packets are dropped."""
        self._flushing = True
        self._wait_until = 0.0
        try:
            out = self._process()
            self._release(out, force=True)
            return out
        finally:
            self._flushing = False

    def _demod(self, u: float) -> PacketResult | Rejection:
        return demodulate_packet(self._L[:, :self._n], u, self.air, self.e, self.p_nom,
                                 self._p, self._p_sigma, self.cfg, grid=self.grid,
                                 retry_unlocked=self._prior_delivered)

    MAX_STEPS = 8
    """Most search/demodulation steps in one push: a safety net so that one push can never
    spin (the state still advances, so the next push continues)."""

    def _process(self) -> list[Packet]:
        out: list[Packet] = []
        self._release(out)
        for _ in range(self.MAX_STEPS):
            if self._expect is not None:
                if self._need(self._expect, expected=True) > self._n or self._n < self._expect_wait:
                    return out
                res = self._demod(self._expect)
                if isinstance(res, Rejection) and res.incomplete:
                    if res.need_frames is not None:  # a longer v2 packet than the last
                        self._expect_wait = res.need_frames
                    return out
                self._expect_wait = 0.0
                if isinstance(res, PacketResult):
                    self._emit_once(res, out)
                    self._accept(res)
                    continue
                log.info("expected header at frame %.1f not found (%s): searching",
                         (self._base or 0) + self._expect, res.reason)
                self._search = max(self._search, self._expect - 2 * self._p)
                self._expect = None
                self._p_sigma = max(self._p_sigma, 50e-6 * self.p_nom)
            # search [self._search, end) for headers whose packet is complete
            lo = int(max(0, np.floor(self._search) - 2))
            hdr = HEADER_SYMBOLS * self._p + 2
            if self._n - lo < hdr + 4 or self._n < self._wait_until:
                return out
            if self._range is None or self._n - self._range_at >= self.RANGE_EVERY:
                # per-LED luminance range from the latest ~2 packets (every 4th frame)
                a = max(0, self._n - self.keep)
                self._range = luminance_range(self._L[:, a:self._n], step=4)
                self._range_at = self._n
            # widened by the searched frames' own range (an LED that just lit up)
            rlo, rhi = luminance_range(self._L[:, lo:self._n])
            y = normalized_mean(self._L[:, lo:self._n], np.fmin(self._range[0], rlo),
                                np.fmax(self._range[1], rhi))
            cands = coarse_header_search(y, self._p, self.e, self.cfg.header_phases,
                                         self.cfg.header_rho)
            cands = sorted((c for c in cands if c.u0 + lo >= self._search - 1), key=lambda c: c.u0)
            progressed = False
            for c in cands:
                u = c.u0 + lo
                if self._need(u) > self._n:
                    # wait for more frames; nothing before u is a header
                    self._search = max(self._search, u - 2)
                    self._wait_until = self._need(u)
                    return out
                res = self._demod(u)
                if isinstance(res, Rejection) and res.incomplete:
                    self._search = max(self._search, u - 2)
                    self._wait_until = self._n + 2 if res.need_frames is None else res.need_frames
                    return out
                if isinstance(res, PacketResult):
                    self._emit_once(res, out)
                    self._accept(res)
                    progressed = True
                    break
                self.stats["false_headers"] += 1
                self._search = max(self._search, u + 1)
            if not progressed:
                # the whole searched range holds no complete packet's header
                self._search = max(self._search, self._n - hdr - 2)
                self._wait_until = self._n + max(16.0, hdr / 2)
                return out
        self.stats["step_limit"] = self.stats.get("step_limit", 0) + 1
        log.warning("packet search hit its step limit in one push; continuing with the next")
        return out
