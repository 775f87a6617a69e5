"""The stereo ``.iscr`` format, version 2 (issue 18): what ``iscd run --record`` writes.

Pairs (whole or windows) read back bit for bit through the index of a sealed file; a file
cut anywhere (a killed writer, a power cut) reads back up to its last whole pair, by a
scan; a damaged header ends the scan; the version-1 reader names the stereo reader.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from iscd.recording import RecordingError, open_recording
from iscd.recording.iscr import FIXED_HEADER
from iscd.recording.pairfile import PAIR_HEADER_SIZE, PairFileWriter
from iscd.recording.pairs import PairRecording, PairSession, frame_ranges

H, W = 24, 40


def _frames(n: int, dtype: str = "uint8", seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    hi = 255 if dtype == "uint8" else 4095
    return [(rng.integers(0, hi, (H, W)).astype(dtype), rng.integers(0, hi, (H, W)).astype(dtype)) for _ in range(n)]


def _write(path: Path, frames, dtype: str = "uint8", whole_first: int = 3) -> list:
    """Pairs 0..n-1: the first ``whole_first`` whole, the rest windows that move; blocks of 4."""
    wins = []
    with PairFileWriter(path, width=W, height=H, dtype=dtype, mode="roi", fps=1000.0, bit_depth=12 if dtype == "uint16" else 8,
                        meta={"session": "t", "intake_buffers": 4}) as w:
        for i, (left, right) in enumerate(frames):
            if i < whole_first:
                w.append(i, 1000 * i, 1000 * i + 7, left, right, block=i // 4)
                wins.append(None)
            else:
                wl, wr = (i % 5, 2, i % 5 + 9, 11), (3, i % 4, 21, i % 4 + 13)
                w.append(i, 1000 * i, 1000 * i + 7, left, right, wl, wr, block=i // 4)
                wins.append((wl, wr))
    return wins


@pytest.mark.parametrize("dtype", ["uint8", "uint16"])
def test_pairs_read_back_bit_for_bit(tmp_path: Path, dtype: str) -> None:
    frames = _frames(11, dtype)
    p = tmp_path / "a.iscr"
    wins = _write(p, frames, dtype)
    rec = PairRecording(p)
    assert rec.sealed and rec.n_pairs == 11 and rec.mode == "roi" and rec.dtype == np.dtype(dtype)
    assert rec.frame_ids.tolist() == list(range(11)) and rec.ts_right_ns[2] == 2007
    assert rec.blocks.tolist() == [i // 4 for i in range(11)]
    L, R = rec.read_pairs(0, 11)
    for i, (left, right) in enumerate(frames):
        if wins[i] is None:
            assert np.array_equal(L[i], left) and np.array_equal(R[i], right) and rec.whole[i]
            continue
        (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = wins[i]
        assert np.array_equal(L[i, ay0:ay1, ax0:ax1], left[ay0:ay1, ax0:ax1])
        assert np.array_equal(R[i, by0:by1, bx0:bx1], right[by0:by1, bx0:bx1])
        assert L[i].sum() == left[ay0:ay1, ax0:ax1].sum()  # nothing outside the window
    assert np.array_equal(rec.left[5], L[5]) and np.array_equal(rec.right.read(3, 6), R[3:6])
    info = rec.info()
    assert info["whole_frame_pairs"] == 3 and info["window_pairs"] == 8 and info["frame_ranges"] == [[0, 10]]
    assert info["windows"]["left"]["width_px_min_median_max"][0] == 9


def test_blocks_emulate_the_intake_buffers(tmp_path: Path) -> None:
    """A replay hands the decoder what the live intake did: pair k of a block is written
    over buffer k, so pixels outside a window are that buffer's earlier content."""
    frames = _frames(11)
    p = tmp_path / "a.iscr"
    _write(p, frames)
    with PairSession(p) as s:
        blocks = list(s.iter_blocks())
        zeros = list(s.iter_blocks(emulate_intake=False))
    assert [b[0].tolist() for b in blocks] == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10]]
    # block 1, buffer 0 (pair 4): its window over pair 0's whole frame
    L4 = frames[0][0].copy()
    L4[2:11, 4:13] = frames[4][0][2:11, 4:13]
    assert np.array_equal(blocks[1][3][0], L4)
    assert zeros[1][3][0][0, 0] == 0 and np.array_equal(zeros[1][3][0][2:11, 4:13], L4[2:11, 4:13])


def test_a_cut_file_reads_back_to_its_last_whole_pair(tmp_path: Path) -> None:
    frames = _frames(9)
    p = tmp_path / "a.iscr"
    _write(p, frames)
    full = PairRecording(p)
    ends = full.offsets + full.sizes
    data = p.read_bytes()
    cut = tmp_path / "cut.iscr"
    for n in sorted({*range(full.data_offset, len(data), 37), *ends.tolist(), *(ends - 1).tolist(), len(data) - 1}):
        cut.write_bytes(data[:n])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = PairRecording(cut)
        whole = int((ends <= n).sum())
        assert r.n_pairs == whole and not r.sealed, n
        assert r.recovery["bytes_in_whole_pairs"] + r.recovery["trailing_bytes_ignored"] == n - r.data_offset
        if whole:
            assert np.array_equal(r.read_pairs(whole - 1, whole)[1][0], full.read_pairs(whole - 1, whole)[1][0])


def test_a_damaged_header_ends_the_scan(tmp_path: Path) -> None:
    p = tmp_path / "a.iscr"
    _write(p, _frames(6))
    rec = PairRecording(p)
    data = bytearray(p.read_bytes())
    data[int(rec.offsets[4]) + 9] ^= 0xFF  # a bit of pair 4's frame id: its header CRC fails
    p.write_bytes(bytes(data))
    with pytest.warns(Warning, match="not sealed"):
        r = PairRecording(p)
    assert r.n_pairs == 4 and not r.sealed


def test_the_one_camera_reader_points_to_the_stereo_one(tmp_path: Path) -> None:
    p = tmp_path / "a.iscr"
    _write(p, _frames(2))
    with pytest.raises(RecordingError, match="stereo .iscr.*open_stereo"):
        open_recording(p)
    data = p.read_bytes()
    magic, ver, hs, ml, doff, rs = FIXED_HEADER.unpack_from(data)
    assert ver == 2 and rs == 0 and doff % 64 == 0 and (len(data) - doff) % 8 == 0
    assert PAIR_HEADER_SIZE == 64


def test_frame_ranges() -> None:
    assert frame_ranges(np.array([3, 4, 5, 9, 10, 12])) == [[3, 5], [9, 10], [12, 12]]
    assert frame_ranges(np.array([], np.int64)) == []


def test_block_notes_say_what_the_decoder_shed(tmp_path: Path) -> None:
    """A block note (a header alone) after a block's pairs: read back per block, not a pair,
    in a sealed file and in a cut one."""
    frames = _frames(8)
    p = tmp_path / "n.iscr"
    with PairFileWriter(p, width=W, height=H, mode="roi", fps=1000.0) as w:
        for i, (left, right) in enumerate(frames):
            w.append(i, i, i, left, right, (0, 0, 8, 8), (0, 0, 8, 8), block=i // 4)
            if i == 3:
                w.note(3, 0, ranging_every=4, per_led=False)
            if i == 7:
                w.note(7, 1, ranging_every=1, per_led=True, ahead=3)
    with PairSession(p) as s:
        r = s.files[0]
        assert r.n_pairs == 8 and r.notes == {0: (4, False, 0), 1: (1, True, 3)}
        assert r.frame_ids.tolist() == list(range(8))
        assert s.block_service(0) == (4, False) and s.block_service(1) == (1, True)
        assert s.block_ahead(0) == 0 and s.block_ahead(1) == 3 and s.block_ahead(2) == 0
        assert [b.block for b in s.iter_blocks()] == [0, 1]
    data = p.read_bytes()
    cut = tmp_path / "cut.iscr"
    cut.write_bytes(data[:int(r.offsets[5]) + 10])
    with pytest.warns(Warning, match="not sealed"):
        c = PairRecording(cut)
    assert c.n_pairs == 5 and c.notes == {0: (4, False, 0)}
