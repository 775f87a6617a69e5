"""The ``.iscr`` format, version 2: stereo pair streams (what ``iscd run --record`` writes).

One file holds both cameras of a stretch of a run, pair by pair, each pair either whole
frames or only the pixel windows the decoder read (full description in
docs/recording-format.md)::

    offset  size  field
    0       32    fixed header as version 1 (magic, version 2, header size 32, metadata
                  length L, data offset D, record size 0 = records of varying size)
    32      L     JSON metadata (mode, width, height, dtype, fps, the config and
                  calibration in force, ...), spaces up to D (a multiple of 64)
    D       ...   pair records, back to back, each a multiple of 8 bytes:
                    64-byte header (PAIR_HEADER: sync "ISCP", record size S, frame id,
                    left and right exposure timestamps ns, decoder block number, left and
                    right window x0 y0 x1 y1 px, flags, CRC-32 of the header's first 60 bytes)
                    left window pixels, right window pixels (row-major), zero padding
                  (or a 64-byte block note, sync "ISCB": what the decoder shed on that block)
    ...     16+8n index (written when the file is closed): "ISCX", 0, n, n uint64 offsets
    end-32  32    seal: "ISCRSEAL", index offset, n, CRC-32 of the index, 0

Records are appended with ``os.write`` (no user-space buffer): a killed writer leaves
every record it handed over, and at most one partial record at the end, which readers
ignore. A file without a valid seal is read by scanning the records from D up to the
first one that is incomplete or whose header does not check.
"""

from __future__ import annotations

import datetime as _dt
import errno
import json
import os
import struct
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from iscd.recording.base import RecordingError
from iscd.recording.iscr import ALIGN, FIXED_HEADER, FIXED_HEADER_SIZE, MAGIC, _DTYPES, _json_default, _writer_name

VERSION = 2
SYNC = b"ISCP"
NOTE_SYNC = b"ISCB"
"""Sync of a block note: a header alone (no pixels, windows 0), ``block`` the decoder block,
``frame_id`` its last pair's, flags = ranging_every | per_led << 16 | ahead << 17 (what the
daemon's overload policy let the decoder do on that block, and how many of its first pairs
were ranged ahead, before the rest was in; written only when it shed something or ranged
ahead; a note without ahead bits: 0)."""
INDEX_SYNC = b"ISCX"
SEAL_MAGIC = b"ISCRSEAL"
PAIR_HEADER = struct.Struct("<4sIqqqq4H4HII")
"""sync, record size S (bytes), frame id, left and right timestamps (ns), block, left window
(x0, y0, x1, y1 px), right window, flags, CRC-32 of the first 60 bytes."""
PAIR_HEADER_SIZE = PAIR_HEADER.size  # 64
CRC_SPAN = PAIR_HEADER_SIZE - 4
INDEX_HEADER = struct.Struct("<4sIQ")  # sync, 0, number of pairs
SEAL = struct.Struct("<8sQQII")  # magic, index offset, number of pairs, CRC-32 of the index, 0
RECORD_ALIGN = 8
FLAG_WHOLE = 1
"""Flag bit: both windows are the whole frame."""
MODES = ("full", "roi", "blackbox")

HEADER_DTYPE = np.dtype([("sync", "S4"), ("size", "<u4"), ("frame_id", "<i8"), ("ts_left_ns", "<i8"),
                         ("ts_right_ns", "<i8"), ("block", "<i8"), ("win_left", "<u2", (4,)),
                         ("win_right", "<u2", (4,)), ("flags", "<u4"), ("crc", "<u4")])
"""A pair header as a numpy record (for reading many at once)."""

Window = tuple[int, int, int, int]
"""(x0, y0, x1, y1) px, x1 and y1 exclusive."""


def window_bytes(w: Window, itemsize: int) -> int:
    """Bytes of a window's pixels.

    Parameters
    ----------
    w : (x0, y0, x1, y1) px
    itemsize : bytes per pixel (1 or 2)
    """
    return (w[2] - w[0]) * (w[3] - w[1]) * itemsize


def record_size(wl: Window, wr: Window, itemsize: int) -> int:
    """Bytes of one pair record (header, both windows, padding to 8 bytes)."""
    n = PAIR_HEADER_SIZE + window_bytes(wl, itemsize) + window_bytes(wr, itemsize)
    return -(-n // RECORD_ALIGN) * RECORD_ALIGN


def pack_pair_into(buf: np.ndarray, off: int, frame_id: int, ts_left_ns: int, ts_right_ns: int, block: int,
                   left: np.ndarray, right: np.ndarray, wl: Window, wr: Window, whole: bool) -> int:
    """Write one pair record into ``buf`` (uint8, at byte ``off``, a multiple of 8); returns
    its size in bytes. ``left``/``right``: the (H, W) frames the windows are cut from (the
    ring's slots: one copy, straight into ``buf``); ``whole``: both windows are the frame."""
    itemsize = left.dtype.itemsize
    size = record_size(wl, wr, itemsize)
    PAIR_HEADER.pack_into(buf, off, SYNC, size, frame_id, ts_left_ns, ts_right_ns, block, *wl, *wr,
                          FLAG_WHOLE if whole else 0, 0)
    struct.pack_into("<I", buf, off + CRC_SPAN, zlib.crc32(buf[off:off + CRC_SPAN]))
    p = off + PAIR_HEADER_SIZE
    for img, (x0, y0, x1, y1) in ((left, wl), (right, wr)):
        n = (x1 - x0) * (y1 - y0) * itemsize
        if n:
            dst = buf[p:p + n].view(img.dtype).reshape(y1 - y0, x1 - x0)
            np.copyto(dst, img[y0:y1, x0:x1])
        p += n
    if p < off + size:
        buf[p:off + size] = 0
    return size


_write = os.write
"""The system call that writes (a test injects a full or slow disk here)."""


def pack_note_into(buf: np.ndarray, off: int, frame_id: int, block: int, ranging_every: int, per_led: bool,
                   ahead: int = 0) -> int:
    """Write a block note (see :data:`NOTE_SYNC`) into ``buf`` at byte ``off``; returns its
    size (64 bytes)."""
    flags = (int(ranging_every) & 0xFFFF) | (int(bool(per_led)) << 16) | ((int(ahead) & 0x7FFF) << 17)
    PAIR_HEADER.pack_into(buf, off, NOTE_SYNC, PAIR_HEADER_SIZE, frame_id, 0, 0, block, 0, 0, 0, 0, 0, 0, 0, 0,
                          flags, 0)
    struct.pack_into("<I", buf, off + CRC_SPAN, zlib.crc32(buf[off:off + CRC_SPAN]))
    return PAIR_HEADER_SIZE


def note_flags(flags: int) -> tuple[int, bool, int]:
    """(ranging_every, per_led, pairs ranged ahead) of a block note's flags."""
    return max(int(flags) & 0xFFFF, 1), bool((int(flags) >> 16) & 1), (int(flags) >> 17) & 0x7FFF


def _write_all(fd: int, data: memoryview) -> None:
    """os.write until all of ``data`` is written (a short write is retried; an error raises
    OSError after what fitted was written)."""
    while len(data):
        k = _write(fd, data)
        if k <= 0:  # pragma: no cover - os.write raises rather than return 0
            raise OSError(errno.EIO, "write returned 0")
        data = data[k:]


class PairFileWriter:
    """Writes one version-2 ``.iscr`` file: the header at creation (fsync'ed), whole pair
    records appended with :meth:`write_records` or :meth:`append`, the index and the
    seal at :meth:`close`.

    Parameters
    ----------
    path : file to create (replaced if it exists; its folder must exist)
    width, height : frame size, px
    dtype : "uint8" or "uint16"
    mode : "full", "roi" or "blackbox" (what the recorder kept of each pair)
    fps : frame rate, frames/s (None if unknown)
    exposure_s : exposure time, s (None if unknown)
    bit_depth : significant bits (default: the dtype's)
    meta : JSON-serializable entries added to the metadata (config_toml, calibration,
        session, segment, reason, ...)

    Raises
    ------
    RecordingError
        The file cannot be created or its header written (one line naming it).
    """

    def __init__(self, path: str | Path, *, width: int, height: int, dtype: str = "uint8", mode: str = "full",
                 fps: float | None = None, exposure_s: float | None = None, bit_depth: int | None = None,
                 meta: dict[str, Any] | None = None) -> None:
        self.path = Path(path)
        self.width, self.height = int(width), int(height)
        self.dtype = _DTYPES[np.dtype(dtype).name]
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        self.mode = mode
        self.n_pairs = 0
        self.bytes_written = 0
        """bytes of whole records written (the header not counted)"""
        self._offsets: list[int] = []
        self._fd: int | None = None
        self._failed = False
        now = time.time_ns()
        metadata = {
            "format": "iscr", "version": VERSION, "layout": "stereo", "mode": mode, "cameras": ["left", "right"],
            "width": self.width, "height": self.height, "dtype": self.dtype.name, "byte_order": "little",
            "bit_depth": int(bit_depth or 8 * self.dtype.itemsize),
            "fps": None if fps is None else float(fps),
            "exposure_s": None if exposure_s is None else float(exposure_s),
            "created_utc": _dt.datetime.fromtimestamp(now / 1e9, _dt.timezone.utc).isoformat(),
            "created_unix_ns": now, "writer": _writer_name(),
            "record": {"header_size": PAIR_HEADER_SIZE, "header_struct": PAIR_HEADER.format,
                       "fields": list(HEADER_DTYPE.names), "align": RECORD_ALIGN},
            **(meta or {}),
        }
        text = json.dumps(metadata, default=_json_default, allow_nan=False).encode("utf-8")
        self.data_offset = -(-(FIXED_HEADER_SIZE + len(text)) // ALIGN) * ALIGN
        head = FIXED_HEADER.pack(MAGIC, VERSION, FIXED_HEADER_SIZE, len(text), self.data_offset, 0)
        blob = head + text + b" " * (self.data_offset - FIXED_HEADER_SIZE - len(text))
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            _write_all(self._fd, memoryview(blob))
            os.fsync(self._fd)
        except OSError as e:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None
            raise RecordingError(self.path, f"cannot create recording: {e.strerror or e}") from None
        self._end = self.data_offset

    @property
    def size(self) -> int:
        """Bytes in the file so far (header and whole records)."""
        return self._end

    def write_records(self, data: memoryview | bytes, sizes: list[int], pairs: int | None = None) -> None:
        """Append whole pair records packed with :func:`pack_pair_into`, back to back in
        ``data``, of byte ``sizes``. An OSError (e.g. ENOSPC) part-way keeps the records
        written whole before it (their number in the error's ``pairs_written``), cuts the
        file back to the last of them and is raised; the writer then takes nothing more and
        writes no seal. ``pairs``: how many of the records are pairs (default all; the rest
        are block notes)."""
        if self._fd is None or self._failed:
            raise ValueError(f"{self.path}: the writer is closed")
        mv = memoryview(data)
        done = 0
        try:
            while done < len(mv):
                k = _write(self._fd, mv[done:])
                if k <= 0:  # pragma: no cover - os.write raises rather than return 0
                    raise OSError(errno.EIO, "write returned 0")
                done += k
        except OSError as e:
            self._failed = True
            whole, nbytes = 0, 0
            while whole < len(sizes) and nbytes + sizes[whole] <= done:
                nbytes += sizes[whole]
                whole += 1
            self._add(sizes[:whole], nbytes, None if pairs is None else min(pairs, whole))
            try:
                os.ftruncate(self._fd, self._end)  # the partial record goes; freeing space works on a full disk
            except OSError:
                pass
            e.pairs_written = whole  # type: ignore[attr-defined]
            raise
        self._add(sizes, len(mv), len(sizes) if pairs is None else pairs)

    def _add(self, sizes: list[int], nbytes: int, pairs: int | None = None) -> None:
        off = self._end
        for s in sizes:
            self._offsets.append(off)
            off += s
        self._end = off
        self.bytes_written += nbytes
        self.n_pairs += len(sizes) if pairs is None else pairs

    def append(self, frame_id: int, ts_left_ns: int, ts_right_ns: int, left: np.ndarray, right: np.ndarray,
               wl: Window | None = None, wr: Window | None = None, block: int = 0) -> None:
        """Append one pair: windows ``wl``/``wr`` (None: the whole frame) cut from
        ``left``/``right`` ((H, W) of the file's dtype)."""
        full = (0, 0, self.width, self.height)
        for img in (left, right):
            if img.shape != (self.height, self.width) or img.dtype != self.dtype:
                raise ValueError(f"frame {img.shape} {img.dtype} does not match the recording's "
                                 f"({self.height}, {self.width}) {self.dtype.name}")
        wl, wr = wl or full, wr or full
        buf = np.empty(record_size(wl, wr, self.dtype.itemsize), np.uint8)
        n = pack_pair_into(buf, 0, frame_id, ts_left_ns, ts_right_ns, block, left, right, wl, wr,
                           wl == full and wr == full)
        self.write_records(buf.data, [n])

    def note(self, frame_id: int, block: int, ranging_every: int, per_led: bool, ahead: int = 0) -> None:
        """Append a block note (what the decoder shed on ``block``, the pairs it ranged ahead)."""
        buf = np.empty(PAIR_HEADER_SIZE, np.uint8)
        self.write_records(buf.data, [pack_note_into(buf, 0, frame_id, block, ranging_every, per_led, ahead)],
                           pairs=0)

    def sync(self) -> None:
        """fsync what was written (survives a power cut)."""
        if self._fd is not None and not self._failed:
            os.fsync(self._fd)

    def close(self) -> None:
        """Write the index and the seal, fsync and close (idempotent). After a failed write
        nothing more is written: the file ends at its last whole record, unsealed."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if not self._failed:
                offs = np.asarray(self._offsets, "<u8").tobytes()
                index = INDEX_HEADER.pack(INDEX_SYNC, 0, len(self._offsets)) + offs
                seal = SEAL.pack(SEAL_MAGIC, self._end, len(self._offsets), zlib.crc32(index), 0)
                try:
                    _write_all(fd, memoryview(index + seal))
                    os.fsync(fd)
                except OSError:
                    try:
                        os.ftruncate(fd, self._end)  # no half index: a reader scans the records
                    except OSError:
                        pass
                    raise
        finally:
            os.close(fd)

    def __enter__(self) -> "PairFileWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
