"""A folder of image files as a recording (one camera, one file per frame).

Frames are the folder's PNG / TIFF (also PGM, BMP) files in natural name order
(``frame_2`` before ``frame_10``); hidden files and other files are ignored. Pixels are
read with OpenCV unchanged (8- or 16-bit grey); colour images are converted to grey.
All frames must have the size and dtype of the first one (PNG sizes are checked when
the folder is opened, other formats when a frame is read).

Frame ids are the last number in each file name when every name has one and they
increase (``left_000052.png`` -> 52), else 0, 1, 2, ... An optional sidecar
``recording.json`` in the folder may give ``fps``, ``exposure_s``, ``camera`` and
``bit_depth``; without fps, timestamps are all 0.
"""

from __future__ import annotations

import contextlib
import json
import re
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from iscd.recording.base import Recording, RecordingError, header_number

EXTENSIONS = (".png", ".tif", ".tiff", ".pgm", ".bmp")
SIDECAR = "recording.json"
_NUM = re.compile(r"(\d+)")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def natural_key(name: str) -> list[Any]:
    """Sort key that orders embedded numbers by value: ``f2`` < ``f10``."""
    return [int(t) if i % 2 else t.lower() for i, t in enumerate(_NUM.split(name))]


def list_frames(folder: Path) -> list[Path]:
    """The frame files of ``folder`` in natural name order (may be empty)."""
    files = [p for p in folder.iterdir()
             if p.suffix.lower() in EXTENSIONS and not p.name.startswith(".") and p.is_file()]
    return sorted(files, key=lambda p: natural_key(p.name))


def ids_from_names(files: list[Path]) -> np.ndarray:
    """Last number of each file stem if all have one and they strictly increase, else 0..n-1."""
    nums = [_NUM.findall(p.stem) for p in files]
    if files and all(nums) and all(len(n[-1].lstrip("0")) <= 18 for n in nums):  # fit int64
        ids = np.array([int(n[-1]) for n in nums], dtype=np.int64)
        if ids.size < 2 or np.all(np.diff(ids) > 0):
            return ids
    return np.arange(len(files), dtype=np.int64)


def _png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk, or None if it is not a PNG."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) == 24 and head[:8] == PNG_SIGNATURE and head[12:16] == b"IHDR":
        w, h = struct.unpack(">II", head[16:24])
        return int(w), int(h)
    return None


MAX_FILE_BYTES = 1 << 30
"""Largest frame file read (1 GiB): a frame of the largest camera (8192 x 8192 x 16-bit) is
128 MiB uncompressed."""
MAX_PIXELS = 8192 * 8192
"""Largest PNG frame decoded (px, the largest [camera] size), checked in the IHDR before
decoding: a small file may claim a huge size. Other formats are bounded by OpenCV's own
limit (OPENCV_IO_MAX_IMAGE_PIXELS, 2**30 px by default)."""


@contextlib.contextmanager
def _opencv_quiet() -> Iterator[None]:
    """OpenCV's own log lines (libpng/libtiff errors on a corrupt file) off for the block:
    the reader reports a bad frame as one RecordingError line instead."""
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is None:  # pragma: no cover - very old OpenCV
        yield
        return
    old = logging.getLogLevel()
    logging.setLogLevel(logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        logging.setLogLevel(old)


_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def check_png(data: bytes, path: Path) -> None:
    """Check a PNG's structure before libpng sees it (libpng prints its errors on stderr
    itself, past OpenCV's log level): chunk lengths within the file, every chunk's CRC,
    IHDR first with a size of at most :data:`MAX_PIXELS`, IDAT data that inflates to
    exactly the image's size (bounded: a zip bomb stops at that size), IEND last.
    Raises RecordingError naming what is wrong."""
    n = len(data)
    pos = 8
    ihdr: tuple[int, int, int, int, int] | None = None
    idat = zlib.decompressobj()
    inflated = 0
    expected = 0
    seen_iend = False
    while pos < n:
        if pos + 12 > n:
            raise RecordingError(path, f"corrupt PNG: truncated chunk at byte {pos}")
        length, ctype = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 8 + length
        if end + 4 > n:
            raise RecordingError(path, f"corrupt PNG: chunk {ctype!r} runs past the end of the file")
        body = data[pos + 8:end]
        (crc,) = struct.unpack(">I", data[end:end + 4])
        if zlib.crc32(ctype + body) != crc:
            raise RecordingError(path, f"corrupt PNG: CRC error in chunk {ctype!r} at byte {pos}")
        if ihdr is None:
            if ctype != b"IHDR" or length != 13:
                raise RecordingError(path, "corrupt PNG: does not start with an IHDR chunk")
            w, h, depth, color, _, _, interlace = struct.unpack(">IIBBBBB", body)
            if w * h > MAX_PIXELS or w == 0 or h == 0:
                raise RecordingError(path, f"PNG claims {w}x{h} px (at most {MAX_PIXELS} px are read)")
            if color not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16):
                raise RecordingError(path, f"corrupt PNG: colour type {color}, bit depth {depth}")
            ihdr = (w, h, depth, color, interlace)
            row = (w * _PNG_CHANNELS[color] * depth + 7) // 8 + 1
            expected = h * row if not interlace else 2 * h * row + 64  # Adam7: bounded above
        elif ctype == b"IDAT":
            try:
                out = idat.decompress(body, max(expected - inflated, 0) + 1)
            except zlib.error as e:
                raise RecordingError(path, f"corrupt PNG: bad image data ({e})") from None
            inflated += len(out)
            if inflated > expected or idat.unconsumed_tail:
                raise RecordingError(path, "corrupt PNG: more image data than its size")
        elif ctype == b"IEND":
            seen_iend = True
            break
        pos = end + 4
    if ihdr is None or not seen_iend:
        raise RecordingError(path, "corrupt PNG: truncated (no IEND chunk)")
    if not idat.eof or (not ihdr[4] and inflated != expected):
        raise RecordingError(path, "corrupt PNG: image data incomplete")


def decode_grey(data: bytes, path: Path) -> np.ndarray:
    """An encoded image (PNG/TIFF/PGM/BMP bytes) as a (height, width) uint8/uint16 grey
    array, or RecordingError naming ``path``; nothing is printed."""
    if not data:
        raise RecordingError(path, "cannot read image (empty file)")
    if data[:8] == PNG_SIGNATURE:
        check_png(data, path)
    buf = np.frombuffer(data, dtype=np.uint8)
    with _opencv_quiet():
        try:
            img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        except cv2.error as e:  # e.g. a claimed size above OpenCV's pixel limit
            msg = " ".join(str(e).split())[-160:]
            raise RecordingError(path, f"cannot read image (corrupt or unsupported: {msg})") from None
    if img is None:
        raise RecordingError(path, "cannot read image (unreadable, corrupt or not an image)")
    return _to_grey(img, path)


def load_grey(path: Path) -> np.ndarray:
    """One image file as a (height, width) uint8/uint16 grey array, or RecordingError
    (read as bytes and decoded in memory with OpenCV's messages off: :func:`decode_grey`)."""
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_FILE_BYTES + 1)
    except OSError as e:
        raise RecordingError(path, f"cannot read: {e.strerror or e}") from None
    if len(data) > MAX_FILE_BYTES:
        raise RecordingError(path, f"frame file larger than {MAX_FILE_BYTES >> 20} MiB")
    return decode_grey(data, path)


def _to_grey(img: np.ndarray, path: Path) -> np.ndarray:
    if img.ndim not in (2, 3) or img.size == 0:
        raise RecordingError(path, f"unsupported image of shape {img.shape}")
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        else:
            raise RecordingError(path, f"unsupported image with {img.shape[2]} channels")
    if img.dtype not in (np.uint8, np.uint16):
        raise RecordingError(path, f"unsupported pixel type {img.dtype} (need 8- or 16-bit grey)")
    return img


def _read_sidecar(folder: Path) -> dict[str, Any]:
    p = folder / SIDECAR
    if not p.is_file():
        return {}
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            raise ValueError("expected a JSON object")
        out: dict[str, Any] = {}
        for key in ("fps", "exposure_s"):
            if data.get(key) is not None:
                v = data[key]
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                    raise ValueError(f"{key} must be a number > 0, got {v!r:.40}")
                out[key] = float(header_number(v, key, lo=0))
        if data.get("camera") is not None:
            out["camera"] = str(data["camera"])
        if data.get("bit_depth") is not None:
            v = data["bit_depth"]
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 16:
                raise ValueError(f"bit_depth must be an integer 1..16, got {v!r}")
            out["bit_depth"] = v
        return out
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
        raise RecordingError(p, f"bad sidecar: {type(e).__name__ if isinstance(e, RecursionError) else e}") from None


class ImageFolderRecording(Recording):
    """Reader of a folder of PNG/TIFF frames (see the module docstring)."""

    format = "images"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise RecordingError(self.path, "not a folder")
        try:
            self.files = list_frames(self.path)
        except OSError as e:
            raise RecordingError(self.path, f"cannot list folder: {e.strerror or e}") from None
        if not self.files:
            others = [p for p in self.path.iterdir() if not p.name.startswith(".")]
            if not others:
                raise RecordingError(self.path, "empty folder: no PNG/TIFF frames")
            jpgs = sum(1 for p in others if p.suffix.lower() in (".jpg", ".jpeg"))
            hint = f"; {jpgs} are JPEG, which is lossy and not accepted" if jpgs else ""
            raise RecordingError(self.path, f"no PNG/TIFF frames in this folder "
                                            f"({len(others)} other entries{hint})")
        side = _read_sidecar(self.path)
        first = load_grey(self.files[0])
        self.height, self.width = first.shape
        self.dtype = first.dtype
        nbits = 8 * self.dtype.itemsize
        self.bit_depth = int(side.get("bit_depth", nbits))
        if self.bit_depth > nbits:
            raise RecordingError(self.path / SIDECAR, f"bit_depth {self.bit_depth} exceeds the "
                                                      f"frames' {self.dtype.name}")
        self.fps = side.get("fps")
        self.exposure_s = side.get("exposure_s")
        self.camera = side.get("camera")
        self._check_png_sizes()
        self.frame_ids = ids_from_names(self.files)
        rel = self.frame_ids - self.frame_ids[0]
        self.timestamps_ns = (np.round(rel * (1e9 / self.fps)).astype(np.int64) if self.fps
                              else np.zeros(len(self.files), dtype=np.int64))

    def _check_png_sizes(self) -> None:
        for p in self.files:
            try:
                size = _png_size(p)
            except OSError as e:
                raise RecordingError(p, f"cannot read: {e.strerror or e}") from None
            if size is not None and size != (self.width, self.height):
                raise RecordingError(p, f"frame size {size[0]}x{size[1]} differs from the first "
                                        f"frame's {self.width}x{self.height} ({self.files[0].name})")

    def _load(self, path: Path) -> np.ndarray:
        img = load_grey(path)
        if img.shape != (self.height, self.width):
            raise RecordingError(path, f"frame size {img.shape[1]}x{img.shape[0]} differs from the "
                                       f"first frame's {self.width}x{self.height} ({self.files[0].name})")
        if img.dtype != self.dtype:
            raise RecordingError(path, f"pixel type {img.dtype} differs from the first frame's "
                                       f"{self.dtype.name} ({self.files[0].name})")
        return img

    def _read(self, start: int, stop: int) -> np.ndarray:
        out = np.empty((stop - start, self.height, self.width), dtype=self.dtype)
        for k, p in enumerate(self.files[start:stop]):
            out[k] = self._load(p)
        return out

    def _extra_info(self) -> dict[str, Any]:
        return {"first_file": self.files[0].name, "last_file": self.files[-1].name,
                "sidecar": (self.path / SIDECAR).is_file()}
