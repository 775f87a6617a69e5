"""Photron MRAW reader: real files checked against pyMRAW, synthetic 8/12/16-bit, bad input."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

pyMRAW = pytest.importorskip("pyMRAW")

from iscd.recording import RecordingError, RecordingWarning, open_recording  # noqa: E402
from iscd.recording.photron import PhotronRecording, unpack_12bit  # noqa: E402

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
PHOTRON = SHARED / "data" / "photron"


def _real(name: str) -> Path:
    p = PHOTRON / name
    if not p.is_file():
        pytest.skip(f"real Photron recording {p} not available (../shared beside the repo)")
    return p


def _pack12(px: np.ndarray) -> bytes:
    """Reference packer, written independently of the reader: 2 pixels -> 3 bytes."""
    p = px.reshape(-1, 2).astype(np.uint32)
    word = (p[:, 0] << 12) | p[:, 1]  # 24 bits, big-endian byte order
    return np.stack([(word >> 16) & 255, (word >> 8) & 255, word & 255], axis=1).astype(np.uint8).tobytes()


def _write_cih(path: Path, *, w: int, h: int, n: int, bit: int, fps: float = 1000,
               start: int = 0, extra: str = "") -> None:
    path.write_text(
        "#Camera Information Header\n"
        f"Record Rate(fps) : {fps}\nShutter Speed(s) : 1/2000\nTotal Frame : {n}\n"
        f"Original Total Frame : {n}\nStart Frame : {start}\nImage Width : {w}\n"
        f"Image Height : {h}\nColor Type : Mono\nColor Bit : {bit}\nFile Format : MRaw\n"
        f"EffectiveBit Depth : {min(bit, 12)}\nEffectiveBit Side : Lower\n"
        f"Camera Type : TEST CAM\n{extra}")


@pytest.mark.shared
@pytest.mark.parametrize("name, mraw_entry", [("ball_12bit", False), ("beam", True)])
def test_real_files_equal_pymraw_for_every_frame(name: str, mraw_entry: bool) -> None:
    cihx = _real(f"{name}.cihx")
    ref, cih = pyMRAW.load_video(str(cihx))
    path = cihx.with_suffix(".mraw") if mraw_entry else cihx
    with open_recording(path) as rec:
        assert isinstance(rec, PhotronRecording)
        assert (len(rec), rec.height, rec.width) == ref.shape
        assert rec.dtype == np.uint16 and rec.bit_depth == 12
        assert rec.fps == cih["Record Rate(fps)"]
        for i in range(len(rec)):  # frame by frame (memmap + unpack of one frame)
            np.testing.assert_array_equal(rec[i], ref[i])
        np.testing.assert_array_equal(rec.read(), ref)  # one block
        np.testing.assert_array_equal(np.concatenate(list(rec.iter_blocks(4))), ref)


@pytest.mark.shared
def test_ball_12bit_metadata_and_range() -> None:
    with open_recording(_real("ball_12bit.cihx")) as rec:
        info = rec.info()
        assert (info["frames"], info["width"], info["height"]) == (15, 384, 384)
        assert info["fps"] == 30000.0 and info["bit_depth"] == 12 and info["format"] == "photron"
        assert info["exposure_s"] == pytest.approx(20e-6)  # shutterSpeedNsec 20000
        # frame ids from <startFrame>52</startFrame>, timestamps index / fps
        np.testing.assert_array_equal(rec.frame_ids, np.arange(52, 67))
        np.testing.assert_array_equal(rec.timestamps_ns, np.round(np.arange(15) * 1e9 / 30000))
        frames = rec.read()
        assert frames.max() > 255 and frames.max() <= 4095  # really more than 8 bits
        assert len(np.unique(frames)) > 256


def test_unpack_12bit_matches_pymraw_reference() -> None:
    raw = np.random.default_rng(5).integers(0, 256, size=3 * 1000, dtype=np.uint8)
    import tempfile
    with tempfile.NamedTemporaryFile(suffix=".mraw") as f:  # pyMRAW's numpy reference reads a file
        raw.tofile(f.name)
        ref = pyMRAW._read_uint12_video(f.name, (2000,))
    np.testing.assert_array_equal(unpack_12bit(raw), ref)
    px = np.random.default_rng(6).integers(0, 4096, size=(3, 10), dtype=np.uint16)
    np.testing.assert_array_equal(unpack_12bit(np.frombuffer(_pack12(px), np.uint8).reshape(3, 15)), px)


@pytest.mark.filterwarnings("ignore:Not 12bit image")  # pyMRAW's loader, on the 8-bit file
@pytest.mark.parametrize("bit", [8, 16])
def test_synthetic_cih_8_and_16_bit(tmp_path: Path, bit: int) -> None:
    rng = np.random.default_rng(bit)
    imgs = rng.integers(0, 2 ** (8 if bit == 8 else 12), size=(7, 16, 24)).astype(np.uint16)
    mraw, cih = pyMRAW.save_mraw(imgs, str(tmp_path / "syn.cih"), bit_depth=bit,
                                 info_dict={"Record Rate(fps)": 2000, "Start Frame": -3})
    with open_recording(cih) as rec:
        assert rec.dtype == (np.uint8 if bit == 8 else np.uint16)
        np.testing.assert_array_equal(rec.read(), imgs)
        np.testing.assert_array_equal(rec.read(), pyMRAW.load_video(cih)[0])
        np.testing.assert_array_equal(rec.frame_ids, np.arange(-3, 4))
        assert rec.fps == 2000.0
        assert rec.timestamps_ns[1] == 500_000


def test_synthetic_cih_12_bit_packed(tmp_path: Path) -> None:
    imgs = np.random.default_rng(12).integers(0, 4096, size=(5, 6, 10), dtype=np.uint16)
    _write_cih(tmp_path / "p12.cih", w=10, h=6, n=5, bit=12, fps=1000, start=7)
    (tmp_path / "p12.mraw").write_bytes(_pack12(imgs))
    with open_recording(tmp_path / "p12.mraw") as rec:
        assert rec.bit_depth == 12 and rec.exposure_s == pytest.approx(1 / 2000)
        np.testing.assert_array_equal(rec.read(), imgs)
        np.testing.assert_array_equal(rec.read(2, 4), imgs[2:4])
        np.testing.assert_array_equal(rec.frame_ids, np.arange(7, 12))
        assert rec.camera == "TEST CAM"


@pytest.mark.shared
def test_truncated_mraw_is_an_error_naming_sizes(tmp_path: Path) -> None:
    src = _real("ball_12bit.cihx")
    shutil.copy(src, tmp_path / "ball.cihx")
    data = src.with_suffix(".mraw").read_bytes()
    frame = 384 * 384 * 3 // 2
    (tmp_path / "ball.mraw").write_bytes(data[: 10 * frame + 1000])
    with pytest.raises(RecordingError) as ei:
        open_recording(tmp_path / "ball.cihx")
    msg = str(ei.value)
    assert "\n" not in msg and "ball.mraw" in msg and "truncated" in msg
    assert str(15 * frame) in msg and str(10 * frame + 1000) in msg
    with pytest.warns(RecordingWarning, match="10 complete frames"):
        rec = PhotronRecording(tmp_path / "ball.cihx", allow_truncated=True)
    assert len(rec) == 10
    ref, _ = pyMRAW.load_video(str(src))
    np.testing.assert_array_equal(rec.read(), ref[:10])


@pytest.mark.shared
def test_missing_partner_files(tmp_path: Path) -> None:
    src = _real("ball_12bit.cihx")
    shutil.copy(src.with_suffix(".mraw"), tmp_path / "only.mraw")
    with pytest.raises(RecordingError, match=r"missing Photron header.*only\.cihx"):
        open_recording(tmp_path / "only.mraw")
    shutil.copy(src, tmp_path / "hdr.cihx")
    with pytest.raises(RecordingError, match=r"missing pixel file hdr\.mraw"):
        open_recording(tmp_path / "hdr.cihx")
    with pytest.raises(RecordingError, match="no such file"):
        open_recording(tmp_path / "nothing.cih")


def test_bad_headers(tmp_path: Path) -> None:
    _write_cih(tmp_path / "b10.cih", w=8, h=8, n=2, bit=10)
    (tmp_path / "b10.mraw").write_bytes(bytes(200))
    with pytest.raises(RecordingError, match="unsupported bit depth 10"):
        open_recording(tmp_path / "b10.cih")
    (tmp_path / "junk.cih").write_text("this is not a header\n")
    (tmp_path / "junk.mraw").write_bytes(bytes(10))
    with pytest.raises(RecordingError, match="cannot parse Photron header"):
        open_recording(tmp_path / "junk.cih")
    (tmp_path / "x.cihx").write_bytes(b"\x00\x01 garbage <cih><broken></cih>")
    (tmp_path / "x.mraw").write_bytes(bytes(10))
    with pytest.raises(RecordingError) as ei:
        open_recording(tmp_path / "x.cihx")
    assert "\n" not in str(ei.value)


def test_long_recording_reads_only_requested_frames(tmp_path: Path) -> None:
    """A block read touches only its frames: the reader never loads the whole .mraw."""
    n, h, w = 400, 64, 64
    _write_cih(tmp_path / "long.cih", w=w, h=h, n=n, bit=12)
    mraw = tmp_path / "long.mraw"
    with open(mraw, "wb") as f:  # sparse file, mostly zeros; frame 321 has a pattern
        f.truncate(n * h * w * 3 // 2)
        pattern = (np.arange(h * w, dtype=np.uint16) % 4096).reshape(h, w)
        f.seek(321 * h * w * 3 // 2)
        f.write(_pack12(pattern))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = open_recording(mraw)
    block = rec.read(320, 323)
    assert block.shape == (3, h, w) and block.nbytes == 3 * h * w * 2
    np.testing.assert_array_equal(block[1], pattern)
    assert not block[0].any() and not block[2].any()
