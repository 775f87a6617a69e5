"""Reading version-2 ``.iscr`` files (stereo pair streams, :mod:`iscd.recording.pairfile`)
and folders of them (one recorded run: its segments, ``config.toml`` and the calibration).

:class:`PairRecording` opens one file: through its index when it is sealed, else by
scanning the records up to the last whole one (a file cut by a crash; :attr:`recovery`
says how much was read back). Frames come back rebuilt: the windows at their positions in
frames of ``fill`` (pixels that were not recorded). ``rec.left`` / ``rec.right`` are
one-camera :class:`~iscd.recording.base.Recording` views.

:class:`PairSession` is the files of one run (or any list of files) in order, with the
pairs grouped into the blocks the live decoder took them in (:meth:`PairSession.iter_blocks`).
"""

from __future__ import annotations

import struct
import warnings
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from iscd.recording.base import Recording, RecordingError, RecordingWarning, missing_ids
from iscd.recording.iscr import frame_fields, read_header
from iscd.recording.pairfile import (CRC_SPAN, FLAG_WHOLE, HEADER_DTYPE, INDEX_HEADER, INDEX_SYNC, MODES, NOTE_SYNC,
                                     PAIR_HEADER, PAIR_HEADER_SIZE, SEAL, SEAL_MAGIC, SYNC, VERSION, note_flags,
                                     record_size)

MAX_V2_SIDE = 8192
"""Largest frame width or height of a stereo file, px (as [camera] allows): a header may
claim anything, and frames are rebuilt whole from small windows."""
MAX_EMULATED_BYTES = 2**31
"""Most memory for the emulated intake buffers; beyond it frames are rebuilt on zeros."""
CONFIG_NAME = "config.toml"
CALIBRATION_NAME = "calibration.yml"
SEGMENT_GLOB = "*.iscr"


def is_pair_file(path: str | Path) -> bool:
    """Whether ``path`` is a version-2 (stereo) ``.iscr`` file, from its first 10 bytes."""
    try:
        with open(path, "rb") as f:
            head = f.read(10)
    except OSError:
        return False
    return len(head) == 10 and head[:8] == b"ISCR\r\n\x1a\n" and struct.unpack("<H", head[8:])[0] == VERSION


class PairRecording:
    """One version-2 ``.iscr`` file (see the module docstring).

    Attributes: ``path``, ``metadata`` (the JSON header), ``mode``, ``width``, ``height``
    (px), ``dtype``, ``bit_depth``, ``fps`` (frames/s or None), ``exposure_s``, and per
    pair (arrays of length :attr:`n_pairs`): ``frame_ids``, ``ts_left_ns``, ``ts_right_ns``
    (ns), ``blocks`` (the decoder block each pair was decoded in), ``windows`` ((n, 2, 4)
    x0 y0 x1 y1 px, left then right), ``whole`` (bool), ``offsets`` (byte of each record).
    :attr:`recovery`: sealed, bytes in whole records, trailing bytes ignored.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        meta, self.data_offset, _ = read_header(self.path, versions=(VERSION,))
        self.metadata = meta
        try:
            (self.width, self.height, self.dtype, self.bit_depth, self.fps,
             self.exposure_s) = frame_fields(meta, MAX_V2_SIDE)
            mode = meta.get("mode")
            if mode not in MODES:
                raise ValueError(f"mode must be one of {list(MODES)}, got {mode!r:.40}")
            self.mode: str = mode
        except KeyError as e:
            raise RecordingError(self.path, f"corrupt .iscr metadata: missing {e}") from None
        except (TypeError, ValueError) as e:
            raise RecordingError(self.path, f"corrupt .iscr metadata: {e}") from None
        self._mm: np.memmap | None = None
        self._load()

    # ---- the records --------------------------------------------------------------
    def _load(self) -> None:
        try:
            self._mm = np.memmap(self.path, np.uint8, "r")
        except ValueError:  # an empty file cannot be mapped
            self._mm = None
        except OSError as e:
            raise RecordingError(self.path, f"cannot read: {e.strerror or e}") from None
        size = 0 if self._mm is None else int(self._mm.size)
        self.file_size = size
        hdr = self._sealed_headers(size)
        self.sealed = hdr is not None
        if hdr is None:
            hdr, offsets = self._scan(size)
        else:
            hdr, offsets = hdr
        end = int(offsets[-1] + hdr["size"][-1]) if offsets.size else self.data_offset
        is_note = hdr["sync"] == NOTE_SYNC
        self.notes: dict[int, tuple[int, bool, int]] = {
            int(b): note_flags(int(f)) for b, f in zip(hdr["block"][is_note], hdr["flags"][is_note])}
        """block -> (ranging_every, per_led, ranged ahead): what the live decoder was let do
        on that block and how many of its first pairs it ranged before the rest was in
        (blocks without a note: everything, nothing ahead)"""
        hdr, offsets = hdr[~is_note], offsets[~is_note]
        self.offsets = offsets
        self.frame_ids = hdr["frame_id"].astype(np.int64)
        self.ts_left_ns = hdr["ts_left_ns"].astype(np.int64)
        self.ts_right_ns = hdr["ts_right_ns"].astype(np.int64)
        self.blocks = hdr["block"].astype(np.int64)
        self.windows = np.stack([hdr["win_left"], hdr["win_right"]], 1).astype(np.int64).reshape(-1, 2, 4)
        self.whole = (hdr["flags"] & FLAG_WHOLE).astype(bool)
        self.sizes = hdr["size"].astype(np.int64)
        self.data_end = min(end, size) if size else 0
        tail = 0 if self.sealed else max(size - self.data_end, 0)
        whole_bytes = max(self.data_end - self.data_offset, 0)
        self.recovery = {"sealed": self.sealed, "pairs": int(offsets.size), "file_bytes": size,
                         "bytes_in_whole_pairs": whole_bytes, "trailing_bytes_ignored": int(tail),
                         # of the bytes after the header, the share read back as whole pairs
                         "recovered_share": 1.0 if self.sealed or whole_bytes + tail == 0
                         else round(whole_bytes / (whole_bytes + tail), 6)}
        if tail:
            warnings.warn(f"{self.path}: not sealed (the writer was interrupted): read back {offsets.size} "
                          f"whole pairs, ignoring {tail} trailing bytes", RecordingWarning, stacklevel=3)

    def _valid(self, h: tuple, pos: int, size: int) -> bool:
        """Whether the header ``h`` unpacked at ``pos`` is a whole, consistent record."""
        sync, rsize, *_rest = h
        wl, wr, crc = h[6:10], h[10:14], h[15]
        if sync not in (SYNC, NOTE_SYNC) or pos + rsize > size:
            return False
        if zlib.crc32(self._mm[pos:pos + CRC_SPAN]) != crc:
            return False
        if sync == NOTE_SYNC:
            return rsize == PAIR_HEADER_SIZE and not any(wl) and not any(wr)
        for x0, y0, x1, y1 in (wl, wr):
            if not (x0 <= x1 <= self.width and y0 <= y1 <= self.height):
                return False
        return rsize == record_size(wl, wr, self.dtype.itemsize)

    def _scan(self, size: int) -> tuple[np.ndarray, np.ndarray]:
        """The records from the data offset up to the first that is not whole and valid."""
        pos, offs, heads = self.data_offset, [], []
        mm = self._mm
        while mm is not None and pos + PAIR_HEADER_SIZE <= size:
            h = PAIR_HEADER.unpack_from(mm, pos)
            if not self._valid(h, pos, size):
                break
            offs.append(pos)
            heads.append(bytes(mm[pos:pos + PAIR_HEADER_SIZE]))
            pos += h[1]
        hdr = np.frombuffer(b"".join(heads), HEADER_DTYPE) if heads else np.zeros(0, HEADER_DTYPE)
        return hdr, np.asarray(offs, np.int64)

    def _sealed_headers(self, size: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The headers through the index when the seal checks, else None (then scan)."""
        mm = self._mm
        if mm is None or size < self.data_offset + INDEX_HEADER.size + SEAL.size:
            return None
        magic, ioff, n, crc, _ = SEAL.unpack_from(mm, size - SEAL.size)
        if magic != SEAL_MAGIC or ioff < self.data_offset or ioff + INDEX_HEADER.size + 8 * n + SEAL.size != size:
            return None
        index = mm[ioff:size - SEAL.size]
        sync, _, n2 = INDEX_HEADER.unpack_from(index, 0)
        if sync != INDEX_SYNC or n2 != n or zlib.crc32(index) != crc:
            return None
        offsets = np.frombuffer(index[INDEX_HEADER.size:], "<u8").astype(np.int64)
        if offsets.size and (offsets.min() < self.data_offset or offsets.max() + PAIR_HEADER_SIZE > ioff):
            return None
        hdr = mm[offsets[:, None] + np.arange(PAIR_HEADER_SIZE)].view(HEADER_DTYPE).ravel() if offsets.size \
            else np.zeros(0, HEADER_DTYPE)
        for k in range(offsets.size):  # every header checks, as in a scan
            if not self._valid(PAIR_HEADER.unpack_from(mm, int(offsets[k])), int(offsets[k]), int(ioff)):
                return None
        return hdr, offsets

    # ---- pixels -------------------------------------------------------------------
    @property
    def n_pairs(self) -> int:
        """Number of whole pairs."""
        return int(self.offsets.size)

    def __len__(self) -> int:
        return self.n_pairs

    def window_pixels(self, i: int, camera: int) -> np.ndarray:
        """The recorded pixels of pair ``i``, camera 0 (left) or 1 (right): (h, w) of the
        window ``windows[i, camera]`` (a copy)."""
        if self._mm is None:
            raise RecordingError(self.path, "recording is closed")
        x0, y0, x1, y1 = (int(v) for v in self.windows[i, 0])
        p = int(self.offsets[i]) + PAIR_HEADER_SIZE
        isz = self.dtype.itemsize
        n0 = (x1 - x0) * (y1 - y0) * isz
        if camera == 1:
            p += n0
            x0, y0, x1, y1 = (int(v) for v in self.windows[i, 1])
        n = (x1 - x0) * (y1 - y0) * isz
        return np.array(self._mm[p:p + n].view(self.dtype.newbyteorder("<")).reshape(y1 - y0, x1 - x0),
                        dtype=self.dtype)

    def read_camera(self, camera: int, start: int, stop: int, fill: int = 0) -> np.ndarray:
        """Frames of pairs ``start <= i < stop`` of one camera (0 left, 1 right), rebuilt:
        (n, height, width), the window at its position, ``fill`` elsewhere."""
        out = np.full((max(stop - start, 0), self.height, self.width), fill, self.dtype)
        for k, i in enumerate(range(start, stop)):
            x0, y0, x1, y1 = (int(v) for v in self.windows[i, camera])
            out[k, y0:y1, x0:x1] = self.window_pixels(i, camera)
        return out

    def read_pairs(self, start: int, stop: int, fill: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(left, right) frames of pairs ``start <= i < stop``, rebuilt (see :meth:`read_camera`)."""
        return self.read_camera(0, start, stop, fill), self.read_camera(1, start, stop, fill)

    @property
    def left(self) -> "PairCameraView":
        """The left camera as a one-camera Recording."""
        return PairCameraView(self, 0)

    @property
    def right(self) -> "PairCameraView":
        """The right camera as a one-camera Recording."""
        return PairCameraView(self, 1)

    # ---- summary ------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        """A JSON-serializable summary: mode, size, pairs, frame ranges, windows, recovery."""
        m = self.metadata
        return {"format": "iscr", "version": VERSION, "layout": "stereo", "mode": self.mode, "path": str(self.path),
                "width": self.width, "height": self.height, "dtype": self.dtype.name, "bit_depth": self.bit_depth,
                "fps": self.fps, "exposure_s": self.exposure_s, "pairs": self.n_pairs,
                **pair_summary(self.frame_ids, self.windows, self.whole, self.blocks, self.sizes, self.fps),
                "recovery": dict(self.recovery),
                "segment": m.get("segment"), "session": m.get("session"), "reason": m.get("reason"),
                "created_utc": m.get("created_utc"), "writer": m.get("writer")}

    def check(self) -> dict[str, Any]:
        """Read every pair's pixels; the recovery summary with pixel_min / pixel_max."""
        lo = hi = None
        for i in range(self.n_pairs):
            for cam in (0, 1):
                px = self.window_pixels(i, cam)
                if px.size:
                    lo = int(px.min()) if lo is None else min(lo, int(px.min()))
                    hi = int(px.max()) if hi is None else max(hi, int(px.max()))
        return {**self.recovery, "pixel_min": lo, "pixel_max": hi}

    def close(self) -> None:
        """Release the memory map (idempotent)."""
        self._mm = None

    def __enter__(self) -> "PairRecording":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def frame_ranges(ids: np.ndarray) -> list[list[int]]:
    """Runs of consecutive frame ids as [first, last] (inclusive) pairs."""
    ids = np.asarray(ids, np.int64)
    if ids.size == 0:
        return []
    cut = np.flatnonzero(np.diff(ids) != 1) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut, [ids.size]]) - 1
    return [[int(ids[a]), int(ids[b])] for a, b in zip(starts, ends)]


def pair_summary(ids: np.ndarray, windows: np.ndarray, whole: np.ndarray, blocks: np.ndarray, sizes: np.ndarray,
                 fps: float | None) -> dict[str, Any]:
    """Frame ranges, window sizes and data per pair of a set of pairs (for ``info``)."""
    n = int(ids.size)
    ranges = frame_ranges(ids)
    out: dict[str, Any] = {
        "first_frame_id": int(ids[0]) if n else None, "last_frame_id": int(ids[-1]) if n else None,
        "missing_frame_ids": missing_ids(ids), "frame_ranges": ranges[:50],
        "frame_ranges_total": len(ranges), "duration_s": (n / fps) if fps else None,
        "whole_frame_pairs": int(whole.sum()), "window_pairs": int(n - whole.sum()),
        "blocks": int(np.unique(blocks).size), "bytes_per_pair_mean": float(sizes.mean()) if n else None}
    sel = ~whole
    wins: dict[str, Any] = {}
    for cam, name in ((0, "left"), (1, "right")):
        w = windows[sel, cam]
        if w.size == 0:
            wins[name] = None
            continue
        ww, hh = w[:, 2] - w[:, 0], w[:, 3] - w[:, 1]
        wins[name] = {"width_px_min_median_max": [int(ww.min()), float(np.median(ww)), int(ww.max())],
                      "height_px_min_median_max": [int(hh.min()), float(np.median(hh)), int(hh.max())],
                      "first": [int(v) for v in w[0]], "last": [int(v) for v in w[-1]],
                      "x0_y0_min": [int(w[:, 0].min()), int(w[:, 1].min())],
                      "x1_y1_max": [int(w[:, 2].max()), int(w[:, 3].max())]}
    out["windows"] = wins
    return out


class PairCameraView(Recording):
    """One camera of a :class:`PairRecording` as a :class:`~iscd.recording.base.Recording`
    (frames rebuilt with zeros outside the recorded windows)."""

    format = "iscr"

    def __init__(self, rec: PairRecording, camera: int) -> None:
        self.rec = rec
        self.cam = int(camera)
        self.path = rec.path
        self.width, self.height, self.dtype, self.bit_depth = rec.width, rec.height, rec.dtype, rec.bit_depth
        self.fps, self.exposure_s = rec.fps, rec.exposure_s
        self.camera = ("left", "right")[self.cam]
        self.frame_ids = rec.frame_ids
        self.timestamps_ns = rec.ts_left_ns if self.cam == 0 else rec.ts_right_ns

    def _read(self, start: int, stop: int) -> np.ndarray:
        return self.rec.read_camera(self.cam, start, stop)

    def _extra_info(self) -> dict[str, Any]:
        return {"version": VERSION, "mode": self.rec.mode, "recovery": dict(self.rec.recovery)}


def session_files(path: str | Path) -> list[Path]:
    """The version-2 ``.iscr`` files of a recorded run's folder, in name order (which is
    recording order), or ``[path]`` for a file. Raises RecordingError when there are none."""
    p = Path(path)
    if p.is_dir():
        files = sorted(f for f in p.glob(SEGMENT_GLOB) if f.is_file() and is_pair_file(f))
        if not files:
            raise RecordingError(p, "no stereo .iscr recording (version 2) in this folder")
        return files
    if not p.exists():
        raise RecordingError(p, "no such file or folder")
    return [p]


class Block(NamedTuple):
    """One decoder block of a recording: frame ids (n,), left and right exposure timestamps
    (n,) ns, left and right frames (n, height, width), the block's number."""

    frame_ids: np.ndarray
    ts_left_ns: np.ndarray
    ts_right_ns: np.ndarray
    left: np.ndarray
    right: np.ndarray
    block: int


class PairSession:
    """The files of one recorded run in order (a folder, or one file): their pairs as one
    sequence, grouped into the decoder's blocks.

    Parameters
    ----------
    path : a folder written by ``iscd run --record`` (its run folder) or one file
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.files: list[PairRecording] = []
        try:
            for f in session_files(self.path):
                self.files.append(PairRecording(f))
        except BaseException:
            self.close()
            raise
        first = self.files[0]
        for r in self.files[1:]:
            if (r.width, r.height, r.dtype) != (first.width, first.height, first.dtype):
                raise RecordingError(r.path, f"{r.width}x{r.height} {r.dtype.name} differs from "
                                             f"{first.path.name}'s {first.width}x{first.height} {first.dtype.name}")
        self.width, self.height, self.dtype = first.width, first.height, first.dtype
        self.fps, self.bit_depth, self.mode = first.fps, first.bit_depth, first.mode
        self.metadata = first.metadata
        self.frame_ids = np.concatenate([r.frame_ids for r in self.files])
        self.n_pairs = int(self.frame_ids.size)

    def config_text(self) -> str | None:
        """The config in force: ``config.toml`` beside the files, else the first file's copy."""
        beside = (self.path if self.path.is_dir() else self.path.parent) / CONFIG_NAME
        if beside.is_file():
            return beside.read_text(encoding="utf-8")
        text = self.metadata.get("config_toml")
        return text if isinstance(text, str) else None

    def calibration_path(self) -> Path | None:
        """The calibration in force, stored beside the files (None: the ideal rig)."""
        beside = (self.path if self.path.is_dir() else self.path.parent) / CALIBRATION_NAME
        return beside if beside.is_file() and self.metadata.get("calibration") else None

    def intake_buffers(self) -> int | None:
        """How many block buffers the live daemon's intake reused (``intake_buffers`` in the
        metadata: ``[daemon] block_max``), or None when the file does not say."""
        v = self.metadata.get("intake_buffers")
        return v if isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 4096 else None

    def block_service(self, block: int) -> tuple[int, bool]:
        """(ranging_every, per_led) the live decoder was let do on ``block`` (its overload
        policy's shedding, from the block notes; (1, True) without a note)."""
        for r in self.files:
            if block in r.notes:
                return r.notes[block][:2]
        return 1, True

    def block_ahead(self, block: int) -> int:
        """How many of ``block``'s first pairs the live decoder ranged before the rest was in
        (``range_ahead``, from the block notes; 0 without a note): a replay ranges them
        apart too, so that its ranges are the live ones."""
        for r in self.files:
            if block in r.notes:
                return r.notes[block][2]
        return 0

    def iter_blocks(self, emulate_intake: bool = True, max_pairs: int = 4096) -> Iterator["Block"]:
        """The pairs in the blocks the live decoder took them in (consecutive pairs with the
        same block number; a block cut by a file rotation is joined again), at most
        ``max_pairs`` a block, as :class:`Block` (frame_ids, ts_left_ns, ts_right_ns, left,
        right, block): frames (n, height, width) rebuilt from the recorded windows.

        ``emulate_intake`` (and the file knows :meth:`intake_buffers`): the frames are
        rebuilt as the daemon's intake (:class:`iscd.service.blocks.BlockReader`) built them,
        pair k of a block written over block buffer k (zeros at the start), so that the
        pixels outside a window are what that buffer held from earlier pairs: the arrays the
        live decoder was handed, bit for bit, when the recording holds every pair of the run
        from its start. Otherwise zeros outside the windows."""
        nbuf = self.intake_buffers() if emulate_intake else None
        if nbuf is not None and 2 * nbuf * self.height * self.width * self.dtype.itemsize > MAX_EMULATED_BYTES:
            nbuf = None
        bufs = None
        if nbuf is not None:
            bufs = (np.zeros((nbuf, self.height, self.width), self.dtype),
                    np.zeros((nbuf, self.height, self.width), self.dtype))
        items: list[tuple[PairRecording, int]] = []
        cur = None
        for r in self.files:
            for i in range(r.n_pairs):
                b = int(r.blocks[i])
                if items and (b != cur or len(items) >= max_pairs):
                    yield self._block(items, bufs, cur)
                    items = []
                cur = b
                items.append((r, i))
        if items:
            yield self._block(items, bufs, cur)

    def _block(self, items: list[tuple[PairRecording, int]], bufs: tuple[np.ndarray, np.ndarray] | None,
               block: int) -> "Block":
        n = len(items)
        if bufs is None or n > bufs[0].shape[0]:
            L = np.zeros((n, self.height, self.width), self.dtype)
            R = np.zeros_like(L)
        else:
            L, R = bufs
        ids, tl, tr = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
        for k, (r, i) in enumerate(items):
            for cam, out in ((0, L), (1, R)):
                x0, y0, x1, y1 = (int(v) for v in r.windows[i, cam])
                out[k, y0:y1, x0:x1] = r.window_pixels(i, cam)
            ids[k], tl[k], tr[k] = r.frame_ids[i], r.ts_left_ns[i], r.ts_right_ns[i]
        return Block(ids, tl, tr, L[:n].copy(), R[:n].copy(), int(block))

    def info(self) -> dict[str, Any]:
        """A JSON-serializable summary of the whole run and of each file."""
        cat = lambda name: np.concatenate([getattr(r, name) for r in self.files])  # noqa: E731
        return {"format": "iscr", "version": VERSION, "layout": "stereo", "mode": self.mode, "path": str(self.path),
                "width": self.width, "height": self.height, "dtype": self.dtype.name, "bit_depth": self.bit_depth,
                "fps": self.fps, "files": len(self.files), "pairs": self.n_pairs,
                **pair_summary(self.frame_ids, np.concatenate([r.windows for r in self.files]), cat("whole"),
                               cat("blocks"), cat("sizes"), self.fps),
                "config": self.config_text() is not None,
                "calibration": str(self.calibration_path()) if self.calibration_path() else None,
                "segments": [{"path": r.path.name, "pairs": r.n_pairs, "first_frame_id": r.info()["first_frame_id"],
                              "last_frame_id": r.info()["last_frame_id"], "reason": r.metadata.get("reason"),
                              "sealed": r.sealed} for r in self.files]}

    def close(self) -> None:
        """Close every file."""
        for r in self.files:
            r.close()

    def __enter__(self) -> "PairSession":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_stereo(path: str | Path) -> PairSession:
    """A recorded run (folder) or one version-2 file as a :class:`PairSession`."""
    return PairSession(path)
