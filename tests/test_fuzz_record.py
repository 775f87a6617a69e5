"""Fuzzing (hypothesis) the stereo ``.iscr`` reader (issue 18; docs/hardening.md's property):
any file gives a :class:`~iscd.recording.pairs.PairRecording` whose pairs read back, or a
:class:`~iscd.recording.base.RecordingError` (one line), never another exception. Inputs: a
valid small file (pairs, a block note, index, seal) with bytes overwritten anywhere, the
metadata replaced, or cut; and raw bytes behind a version-2 header.
"""

from __future__ import annotations

import json
import tempfile
import warnings
from pathlib import Path

import numpy as np
from fuzzing import fuzz
from hypothesis import example, given
from hypothesis import strategies as st

from iscd.recording import RecordingError
from iscd.recording.iscr import FIXED_HEADER, MAGIC
from iscd.recording.pairfile import PairFileWriter
from iscd.recording.pairs import PairRecording, PairSession


def _valid() -> bytes:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "v.iscr"
        img = (np.arange(20 * 16) % 251).astype(np.uint8).reshape(16, 20)
        with PairFileWriter(p, width=20, height=16, mode="roi", fps=1000.0, meta={"intake_buffers": 2}) as w:
            for i in range(5):
                w.append(i, i, i, img, img, *(((1, 2, 7, 9), (0, 0, 20, 3)) if i else (None, None)), block=i // 2)
            w.note(4, 2, 4, False)
        return p.read_bytes()


VALID = _valid()


def _exercise(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "f.iscr"
        p.write_bytes(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                rec = PairRecording(p)
            except RecordingError as e:
                assert "\n" not in str(e)
                return
            with rec:
                assert rec.n_pairs <= 5 + len(data) // 64
                info = rec.info()
                assert info["pairs"] == rec.n_pairs
                k = min(rec.n_pairs, max(1, 2**22 // (rec.width * rec.height)))  # bounded reads
                if rec.n_pairs:
                    L, R = rec.read_pairs(0, k)
                    assert L.shape == (k, rec.height, rec.width)
                    rec.check()
            if rec.width * rec.height <= 2**16:
                with PairSession(p) as s:
                    for _ in s.iter_blocks(max_pairs=8):
                        pass


@fuzz(80)
@given(st.lists(st.tuples(st.integers(0, len(VALID) - 1), st.integers(0, 255)), max_size=6),
       st.one_of(st.none(), st.integers(0, len(VALID))))
def test_mutated_files(edits: list[tuple[int, int]], cut: int | None) -> None:
    data = bytearray(VALID)
    for pos, val in edits:
        data[pos] = val
    _exercise(bytes(data[:cut] if cut is not None else data))


meta_values = st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(allow_nan=True),
                        st.text(max_size=6), st.lists(st.integers(), max_size=2))


@fuzz(60)
@example({"width": 8192, "height": 8192, "intake_buffers": 4096})
@example({"width": 65535})
@given(st.dictionaries(st.sampled_from(["width", "height", "dtype", "bit_depth", "fps", "exposure_s", "mode",
                                        "intake_buffers"]), meta_values, max_size=4))
def test_metadata_replaced(changes: dict) -> None:
    hs, ml, doff = FIXED_HEADER.unpack_from(VALID)[2:5]
    meta = json.loads(VALID[hs:hs + ml])
    meta.update(changes)
    text = json.dumps(meta).encode()
    if 32 + len(text) > doff:
        return
    head = FIXED_HEADER.pack(MAGIC, 2, 32, len(text), doff, 0)
    _exercise(head + text + b" " * (doff - 32 - len(text)) + VALID[doff:])


@fuzz(40)
@given(st.binary(max_size=1024))
def test_raw_bytes_behind_a_header(body: bytes) -> None:
    text = json.dumps({"width": 8, "height": 8, "dtype": "uint8", "mode": "full"}).encode()
    head = FIXED_HEADER.pack(MAGIC, 2, 32, len(text), 64, 0)
    _exercise(head + text + b" " * (64 - 32 - len(text)) + body)
