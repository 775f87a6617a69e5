"""Calibration against ground truth: boards rendered by a known stereo rig (512x512, fx ~ 600
px, k1/k2/p1/p2 distortion, 0.5 degree rotation between the cameras, 0.25 m baseline)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from iscd.calibration.boards import BoardSpec
from iscd.calibration.detect import Detection, Miss, detect, pair_detections
from iscd.calibration.solve import calibrate_stereo
from iscd.calibration.synthetic import default_rig, make_pairs


def rel(a: float, b: float) -> float:
    return abs(a - b) / abs(b)


def rotation_error_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(Ra @ Rb.T)[0])))


def observe(sp, board):  # type: ignore[no-untyped-def]
    obs = []
    for i, (l, r) in enumerate(zip(sp.left, sp.right)):
        dl, dr = detect(l, board), detect(r, board)
        if isinstance(dl, Detection) and isinstance(dr, Detection):
            po = pair_detections(f"{i:02d}", dl, dr, board)
            if po is not None:
                obs.append(po)
    return obs


@pytest.fixture(scope="module")
def chessboard_pairs():  # type: ignore[no-untyped-def]
    return make_pairs(20, seed=11)


@pytest.fixture(scope="module")
def chessboard_obs(chessboard_pairs):  # type: ignore[no-untyped-def]
    """The pairs' detected corners (each test that changes them takes a copy of the list)."""
    return tuple(observe(chessboard_pairs, chessboard_pairs.board))


@pytest.fixture(scope="module")
def chessboard_cal(chessboard_obs):  # type: ignore[no-untyped-def]
    return calibrate_stereo(list(chessboard_obs), (512, 512))


def test_truth_rig_is_what_the_issue_asks_for() -> None:
    t = default_rig()
    assert t.image_size == (512, 512)
    assert 0.4 < t.rotation_deg < 0.6
    assert t.baseline_m == pytest.approx(0.25)
    assert t.D1[0, 0] < -0.1 and t.D2[0, 0] < -0.1  # real barrel distortion


def test_corner_detection_is_subpixel_accurate(chessboard_pairs) -> None:  # type: ignore[no-untyped-def]
    sp = chessboard_pairs
    errs = []
    for i in range(6):
        for img, truth in ((sp.left[i], sp.corners_left[i]), (sp.right[i], sp.corners_right[i])):
            d = detect(img, sp.board)
            assert isinstance(d, Detection), d
            p = d.image_points
            if np.abs(p[::-1] - truth).max() < np.abs(p - truth).max():
                p = p[::-1]  # the board's 180-degree symmetry
            errs.append(np.linalg.norm(p - truth, axis=1))
    e = np.concatenate(errs)
    assert np.sqrt(np.mean(e ** 2)) < 0.08  # measured 0.04 px RMS
    assert e.max() < 0.4


def test_recovers_known_rig(chessboard_pairs, chessboard_obs, chessboard_cal) -> None:  # type: ignore[no-untyped-def]
    sp = chessboard_pairs
    assert len(chessboard_obs) >= 18
    res = chessboard_cal
    c, t = res.calibration, sp.truth
    for est, true in ((c.M1, t.M1), (c.M2, t.M2)):
        for idx in ((0, 0), (1, 1), (0, 2), (1, 2)):  # fx, fy, cx, cy
            assert rel(est[idx], true[idx]) < 0.005, (idx, est[idx], true[idx])
    assert rel(c.baseline_m, t.baseline_m) < 0.005
    assert rotation_error_deg(c.R, t.R) < 0.05
    # The direction of the baseline too, not only its length.
    assert float(c.T.ravel() @ t.T.ravel()) / (c.baseline_m * t.baseline_m) > 0.9999
    # Fit quality numbers are those of a good calibration.
    assert res.rms_stereo < 0.1 and res.epipolar_rms_px < 0.1
    assert not res.rejected


def test_distortion_is_modelled(chessboard_pairs, chessboard_cal) -> None:  # type: ignore[no-untyped-def]
    """Image points through the estimated model land where the true model puts them."""
    sp = chessboard_pairs
    res = chessboard_cal
    c, t = res.calibration, sp.truth
    gx, gy = np.meshgrid(np.linspace(20, 490, 12), np.linspace(20, 490, 12))
    pts = np.column_stack([gx.ravel(), gy.ravel()]).reshape(-1, 1, 2)
    for M, D, Mt, Dt in ((c.M1, c.D1, t.M1, t.D1), (c.M2, c.D2, t.M2, t.D2)):
        ray_t = cv2.undistortPoints(pts, Mt, Dt).reshape(-1, 2)
        ray_e = cv2.undistortPoints(pts, M, D).reshape(-1, 2)
        assert np.max(np.linalg.norm(ray_e - ray_t, axis=1)) * Mt[0, 0] < 1.0  # px


def test_outlier_pair_is_rejected_with_reason(chessboard_pairs, chessboard_obs) -> None:  # type: ignore[no-untyped-def]
    sp = chessboard_pairs
    obs = list(chessboard_obs)
    bad = obs[3]
    # Corrupt the right view of one pair: 1.5 px of extra shift in one corner row region.
    shifted = bad.right_points.copy()
    shifted[:20] += np.array([1.5, -1.0], np.float32)
    obs[3] = type(bad)(bad.name, bad.object_points, bad.left_points, shifted, bad.ids)
    res = calibrate_stereo(obs, (512, 512))
    rejected = {p.name: p.reason for p in res.rejected}
    assert list(rejected) == [bad.name]
    assert "x the median" in rejected[bad.name] and "px" in rejected[bad.name]
    assert rel(res.calibration.baseline_m, sp.truth.baseline_m) < 0.005


def test_wrong_board_size_is_not_detected_as_a_smaller_board(chessboard_pairs) -> None:  # type: ignore[no-untyped-def]
    sp = chessboard_pairs
    wrong = BoardSpec("chessboard", 8, 6, 0.08)
    d = detect(sp.left[0], wrong)
    assert isinstance(d, Miss)
    assert "more corners than 8x6" in d.reason or "not found" in d.reason


def test_charuco_board() -> None:
    board = BoardSpec("charuco", 10, 7, 0.07, 0.052, "4X4_50")
    sp = make_pairs(16, board=board, seed=3, z_range_m=(1.2, 2.6))
    d = detect(sp.left[0], board)
    assert isinstance(d, Detection) and d.n >= 8
    # ChArUco corners are identified: compare with the truth by id.
    err = np.linalg.norm(d.image_points - sp.corners_left[0][d.ids], axis=1)
    assert np.median(err) < 0.15
    res = calibrate_stereo(observe(sp, board), (512, 512))
    c, t = res.calibration, sp.truth
    assert rel(c.M1[0, 0], t.M1[0, 0]) < 0.005
    assert rel(c.baseline_m, t.baseline_m) < 0.005
    assert rotation_error_deg(c.R, t.R) < 0.1


def test_nonideal_rig_pieces_for_ranging() -> None:
    """The pieces the simulator/ranging test will use: render LED positions through a
    non-ideal rig (project_points) and range them through its calibration (rectify_points,
    Z = f*b/d): exact with the true calibration, badly off with the ideal one."""
    from iscd.calibration.io import StereoCalibration, project_points, rectify_points
    from iscd.calibration.synthetic import nonideal_rig
    from iscd.core.config import CameraConfig

    cfg = CameraConfig()
    truth, ideal = nonideal_rig(cfg), StereoCalibration.ideal(cfg)
    X = np.array([[0.3, -0.2, z] for z in (20.0, 40.0, 60.0)])
    xl, xr = project_points(truth, X, "left"), project_points(truth, X, "right")
    z_rect = (truth.R1 @ X.T)[2]
    for cal, tol in ((truth, 1e-6), (ideal, None)):
        d = rectify_points(cal, xl, "left")[:, 0] - rectify_points(cal, xr, "right")[:, 0]
        z = cal.range_m(d)
        if tol is not None:
            np.testing.assert_allclose(z, z_rect, rtol=tol)
        else:
            assert np.min(np.abs(z / z_rect - 1)) > 0.2  # an uncalibrated rig ranges > 20 % off
