"""Several transmitters at once: one :class:`~iscd.decode.stream.StreamDecoder` per transmitter.

A road has several transmitters in view (a traffic light's array, the tail lights of the car
ahead, a road-side unit), each on its own clock and at its own distance, and LED lights that
blink without sending anything. :class:`MultiDecoder` holds up to ``[tracking]
max_transmitters`` stream decoders, each with its own tracking, symbol timing, channel,
packet assembly and ranging:

* **one searcher.** While fewer than ``max_transmitters`` are tracked, one decoder without a
  track looks for the next transmitter. Its detection leaves out the boxes of every
  transmitter the others track (in both cameras) and every candidate one of them rejected
  (a blinker is rejected once, for all). While nothing is tracked it searches every frame,
  as one decoder does; while something is, it tries every ``search_every_frames`` frames
  (each try reads ``acquire_frames`` whole frames), so that following the transmitters in
  view stays the frame loop's main cost.
* **confirmed by its own header.** A new track is a *candidate*: its records (ranges, a
  failed packet) are held back, bounded, until its first CRC-valid packet. Then it gets the
  next ``tx`` index (0, 1, 2, ...; never reused in a run), its held records go out with it,
  and it keeps that index while it is tracked. A candidate that sends no header within
  ``verify_packets`` packet durations is rejected (the stream decoder's own rule: PWM-dimmed
  tail lights, flickering lamps) and its held records are dropped (counted).
* **born and lost.** A transmitter dark for ``lost_packets`` packet durations is lost (its
  ``tx`` retired); its decoder becomes the searcher, or is closed if there is one already.
* **one place per transmitter.** Two tracks that settle on the same lights (both cameras'
  centres within a pitch) keep the older; the younger starts again.

Records are the stream decoder's, with ``tx`` set to the transmitter's index; packets that
complete after their track ended keep the index the track had. ``counters`` sums every
decoder's (those of closed ones included) and adds the transmitters' own; :meth:`transmitters`
gives per-transmitter figures for the stats.

No threads and no I/O of its own (the stream decoders' demodulation workers, if any, are
theirs); ``replay`` and the daemon use it alike when ``max_transmitters > 1``.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from iscd.calibration.io import StereoCalibration
from iscd.core.config import Config, section
from iscd.decode.stream import KeptFrames, PipelineSettings, StreamDecoder, parse_shapes, shared_buffers

log = logging.getLogger(__name__)

HELD_RECORDS = 20000
"""At most this many records of one candidate are held back before its first packet
(older ones are dropped, counted): a candidate is decided within ``verify_packets``
packet durations, ~2 records a frame."""


@dataclass
class _Slot:
    """One stream decoder and the transmitter it tracks."""

    dec: StreamDecoder
    born: int
    """order of creation (the older of two tracks on the same lights is kept)"""
    tx: int | None = None
    """the transmitter's index once confirmed by a CRC-valid packet, else None"""
    held: list[dict] = field(default_factory=list)
    """records of an unconfirmed candidate, held back"""
    retired: list[tuple[int, int]] = field(default_factory=list)
    """(tx, last frame) of this decoder's earlier transmitters (late packets keep their tx)"""
    acquisitions: int = 0
    """the decoder's acquisitions counter when this slot's tx was given"""
    since_frame: int = -1
    """first frame of the current track"""
    stats: Counter = field(default_factory=Counter)
    """this slot's current transmitter's packets_ok, packets_bad, ranges"""
    last_z: float = math.nan


class MultiDecoder:
    """Decodes every transmitter in view, each with its own :class:`StreamDecoder` (see the
    module docstring). The interface is the stream decoder's (push, finish_block, finish,
    finish_within, close, restart, counters, needed_windows), so replay and the daemon take
    either."""

    def __init__(self, cfg: Config, calibration: StereoCalibration | None = None, *,
                 max_transmitters: int | None = None, async_demod: bool | str = False,
                 compiled: bool = True) -> None:
        self.cfg = cfg
        self.cal = calibration
        self.settings = section(cfg, PipelineSettings)
        self.max_transmitters = int(max_transmitters or self.settings.max_transmitters)
        if self.max_transmitters < 1:
            raise ValueError(f"max_transmitters must be >= 1, got {self.max_transmitters}")
        self.search_every = max(self.settings.acquire_frames, int(self.settings.search_every_frames))
        self.allowed_shapes = parse_shapes(self.settings.shapes)
        if self.allowed_shapes != "config" and not cfg.transmitter.shape_auto:
            # each transmitter's shape inferred (v1 packets read with [transmitter]'s M, K, F)
            self.cfg = cfg = cfg.replace(transmitter=replace(cfg.transmitter, rows=0, cols=0))
        self._async = async_demod
        self._compiled = compiled
        self._shared: Any = None
        """one demodulation worker process for every transmitter (async_demod="process"):
        each decoder has its slot in it (:class:`iscd.decode.worker.SlotWorker`)"""
        if async_demod == "process":
            from iscd.decode.pipe import PipeDemodWorker

            self._shared = PipeDemodWorker()
        self._born = 0
        self.slots: list[_Slot] = []
        self._closed: Counter = Counter()
        """counters of the decoders closed so far"""
        self.own: dict[str, int] = {"transmitters_confirmed": 0, "transmitters_lost": 0,
                                    "candidate_records_dropped": 0,
                                    "duplicate_tracks": 0, "search_attempts": 0, "demod_steps_abandoned": 0}
        self._next_tx = 0
        self.events: deque[tuple[str, int, int]] = deque(maxlen=1000)
        """("confirmed" | "lost", tx, frame id) as they happen (the last 1000)"""
        self._last_id: int | None = None
        self._deferred: list[_Slot] = []
        self._excluded: list[tuple[tuple[int, int, int, int], int]] = []
        """(left box, until frame id) of rejected candidates, for every searcher"""
        self._final: list[dict[str, Any]] = []
        self._rejections: list[tuple[tuple[int, int, int, int], int]] = []
        """(box, times) of places rejected (exclusion back-off)"""
        self._search_block: tuple | None = None
        """a block pushed with defer=True, for the searcher in finish_block"""
        self._catch_buffers: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        """the buffers every decoder decodes a find's kept frames through and looks in
        (:meth:`prepare` makes them before the first frame, not while a find waits)"""
        self._look_lock = threading.Lock()
        self._new_slot()

    # ------------------------------------------------------------------ slots
    def _new_slot(self) -> _Slot:
        worker = None
        if self._shared is not None:
            from iscd.decode.worker import SlotWorker

            worker = SlotWorker(self._shared, self._born)
        dec = StreamDecoder(self.cfg, self.cal, tx_index=-1, settings=self.settings,
                            async_demod=self._async, compiled=self._compiled, demod_worker=worker)
        if isinstance(self.allowed_shapes, set):
            dec.allowed_shapes = self.allowed_shapes
        dec.catch_buffers = self._catch_buffers  # one set for all (they decode one at a time,
        dec.look_lock = self._look_lock          # and look one at a time)
        s = _Slot(dec=dec, born=self._born)
        self._born += 1
        self.slots.append(s)
        return s

    def _close_slot(self, s: _Slot, wait: bool = True) -> list[dict]:
        if wait:
            recs = s.dec.finish()
        else:
            recs, abandoned = s.dec.drop()
            self.own["demod_steps_abandoned"] += abandoned
        out = self._route(s, recs)
        self._closed.update(s.dec.counters)
        self.slots.remove(s)
        return out

    def prepare(self, height: int, width: int, dtype: Any) -> None:
        """Make and touch the look and catch-up buffers for frames of this size now (the
        daemon, before its first frame: their page faults are ~0.1 s here)."""
        frame = np.empty((int(height), int(width)), dtype)
        for use in ("catch", "look"):
            shared_buffers(self._catch_buffers, frame, self.settings.acquire_frames, use)

    @property
    def lookback_frames(self) -> int:
        """Most recent frames a searcher keeps (whole pairs: the look-back of
        :meth:`StreamDecoder.set_lookback`), for the daemon's block pool."""
        return self.search_every + self.settings.acquire_frames

    @property
    def searcher(self) -> _Slot | None:
        """The decoder looking for the next transmitter (None when all slots track one)."""
        for s in self.slots:
            if s.dec.track is None:
                return s
        return None

    def tracked(self) -> list[_Slot]:
        """Slots with a track (confirmed or candidate), oldest first."""
        return [s for s in self.slots if s.dec.track is not None]

    # ------------------------------------------------------------------ records
    def _route(self, s: _Slot, records: list[dict]) -> list[dict]:
        """The slot's records with their ``tx``; a candidate's held back until it is confirmed."""
        out: list[dict] = []
        for rec in records:
            if rec.get("type") == "packet":
                # a packet that completed after its track ended keeps that track's tx
                old = next((tx for tx, last in s.retired if rec.get("frame", -1) <= last), None)
                if old is not None:
                    rec["tx"] = old
                    out.append(rec)
                    continue
                if s.tx is None and rec.get("crc_ok") and s.dec.track is not None:
                    self._confirm(s)
                    out += self._release(s)
            if s.tx is None:
                if len(s.held) >= HELD_RECORDS:
                    s.held.pop(0)
                    self.own["candidate_records_dropped"] += 1
                s.held.append(rec)
                continue
            rec["tx"] = s.tx
            self._tally(s, rec)
            out.append(rec)
        return out

    def _tally(self, s: _Slot, rec: dict) -> None:
        t = rec.get("type")
        if t == "packet":
            s.stats["packets_ok" if rec.get("crc_ok") else "packets_bad"] += 1
        elif t == "range":
            s.stats["ranges"] += 1
            s.last_z = float(rec.get("z_m") or math.nan)

    def _confirm(self, s: _Slot) -> None:
        s.tx = self._next_tx
        self._next_tx += 1
        s.dec.tx_index = s.tx
        s.stats = Counter()
        s.last_z = math.nan
        self.own["transmitters_confirmed"] += 1
        self.events.append(("confirmed", s.tx, self._last_id if self._last_id is not None else -1))
        tr = s.dec.track
        assert tr is not None
        log.info("transmitter tx=%d confirmed by its header at left %.1f,%.1f (%dx%d LEDs)",
                 s.tx, *tr.left.center, tr.left.rows, tr.left.cols)

    def _release(self, s: _Slot) -> list[dict]:
        out = []
        for rec in s.held:
            rec["tx"] = s.tx
            self._tally(s, rec)
            out.append(rec)
        s.held = []
        return out

    BACKOFF_MAX = 16
    """A place rejected again is left out twice as long each time, up to this many times
    ``exclude_packets`` (a PWM-dimmed tail light stays in view: trying it again every
    ``exclude_packets`` would track it a quarter of the time)."""

    def _back_off(self, s: _Slot, now: int) -> None:
        """The candidate ``s`` just rejected: lengthen its exclusion if its place was
        rejected before (its centre inside an earlier rejection's box)."""
        box, until = s.dec.excluded[-1]
        cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
        n = 1
        for i, (b, k) in enumerate(self._rejections):
            if b[0] <= cx < b[2] and b[1] <= cy < b[3]:
                n = k + 1
                del self._rejections[i]
                break
        self._rejections.append((box, n))
        self._rejections = self._rejections[-64:]
        factor = min(2 ** (n - 1), self.BACKOFF_MAX)
        if factor > 1:
            log.info("the place at %d,%d was rejected %d times: left out %d times as long", int(cx), int(cy), n, factor)
        until = now + factor * (until - now)
        s.dec.excluded[-1] = (box, until)
        self._excluded.append((box, until))  # for every searcher, whichever slot it is

    def _track_ended(self, s: _Slot, last_frame: int) -> None:
        """The slot's track is gone (lost, rejected, restarted)."""
        if s.tx is None:
            if s.held:
                self.own["candidate_records_dropped"] += len(s.held)
            s.held = []
            return
        log.info("transmitter tx=%d lost at frame %d", s.tx, last_frame)
        self.own["transmitters_lost"] += 1
        self.events.append(("lost", s.tx, last_frame))
        s.retired.append((s.tx, last_frame))
        s.retired = s.retired[-4:]
        s.tx = None
        s.dec.tx_index = -1

    # ------------------------------------------------------------------ main entry
    def _excludes(self, s: _Slot) -> tuple[list, list]:
        """What the searcher ``s`` leaves out: the others' tracks and rejected candidates."""
        left: list = []
        right: list = []
        for o in self.slots:
            if o is s:
                continue
            tr = o.dec.track
            if tr is not None:
                for fit, out in ((tr.left, left), (tr.right, right)):
                    out.append(fit.bbox(max(4.0, fit.pitch_px, fit.spot_px)))
        now = self._last_id if self._last_id is not None else 0
        self._excluded = [(b, until) for b, until in self._excluded if until > now]
        left += [b for b, _ in self._excluded]
        return left, right

    def push(self, frame_ids: np.ndarray, t_s: np.ndarray, left: np.ndarray, right: np.ndarray,
             *, ranging: bool = True, ranging_every: int = 1, per_led: bool = True,
             defer: bool = False, owned: bool = False) -> list[dict]:
        """Process a block of stereo frames (as :meth:`StreamDecoder.push`, ``owned``
        included: the searcher keeps views of owned frames); returns the records it
        produced, each with its transmitter's ``tx``."""
        out: list[dict] = self.finish_block() if (self._deferred or self._search_block) else []
        n = len(frame_ids)
        if n == 0:
            return out
        last = int(frame_ids[-1])
        self._last_id = last
        kw = dict(ranging=ranging, ranging_every=ranging_every, per_led=per_led)
        for s in list(self.slots):
            if s.dec.track is None:
                continue
            out += self._push_slot(s, frame_ids, t_s, left, right, defer=defer, **kw)
        kw_search = dict(kw, owned=owned)
        if defer:  # the searcher's turn comes in finish_block (the caller keeps the frames)
            self._search_block = (frame_ids, t_s, left, right, kw_search)
            return out
        out += self._search(frame_ids, t_s, left, right, **kw_search)
        out += self._housekeeping(last)
        return out

    def range_ahead(self, frame_ids: np.ndarray, t_s: np.ndarray, left: np.ndarray, right: np.ndarray,
                    *, ranging: bool = True, ranging_every: int = 1, per_led: bool = True) -> list[dict]:
        """:meth:`StreamDecoder.range_ahead` for every tracked transmitter (records with
        their ``tx``; a candidate's held until its header, as its other records)."""
        self.drop_ahead()
        if self._deferred or self._search_block:
            return []
        out: list[dict] = []
        for s in self.slots:
            if s.dec.track is not None:
                out += self._route(s, s.dec.range_ahead(frame_ids, t_s, left, right, ranging=ranging,
                                                       ranging_every=ranging_every, per_led=per_led))
        return out

    @property
    def ranged_ahead(self) -> int:
        """Pairs whose range records :meth:`range_ahead` put out for every tracked
        transmitter (0 when one of them did not, or none is tracked)."""
        counts = [s.dec.ranged_ahead for s in self.slots if s.dec.track is not None]
        return min(counts) if counts else 0

    def drop_ahead(self) -> None:
        """:meth:`StreamDecoder.drop_ahead` for every transmitter."""
        for s in self.slots:
            s.dec.drop_ahead()

    def _push_slot(self, s: _Slot, frame_ids, t_s, left, right, *, defer: bool = False,
                   adopt: KeptFrames | None = None, **kw: Any) -> list[dict]:
        had = s.dec.track is not None
        acq = s.dec.counters["acquisitions"]
        rejected = s.dec.counters["rejected_candidates"]
        recs = s.dec.push(frame_ids, t_s, left, right, defer=defer, adopt=adopt, **kw)
        if s.dec.counters["rejected_candidates"] != rejected and s.dec.excluded:
            self._back_off(s, int(frame_ids[-1]))
        if defer and s.dec.track is not None:
            self._deferred.append(s)
        out = self._route(s, recs)
        if s.dec.counters["acquisitions"] != acq:
            s.since_frame = int(frame_ids[0])
        if had and s.dec.track is None:
            self._track_ended(s, int(frame_ids[-1]))
        return out

    def _search(self, frame_ids, t_s, left, right, **kw: Any) -> list[dict]:
        """Hand the block to the searcher when it is time to look for another transmitter."""
        tracked = self.tracked()
        s = self.searcher
        if s is None and len(self.slots) < self.max_transmitters:
            s = self._new_slot()
        if s is None:
            return []
        out: list[dict] = []
        A = self.settings.acquire_frames
        adopt: KeptFrames | None = None
        while True:
            s.dec.extra_exclude = self._excludes(s)
            s.dec.blinker_places = [b for b, _ in self._rejections]
            s.dec.keep_acquired = True
            # nothing tracked: look at every acquire_frames, as one decoder does; else every
            # search_every, keeping the frames since the last look (decoded from the first
            # of them if something new is found: its first whole packet is among them)
            s.dec.set_lookback(A if not tracked else self.search_every, self.search_every + A,
                               look_async=self._async == "process")
            attempts = s.dec.attempts
            out += self._push_slot(s, frame_ids, t_s, left, right, adopt=adopt, **kw)
            got, s.dec.acquired = s.dec.acquired, None
            if s.dec.attempts != attempts:
                self.own["search_attempts"] += s.dec.attempts - attempts
            if s.dec.track is None:
                return out
            if got is None or len(self.slots) >= self.max_transmitters:
                return out
            # found one: another transmitter may be in the same frames (a first packet
            # whose header is among them): a new searcher looks at them at once
            s = self._new_slot()
            # its kept frames, taken over without a copy (the look is on their last frames)
            adopt = got
            frame_ids, t_s, left, right = got.ids, got.t_s, None, None

    def finish_block(self) -> list[dict]:
        """The rest of the blocks pushed with ``defer=True`` (see :meth:`StreamDecoder.finish_block`)."""
        out: list[dict] = []
        deferred, self._deferred = self._deferred, []
        now = self._last_id if self._last_id is not None else -1
        for s in deferred:
            had = s.dec.track is not None
            rejected = s.dec.counters["rejected_candidates"]
            out += self._route(s, s.dec.finish_block())
            # a candidate rejected in the deferred part (its header search runs there): the
            # same back-off as in _push_slot (without it the daemon, which defers, tried a
            # tail light again every exclude_packets)
            if s.dec.counters["rejected_candidates"] != rejected and s.dec.excluded:
                self._back_off(s, now)
            if had and s.dec.track is None:
                self._track_ended(s, now)
        blk, self._search_block = self._search_block, None
        if blk is not None:
            frame_ids, t_s, left, right, kw = blk
            out += self._search(frame_ids, t_s, left, right, **kw)
            out += self._housekeeping(int(frame_ids[-1]))
        return out

    def _housekeeping(self, now: int) -> list[dict]:
        out: list[dict] = []
        # tracks that ended (after their own step): their slots free; one searcher at most
        for s in self.slots:
            if s.dec.track is None and s.tx is not None:
                self._track_ended(s, now)
        idle = [s for s in self.slots if s.dec.track is None]
        if len(idle) > 1:
            # one searcher is enough; keep the one whose last transmitter may still have a
            # packet in the worker, close the others without waiting for the worker (a
            # rejected candidate has nothing to deliver; a wait stalled the frame loop)
            idle.sort(key=lambda s: not (s.retired and s.dec.pending_steps))
            for s in idle[1:]:
                out += self._close_slot(s, wait=False)
        # two tracks on the same lights: the younger starts again
        tr = sorted(self.tracked(), key=lambda s: (s.tx is None, s.born))
        for i, a in enumerate(tr):
            for b in tr[i + 1:]:
                if a.dec.track is None or b.dec.track is None:
                    continue
                if _same_place(a.dec.track, b.dec.track):
                    self.own["duplicate_tracks"] += 1
                    log.info("two tracks on the same lights at %.0f,%.0f: the younger restarts",
                             *b.dec.track.left.center)
                    b.dec.restart()
                    self._track_ended(b, now)
        return out

    def finish(self) -> list[dict]:
        """End of stream: every decoder's last packets."""
        out = self.finish_block()
        self._final = self.transmitters()  # what the final stats report
        for s in list(self.slots):
            out += self._close_slot(s)
        self._stop_shared()
        return out

    def _stop_shared(self, wait: bool = True) -> None:
        if self._shared is not None:
            self._shared.shutdown(wait=wait)
            self._shared = None

    def finish_within(self, timeout_s: float) -> tuple[list[dict], int]:
        """:meth:`StreamDecoder.finish_within` of every decoder, sharing ``timeout_s``."""
        import time

        out = self.finish_block()
        self._final = self.transmitters()
        t_end = time.monotonic() + timeout_s
        abandoned = 0
        for s in list(self.slots):
            recs, ab = s.dec.finish_within(max(0.0, t_end - time.monotonic()))
            abandoned += ab
            out += self._route(s, recs)
            self._closed.update(s.dec.counters)
            self.slots.remove(s)
        self._stop_shared(wait=not abandoned)
        return out, abandoned

    def close(self) -> None:
        """Stop every decoder's demodulation worker without waiting (idempotent)."""
        for s in self.slots:
            s.dec.close()
        self._stop_shared(wait=False)

    def restart(self) -> None:
        """Drop every track (the daemon after a decoding error)."""
        now = self._last_id if self._last_id is not None else -1
        self._deferred = []
        self._search_block = None
        for s in self.slots:
            had = s.dec.track is not None
            s.dec.restart()
            if had:
                self._track_ended(s, now)

    def wait_for_worker(self, most: int) -> None:
        """:meth:`StreamDecoder.wait_for_worker` for every transmitter's decoder."""
        for s in self.slots:
            s.dec.wait_for_worker(most)

    def wait_ready(self, timeout_s: float = 300.0, should_stop: Callable[[], bool] | None = None) -> bool:
        return all(s.dec.wait_ready(timeout_s, should_stop) for s in self.slots)

    # ------------------------------------------------------------------ views for the daemon
    @property
    def counters(self) -> dict[str, int]:
        """Every decoder's counters summed (closed ones included), and the transmitters' own."""
        c = Counter(self._closed)
        for s in self.slots:
            c.update(s.dec.counters)
        out = dict(c)
        out.update(self.own)
        out["transmitters_tracked"] = sum(1 for s in self.slots if s.tx is not None and s.dec.track is not None)
        return out

    def transmitters(self) -> list[dict[str, Any]]:
        """Per confirmed transmitter in view: tx, since (frame), packets_ok/bad, ranges, the
        last range z_m, the array's shape and its left-camera centre (px); after
        :meth:`finish`, those of the end of the stream."""
        if not self.slots:
            return list(self._final)
        out = []
        for s in self.slots:
            tr = s.dec.track
            if s.tx is None or tr is None:
                continue
            out.append({"tx": s.tx, "since_frame": s.since_frame, "rows": tr.left.rows, "cols": tr.left.cols,
                        "center_px": [round(tr.left.center[0], 1), round(tr.left.center[1], 1)],
                        "packets_ok": s.stats["packets_ok"], "packets_bad": s.stats["packets_bad"],
                        "ranges": s.stats["ranges"],
                        "z_m": None if not math.isfinite(s.last_z) else round(s.last_z, 3)})
        return sorted(out, key=lambda d: d["tx"])

    @property
    def track(self) -> Any:
        """The oldest confirmed transmitter's track (the daemon's single-transmitter views)."""
        conf = [s for s in self.tracked() if s.tx is not None]
        return conf[0].dec.track if conf else None

    def tracks(self) -> list[tuple[int, Any]]:
        """(tx, track) of every confirmed transmitter in view."""
        return [(s.tx, s.dec.track) for s in self.tracked() if s.tx is not None]

    @property
    def last_luminance(self) -> Any:
        conf = [s for s in self.tracked() if s.tx is not None]
        return conf[0].dec.last_luminance if conf else None

    @last_luminance.setter
    def last_luminance(self, value: Any) -> None:
        for s in self.slots:
            s.dec.last_luminance = value

    @property
    def air(self) -> Any:
        return self.slots[0].dec.air if self.slots else StreamDecoder(self.cfg, self.cal).air

    @property
    def worker_pids(self) -> list[int]:
        return sorted({p for s in self.slots for p in s.dec.worker_pids})

    def needed_windows(self) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]] | None:
        """The union of the decoders' windows; None (whole frames) while the searcher reads."""
        if self.searcher is not None or len(self.slots) < self.max_transmitters:
            return None  # the searcher keeps whole frames
        wins = [s.dec.needed_windows() for s in self.tracked()]
        if not wins or any(w is None for w in wins):
            return None
        wl = [w[0] for w in wins]  # type: ignore[index]
        wr = [w[1] for w in wins]  # type: ignore[index]
        return _union_all(wl), _union_all(wr)


def _union_all(boxes: list[tuple[int, int, int, int]]) -> tuple[int, int, int, int]:
    return (min(b[0] for b in boxes), min(b[1] for b in boxes), max(b[2] for b in boxes), max(b[3] for b in boxes))


def _same_place(a: Any, b: Any) -> bool:
    """Two tracks on the same lights: both cameras' array centres within a pitch (4 px at least)."""
    for fa, fb in ((a.left, b.left), (a.right, b.right)):
        d = math.hypot(fa.center[0] - fb.center[0], fa.center[1] - fb.center[1])
        if d > max(4.0, fa.pitch_px, fb.pitch_px):
            return False
    return True


def make_decoder(cfg: Config, calibration: StereoCalibration | None = None, **kw: Any) -> StreamDecoder | MultiDecoder:
    """The decoder a config asks for: a :class:`MultiDecoder` when ``[tracking]
    max_transmitters`` > 1, else the one-transmitter :class:`StreamDecoder` (``kw``: their
    common keywords, ``async_demod`` and ``compiled``)."""
    if section(cfg, PipelineSettings).max_transmitters > 1:
        return MultiDecoder(cfg, calibration, **kw)
    return StreamDecoder(cfg, calibration, **kw)
