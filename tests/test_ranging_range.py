"""Disparity -> range (eq. 2.2), the stereo ranger on rendered frames, rectification."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from iscd.core.config import ConfigError, loads
from iscd.decode.ranging.config import ranging_config
from iscd.decode.ranging.range import (LedRanger, cut_patches, disparity_from_range, range_from_disparity,
                                range_sigma)
from iscd.decode.ranging.synth import disk_spots, sensor

F_PX = 3500.0


def test_z_formula_reference_numbers() -> None:
    """SPEC 6: 105 px at 20 m with f/rho = 3500 px and b = 0.6 m; 1.71 m per px at 60 m."""
    assert range_from_disparity(105.0, F_PX, 0.6) == pytest.approx(20.0)
    assert disparity_from_range(20.0, F_PX, 0.6) == pytest.approx(105.0)
    assert range_sigma(60.0, 1.0, F_PX, 0.6) == pytest.approx(60 ** 2 / (F_PX * 0.6))
    assert range_sigma(60.0, 1.0, F_PX, 0.6) == pytest.approx(1.714, abs=1e-3)
    z = range_from_disparity([35.0, 0.0, -3.0, np.nan], F_PX, 0.6)
    assert z[0] == pytest.approx(60.0) and np.isnan(z[1:]).all()


def test_cut_patches_positions_and_borders() -> None:
    img = np.arange(100 * 80, dtype=np.float64).reshape(100, 80)
    p, o = cut_patches(img, [[40.4, 50.6], [1.0, 1.0]], 16)
    assert p.shape == (2, 16, 16)
    assert o[0].tolist() == [33, 43]                   # round(40.4 - 7.5), round(50.6 - 7.5)
    assert p[0, 0, 0] == img[43, 33] and p[0, 15, 15] == img[58, 48]
    assert p[1, 0, 0] == img[0, 0]                      # outside: the nearest edge pixel
    with pytest.raises(ValueError, match="2-D"):
        cut_patches(np.zeros((4, 4, 3)), [[1, 1]], 4)
    with pytest.raises(ValueError, match="NaN"):
        cut_patches(img, [[np.nan, 1]], 4)


def render_frame(points: np.ndarray, rng: np.random.Generator, shape: tuple[int, int] = (512, 512),
                 radius: float = 1.0, peak: float = 500.0) -> np.ndarray:
    """A frame with a spot at each (x, y) px, realistic noise and 8 bits."""
    img = np.zeros(shape)
    for x, y in points:
        x0, y0 = int(x) - 8, int(y) - 8
        img[y0:y0 + 16, x0:x0 + 16] += disk_spots(1, (16, 16), x - x0, y - y0, radius, peak=peak)[0]
    return sensor(img, rng, 40, 0.26, 78)


@pytest.mark.parametrize("z_m,tol_m", [(20.0, 0.005), (40.0, 0.02), (60.0, 0.03)])
def test_single_led_range_on_rendered_frames(z_m: float, tol_m: float) -> None:
    """Chapter 3 geometry (b = 0.6 m): 20 frames per distance, LED detected to +-1 px only."""
    rng = np.random.default_rng(int(z_m))
    cal = SimpleNamespace(focal_px=F_PX, baseline_m=0.6)
    ranger = LedRanger(cal)
    d = disparity_from_range(z_m, F_PX, 0.6)
    errs, sig = [], []
    for _ in range(20):
        xl, y = 255.5 + rng.uniform(-0.5, 0.5), 250.5 + rng.uniform(-0.5, 0.5)
        left = render_frame(np.array([[xl, y]]), rng, radius=F_PX * 0.015 / z_m)
        right = render_frame(np.array([[xl - d, y]]), rng, radius=F_PX * 0.015 / z_m)
        guess_l = [[xl + rng.uniform(-1, 1), y + rng.uniform(-1, 1)]]
        guess_r = [[xl - d + rng.uniform(-1, 1), y + rng.uniform(-1, 1)]]
        r = ranger.measure(left, right, guess_l, guess_r)
        assert r.valid.all()
        errs.append(r.z_m[0] - z_m)
        sig.append(r.sigma_m[0])
    errs_a = np.abs(np.array(errs))
    assert errs_a.mean() < tol_m
    # the reported sigma is the right size (within a factor of 4 of the observed RMS)
    rms = np.sqrt(np.mean(np.square(errs)))
    assert rms / 4 < np.mean(sig) < rms * 4


def test_led_array_whole_and_per_led() -> None:
    """8x8 array, 6 cm pitch, at 50 m with b = 0.25 m (4.2 px pitch, 17.5 px disparity)."""
    rng = np.random.default_rng(3)
    b, z = 0.25, 50.0
    cal = SimpleNamespace(focal_px=F_PX, baseline_m=b)
    pitch = F_PX * 0.06 / z
    d = disparity_from_range(z, F_PX, b)
    gy, gx = np.mgrid[0:8, 0:8]
    pts_l = np.stack([250.3 + gx.ravel() * pitch, 240.7 + gy.ravel() * pitch], axis=1)
    pts_r = pts_l - [d, 0.0]
    left = render_frame(pts_l, rng, radius=0.6, peak=400)
    right = render_frame(pts_r, rng, radius=0.6, peak=400)
    ranger = LedRanger(cal)
    whole = ranger.measure_group(left, right, pts_l + rng.uniform(-1, 1, pts_l.shape),
                                 pts_r + rng.uniform(-1, 1, pts_r.shape))
    assert whole.z_m.shape == (1,) and whole.valid.all()
    assert abs(whole.z_m[0] - z) < 0.03
    per = ranger.measure(left, right, np.round(pts_l), np.round(pts_r))
    assert per.z_m.shape == (64,) and per.valid.all()
    assert np.abs(per.z_m - z).mean() < 0.06         # neighbours in each patch: windowed
    assert whole.sigma_m[0] < np.median(per.sigma_m)


def rig_calibration(baseline: float = 0.25) -> SimpleNamespace:
    """A non-ideal rig: distortion, a 0.5 degree rotation, different principal points."""
    m1 = np.array([[F_PX, 0, 250.0], [0, F_PX, 260.0], [0, 0, 1]])
    m2 = np.array([[F_PX * 1.002, 0, 262.0], [0, F_PX * 1.002, 251.0], [0, 0, 1]])
    d1 = np.array([-0.2, 0.1, 0.0, 0.0, 0.0])
    d2 = np.array([-0.15, 0.05, 0.0, 0.0, 0.0])
    r, _ = cv2.Rodrigues(np.deg2rad([0.3, -0.5, 0.4]))
    t = np.array([[-baseline], [0.002], [0.001]])
    r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(m1, d1, m2, d2, (512, 512), r, t, alpha=0)
    return SimpleNamespace(M1=m1, D1=d1, M2=m2, D2=d2, R=r, T=t, R1=r1, R2=r2, P1=p1, P2=p2, Q=q,
                           focal_px=float(p1[0, 0]), baseline_m=float(np.linalg.norm(t)))


def test_rectification_from_the_calibration_removes_rig_errors() -> None:
    rng = np.random.default_rng(4)
    cal = rig_calibration()
    errs_auto, errs_raw = [], []
    for x_m, y_m, z_m in [(0.5, -0.3, 30.0), (-1.0, 0.4, 40.0), (1.5, 0.8, 25.0), (-0.6, -0.9, 35.0)]:
        pt = np.array([[x_m, y_m, z_m]])
        pl = cv2.projectPoints(pt, np.zeros(3), np.zeros(3), cal.M1, cal.D1)[0].reshape(2)
        pr = cv2.projectPoints(pt, cv2.Rodrigues(cal.R)[0], cal.T, cal.M2, cal.D2)[0].reshape(2)
        left = render_frame(pl[None], rng, radius=1.0)
        right = render_frame(pr[None], rng, radius=1.0)
        z_rect = (cal.R1 @ pt[0])[2]                      # depth in the rectified left camera
        auto = LedRanger(cal).measure(left, right, [pl], [pr])
        raw = LedRanger(cal, rectify=None).measure(left, right, [pl], [pr])
        errs_auto.append(auto.z_m[0] - z_rect)
        errs_raw.append(raw.z_m[0] - z_rect)
        assert abs(auto.dy_px[0]) < 0.05                 # rows agree after rectification
    assert np.abs(errs_auto).max() < 0.05
    assert np.abs(errs_raw).max() > 1.0


def test_ranger_input_errors() -> None:
    with pytest.raises(ValueError, match="focal_px"):
        LedRanger(object())
    with pytest.raises(ValueError, match="> 0"):
        LedRanger(SimpleNamespace(focal_px=3500.0, baseline_m=0.0))
    ranger = LedRanger(SimpleNamespace(focal_px=3500.0, baseline_m=0.6))
    with pytest.raises(ValueError, match="differ in shape"):
        ranger.measure(np.zeros((64, 64)), np.zeros((64, 64)), [[10, 10]], [[10, 10], [20, 20]])
    # a dark frame (LED off): no crash, not valid; a flat one: NaN, not valid (also rectified)
    dark = sensor(np.zeros((64, 64)), np.random.default_rng(0), 40, 0.26, 78)
    r = ranger.measure(dark, dark.copy() + 1, [[30, 30]], [[20, 30]])
    assert not r.valid.any()
    flat = np.full((512, 512), 40.0)
    r = LedRanger(rig_calibration()).measure(flat, flat, [[200, 200]], [[190, 200]])
    assert not r.valid.any() and np.isnan(r.z_m).all()


def test_ranging_config_section() -> None:
    cfg = ranging_config(loads("[ranging]\nmethod = 'dissertation'\nkalman = true\n"))
    assert cfg.method == "dissertation" and cfg.kalman
    assert ranging_config(loads("")).method == "iscd-fast"
    with pytest.raises(ConfigError, match="ranging.method"):
        ranging_config(loads("[ranging]\nmethod = 'magic'\n"))
    with pytest.raises(ConfigError, match="ranging.bogus"):
        ranging_config(loads("[ranging]\nbogus = 1\n"))
