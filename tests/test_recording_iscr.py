"""The project's own recording format (.iscr): writer, reader, crash safety."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from iscd.recording import (IscrRecording, IscrWriter, RecordingError, RecordingWarning,
                            match_frames, open_recording)
from iscd.recording.iscr import FIXED_HEADER_SIZE

H, W = 24, 40


def _frames(n: int, dtype: str, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    hi = 256 if dtype == "uint8" else 4096
    return rng.integers(0, hi, size=(n, H, W), dtype=dtype)


def _write(path: Path, imgs: np.ndarray, **kw) -> tuple[np.ndarray, np.ndarray]:
    n = len(imgs)
    ids = 100 + np.arange(n, dtype=np.int64) * 1 + (np.arange(n) >= 5)  # one dropped id after 5
    ts = 7_000_000 + ids * 1_000_000
    args = dict(width=W, height=H, dtype=imgs.dtype.name, camera="right", fps=1000.0,
                exposure_s=1e-3, bit_depth=12 if imgs.dtype == np.uint16 else 8,
                meta={"scene": {"distance_m": 30.0}, "seed": np.int64(3)})
    args.update(kw)
    with IscrWriter(path, **args) as w:
        for i in range(min(3, n)):  # one by one, then the rest in a block
            w.append(int(ids[i]), int(ts[i]), imgs[i])
        w.append_many(ids[3:], ts[3:], imgs[3:])
        assert w.n_frames == n
    return ids, ts


@pytest.mark.parametrize("dtype", ["uint8", "uint16"])
def test_round_trip(tmp_path: Path, dtype: str) -> None:
    imgs = _frames(12, dtype)
    path = tmp_path / "cam.iscr"
    ids, ts = _write(path, imgs)
    with open_recording(path) as rec:
        assert isinstance(rec, IscrRecording)
        assert (len(rec), rec.height, rec.width) == (12, H, W)
        assert rec.dtype == np.dtype(dtype)
        assert rec.bit_depth == (8 if dtype == "uint8" else 12)
        assert rec.fps == 1000.0 and rec.exposure_s == 1e-3 and rec.camera == "right"
        np.testing.assert_array_equal(rec.frame_ids, ids)
        np.testing.assert_array_equal(rec.timestamps_ns, ts)
        block = rec.read()
        assert block.dtype == np.dtype(dtype) and block.flags.c_contiguous
        np.testing.assert_array_equal(block, imgs)
        np.testing.assert_array_equal(rec.read(4, 9), imgs[4:9])
        np.testing.assert_array_equal(rec[-1], imgs[-1])
        np.testing.assert_array_equal(rec[np.int64(2)], imgs[2])
        np.testing.assert_array_equal(rec[1:11:3], imgs[1:11:3])
        np.testing.assert_array_equal(np.stack(list(rec)), imgs)
        blocks = list(rec.iter_blocks(5))
        assert [len(b) for b in blocks] == [5, 5, 2]
        np.testing.assert_array_equal(np.concatenate(blocks), imgs)
        assert rec.read(20, 30).shape == (0, H, W)
        with pytest.raises(IndexError):
            rec[12]
        info = rec.info()
        assert info["frames"] == 12 and info["width"] == W and info["height"] == H
        assert info["fps"] == 1000.0 and info["bit_depth"] == rec.bit_depth
        assert info["format"] == "iscr" and info["camera"] == "right"
        assert info["duration_s"] == pytest.approx(0.012)
        assert info["missing_frame_ids"] == 1
        assert info["extra"]["meta"] == {"scene": {"distance_m": 30.0}, "seed": 3}
        json.dumps(info)  # serializable


def test_layout_matches_the_documented_bytes(tmp_path: Path) -> None:
    """Read a file with plain struct/numpy exactly as docs/recording-format.md describes."""
    imgs = _frames(6, "uint16", seed=1)
    path = tmp_path / "doc.iscr"
    ids, ts = _write(path, imgs)
    raw = path.read_bytes()
    magic, ver, hsize, mlen, doff, rsize = struct.unpack("<8sHHIQQ", raw[:32])
    assert magic == b"ISCR\r\n\x1a\n" and ver == 1 and hsize == 32
    assert doff % 64 == 0 and doff >= hsize + mlen
    assert rsize == 16 + H * W * 2
    meta = json.loads(raw[hsize:hsize + mlen])
    assert set(raw[hsize + mlen:doff]) <= {0x20}
    assert (meta["width"], meta["height"], meta["dtype"], meta["camera"]) == (W, H, "uint16", "right")
    assert len(raw) == doff + 6 * rsize
    for k in range(6):
        rec = raw[doff + k * rsize: doff + (k + 1) * rsize]
        fid, t = struct.unpack("<qq", rec[:16])
        assert (fid, t) == (ids[k], ts[k])
        img = np.frombuffer(rec[16:], dtype="<u2").reshape(H, W)
        np.testing.assert_array_equal(img, imgs[k])


@pytest.mark.parametrize("cut", [1, 10, 16 + 5, H * W - 1])
def test_partial_trailing_record_is_ignored_with_warning(tmp_path: Path, cut: int) -> None:
    imgs = _frames(5, "uint8")
    path = tmp_path / "p.iscr"
    _write(path, imgs)
    rsize = 16 + H * W
    with open(path, "ab") as f:  # an interrupted 6th record: `cut` bytes of it
        f.write(struct.pack("<qq", 999, 999)[:cut] + b"\x07" * max(cut - 16, 0))
    with pytest.warns(RecordingWarning, match=rf"partial trailing record \({cut} of {rsize} bytes"):
        rec = open_recording(path)
    assert len(rec) == 5
    np.testing.assert_array_equal(rec.read(), imgs)
    assert rec.info()["extra"]["partial_trailing_bytes"] == cut


def test_killed_writer_keeps_flushed_frames(tmp_path: Path) -> None:
    path = tmp_path / "killed.iscr"
    code = textwrap.dedent(f"""
        import os, signal, numpy as np
        from iscd.recording import IscrWriter
        w = IscrWriter({str(path)!r}, width={W}, height={H}, fps=1000.0)
        for i in range(7):
            w.append(i, i * 1000, np.full(({H}, {W}), i, np.uint8))
            if i == 4:
                w.flush()
        os.kill(os.getpid(), signal.SIGKILL)   # no close(), no atexit
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60)
    assert proc.returncode == -9, proc.stderr.decode()
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingWarning)
        rec = open_recording(path)
    assert 5 <= len(rec) <= 7  # the flushed 5 for sure; the unflushed tail may be lost
    np.testing.assert_array_equal(rec.frame_ids, np.arange(len(rec)))
    np.testing.assert_array_equal(rec.read()[:, 0, 0], np.arange(len(rec)))


def test_settings_dataclass_is_stored(tmp_path: Path) -> None:
    from iscd.drivers.base import CameraSettings, Roi

    st = CameraSettings(fps=500.0, exposure_s=1e-3, gain_db=3.0, roi=Roi(0, 0, W, H), trigger="slave")
    with IscrWriter(tmp_path / "s.iscr", width=W, height=H, fps=st.fps, settings=st):
        pass
    rec = open_recording(tmp_path / "s.iscr")
    settings = rec.info()["extra"]["settings"]
    assert settings["gain_db"] == 3.0 and settings["trigger"] == "slave"
    assert settings["roi"] == {"x": 0, "y": 0, "width": W, "height": H}


def test_growing_file_refresh(tmp_path: Path) -> None:
    path = tmp_path / "live.iscr"
    imgs = _frames(4, "uint8")
    w = IscrWriter(path, width=W, height=H, fps=500.0)
    w.flush()
    rec = IscrRecording(path)
    assert len(rec) == 0 and rec.read().shape == (0, H, W)
    assert rec.info()["first_frame_id"] is None
    w.append_many([0, 1], [0, 2], imgs[:2])
    w.flush()
    assert rec.refresh() == 2
    np.testing.assert_array_equal(rec.read(), imgs[:2])
    w.append_many([2, 3], [4, 6], imgs[2:])
    w.close()
    assert rec.refresh() == 4
    np.testing.assert_array_equal(rec[3], imgs[3])


def test_append_rejects_wrong_shape_dtype_and_writes_nothing(tmp_path: Path) -> None:
    path = tmp_path / "bad.iscr"
    with IscrWriter(path, width=W, height=H, dtype="uint8") as w:
        w.append(0, 0, np.zeros((H, W), np.uint8))
        w.flush()
        size = path.stat().st_size
        for bad in (np.zeros((W, H), np.uint8), np.zeros((H, W), np.uint16),
                    np.zeros((H, W), np.float32), np.zeros((H, W, 1), np.uint8), [[0] * W] * H):
            with pytest.raises(ValueError):
                w.append(1, 1, bad)
        with pytest.raises(ValueError):
            w.append(1.5, 1, np.zeros((H, W), np.uint8))
        with pytest.raises(ValueError):
            w.append_many([1, 2], [1, 2], np.zeros((3, H, W), np.uint8))
        with pytest.raises(ValueError):
            w.append_many([1, 2], [1, 2], np.zeros((2, H, W + 1), np.uint8))
        w.flush()
        assert path.stat().st_size == size
    with pytest.raises(ValueError, match="closed"):
        w.append(2, 2, np.zeros((H, W), np.uint8))
    assert len(open_recording(path)) == 1


@pytest.mark.parametrize("kw", [dict(dtype="float32"), dict(width=0), dict(bit_depth=9),
                                dict(fps=-1.0), dict(meta={"x": object()})])
def test_writer_rejects_bad_arguments(tmp_path: Path, kw: dict) -> None:
    args = dict(width=W, height=H)
    args.update(kw)
    with pytest.raises(ValueError):
        IscrWriter(tmp_path / "x.iscr", **args)


def test_corrupt_headers_give_one_line_errors(tmp_path: Path) -> None:
    good = tmp_path / "good.iscr"
    _write(good, _frames(2, "uint8"))
    raw = bytearray(good.read_bytes())
    cases = {
        "magic": b"NOPE" + bytes(raw[4:]),
        "version": bytes(raw[:8]) + struct.pack("<H", 99) + bytes(raw[10:]),
        "short": bytes(raw[:20]),
        "record size": bytes(raw[:24]) + struct.pack("<Q", 17) + bytes(raw[32:]),
        "metadata": bytes(raw[:FIXED_HEADER_SIZE]) + b"}" + bytes(raw[FIXED_HEADER_SIZE + 1:]),
    }
    expect = {"magic": "bad magic", "version": "version 99", "short": "too short",
              "record size": "record size", "metadata": "corrupt .iscr metadata"}
    for name, data in cases.items():
        p = tmp_path / f"{name.replace(' ', '_')}.iscr"
        p.write_bytes(data)
        with pytest.raises(RecordingError) as ei:
            open_recording(p)
        msg = str(ei.value)
        assert "\n" not in msg and msg.startswith(str(p)) and expect[name] in msg, msg


def test_open_recording_dispatch_errors(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no such file"):
        open_recording(tmp_path / "missing.iscr")
    other = tmp_path / "notes.txt"
    other.write_text("hello")
    with pytest.raises(RecordingError, match="unknown recording format"):
        open_recording(other)
    # an .iscr under another name is recognised by its magic
    p = tmp_path / "left.bin"
    _write(p, _frames(2, "uint8"))
    assert open_recording(p).format == "iscr"


def test_stereo_pair_matched_by_frame_id(tmp_path: Path) -> None:
    imgs = _frames(8, "uint8")
    for cam, ids in (("left", [0, 1, 2, 3, 4, 5, 6, 7]), ("right", [1, 2, 4, 5, 6, 7, 8, 9])):
        with IscrWriter(tmp_path / f"{cam}.iscr", width=W, height=H, camera=cam, fps=1000.0) as w:
            w.append_many(ids, np.array(ids) * 10**6, imgs)
    left, right = open_recording(tmp_path / "left.iscr"), open_recording(tmp_path / "right.iscr")
    li, ri = match_frames(left.frame_ids, right.frame_ids)
    np.testing.assert_array_equal(left.frame_ids[li], [1, 2, 4, 5, 6, 7])
    np.testing.assert_array_equal(left.frame_ids[li], right.frame_ids[ri])
    assert (left.camera, right.camera) == ("left", "right")
