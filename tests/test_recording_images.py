"""Folders of PNG/TIFF frames as recordings."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from iscd.recording import RecordingError, open_recording
from iscd.recording.images import ImageFolderRecording, natural_key

H, W = 12, 20


def _img(value: int, dtype=np.uint8, shape=(H, W)) -> np.ndarray:
    img = np.full(shape, value, dtype=dtype)
    img[0, 0] = 0  # not constant, so nothing can pass by accident
    return img


def test_natural_sort_order_and_ids_from_names(tmp_path: Path) -> None:
    for i in (10, 2, 1, 33, 100):
        assert cv2.imwrite(str(tmp_path / f"frame_{i}.png"), _img(i))
    (tmp_path / "notes.txt").write_text("ignored")
    (tmp_path / ".hidden.png").write_bytes(b"ignored")
    with open_recording(tmp_path) as rec:
        assert isinstance(rec, ImageFolderRecording)
        assert [p.name for p in rec.files] == [f"frame_{i}.png" for i in (1, 2, 10, 33, 100)]
        np.testing.assert_array_equal(rec.frame_ids, [1, 2, 10, 33, 100])
        np.testing.assert_array_equal(rec.read()[:, 5, 5], [1, 2, 10, 33, 100])
        assert rec.fps is None and rec.bit_depth == 8 and rec.dtype == np.uint8
        assert not rec.timestamps_ns.any()
        info = rec.info()
        assert (info["frames"], info["width"], info["height"], info["fps"]) == (5, W, H, None)
        assert info["missing_frame_ids"] == 95


def test_natural_key() -> None:
    names = ["a10.png", "a2.png", "A1.png", "b1.png", "a2b3.png", "a2b10.png"]
    assert sorted(names, key=natural_key) == ["A1.png", "a2.png", "a2b3.png", "a2b10.png",
                                              "a10.png", "b1.png"]


def test_ids_fall_back_to_positions(tmp_path: Path) -> None:
    for name in ("first.png", "second.png", "third.png"):
        cv2.imwrite(str(tmp_path / name), _img(3))
    np.testing.assert_array_equal(open_recording(tmp_path).frame_ids, [0, 1, 2])


def test_16bit_png_and_tiff_and_sidecar(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    imgs = rng.integers(0, 4096, size=(4, H, W), dtype=np.uint16)
    for i, img in enumerate(imgs):
        ext = ".png" if i % 2 else ".tif"
        assert cv2.imwrite(str(tmp_path / f"cam_{i:04d}{ext}"), img)
    (tmp_path / "recording.json").write_text(json.dumps({"fps": 1000, "camera": "left",
                                                         "bit_depth": 12}))
    with open_recording(tmp_path) as rec:
        assert rec.dtype == np.uint16 and rec.bit_depth == 12 and rec.camera == "left"
        assert rec.fps == 1000.0
        np.testing.assert_array_equal(rec.read(), imgs)
        np.testing.assert_array_equal(rec.timestamps_ns, [0, 1_000_000, 2_000_000, 3_000_000])
        assert rec.info()["duration_s"] == pytest.approx(0.004)


def test_colour_frames_become_grey(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 256, size=(2, H, W, 3), dtype=np.uint8)
    for i, img in enumerate(bgr):
        cv2.imwrite(str(tmp_path / f"c{i}.png"), img)
    rec = open_recording(tmp_path)
    assert rec.read().shape == (2, H, W)
    np.testing.assert_array_equal(rec[1], cv2.cvtColor(bgr[1], cv2.COLOR_BGR2GRAY))


def test_empty_folder(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="empty folder"):
        open_recording(tmp_path)
    (tmp_path / "a.jpg").write_bytes(b"x")
    with pytest.raises(RecordingError, match="no PNG/TIFF frames.*JPEG"):
        open_recording(tmp_path)


def test_mixed_sizes(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "f1.png"), _img(1))
    cv2.imwrite(str(tmp_path / "f2.png"), _img(2, shape=(H + 1, W)))
    with pytest.raises(RecordingError) as ei:  # PNG sizes are checked when opening
        open_recording(tmp_path)
    assert "f2.png" in str(ei.value) and f"{W}x{H + 1}" in str(ei.value)
    (tmp_path / "f2.png").unlink()
    cv2.imwrite(str(tmp_path / "f3.tif"), _img(3, shape=(H, W + 2)))
    rec = open_recording(tmp_path)  # TIFF sizes when the frame is read
    np.testing.assert_array_equal(rec[0], _img(1))
    with pytest.raises(RecordingError, match=r"f3\.tif: frame size"):
        rec.read()
    cv2.imwrite(str(tmp_path / "f3.tif"), _img(3, dtype=np.uint16))
    with pytest.raises(RecordingError, match="pixel type uint16 differs"):
        open_recording(tmp_path).read()


def test_unreadable_file(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "f1.png"), _img(1))
    (tmp_path / "f2.tif").write_bytes(b"definitely not a TIFF")
    rec = open_recording(tmp_path)
    with pytest.raises(RecordingError) as ei:
        rec[1]
    assert "f2.tif" in str(ei.value) and "cannot read image" in str(ei.value)
    (tmp_path / "f0.png").write_bytes(b"broken")  # the first frame: fails at open
    with pytest.raises(RecordingError, match=r"f0\.png: cannot read image"):
        open_recording(tmp_path)


def test_bad_sidecar(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "f1.png"), _img(1))
    (tmp_path / "recording.json").write_text('{"fps": -5}')
    with pytest.raises(RecordingError, match=r"recording\.json: bad sidecar: fps"):
        open_recording(tmp_path)
    (tmp_path / "recording.json").write_text('{"bit_depth": 12}')
    with pytest.raises(RecordingError, match="bit_depth 12 exceeds"):
        open_recording(tmp_path)
