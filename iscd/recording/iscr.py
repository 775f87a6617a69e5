"""The project's own recording format, ``.iscr`` (one file per camera).

Byte layout (all integers little-endian; full description in docs/recording-format.md)::

    offset  size  field
    0       8     magic  b"ISCR\\r\\n\\x1a\\n"
    8       2     uint16 format version (1)
    10      2     uint16 fixed header size (32)
    12      4     uint32 length L of the JSON metadata, bytes
    16      8     uint64 data offset D (start of the first record; multiple of 64)
    24      8     uint64 record size R = 16 + height*width*itemsize
    32      L     JSON metadata, UTF-8 (camera, width, height, dtype, bit_depth, fps, ...)
    32+L    ...   spaces (0x20) up to D
    D + k*R R     record k: int64 frame_id, int64 timestamp_ns, height*width pixels
                  (row-major, uint8 or little-endian uint16)

The file is append-only: the header is written (and fsync'ed) once when the writer is
created, then records are appended. The frame count is NOT stored; it is
``(file size - D) // R``. A writer that is killed loses at most its unflushed tail; a
trailing partial record is ignored by the reader with a warning.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import operator
import os
import struct
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from iscd.recording.base import Recording, RecordingError, RecordingWarning, header_number

MAGIC = b"ISCR\r\n\x1a\n"
VERSION = 1
FIXED_HEADER = struct.Struct("<8sHHIQQ")  # magic, version, header size, L, D, R
FIXED_HEADER_SIZE = FIXED_HEADER.size  # 32
ALIGN = 64
RECORD_HEADER = struct.Struct("<qq")  # frame_id, timestamp_ns
SUFFIX = ".iscr"

_DTYPES = {"uint8": np.dtype("<u1"), "uint16": np.dtype("<u2")}
MAX_SIDE = 65535
"""Largest frame width or height read, px (a header may claim anything)."""


def record_dtype(width: int, height: int, dtype: str | np.dtype) -> np.dtype:
    """The numpy structured dtype of one record (for ``np.memmap``)."""
    return np.dtype([("frame_id", "<i8"), ("timestamp_ns", "<i8"),
                     ("image", _DTYPES[np.dtype(dtype).name], (int(height), int(width)))])


def _json_default(o: Any) -> Any:
    """Let numpy scalars/arrays and paths pass into the JSON metadata."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON-serializable")


class IscrWriter:
    """Append frames of one camera to a new ``.iscr`` file (an existing file is replaced).

    Args:
      path: output file (``.iscr`` by convention; the parent folder must exist).
      width, height: frame size, px.
      dtype: ``"uint8"`` or ``"uint16"``.
      camera: camera name, ``"left"``/``"right"`` for a stereo pair.
      fps: frame rate, frames/s (None if unknown).
      exposure_s: exposure time, s (None if unknown).
      bit_depth: significant bits (default 8 for uint8, 16 for uint16).
      meta: free JSON-serializable dict (e.g. the config, ground truth pointers).
      settings: camera settings as a JSON-serializable dict (e.g. gain_db, roi, trigger) or
        a dataclass such as ``iscd.drivers.base.CameraSettings``.

    ``append``/``append_many`` raise ValueError for a wrong shape or dtype. ``flush()``
    hands everything appended so far to the OS (survives a killed process);
    ``flush(sync=True)`` and ``close()`` also fsync (survives a power cut).
    """

    def __init__(self, path: str | Path, *, width: int, height: int, dtype: str = "uint8",
                 camera: str = "left", fps: float | None = None, exposure_s: float | None = None,
                 bit_depth: int | None = None, meta: dict[str, Any] | None = None,
                 settings: dict[str, Any] | Any | None = None) -> None:
        self.path = Path(path)
        try:
            self.width, self.height = operator.index(width), operator.index(height)
        except TypeError:
            raise ValueError(f"width and height must be integers, got {width!r}, {height!r}") from None
        if self.width < 1 or self.height < 1:
            raise ValueError(f"width and height must be >= 1 px, got {width}x{height}")
        try:
            self.dtype = _DTYPES[np.dtype(dtype).name]
        except (TypeError, KeyError):
            raise ValueError(f"dtype must be 'uint8' or 'uint16', got {dtype!r}") from None
        nbits = 8 * self.dtype.itemsize
        self.bit_depth = nbits if bit_depth is None else operator.index(bit_depth)
        if not 1 <= self.bit_depth <= nbits:
            raise ValueError(f"bit_depth must be 1..{nbits} for {self.dtype.name}, got {bit_depth}")
        if fps is not None and not float(fps) > 0:
            raise ValueError(f"fps must be > 0 or None, got {fps}")
        if exposure_s is not None and not float(exposure_s) > 0:
            raise ValueError(f"exposure_s must be > 0 or None, got {exposure_s}")
        self.camera = str(camera)
        self.fps = None if fps is None else float(fps)
        self.exposure_s = None if exposure_s is None else float(exposure_s)
        self.record_dtype = record_dtype(self.width, self.height, self.dtype)
        self.record_size = self.record_dtype.itemsize
        self.n_frames = 0
        self._shape = (self.height, self.width)

        if dataclasses.is_dataclass(settings) and not isinstance(settings, type):
            settings = dataclasses.asdict(settings)  # e.g. iscd.drivers.base.CameraSettings
        now = time.time_ns()
        metadata = {
            "format": "iscr",
            "version": VERSION,
            "camera": self.camera,
            "width": self.width,
            "height": self.height,
            "dtype": self.dtype.name,
            "byte_order": "little",
            "bit_depth": self.bit_depth,
            "fps": self.fps,
            "exposure_s": self.exposure_s,
            "settings": dict(settings or {}),
            "meta": dict(meta or {}),
            "created_utc": _dt.datetime.fromtimestamp(now / 1e9, _dt.timezone.utc).isoformat(),
            "created_unix_ns": now,
            "writer": _writer_name(),
            "record": {"size": self.record_size,
                       "fields": [["frame_id", "<i8", 0], ["timestamp_ns", "<i8", 8],
                                  ["image", self.dtype.str, 16, [self.height, self.width]]]},
        }
        try:
            text = json.dumps(metadata, default=_json_default, allow_nan=False).encode("utf-8")
        except (TypeError, ValueError) as e:
            raise ValueError(f"meta/settings must be JSON-serializable (finite numbers): {e}") from None
        self.data_offset = -(-(FIXED_HEADER_SIZE + len(text)) // ALIGN) * ALIGN
        head = FIXED_HEADER.pack(MAGIC, VERSION, FIXED_HEADER_SIZE, len(text),
                                 self.data_offset, self.record_size)
        blob = head + text + b" " * (self.data_offset - FIXED_HEADER_SIZE - len(text))
        try:
            self._f = open(self.path, "wb")
            self._f.write(blob)
            self._f.flush()
            os.fsync(self._f.fileno())
        except OSError as e:
            raise RecordingError(self.path, f"cannot create recording: {e.strerror or e}") from None

    # -- appending -------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._f is None or self._f.closed:
            raise ValueError(f"{self.path}: recording writer is closed")

    def _check_pixels(self, image: Any, shape: tuple[int, ...]) -> np.ndarray:
        if not isinstance(image, np.ndarray):
            raise ValueError(f"image must be a numpy array, got {type(image).__name__}")
        if image.shape != shape:
            raise ValueError(f"image shape {image.shape} does not match the recording's {shape}")
        if image.dtype.kind != "u" or image.dtype.itemsize != self.dtype.itemsize:
            raise ValueError(f"image dtype {image.dtype} does not match the recording's {self.dtype.name}")
        return image.astype(self.dtype, copy=False)

    def append(self, frame_id: int, timestamp_ns: int, image: np.ndarray) -> None:
        """Append one frame: ``image`` (height, width) of the recording's dtype."""
        self._check_open()
        try:
            fid, ts = operator.index(frame_id), operator.index(timestamp_ns)
        except TypeError:
            raise ValueError(f"frame_id and timestamp_ns must be integers, got "
                             f"{frame_id!r}, {timestamp_ns!r}") from None
        pixels = np.ascontiguousarray(self._check_pixels(image, self._shape))
        self._f.write(RECORD_HEADER.pack(fid, ts))
        self._f.write(pixels.data)
        self.n_frames += 1

    def append_many(self, frame_ids: Any, timestamps_ns: Any, images: np.ndarray) -> None:
        """Append n frames at once: ids (n,), timestamps (n,) and images (n, height, width)."""
        self._check_open()
        ids = np.asarray(frame_ids)
        tss = np.asarray(timestamps_ns)
        if not isinstance(images, np.ndarray) or images.ndim != 3:
            raise ValueError(f"images must be a (n, {self.height}, {self.width}) array, got "
                             f"{getattr(images, 'shape', type(images).__name__)}")
        n = images.shape[0]
        pixels = self._check_pixels(images, (n, *self._shape))
        for name, a in (("frame_ids", ids), ("timestamps_ns", tss)):
            if a.shape != (n,) or (a.size and a.dtype.kind not in "iu"):
                raise ValueError(f"{name} must be {n} integers, got shape {a.shape} dtype {a.dtype}")
        rec = np.empty(n, dtype=self.record_dtype)
        rec["frame_id"] = ids
        rec["timestamp_ns"] = tss
        rec["image"] = pixels
        self._f.write(rec.data)
        self.n_frames += n

    def flush(self, sync: bool = False) -> None:
        """Hand the appended frames to the OS; with ``sync`` also fsync to the disk."""
        self._check_open()
        self._f.flush()
        if sync:
            os.fsync(self._f.fileno())

    def close(self) -> None:
        """Flush, fsync and close (idempotent)."""
        f, self._f = getattr(self, "_f", None), None
        if f is not None and not f.closed:
            try:
                f.flush()
                os.fsync(f.fileno())
            finally:
                f.close()

    def __enter__(self) -> "IscrWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass


def _writer_name() -> str:
    try:
        from iscd import __version__
        return f"iscd {__version__}"
    except Exception:  # pragma: no cover
        return "iscd"


def read_header(path: str | Path, versions: tuple[int, ...] = (VERSION,)) -> tuple[dict[str, Any], int, int]:
    """Parse an ``.iscr`` header: (metadata dict, data offset D, record size R).
    ``versions``: the format versions the caller reads (1: one camera, fixed-size records;
    2: stereo pair streams, :mod:`iscd.recording.pairfile`).
    Raises :class:`RecordingError` for anything that is not a valid header of those versions."""
    p = Path(path)
    try:
        with open(p, "rb") as f:
            head = f.read(FIXED_HEADER_SIZE)
            if len(head) < FIXED_HEADER_SIZE:
                raise RecordingError(p, f"too short for an .iscr header ({len(head)} of "
                                        f"{FIXED_HEADER_SIZE} bytes)")
            magic, version, hsize, mlen, doff, rsize = FIXED_HEADER.unpack(head)
            if magic != MAGIC:
                raise RecordingError(p, "not an .iscr recording (bad magic bytes)")
            if version not in versions:
                if version == 2 and 2 not in versions:
                    raise RecordingError(p, "a stereo .iscr (version 2, both cameras, as 'iscd run "
                                            "--record' writes): give it alone to 'iscd replay' or "
                                            "'iscd info', or open it with iscd.recording.open_stereo")
                raise RecordingError(p, f".iscr version {version} is not supported (this reader "
                                        f"reads version {', '.join(map(str, versions))})")
            if hsize < FIXED_HEADER_SIZE or doff < hsize + mlen:
                raise RecordingError(p, f"corrupt .iscr header (header size {hsize}, metadata "
                                        f"{mlen} bytes, data offset {doff})")
            f.seek(hsize)
            text = f.read(mlen)
    except FileNotFoundError:
        raise RecordingError(p, "no such file") from None
    except IsADirectoryError:
        raise RecordingError(p, "is a folder, not an .iscr file") from None
    except OSError as e:
        raise RecordingError(p, f"cannot read: {e.strerror or e}") from None
    if len(text) < mlen:
        raise RecordingError(p, f"incomplete .iscr header (metadata {len(text)} of {mlen} bytes)")
    try:
        meta = json.loads(text.decode("utf-8"))
        if not isinstance(meta, dict):
            raise ValueError("not a JSON object")
    except (UnicodeDecodeError, ValueError) as e:
        raise RecordingError(p, f"corrupt .iscr metadata: {e}") from None
    except RecursionError:
        raise RecordingError(p, "corrupt .iscr metadata: nested too deeply") from None
    return meta, int(doff), int(rsize)


def frame_fields(meta: dict[str, Any], max_side: int
                 ) -> tuple[int, int, np.dtype, int, float | None, float | None]:
    """The frame description of an ``.iscr`` header's metadata (either version): width and
    height (px, 1 .. ``max_side``), pixel dtype, bit depth (bits, at most the dtype's), frame
    rate (frames/s, or None) and exposure (s, or None).

    Raises
    ------
    KeyError
        A required field (width, height, dtype) missing.
    ValueError
        A field of the wrong type or out of range (the message names it).
    """
    width = int(header_number(meta["width"], "width", integer=True, lo=1, hi=max_side))
    height = int(header_number(meta["height"], "height", integer=True, lo=1, hi=max_side))
    name = meta["dtype"]
    if not isinstance(name, str) or name not in _DTYPES:
        raise ValueError(f"unsupported dtype {name!r:.40}")
    dtype = np.dtype(name)
    nbits = 8 * dtype.itemsize
    bd = meta.get("bit_depth")
    bit_depth = nbits if bd is None else int(header_number(bd, "bit_depth", integer=True, lo=1, hi=nbits))
    fps, exp = meta.get("fps"), meta.get("exposure_s")
    return (width, height, dtype, bit_depth, None if fps is None else float(header_number(fps, "fps", lo=1e-9)),
            None if exp is None else float(header_number(exp, "exposure_s", lo=0)))


class IscrRecording(Recording):
    """Reader of an ``.iscr`` file (numpy memmap over the records; reads copy a block)."""

    format = "iscr"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        meta, self.data_offset, self.record_size = read_header(self.path)
        self.metadata = meta
        try:
            (self.width, self.height, self.dtype, self.bit_depth, self.fps,
             self.exposure_s) = frame_fields(meta, MAX_SIDE)
            self.camera = None if meta.get("camera") is None else str(meta["camera"])[:200]
        except KeyError as e:
            raise RecordingError(self.path, f"corrupt .iscr metadata: missing {e}") from None
        except (TypeError, ValueError) as e:
            raise RecordingError(self.path, f"corrupt .iscr metadata: {e}") from None
        self._rec_dtype = record_dtype(self.width, self.height, self.dtype)
        if self._rec_dtype.itemsize != self.record_size:
            raise RecordingError(self.path, f"corrupt .iscr header: record size {self.record_size} "
                                            f"bytes, but {self.width}x{self.height} {self.dtype.name} "
                                            f"needs {self._rec_dtype.itemsize}")
        self._mm: np.memmap | None = None
        self.partial_bytes = 0
        self.refresh()

    def refresh(self) -> int:
        """Re-map the file (it may have grown since it was opened, e.g. while a writer is
        still appending); returns the number of complete frames."""
        try:
            size = os.path.getsize(self.path)
        except OSError as e:
            raise RecordingError(self.path, f"cannot read: {e.strerror or e}") from None
        body = max(size - self.data_offset, 0)
        n, tail = divmod(body, self.record_size)
        if tail and tail != self.partial_bytes:
            warnings.warn(f"{self.path}: ignoring a partial trailing record ({tail} of "
                          f"{self.record_size} bytes; the writer was interrupted)",
                          RecordingWarning, stacklevel=2)
        self.partial_bytes = tail
        if n:
            self._mm = np.memmap(self.path, dtype=self._rec_dtype, mode="r",
                                 offset=self.data_offset, shape=(n,))
            self.frame_ids = np.array(self._mm["frame_id"], dtype=np.int64)
            self.timestamps_ns = np.array(self._mm["timestamp_ns"], dtype=np.int64)
        else:
            self._mm = None
            self.frame_ids = np.empty(0, dtype=np.int64)
            self.timestamps_ns = np.empty(0, dtype=np.int64)
        return int(n)

    def _read(self, start: int, stop: int) -> np.ndarray:
        if self._mm is None:
            raise RecordingError(self.path, "recording is closed")
        return np.array(self._mm["image"][start:stop], dtype=self.dtype, order="C")

    def _extra_info(self) -> dict[str, Any]:
        m = self.metadata
        return {"version": m.get("version"), "created_utc": m.get("created_utc"),
                "writer": m.get("writer"), "settings": m.get("settings", {}),
                "meta": m.get("meta", {}), "partial_trailing_bytes": int(self.partial_bytes)}

    def close(self) -> None:
        self._mm = None
