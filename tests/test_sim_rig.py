"""The simulator rendering through a non-ideal rig (``Scene(cfg, rig=...)``).

A rig equal to the ideal one must reproduce the ideal frames; a rotated, distorted rig must
place the spots where :func:`iscd.calibration.io.project_points` says its cameras image the LED
(checked on the spot centroids of noise-free frames, not only on the truth arrays).
"""

from __future__ import annotations

import numpy as np
import pytest

from iscd.calibration.io import StereoCalibration, project_points
from iscd.calibration.synthetic import nonideal_rig
from iscd.core.config import default_config
from iscd.sim import ArraySource, Scene
from iscd.sim.geometry import project_rig
from iscd.sim.presets import override, single_led

DARK = 2.0  # sensor.dark_dn default


def _cfg(distance_m: float = 30.0, **scene):
    return single_led(default_config(), distance_m, led_phase_s=0.0, led_drift_ppm=0.0, **scene)


def _centroid(img: np.ndarray, u: float, v: float, half: int = 7) -> tuple[float, float]:
    x0, y0 = int(round(u)) - half, int(round(v)) - half
    w = np.clip(img[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1].astype(np.float64) - DARK, 0, None)
    ys, xs = np.mgrid[:w.shape[0], :w.shape[1]]
    return x0 + (w * xs).sum() / w.sum(), y0 + (w * ys).sum() / w.sum()


def test_project_rig_of_ideal_rig_is_pinhole_projection():
    cfg = _cfg()
    scene = Scene(cfg, noise=False, bank_size=1)
    X, Y, Z = np.array([0.0, 0.3, -0.7]), np.array([0.0, -0.2, 0.45]), np.array([30.0, 12.0, 55.0])
    ul, ur, v = scene.geometry.project(X, Y, Z)
    pl, vl, pr, vr = project_rig(StereoCalibration.ideal(cfg.camera), X, Y, Z)
    np.testing.assert_allclose(pl, ul, atol=1e-9)
    np.testing.assert_allclose(pr, ur, atol=1e-9)
    np.testing.assert_allclose(vl, v, atol=1e-9)
    np.testing.assert_allclose(vr, v, atol=1e-9)


def test_ideal_rig_gives_identical_frames():
    """Textured background, jitter, vibration and noise on: only the LED positions could
    differ, and for the ideal rig they agree to rounding, so the frames are identical."""
    cfg = _cfg(35.0, background="texture", jitter_px=0.05, vibration_px=0.2, lateral_m=0.11)
    a = Scene(cfg, bank_size=4)
    b = Scene(cfg, bank_size=4, rig=StereoCalibration.ideal(cfg.camera))
    ta, tb = a.truth(np.arange(6)), b.truth(np.arange(6))
    np.testing.assert_allclose(tb.u_right, ta.u_right, atol=1e-9)
    np.testing.assert_allclose(tb.v_left, ta.v_left, atol=1e-9)
    for n in range(6):
        la, ra = a.render_pair(n)
        lb, rb = b.render_pair(n)
        np.testing.assert_array_equal(lb, la)
        np.testing.assert_array_equal(rb, ra)


@pytest.mark.parametrize("distance_m,lateral_m,vertical_m", [(30.0, 0.4, -0.3), (50.0, -0.9, 0.6)])
def test_rotated_rig_moves_spots_as_project_points_says(distance_m, lateral_m, vertical_m):
    cfg = _cfg(distance_m, background="none", distractors=[], lateral_m=lateral_m,
               vertical_m=vertical_m, jitter_px=0.0, vibration_px=0.0)
    rig = nonideal_rig(cfg.camera, rotation_deg=(0.05, 0.08, 0.03))
    src = ArraySource(np.full((1, 1), 3), repeat=True)  # level 3 of 8: unsaturated
    ideal = Scene(cfg, src, noise=False, bank_size=1)
    real = Scene(cfg, src, noise=False, bank_size=1, rig=rig)
    P = np.array([[lateral_m, vertical_m, distance_m]])
    want_l, want_r = project_points(rig, P, "left")[0], project_points(rig, P, "right")[0]
    t = real.truth([3])
    assert (t.u_left[0, 0], t.v_left[0, 0]) == pytest.approx(tuple(want_l), abs=1e-9)
    assert (t.u_right[0, 0], t.v_right[0, 0]) == pytest.approx(tuple(want_r), abs=1e-9)
    left, right = real.render_pair(3)
    assert left.max() < 255 and right.max() < 255
    assert _centroid(left, *want_l) == pytest.approx(tuple(want_l), abs=0.05)
    assert _centroid(right, *want_r) == pytest.approx(tuple(want_r), abs=0.05)
    # the same rig without the rotation puts the right spot ~4.9 px (0.08 deg about y at
    # f = 3500 px) elsewhere, and the rendered spot follows
    rig0 = nonideal_rig(cfg.camera, rotation_deg=(0.0, 0.0, 0.0))
    want_r0 = project_points(rig0, P, "right")[0]
    assert np.hypot(*(want_r - want_r0)) > 4.0
    _, right0 = Scene(cfg, src, noise=False, bank_size=1, rig=rig0).render_pair(3)
    assert _centroid(right0, *want_r0) == pytest.approx(tuple(want_r0), abs=0.05)
    # and the ideal rig's spot is where the ideal geometry says (not where the rig puts it)
    ti = ideal.truth([3])
    _, ri = ideal.render_pair(3)
    assert _centroid(ri, ti.u_right[0, 0], ti.v_right[0, 0]) == pytest.approx(
        (ti.u_right[0, 0], ti.v_right[0, 0]), abs=0.05)
    assert np.hypot(ti.u_right[0, 0] - want_r[0], ti.v_right[0, 0] - want_r[1]) > 1.0


def test_rig_of_wrong_size_is_refused():
    cfg = _cfg()
    rig = StereoCalibration.from_parameters(640, 480, 3500.0, baseline_m=0.6)
    with pytest.raises(ValueError, match="640x480"):
        Scene(cfg, noise=False, bank_size=1, rig=rig)
