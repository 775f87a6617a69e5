"""Photron MRAW recordings: a ``.cih`` (text) or ``.cihx`` (XML after a binary preamble)
header with the raw ``.mraw`` pixel file of the same name beside it.

The header is parsed by pyMRAW (``pyMRAW.get_cih``); the pixels are read here, through a
memory map of the ``.mraw``, so that only the requested frames are touched (pyMRAW's own
loader unpacks a whole 12-bit recording into memory). Pixel layout of the ``.mraw``:
frames back to back, rows top to bottom, no padding;

- 8-bit: one byte per pixel;
- 16-bit: little-endian uint16 per pixel;
- 12-bit packed: two pixels in three bytes, big-endian bit order:
  ``p0 = b0 << 4 | b1 >> 4``, ``p1 = (b1 & 0xF) << 8 | b2``.

Frame ids count from the header's start frame (negative before the trigger); timestamps
are ``index / fps`` (ns from the first saved frame).
"""

from __future__ import annotations

import math
import os
import warnings
import xml.etree.ElementTree as ET
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from iscd.recording.base import Recording, RecordingError, RecordingWarning

SUPPORTED_BITS = (8, 12, 16)


def unpack_12bit(raw: np.ndarray) -> np.ndarray:
    """Unpack Photron 12-bit packed pixels: uint8 array (..., 3k) -> uint16 (..., 2k).

    Bytes ``b0 b1 b2`` hold ``p0 = b0 << 4 | b1 >> 4`` and ``p1 = (b1 & 0xF) << 8 | b2``,
    i.e. p0 is the big-endian uint16 at byte 0 shifted right by 4 and p1 the big-endian
    uint16 at byte 1 masked to 12 bits; both are read as strided views (no byte copies).
    """
    if raw.shape[-1] % 3:
        raise ValueError(f"12-bit packed data needs a multiple of 3 bytes, got {raw.shape[-1]}")
    flat = np.ascontiguousarray(raw, dtype=np.uint8).reshape(-1)
    m = flat.size // 3
    out = np.empty((m, 2), dtype=np.uint16)
    if m:
        hi = np.ndarray((m,), dtype=">u2", buffer=flat, offset=0, strides=(3,))
        lo = np.ndarray((m,), dtype=">u2", buffer=flat, offset=1, strides=(3,))
        np.right_shift(hi, 4, out=out[:, 0])
        np.bitwise_and(lo, 0xFFF, out=out[:, 1])
    return out.reshape(*raw.shape[:-1], raw.shape[-1] // 3 * 2)


def find_files(path: Path) -> tuple[Path, Path]:
    """(header, mraw) for a ``.cih``/``.cihx``/``.mraw`` path, or RecordingError."""
    suffix = path.suffix.lower()
    if suffix == ".mraw":
        mraw = path
        if not mraw.is_file():
            raise RecordingError(mraw, "no such file")
        for ext in (".cihx", ".cih", ".CIHX", ".CIH"):
            header = mraw.with_suffix(ext)
            if header.is_file():
                return header, mraw
        raise RecordingError(mraw, f"missing Photron header: no {mraw.stem}.cihx or "
                                   f"{mraw.stem}.cih beside the .mraw")
    header = path
    if not header.is_file():
        raise RecordingError(header, "no such file")
    for ext in (".mraw", ".MRAW"):
        mraw = header.with_suffix(ext)
        if mraw.is_file():
            return header, mraw
    raise RecordingError(header, f"missing pixel file {header.with_suffix('.mraw').name} beside the header")


def _cihx_xml(header: Path) -> ET.Element:
    """The XML tree of a ``.cihx`` (the text between ``<cih>`` and ``</cih>``)."""
    text = header.read_bytes().decode("utf-8", errors="ignore")
    a, b = text.find("<cih>"), text.rfind("</cih>")
    if a < 0 or b < 0:
        raise ValueError("no <cih> XML block")
    return ET.fromstring(text[a:b + len("</cih>")])


def _number(value: Any) -> float | None:
    """A header number; accepts ``1/50000`` fractions. None when absent or unparsable."""
    if value is None or value == "":
        return None
    try:
        out = float(Fraction(str(value).strip()))
    except (ValueError, ZeroDivisionError, OverflowError):
        return None
    return out if math.isfinite(out) else None


def parse_header(header: Path) -> dict[str, Any]:
    """Normalized header fields: width, height, frames, color_bit, effective_bit,
    effective_side, file_format, fps, exposure_s, start_frame, camera_type, extra."""
    try:
        import pyMRAW
        cih = pyMRAW.get_cih(str(header))
    except Exception as e:  # pyMRAW raises bare Exception/KeyError/ExpatError on bad input
        raise RecordingError(header, f"cannot parse Photron header: {type(e).__name__}: {e}") from None
    extra: dict[str, Any] = {}
    try:
        if header.suffix.lower() == ".cihx":
            root = _cihx_xml(header)
            start = root.findtext("frameInfo/startFrame")
            ns = _number(root.findtext("recordInfo/shutterSpeedNsec"))
            speed = _number(cih.get("Shutter Speed(s)"))
            exposure = ns * 1e-9 if ns else (1.0 / speed if speed else None)
            extra["camera_name"] = root.findtext("basicInfo/cameraName")
            skip = _number(root.findtext("frameInfo/skipFrame"))
            extra["skip_frame"] = None if skip is None else int(skip)
            color_type = root.findtext("imageDataInfo/colorInfo/type")
        else:
            start = cih.get("Start Frame")
            shutter = _number(cih.get("Shutter Speed(s)"))  # "1/50000" or a number of seconds
            exposure = shutter if shutter and shutter <= 1 else (1.0 / shutter if shutter else None)
            color_type = cih.get("Color Type")
        color_bit = int(cih["Color Bit"])
        fields = {
            "width": int(cih["Image Width"]),
            "height": int(cih["Image Height"]),
            "frames": int(cih["Total Frame"]),
            "color_bit": color_bit,
            "effective_bit": int(cih.get("EffectiveBit Depth") or color_bit),
            "effective_side": str(cih.get("EffectiveBit Side") or "Lower"),
            "file_format": str(cih.get("File Format", "")),
            "fps": _number(cih.get("Record Rate(fps)")),
            "exposure_s": exposure,
            "start_frame": int(float(start)) if start not in (None, "") else 0,
            "camera_type": cih.get("Camera Type"),
        }
        extra.update({"date": cih.get("Date"), "color_type": color_type,
                      "recorded_frames": cih.get("Original Total Frame"),
                      "comment": cih.get("Comment Text") or ""})
    except (KeyError, TypeError, ValueError, OverflowError, ET.ParseError) as e:
        raise RecordingError(header, f"cannot parse Photron header: {type(e).__name__}: {e}") from None
    if abs(fields["start_frame"]) > 2**62:
        raise RecordingError(header, f"cannot parse Photron header: start frame {fields['start_frame']} out of range")
    fields["extra"] = extra
    return fields


class PhotronRecording(Recording):
    """Reader of a Photron MRAW recording (8-, 12-packed or 16-bit, monochrome).

    Args:
      path: the ``.cih``, ``.cihx`` or ``.mraw`` file (the other one must be beside it).
      allow_truncated: if the ``.mraw`` is shorter than the header says, read the complete
        frames with a warning instead of raising :class:`RecordingError`.
    """

    format = "photron"

    def __init__(self, path: str | Path, *, allow_truncated: bool = False) -> None:
        self.path = Path(path)
        self.header_path, self.mraw_path = find_files(self.path)
        h = parse_header(self.header_path)
        self.header = h
        self.width, self.height, n = h["width"], h["height"], h["frames"]
        if self.width < 1 or self.height < 1 or n < 0:
            raise RecordingError(self.header_path, f"invalid size in header: {self.width}x"
                                                   f"{self.height}, {n} frames")
        if h["file_format"].lower() != "mraw":
            raise RecordingError(self.header_path, f"unsupported Photron file format "
                                                   f"{h['file_format']!r} (only MRAW is read)")
        self.color_bit = bits = h["color_bit"]
        if bits not in SUPPORTED_BITS:
            raise RecordingError(self.header_path, f"unsupported bit depth {bits} "
                                                   f"(supported: 8, 12 and 16-bit monochrome)")
        if bits == 12 and (self.width * self.height) % 2:
            raise RecordingError(self.header_path, "12-bit packed frames need an even pixel count")
        self.dtype = np.dtype(np.uint8 if bits == 8 else np.uint16)
        eff = h["effective_bit"]
        # Pixels are returned as stored; with the significant bits on the "Higher" side the
        # values span the whole container, so bit_depth is the container's then.
        self.bit_depth = eff if (0 < eff <= bits and h["effective_side"].lower() == "lower") else bits
        self.fps = h["fps"] if h["fps"] and h["fps"] > 0 else None
        self.exposure_s = h["exposure_s"]
        self.camera = None if h["camera_type"] is None else str(h["camera_type"])
        self.frame_bytes = self.width * self.height * bits // 8

        expected = n * self.frame_bytes
        actual = os.path.getsize(self.mraw_path)
        if actual < expected:
            msg = (f"truncated .mraw: expected {expected} bytes ({n} frames x {self.frame_bytes}) "
                   f"but the file has {actual} bytes")
            if not allow_truncated:
                raise RecordingError(self.mraw_path, msg)
            n = actual // self.frame_bytes
            warnings.warn(f"{self.mraw_path}: {msg}; reading the {n} complete frames",
                          RecordingWarning, stacklevel=2)
        self._mm: np.memmap | None = None
        if n:
            self._mm = np.memmap(self.mraw_path, dtype=np.uint8, mode="r", shape=(n, self.frame_bytes))
        self.frame_ids = h["start_frame"] + np.arange(n, dtype=np.int64)
        self.timestamps_ns = (np.round(np.arange(n) * (1e9 / self.fps)).astype(np.int64)
                              if self.fps else np.zeros(n, dtype=np.int64))

    def _read(self, start: int, stop: int) -> np.ndarray:
        if self._mm is None:
            raise RecordingError(self.mraw_path, "recording is closed")
        raw = self._mm[start:stop]
        shape = (stop - start, self.height, self.width)
        if self.color_bit == 8:
            return np.array(raw).reshape(shape)
        if self.color_bit == 16:
            return np.array(raw).view("<u2").astype(np.uint16, copy=False).reshape(shape)
        return unpack_12bit(raw).reshape(shape)

    def _extra_info(self) -> dict[str, Any]:
        h = self.header
        return {"header": str(self.header_path), "mraw": str(self.mraw_path),
                "color_bit": self.color_bit, "effective_bit": h["effective_bit"],
                "effective_side": h["effective_side"], "start_frame": h["start_frame"],
                **h["extra"]}

    def close(self) -> None:
        self._mm = None
