"""iscd.calibration.io: the calibration file contract (SPEC section 7) and its geometry helpers."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from iscd.calibration.io import (CalibrationError, StereoCalibration, dumps_calibration,
                            load_calibration, project_points, rectify_points, save_calibration)
from iscd.core.config import CameraConfig


def distorted_rig() -> StereoCalibration:
    return StereoCalibration.from_parameters(
        640, 480, 800.0, 802.0, 331.0, 236.0, baseline_m=0.3,
        D1=[-0.2, 0.05, 1e-3, -5e-4, 0.0], D2=[-0.18, 0.04, -2e-4, 3e-4, 0.0],
        rvec=np.radians([0.3, -0.5, 0.2]))


def test_ideal_rig_from_config() -> None:
    cfg = CameraConfig(baseline_m=0.6)
    cal = StereoCalibration.ideal(cfg)
    assert cal.image_size == (512, 512)
    assert cal.focal_px == pytest.approx(3500.0)
    assert cal.baseline_m == pytest.approx(0.6)
    np.testing.assert_allclose(cal.T.ravel(), [-0.6, 0, 0], atol=1e-15)
    np.testing.assert_allclose(cal.M1[:2, 2], [255.5, 255.5])
    assert cal.is_rectified
    # The dissertation's numbers (SPEC section 6): 105 px of disparity at 20 m.
    assert cal.range_m(105.0) == pytest.approx(20.0)


def test_ideal_rig_rectification_is_identity_like() -> None:
    cal = StereoCalibration.ideal(CameraConfig())
    pts = np.array([[10.0, 20.0], [300.5, 411.25], [255.5, 255.5]])
    np.testing.assert_allclose(rectify_points(cal, pts, "left"), pts, atol=1e-9)
    np.testing.assert_allclose(rectify_points(cal, pts, "right"), pts, atol=1e-9)


def test_rectify_points_recovers_range_on_a_distorted_rotated_rig() -> None:
    cal = distorted_rig()
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-0.7, 0.7, 50), rng.uniform(3, 40, 50)])
    xl, xr = project_points(cal, X, "left"), project_points(cal, X, "right")
    rl, rr = rectify_points(cal, xl, "left"), rectify_points(cal, xr, "right")
    # Rows agree after rectification ...
    np.testing.assert_allclose(rl[:, 1], rr[:, 1], atol=1e-6)
    # ... and Z = f*b/d gives the depth along the rectified optical axis.
    z_rect = (cal.R1 @ X.T)[2]
    np.testing.assert_allclose(cal.range_m(rl[:, 0] - rr[:, 0]), z_rect, rtol=1e-7)
    # Without rectification the rows differ by pixels: the test above is not vacuous.
    assert np.max(np.abs(xl[:, 1] - xr[:, 1])) > 2.0


def test_save_load_roundtrip(tmp_path: Path) -> None:
    cal = distorted_rig()
    cal.rms_left, cal.rms_stereo, cal.board, cal.n_pairs = 0.12, 0.2, "chessboard 9x6", 14
    path = tmp_path / "cal.yml"
    save_calibration(cal, path)
    text = path.read_text()
    for key in ("image_width", "image_height", "M1", "D1", "M2", "D2", "R", "T", "R1", "R2",
                "P1", "P2", "Q"):
        assert f"\n{key}:" in text
    # Readable by plain OpenCV, as the contract promises.
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    np.testing.assert_array_equal(fs.getNode("M1").mat(), cal.M1)
    fs.release()
    back = load_calibration(path)
    for name in ("M1", "D1", "M2", "D2", "R", "T", "R1", "R2", "P1", "P2", "Q"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cal, name))
    assert back.image_size == (640, 480)
    assert back.rms_left == 0.12 and back.rms_stereo == 0.2 and back.rms_right is None
    assert back.board == "chessboard 9x6" and back.n_pairs == 14
    assert back.focal_px == cal.focal_px and back.baseline_m == pytest.approx(0.3)


def test_load_file_without_rectification_computes_it(tmp_path: Path) -> None:
    cal = distorted_rig()
    path = tmp_path / "minimal.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    for name in ("M1", "D1", "M2", "D2", "R", "T"):
        fs.write(name, getattr(cal, name))
    fs.release()
    back = load_calibration(path)
    assert back.is_rectified
    np.testing.assert_allclose(back.P2, cal.P2, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("content, message", [
    ("", "empty"),
    ("image_width: [1, 2", "not an OpenCV FileStorage YAML file"),
    ("just text", "not an OpenCV FileStorage YAML file"),
    ("%YAML:1.0\nimage_width: 640\nimage_height: 480\n", "missing keys M1, D1, M2, D2, R, T"),
    ("%YAML:1.0\nimage_width: 640\nimage_height: 480\nM1: 3\nD1: 1\nM2: 1\nD2: 1\nR: 1\nT: 1\n",
     "M1: expected an opencv-matrix"),
])
def test_load_errors_are_one_line(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "bad.yml"
    path.write_text(content)
    with pytest.raises(CalibrationError) as e:
        load_calibration(path)
    assert message in str(e.value) and "\n" not in str(e.value)
    assert str(path) in str(e.value)


def test_load_missing_file_and_wrong_shapes(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="calibration file not found"):
        load_calibration(tmp_path / "nope.yml")
    orig = dumps_calibration(distorted_rig())
    text = orig.replace("rows: 3\n   cols: 1", "rows: 1\n   cols: 3")
    assert text != orig
    cal = load_calibration(_write(tmp_path / "t_row.yml", text))  # T as a row is accepted
    assert cal.T.shape == (3, 1)
    bad = dumps_calibration(distorted_rig())
    bad = bad.replace("R1: !!opencv-matrix", "XX: !!opencv-matrix")
    with pytest.raises(CalibrationError, match="incomplete rectification"):
        load_calibration(_write(tmp_path / "partial.yml", bad))


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_atomic_write_keeps_old_file_when_writing_fails(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "cal.yml"
    old = StereoCalibration.ideal(CameraConfig())
    save_calibration(old, path)
    before = path.read_bytes()

    def broken_fsync(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", broken_fsync)
    with pytest.raises(CalibrationError, match="No space left on device"):
        save_calibration(distorted_rig(), path)
    assert path.read_bytes() == before  # old file intact, not half-overwritten
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.yml"]  # no temp file left


def test_atomic_write_new_file_absent_after_failure(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    def broken_replace(a: str, b: str) -> None:
        raise OSError(5, "I/O error")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(CalibrationError):
        save_calibration(distorted_rig(), tmp_path / "new.yml")
    assert list(tmp_path.iterdir()) == []


def test_invalid_matrices_rejected() -> None:
    with pytest.raises(CalibrationError, match="M1: expected shape"):
        StereoCalibration(512, 512, np.eye(2), np.zeros(5), np.eye(3), np.zeros(5), np.eye(3),
                          np.zeros(3))
    with pytest.raises(CalibrationError, match="non-finite"):
        StereoCalibration(512, 512, np.eye(3), np.zeros(5), np.eye(3), np.zeros(5), np.eye(3),
                          np.array([np.nan, 0, 0]))
