"""Recording the live stereo pairs without slowing the frame loop: ``[record]`` and
:class:`Recorder`.

The frame loop hands each pair to :meth:`Recorder.offer` (or :meth:`Recorder.pair`, the
intake's tap, with a ring slot): the pair, whole or only its windows, is packed straight
into a bounded in-memory :class:`~iscd.recording.spool.Spool` (one copy, never a wait);
when the spool is full the pair is dropped and counted. A writer thread takes the packed
records out and appends them to version-2 ``.iscr`` files (:mod:`iscd.recording.pairfile`)
in the run's folder, rotated by size or time, each sealed when it is closed. A write that
fails (disk full) stops the recording with one log line; the pairs offered after that are
counted as dropped, and the frame loop never notices.

Modes (``[record] mode``): ``full`` every pair whole; ``roi`` only the pixel windows the
decoder reads (whole frames while it has none); ``blackbox`` the last ``pre_s`` seconds
kept in the spool (pairs older than that are let go, not written), written out on
:meth:`Recorder.trigger` together with the ``post_s`` seconds after it, with no gap (a
trigger during that time extends it).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from iscd.core.config import config_section
from iscd.recording.base import RecordingError
from iscd.recording.pairfile import (MODES, PAIR_HEADER_SIZE, PairFileWriter, Window, pack_note_into, pack_pair_into,
                                     record_size)
from iscd.recording.spool import Spool

log = logging.getLogger(__name__)

MiB = 2**20


@config_section("record")
@dataclass(frozen=True)
class RecordSettings:
    """Recording the stereo pairs of a live run: full, roi or blackbox (docs/recording.md)."""

    dir: str = field(default="", metadata={"doc": "record into this folder (a sub-folder per run); '' = off (--record)"})
    mode: str = field(default="roi", metadata={"choices": MODES, "doc": "full: every pair whole; roi: the windows the decoder reads (whole frames while acquiring); blackbox: the last pre_s seconds in memory, written on a trigger with post_s after (--record-mode)"})
    rotate_mb: float = field(default=1024.0, metadata={"lo": 1, "doc": "start a new file past this size, MiB"})
    rotate_s: float = field(default=0.0, metadata={"lo": 0, "doc": "start a new file after this long, s (0 = by size only)"})
    queue_mb: float = field(default=256.0, metadata={"lo": 1, "hi": 65536, "doc": "memory between the frame loop and the writer, MiB: pairs that do not fit are dropped (record_dropped); in blackbox mode it must also hold pre_s seconds"})
    fsync_s: float = field(default=1.0, metadata={"lo": 0, "doc": "force the file to disk this often, s (0 = only when a file is closed)"})
    pre_s: float = field(default=10.0, metadata={"lo": 0, "doc": "blackbox: seconds kept before a trigger"})
    post_s: float = field(default=5.0, metadata={"lo": 0, "doc": "blackbox: seconds written after a trigger"})
    blackbox_frames: str = field(default="roi", metadata={"choices": ("roi", "full"), "doc": "blackbox: keep the decoder's windows (roi) or whole pairs (full)"})
    trigger_bad_packet: bool = field(default=True, metadata={"doc": "blackbox: a packet that fails its CRC triggers"})
    trigger_lost: bool = field(default=True, metadata={"doc": "blackbox: losing the tracked transmitter triggers"})
    drain_s: float = field(default=10.0, metadata={"lo": 0, "doc": "at the end of a run, wait at most this long for the queue to be written (the rest is counted in record_dropped)"})


RECORDING, ARMED, DUMPING, FAILED, CLOSED = "recording", "armed", "dumping", "failed", "closed"
_RUN_BYTES = 8 * MiB
"""Most bytes handed to one write."""


class Recorder:
    """Packs offered pairs into a bounded spool; a thread writes them (module docstring).

    Parameters
    ----------
    folder : the run's folder (created if missing); files ``NNNNNN-<kind>.iscr`` go there
    settings : the ``[record]`` table
    width, height : frame size, px
    dtype : pixel type (uint8 or uint16)
    fps : frame rate, frames/s (blackbox seconds are counted in frame ids at this rate)
    exposure_s : exposure time, s
    bit_depth : significant bits per pixel
    meta : JSON-serializable entries stored in every file's metadata (the config, the
        calibration, the session name)
    beside : files written into ``folder`` at the start (name -> text), e.g. config.toml
    """

    def __init__(self, folder: str | Path, settings: RecordSettings, *, width: int, height: int, dtype: Any,
                 fps: float, exposure_s: float | None = None, bit_depth: int | None = None,
                 meta: dict[str, Any] | None = None, beside: dict[str, str] | None = None) -> None:
        self.folder = Path(folder)
        self.settings = s = settings
        self.mode = s.mode
        self.width, self.height = int(width), int(height)
        self.dtype = np.dtype(dtype)
        self.fps = float(fps)
        self._file_args = dict(width=self.width, height=self.height, dtype=self.dtype.name, mode=self.mode,
                               fps=self.fps, exposure_s=exposure_s, bit_depth=bit_depth)
        self.meta = dict(meta or {})
        self.keep_whole = s.mode == "full" or (s.mode == "blackbox" and s.blackbox_frames == "full")
        self._full: Window = (0, 0, self.width, self.height)
        self.pre_frames = int(round(s.pre_s * self.fps))
        self.post_frames = int(round(s.post_s * self.fps))
        self.spool = Spool(int(s.queue_mb * MiB))
        self.rotate_bytes = int(s.rotate_mb * MiB)
        # counters: the frame loop's (written by it only) ...
        self.offered = 0
        self.dropped_queue = 0
        """pairs dropped because the spool was full"""
        self.dropped_stopped = 0
        """pairs offered after the recording stopped (disk full)"""
        self.errors = 0
        self.triggers = 0
        self.evicted = 0
        """blackbox: pairs let go unwritten (older than pre_s before any trigger)"""
        # ... the writer's (written by it only) ...
        self.written = 0
        self.bytes_written = 0
        self.files = 0
        self.write_errors = 0
        self.lost_at_failure = 0
        """pairs the spool held when the recording stopped"""
        # ... and the end's
        self.dropped_end = 0
        """pairs still in the spool when the run ended and drain_s ran out"""
        self.failure: str | None = None
        self.paths: list[Path] = []
        self._state = ARMED if s.mode == "blackbox" else RECORDING
        self._state_lock = threading.Lock()
        self._trigger_req: str | None = None
        self._dump_reason = ""
        self._trigger_id = -1
        self._next_trigger: tuple[int, str] | None = None
        self._end_id = -1
        self._last_id: int | None = None
        self._file: PairFileWriter | None = None
        self._file_t0 = 0.0
        self._seq = 0
        self._last_sync = time.monotonic()
        self._closing = False
        self._wake = threading.Event()
        self._rate_t, self._rate_bytes = time.monotonic(), 0
        self._drop_logged = 0.0
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            for name, text in (beside or {}).items():
                (self.folder / name).write_text(text, encoding="utf-8")
        except OSError as e:
            self._fail(f"{self.folder}: {e.strerror or e}")
        log.info("recording (%s) into %s", self.mode if self.mode != "blackbox" else
                 f"blackbox, {s.pre_s:g} s before and {s.post_s:g} s after a trigger", self.folder)
        self._thread = threading.Thread(target=self._run, name="iscd-record", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the frame loop's side
    def pair(self, slot: Any, windows: tuple[Window, Window] | None, block: int) -> None:
        """The intake's tap: a ring slot (``left``, ``right``, ``frame_id``, ``ts_left_ns``,
        ``ts_right_ns``) taken into decoder block ``block``, read in ``windows`` (None:
        whole frames). Never raises, never waits."""
        try:
            self.offer(slot.frame_id, slot.ts_left_ns, slot.ts_right_ns, block, slot.left, slot.right, windows)
        except Exception:  # noqa: BLE001 - a recording must never stop the decoding
            self.errors += 1
            if self.errors <= 3:
                log.exception("recording: a pair could not be packed")

    def offer(self, frame_id: int, ts_left_ns: int, ts_right_ns: int, block: int, left: np.ndarray,
              right: np.ndarray, windows: tuple[Window, Window] | None) -> bool:
        """Pack one pair into the spool (a copy of its windows, or of the whole frames);
        False when it was dropped (spool full, recording stopped). ``left``/``right``: (H, W)
        frames; ``ts_*_ns``: exposure timestamps, ns; ``block``: the decoder's block number."""
        self.offered += 1
        fid = int(frame_id)
        if self._trigger_req is not None:
            self._start_trigger(fid)
        state = self._state
        if state in (FAILED, CLOSED):
            self.dropped_stopped += 1
            return False
        if windows is None or self.keep_whole:
            wl = wr = self._full
        else:
            wl, wr = windows
        whole = wl == self._full and wr == self._full
        size = record_size(wl, wr, self.dtype.itemsize)
        if state == ARMED:
            self.evicted += self.spool.evict_before(fid - self.pre_frames)
            off, k = self.spool.reserve_evicting(size)
            self.evicted += k
        else:
            off = self.spool.reserve(size)
        self._last_id = fid
        if off is None:
            self.dropped_queue += 1
            now = time.monotonic()
            if now - self._drop_logged >= 10.0:
                self._drop_logged = now
                log.warning("recording: the writer is behind, pairs are dropped (%d so far; record_dropped "
                            "in the stats); a faster disk, a larger [record] queue_mb or mode roi",
                            self.dropped_queue)
            return False
        pack_pair_into(self.spool.buf, off, fid, int(ts_left_ns), int(ts_right_ns), int(block), left, right,
                       wl, wr, whole)
        self.spool.commit(off, size, fid)
        return True

    def note_block(self, block: int, ranging_every: int, per_led: bool, ahead: int = 0) -> None:
        """What the decoder was let do on ``block`` (the overload policy's shedding) and how
        many of its first pairs it ranged ahead, stored after its pairs as a block note so
        that a replay does the same; only called when something was shed or ranged ahead. A
        note that does not fit in the spool is left out."""
        state = self._state
        if state in (FAILED, CLOSED) or self._last_id is None:
            return
        off = self.spool.reserve(PAIR_HEADER_SIZE)
        if off is None:
            return
        pack_note_into(self.spool.buf, off, self._last_id, int(block), int(ranging_every), bool(per_led), int(ahead))
        self.spool.commit(off, PAIR_HEADER_SIZE, self._last_id, pair=False)

    def trigger(self, reason: str) -> None:
        """Blackbox: write out the last ``pre_s`` seconds and the ``post_s`` after (taken at
        the next pair offered; safe from a signal handler or another thread). Other modes:
        nothing."""
        if self.mode == "blackbox":
            self._trigger_req = reason

    def _start_trigger(self, fid: int) -> None:
        reason, self._trigger_req = self._trigger_req or "trigger", None
        with self._state_lock:
            self.triggers += 1
            if self._state == ARMED:
                self.evicted += self.spool.evict_before(fid - self.pre_frames)
                self._dump_reason = reason
                self._trigger_id = fid
                self._end_id = fid + self.post_frames
                self._state = DUMPING
                held = self.spool.peek(1)
                first = held[0].frame_id if held else fid
                log.warning("blackbox: %s at frame %d: writing frames from %d (%.2f s before; pre_s %g) to %d "
                            "(%g s after)", reason, fid, first, (fid - first) / self.fps, self.settings.pre_s,
                            self._end_id, self.settings.post_s)
            elif self._state == DUMPING and fid <= self._end_id:  # within the frames after the last one
                self._end_id = fid + self.post_frames
                log.info("blackbox: %s at frame %d: writing on to frame %d", reason, fid, self._end_id)
            elif self._state == DUMPING:  # after them, but the writer is not done: the next dump
                self._next_trigger = (fid, reason)
        self._wake.set()

    # ------------------------------------------------------------------ the writer thread
    def _run(self) -> None:
        while True:
            self._wake.wait(0.01)
            self._wake.clear()
            closing = self._closing
            try:
                more = self._write_some()
                if self._file is not None and self.settings.fsync_s > 0 \
                        and time.monotonic() - self._last_sync >= self.settings.fsync_s:
                    self._file.sync()
                    self._last_sync = time.monotonic()
            except OSError as e:
                path = self._file.path if self._file is not None else self.folder
                self._fail(f"{path}: {e.strerror or e}")
                more = False
            except RecordingError as e:  # a new file could not be created
                self._fail(str(e))
                more = False
            if closing and not more:
                break
            if more:
                self._wake.set()
        self._close_file()

    def _write_some(self) -> bool:
        """Write what the spool holds (at most ~8 MiB at a time); True if more is waiting."""
        state = self._state
        if state not in (RECORDING, DUMPING):
            return False  # armed: the blackbox holds its pairs; failed or closed: nothing more
        items = self.spool.peek(512)
        if state == DUMPING and not self._closing:  # (closing: what is held up to the last pair)
            with self._state_lock:
                end = self._end_id
            n = 0
            while n < len(items) and items[n].frame_id <= end:
                n += 1
            if n == 0:
                if items or (self._last_id is not None and self._last_id > end):
                    self._end_dump()
                return False
            items = items[:n]
        if not items:
            return False
        done = 0
        for a, _, run in self.spool.runs(items):
            sizes = [it.size for it in run]
            pos, i = a, 0
            while i < len(sizes):  # a run is cut by the write size and by rotations
                f = self._current_file()
                limit = self.rotate_bytes - f.size
                j, nbytes = i, 0
                while j < len(sizes):
                    s = sizes[j]
                    if j > i and nbytes + s > _RUN_BYTES:
                        break
                    if nbytes + s > limit and not (f.n_pairs == 0 and j == i):
                        break
                    nbytes += s
                    j += 1
                if j == i:  # this file is full
                    self._close_file()
                    continue
                pairs = sum(it.pair for it in run[i:j])
                try:
                    f.write_records(self.spool.buf[pos:pos + nbytes].data, sizes[i:j], pairs)
                except OSError as e:  # the records written whole before the error count
                    k = getattr(e, "pairs_written", 0)
                    self.spool.release(k)
                    self.written += sum(it.pair for it in run[i:i + k])
                    self.bytes_written += sum(sizes[i:i + k])
                    raise
                self.spool.release(j - i)
                self.written += pairs
                self.bytes_written += nbytes
                done += nbytes
                pos += nbytes
                i = j
                if done >= _RUN_BYTES:
                    return True
        return len(self.spool) > 0

    def _current_file(self) -> PairFileWriter:
        f = self._file
        if f is not None and self.settings.rotate_s > 0 and time.monotonic() - self._file_t0 >= self.settings.rotate_s:
            self._close_file()
            f = None
        if f is None:
            kind = self.mode if self.mode != "blackbox" else "trigger-" + re.sub(r"[^a-z0-9]+", "-",
                                                                               self._dump_reason.lower()).strip("-")
            path = self.folder / f"{self._seq:06d}-{kind}.iscr"
            meta = {**self.meta, "segment": self._seq}
            if self.mode == "blackbox":
                meta.update(reason=self._dump_reason, trigger_frame=self._trigger_id, pre_s=self.settings.pre_s,
                            post_s=self.settings.post_s)
            self._seq += 1
            f = self._file = PairFileWriter(path, meta=meta, **self._file_args)
            self._file_t0 = time.monotonic()
            self.files += 1
            self.paths.append(path)
        return f

    def _close_file(self) -> None:
        f, self._file = self._file, None
        if f is not None:
            try:
                f.close()
            except OSError as e:
                self._fail(f"{f.path}: {e.strerror or e}")

    def _end_dump(self) -> None:
        """The frames after a trigger are written: close the file; armed again, or the next
        dump when a trigger came meanwhile."""
        self._close_file()
        with self._state_lock:
            if self._state != DUMPING:
                return
            log.info("blackbox: written up to frame %d", self._end_id)
            nxt, self._next_trigger = self._next_trigger, None
            if nxt is None:
                self._state = ARMED
                return
            fid, reason = nxt
            self.evicted += self.spool.evict_before(fid - self.pre_frames)
            self._dump_reason, self._trigger_id, self._end_id = reason, fid, fid + self.post_frames
        log.warning("blackbox: %s at frame %d: writing frames from %d (%g s before) to %d (%g s after)",
                    reason, fid, max(fid - self.pre_frames, 0), self.settings.pre_s, self._end_id,
                    self.settings.post_s)

    def _fail(self, why: str) -> None:
        """Stop recording for good: one log line; what the spool holds counts as dropped."""
        with self._state_lock:
            if self._state in (FAILED, CLOSED):
                return
            self._state = FAILED
        self.write_errors += 1
        self.failure = why
        left = len(self.spool)
        pairs = self.spool.pairs_held()
        self.spool.release(left)
        self.lost_at_failure += pairs
        log.error("recording stopped: %s; decoding goes on (%d pairs written; the pairs from now on are not "
                  "written, counted in record_dropped)", why, self.written)
        f, self._file = self._file, None
        if f is not None:
            try:
                f.close()  # a failed writer writes nothing more: the file ends at its last whole pair
            except OSError:
                pass

    # ------------------------------------------------------------------ end and stats
    def drain(self, timeout_s: float) -> None:
        """Write what the spool holds (a blackbox in the middle of a dump: up to the last
        pair offered; an armed one lets its pairs go), waiting at most ``timeout_s``; the
        writer then stops. No pair may be offered after it."""
        if self._closing:
            return
        self._closing = True
        self._wake.set()
        self._thread.join(timeout_s)
        with self._state_lock:
            state = self._state
            if self._thread.is_alive():  # a stuck disk: the writer stops after its write
                self._state = CLOSED
        left = self.spool.pairs_held()
        if self._thread.is_alive():
            log.warning("recording: the writer did not finish in %g s; %d pairs are not written", timeout_s, left)
        if state in (RECORDING, DUMPING):
            self.dropped_end += left
        elif state == FAILED:
            self.dropped_stopped += left  # offered as it failed
        if not self._thread.is_alive():
            self.spool.release(len(self.spool))

    def close(self) -> None:
        """Drain (at most ``drain_s``), seal the last file, stop the writer (idempotent)."""
        if self._state == CLOSED and self._closing:
            return
        self.drain(self.settings.drain_s)
        with self._state_lock:
            failed = self._state == FAILED
            self._state = CLOSED
        log.info("recording %s: %d pairs written (%.1f MiB, %d files), %d dropped%s", self.folder, self.written,
                 self.bytes_written / MiB, self.files, self.dropped, f"; stopped: {self.failure}" if failed else "")

    @property
    def dropped(self) -> int:
        """Pairs offered that were not (and will not be) written: spool full, recording
        stopped, left at the end."""
        return self.dropped_queue + self.dropped_stopped + self.lost_at_failure + self.dropped_end

    def counters(self) -> dict[str, int | float]:
        """For the stats record: ``record_written``, ``record_dropped`` (and its parts),
        ``record_queued``, ``record_mb`` (MiB written), ``record_mb_per_s`` (MiB/s since the
        last call), ``record_files``, ``record_stopped``, blackbox ``record_triggers`` and
        ``record_held_s`` (seconds of pairs held)."""
        now = time.monotonic()
        dt = now - self._rate_t
        rate = (self.bytes_written - self._rate_bytes) / MiB / dt if dt > 0 else 0.0
        self._rate_t, self._rate_bytes = now, self.bytes_written
        out: dict[str, int | float] = {
            "record_written": self.written, "record_dropped": self.dropped,
            "record_dropped_queue_full": self.dropped_queue,
            "record_dropped_stopped": self.dropped_stopped + self.lost_at_failure,
            "record_dropped_end": self.dropped_end, "record_queued": self.spool.pairs_held() if self._state != ARMED else 0,
            "record_mb": round(self.bytes_written / MiB, 3), "record_mb_per_s": round(rate, 3),
            "record_files": self.files, "record_errors": self.errors + self.write_errors, "record_stopped": self.failure is not None}
        if self.mode == "blackbox":
            items = self.spool.peek(1)
            held = (self._last_id - items[0].frame_id + 1) / self.fps if items and self._last_id is not None else 0.0
            out.update(record_triggers=self.triggers, record_held_s=round(held, 3))
        return out
