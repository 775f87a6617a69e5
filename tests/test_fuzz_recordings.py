"""Property-based fuzzing (hypothesis) of the recording readers: ``.iscr``, Photron
``.cih``/``.cihx`` + ``.mraw``, and PNG/TIFF folders (with their ``recording.json``). Any
file gives a :class:`~iscd.recording.base.Recording` whose frames read back, or a
:class:`~iscd.recording.base.RecordingError` (one line), never another exception, and the
image reader prints nothing.

Bounds: files up to ~64 KiB each, headers whose numbers range over the whole of their field
(sizes up to 2**64, NaN, inf, negative); what a reader allocates is bounded by the file's
size (the frame count comes from the data present, never from the header alone). CI runs a
few dozen derandomized cases per target; ``ISCD_FUZZ_EXAMPLES=N`` for a long run
(docs/hardening.md).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import struct
import tempfile
import warnings
import zlib
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from fuzzing import fuzz
from hypothesis import example, given
from hypothesis import strategies as st

from iscd.recording import RecordingError, open_recording
from iscd.recording.iscr import FIXED_HEADER, MAGIC, IscrWriter

MAX_READ_BYTES = 1 << 20




@contextlib.contextmanager
def _workdir() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="iscd-fuzz-") as d:
        yield Path(d)


@contextlib.contextmanager
def _stderr_fd() -> Iterator[list[str]]:
    """What is written to file descriptor 2 (C libraries included) inside the block."""
    got: list[str] = []
    with tempfile.TemporaryFile() as tmp:
        saved = os.dup(2)
        os.dup2(tmp.fileno(), 2)
        try:
            yield got
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            got.append(tmp.read().decode("utf-8", "replace"))


def _exercise(path: Path) -> None:
    """Open ``path`` as a recording and read every frame (bounded), or accept RecordingError."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            rec = open_recording(path)
        except RecordingError as e:
            assert "\n" not in str(e)
            return
    with rec:
        info = rec.info()
        assert info["frames"] == rec.n_frames >= 0
        assert rec.width >= 1 and rec.height >= 1
        assert rec.fps is None or (math.isfinite(rec.fps) and rec.fps > 0)
        n = rec.n_frames
        if n:
            per = rec.width * rec.height * np.dtype(rec.dtype).itemsize
            k = max(1, min(n, MAX_READ_BYTES // max(per, 1)))
            try:
                block = rec.read(0, k)
                last = rec[n - 1]
            except RecordingError as e:
                assert "\n" not in str(e)
                return
            assert block.shape == (k, rec.height, rec.width) and block.dtype == rec.dtype
            assert last.shape == (rec.height, rec.width)


# --------------------------------------------------------------------------- .iscr
json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats(allow_nan=True) | st.text(max_size=8),
    lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=5), c, max_size=3), max_leaves=6)

meta_values = {
    "width": st.one_of(st.integers(-3, 70), st.integers(-2**64, 2**64), json_values),
    "height": st.one_of(st.integers(-3, 70), st.integers(-2**64, 2**64), json_values),
    "dtype": st.one_of(st.sampled_from(["uint8", "uint16", "float32", "int8", "", "uint8 "]), json_values),
    "bit_depth": st.one_of(st.integers(-2, 40), json_values),
    "fps": st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-2**1100, 2**1100), json_values),
    "exposure_s": st.one_of(st.floats(allow_nan=True), st.integers(-2**1100, 2**1100), json_values),
    "camera": json_values,
}


@st.composite
def iscr_files(draw: st.DrawFn) -> bytes:
    """A valid small .iscr, then some of its header fields, metadata and body replaced."""
    w, h = draw(st.integers(1, 12)), draw(st.integers(1, 12))
    dtype = draw(st.sampled_from(["uint8", "uint16"]))
    n = draw(st.integers(0, 4))
    with _workdir() as d:
        p = d / "x.iscr"
        with IscrWriter(p, width=w, height=h, dtype=dtype, fps=1000.0) as wr:
            for i in range(n):
                wr.append(i, i * 1000, np.full((h, w), i, dtype))
        data = bytearray(p.read_bytes())
    magic, version, hsize, mlen, doff, rsize = FIXED_HEADER.unpack_from(data)
    meta = json.loads(bytes(data[hsize:hsize + mlen]))
    for key, strat in meta_values.items():
        if draw(st.booleans()) and draw(st.booleans()):
            meta[key] = draw(strat)
    if draw(st.booleans()):
        meta.pop(draw(st.sampled_from(sorted(meta_values))), None)
    text = json.dumps(meta).encode()
    body = bytes(data[doff:])
    if draw(st.booleans()):
        doff = max(doff, -(-(32 + len(text)) // 64) * 64)
        mlen = len(text)
    fields = [magic, version, hsize, mlen, doff, rsize]
    for i, bound in ((1, 2**16 - 1), (2, 2**16 - 1), (3, 2**32 - 1), (4, 2**64 - 1), (5, 2**64 - 1)):
        if draw(st.integers(0, 5)) == 0:
            fields[i] = draw(st.integers(0, bound))
    head = FIXED_HEADER.pack(*fields)
    pad = b" " * max(0, min(int(fields[4]), 4096) - 32 - len(text))
    out = head + text + pad + body
    if draw(st.booleans()):
        cut = draw(st.integers(0, len(out)))
        out = out[:cut]
    return out


@fuzz(150)
@given(iscr_files())
@example(FIXED_HEADER.pack(MAGIC, 1, 32, 2, 64, 16) + b"{}" + b" " * 30)
def test_iscr_reader(data: bytes) -> None:
    with _workdir() as d:
        p = d / "f.iscr"
        p.write_bytes(data)
        _exercise(p)


@fuzz(60)
@given(st.binary(max_size=2048))
def test_iscr_reader_raw_bytes(data: bytes) -> None:
    with _workdir() as d:
        p = d / "f.iscr"
        p.write_bytes(MAGIC + data if data[:1] != b"\0" else data)
        _exercise(p)


# --------------------------------------------------------------------------- Photron
numbers = st.one_of(st.integers(-5, 70), st.integers(-2**70, 2**70),
                    st.sampled_from(["", "nan", "inf", "-inf", "1e400", "1/0", "1/50000", "abc", "12.5", "0x10"]),
                    st.floats(allow_nan=True).map(repr))

cih_fields = {
    "Record Rate(fps)": numbers, "Shutter Speed(s)": numbers, "Total Frame": numbers,
    "Original Total Frame": numbers, "Start Frame": numbers, "Image Width": numbers,
    "Image Height": numbers, "Color Type": st.sampled_from(["Mono", "Color", ""]),
    "Color Bit": st.one_of(st.sampled_from([8, 12, 16]), numbers),
    "File Format": st.sampled_from(["MRAW", "mraw", "TIFF", ""]),
    "EffectiveBit Depth": numbers, "EffectiveBit Side": st.sampled_from(["Lower", "Higher", "", "x"]),
    "Camera Type": st.text(max_size=10).filter(lambda s: "\n" not in s and "\r" not in s),
}


@st.composite
def cih_recordings(draw: st.DrawFn) -> tuple[str, bytes]:
    """A .cih text header (some fields missing or wild) and an .mraw of a drawn size."""
    w, h = draw(st.integers(1, 10)), draw(st.integers(1, 10))
    bits = draw(st.sampled_from([8, 12, 16]))
    n = draw(st.integers(0, 3))
    vals: dict[str, object] = {"Record Rate(fps)": 1000, "Shutter Speed(s)": "1/2000", "Total Frame": n,
                               "Original Total Frame": n, "Start Frame": 0, "Image Width": w,
                               "Image Height": h * 2, "Color Type": "Mono", "Color Bit": bits,
                               "File Format": "MRAW", "EffectiveBit Depth": bits,
                               "EffectiveBit Side": "Lower", "Camera Type": "FASTCAM"}
    for key, strat in cih_fields.items():
        if draw(st.integers(0, 3)) == 0:
            vals[key] = draw(strat)
    for key in list(vals):
        if draw(st.integers(0, 12)) == 0:
            del vals[key]
    text = "#Camera Information Header\n" + "".join(f"{k} : {v}\n" for k, v in vals.items()) + "END\n"
    mraw = draw(st.binary(max_size=2 * w * h * 2 * 3 + 8))
    return text, mraw


def _cih(**over: object) -> tuple[str, bytes]:
    vals: dict[str, object] = {"Record Rate(fps)": 1000, "Shutter Speed(s)": "1/2000", "Total Frame": 1,
                               "Start Frame": 0, "Image Width": 4, "Image Height": 4, "Color Type": "Mono",
                               "Color Bit": 8, "File Format": "MRAW", "EffectiveBit Depth": 8,
                               "EffectiveBit Side": "Lower"}
    vals.update(over)
    return "#Camera Information Header\n" + "".join(f"{k} : {v}\n" for k, v in vals.items()) + "END\n", b"\0" * 16


@fuzz(120)
@given(cih_recordings())
@example(_cih(**{"Start Frame": "inf"}))  # the fuzzer's findings: OverflowError escaped
@example(_cih(**{"Start Frame": "1e400"}))
@example(_cih(**{"Record Rate(fps)": "1e400"}))
@example(_cih(**{"Start Frame": 2**70}))
@example(_cih(**{"Shutter Speed(s)": "1/1e-400"}))
def test_photron_cih_reader(rec: tuple[str, bytes]) -> None:
    text, mraw = rec
    with _workdir() as d:
        (d / "r.cih").write_text(text, encoding="utf-8")
        (d / "r.mraw").write_bytes(mraw)
        _exercise(d / "r.cih")
        _exercise(d / "r.mraw")


@fuzz(60)
@given(cih_recordings(), st.sampled_from(["1000", "nan", "1e400", "-3", "x", "", "inf"]),
       st.sampled_from(["0", "-10", "inf", "1e400", "nan", "x", "99999999999999999999999"]),
       st.booleans())
def test_photron_cihx_reader(rec: tuple[str, bytes], shutter: str, start: str, break_xml: bool) -> None:
    text, mraw = rec
    xml = ("<cih><fileFormat>MRAW</fileFormat><frameInfo><startFrame>" + start + "</startFrame>"
           "<skipFrame>" + start + "</skipFrame></frameInfo><recordInfo><shutterSpeedNsec>" + shutter +
           "</shutterSpeedNsec></recordInfo><basicInfo><cameraName>c</cameraName></basicInfo></cih>")
    if break_xml:
        xml = xml[: len(xml) // 2]
    with _workdir() as d:
        (d / "r.cihx").write_bytes(b"\x00\x01binary preamble" + text.encode() + xml.encode())
        (d / "r.mraw").write_bytes(mraw)
        _exercise(d / "r.cihx")


@fuzz(40)
@given(st.binary(max_size=4096), st.binary(max_size=256))
def test_photron_raw_bytes(header: bytes, mraw: bytes) -> None:
    with _workdir() as d:
        for suffix in (".cih", ".cihx"):
            (d / f"r{suffix}").write_bytes(header)
            (d / "r.mraw").write_bytes(mraw)
            _exercise(d / f"r{suffix}")


# --------------------------------------------------------------------------- image folders
def _png(w: int, h: int, dtype: str, value: int) -> bytes:
    ok, buf = cv2.imencode(".png", np.full((h, w), value, np.dtype(dtype)))
    assert ok
    return buf.tobytes()


@st.composite
def frame_files(draw: st.DrawFn) -> tuple[str, bytes]:
    stem = draw(st.sampled_from(["f", "left_", "x9_", "frame"])) + draw(
        st.sampled_from(["", "1", "007", "10", "99999999999999999999999", "3_4"]))
    ext = draw(st.sampled_from([".png", ".tif", ".pgm", ".bmp", ".PNG", ".jpg", ".txt"]))
    kind = draw(st.sampled_from(["png", "png", "truncated", "mutated", "idat", "random", "empty"]))
    w, h = draw(st.integers(1, 9)), draw(st.integers(1, 9))
    dtype = draw(st.sampled_from(["uint8", "uint16"]))
    good = _png(w, h, dtype, draw(st.integers(0, 255)))
    if kind == "png":
        data = good
    elif kind == "truncated":
        data = good[: draw(st.integers(0, len(good)))]
    elif kind == "mutated":
        b = bytearray(good)
        for _ in range(draw(st.integers(1, 6))):
            b[draw(st.integers(0, len(b) - 1))] = draw(st.integers(0, 255))
        if draw(st.booleans()):  # claim any size in an IHDR with a valid CRC
            b[16:24] = struct.pack(">II", draw(st.integers(0, 2**32 - 1)), draw(st.integers(0, 2**32 - 1)))
            b[29:33] = struct.pack(">I", zlib.crc32(bytes(b[12:29])))
        data = bytes(b)
    elif kind == "idat":  # bad compressed data under valid chunk CRCs: only zlib can tell
        b = bytearray(good)
        at = b.index(b"IDAT")
        length = struct.unpack(">I", b[at - 4:at])[0]
        k = at + 4 + draw(st.integers(0, max(length - 1, 0)))
        b[k] = draw(st.integers(0, 255))
        b[at + 4 + length:at + 8 + length] = struct.pack(">I", zlib.crc32(bytes(b[at:at + 4 + length])))
        data = bytes(b)
    elif kind == "random":
        data = draw(st.sampled_from([b"II*\x00", b"MM\x00*", b"BM", b"P5\n", b"\x89PNG\r\n\x1a\n"])) + \
            draw(st.binary(max_size=200))
    else:
        data = b""
    return stem + ext, data


sidecars = st.one_of(
    st.none(), st.binary(max_size=40),
    st.builds(lambda d: json.dumps(d), st.dictionaries(
        st.sampled_from(["fps", "exposure_s", "camera", "bit_depth", "other"]),
        st.one_of(json_values, st.integers(-2**1100, 2**1100), st.floats(allow_nan=True)), max_size=4)))


@fuzz(120)
@given(st.lists(frame_files(), min_size=0, max_size=5), sidecars)
@example([("f_1.png", _png(4, 4, "uint8", 1)), ("f_99999999999999999999999.png", _png(4, 4, "uint8", 2))], None)
@example([("f_1.png", _png(4, 4, "uint8", 1))], json.dumps({"fps": 10 ** 400}))
def test_image_folder_reader(files: list[tuple[str, bytes]], sidecar: str | bytes | None) -> None:
    with _workdir() as d:
        folder = d / "frames"
        folder.mkdir()
        for name, data in files:
            (folder / name).write_bytes(data)
        if sidecar is not None:
            p = folder / "recording.json"
            p.write_bytes(sidecar if isinstance(sidecar, bytes) else sidecar.encode())
        with _stderr_fd() as err:
            _exercise(folder)
        assert err == [""], f"the image reader printed: {err[0]!r}"


def test_image_folder_huge_png_claim_is_refused_before_decoding() -> None:
    """A PNG whose IHDR claims 100000 x 100000 px is refused from its header (no allocation)."""
    from iscd.recording.images import decode_grey

    b = bytearray(_png(4, 4, "uint8", 3))
    b[16:24] = struct.pack(">II", 100_000, 100_000)
    b[29:33] = struct.pack(">I", zlib.crc32(bytes(b[12:29])))  # a consistent IHDR
    with pytest.raises(RecordingError, match="100000x100000"):
        decode_grey(bytes(b), Path("huge.png"))
