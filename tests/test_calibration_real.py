"""The public OpenCV stereo sample (9x6 inner corners, 13 pairs): ``iscd calibrate`` against a
direct cv2.stereoCalibrate, and ``--verify`` against intact and disturbed calibrations."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from iscd.calibration.boards import BoardSpec
from iscd.calibration.io import load_calibration, save_calibration
from iscd.calibration.pipeline import detect_files, pair_files
from iscd.cli.main import main

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
DATA = SHARED / "data" / "opencv-stereo-chessboard"

pytestmark = [
    pytest.mark.shared,
    pytest.mark.skipif(not DATA.is_dir(), reason=f"OpenCV stereo sample not found at {DATA}"),
]

SQUARE = 0.025
BOARD = BoardSpec("chessboard", 9, 6, SQUARE)
LEFT, RIGHT = str(DATA / "left*.jpg"), str(DATA / "right*.jpg")


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    out = tmp_path_factory.mktemp("real") / "rig.yml"
    rc = main(["-q", "calibrate", "--left", LEFT, "--right", RIGHT, "--board", "9x6",
               "--square", str(SQUARE), "--out", str(out)])
    assert rc == 0
    return out, out.with_name("rig_report")


@pytest.fixture(scope="module")
def corners():  # type: ignore[no-untyped-def]
    det = detect_files(pair_files(LEFT, RIGHT), BOARD)
    obj = [o.object_points.reshape(-1, 1, 3) for o in det.observations]
    il = [o.left_points.reshape(-1, 1, 2) for o in det.observations]
    ir = [o.right_points.reshape(-1, 1, 2) for o in det.observations]
    return det, obj, il, ir


def test_all_13_pairs_used(calibrated) -> None:  # type: ignore[no-untyped-def]
    _, report = calibrated
    data = json.loads((report / "report.json").read_text())
    assert data["pairs_used"] == 13 and data["pairs_rejected"] == 0


def test_matches_direct_stereo_calibrate_on_same_corners(calibrated, corners) -> None:  # type: ignore[no-untyped-def]
    out, report = calibrated
    cal = load_calibration(out)
    det, obj, il, ir = corners
    size = det.image_size
    # Per camera: the reported RMS is cv2.calibrateCamera's on the same corners.
    rl = cv2.calibrateCamera(obj, il, size, None, None)[0]
    rr = cv2.calibrateCamera(obj, ir, size, None, None)[0]
    assert cal.rms_left == pytest.approx(rl, rel=1e-9)
    assert cal.rms_right == pytest.approx(rr, rel=1e-9)
    # Pair: one direct cv2.stereoCalibrate of everything from scratch.
    rms, *_, R, T, E, F = cv2.stereoCalibrate(obj, il, ir, None, None, None, None, size, flags=0)
    assert abs(cal.baseline_m - np.linalg.norm(T)) / np.linalg.norm(T) < 0.005
    assert cal.rms_stereo == pytest.approx(rms, abs=1e-6)
    data = json.loads((report / "report.json").read_text())
    assert data["rms_stereo_px"] == pytest.approx(rms, abs=1e-6)
    assert data["baseline_m"] == pytest.approx(cal.baseline_m)
    assert data["focal_px"] == pytest.approx(cal.focal_px)
    assert 0 < data["epipolar_rms_px"] < 0.3


def test_matches_opencv_sample_pipeline_on_same_images(calibrated) -> None:  # type: ignore[no-untyped-def]
    """The OpenCV stereo_calib sample's own detection (findChessboardCorners + cornerSubPix
    11x11) and calibration, independent of ours: the baselines agree within 0.5 %."""
    out, _ = calibrated
    cal = load_calibration(out)
    obj0 = np.zeros((54, 3), np.float32)
    obj0[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * SQUARE
    obj, il, ir = [], [], []
    for lp, rp in pair_files(LEFT, RIGHT):
        pts = []
        for p in (lp, rp):
            g = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            ok, c = cv2.findChessboardCorners(g, (9, 6), flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                              | cv2.CALIB_CB_NORMALIZE_IMAGE)
            assert ok
            pts.append(cv2.cornerSubPix(g, c, (11, 11), (-1, -1),
                                        (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)))
        obj.append(obj0)
        il.append(pts[0])
        ir.append(pts[1])
    T = cv2.stereoCalibrate(obj, il, ir, None, None, None, None, (640, 480), flags=0)[6]
    assert abs(cal.baseline_m - np.linalg.norm(T)) / np.linalg.norm(T) < 0.005
    # Our corners fit better than the sample's (their RMS is ~0.44 px, ours ~0.19 px).
    assert cal.rms_stereo < 0.3


def test_preview_is_a_rectified_pair(calibrated) -> None:  # type: ignore[no-untyped-def]
    _, report = calibrated
    img = cv2.imread(str(report / "preview.png"))
    assert img is not None and img.shape == (480, 1280, 3)
    assert "| baseline |" in (report / "report.md").read_text()


def test_verify_ok_on_matching_set(calibrated, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    out, _ = calibrated
    rc = main(["-q", "calibrate", "--left", LEFT, "--right", RIGHT, "--board", "9x6", "--square",
               str(SQUARE), "--verify", str(out), "--report", str(tmp_path)])
    assert rc == 0
    assert capsys.readouterr().out.startswith("OK:")
    data = json.loads((tmp_path / "verify.json").read_text())
    assert data["verdict"] == "OK"
    assert data["epipolar_rms_px"] < 0.3 and data["transfer_rms_px"] < 0.5
    assert abs(data["scale_error"]) < 0.005


@pytest.mark.parametrize("kind, expect", [
    ("pitch", "epipolar error"),  # right camera tilted 0.3 deg about x
    ("yaw", "transfer error"),  # right camera turned 0.3 deg about y: ranges go wrong
    ("baseline", "squares are +3.0"),  # baseline 3 % too long
])
def test_verify_says_recalibrate_when_disturbed(calibrated, tmp_path: Path, kind: str, expect: str,
                                                capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    out, _ = calibrated
    cal = load_calibration(out)
    if kind == "baseline":
        bad = dataclasses.replace(cal, T=cal.T * 1.03)
    else:
        rvec = np.radians([0.3, 0, 0] if kind == "pitch" else [0, 0.3, 0])
        dR = cv2.Rodrigues(rvec)[0]
        bad = dataclasses.replace(cal, R=dR @ cal.R, T=dR @ cal.T)
    path = tmp_path / f"{kind}.yml"
    save_calibration(bad.with_rectification(), path)
    rc = main(["-q", "calibrate", "--left", LEFT, "--right", RIGHT, "--board", "9x6", "--square",
               str(SQUARE), "--verify", str(path)])
    line = capsys.readouterr().out
    assert rc == 1
    assert line.startswith("RECALIBRATE:") and expect in line
