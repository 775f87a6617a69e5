"""Geometry, motion, vibration and jitter of the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.core.config import default_config
from iscd.sim import Scene
from iscd.sim.geometry import Jitter, StereoGeometry, Vibration, distance, led_offsets
from iscd.sim.presets import override


def test_projection_and_disparity():
    g = StereoGeometry(3500.0, 0.6, 512, 512)
    ul, ur, v = g.project(np.array(0.5), np.array(-0.25), np.array(20.0))
    assert (float(ul), float(v)) == pytest.approx((255.5 + 87.5, 255.5 - 43.75))
    assert float(ul - ur) == pytest.approx(105.0)
    assert float(g.disparity(50.0)) == pytest.approx(42.0)
    assert float(StereoGeometry(3500.0, 0.25, 512, 512).disparity(50.0)) == pytest.approx(17.5)


def test_led_layout_row_major():
    tx = default_config().transmitter
    off = led_offsets(tx)
    assert off.shape == (64, 2)
    np.testing.assert_allclose(off[0], [-0.21, -0.21])
    np.testing.assert_allclose(off[1] - off[0], [0.06, 0.0])   # next column
    np.testing.assert_allclose(off[8] - off[0], [0.0, 0.06])   # next row


def test_approach_stops_at_min_distance():
    sc = override(default_config(), scene={"distance_m": 30, "speed_mps": 10, "min_distance_m": 5}).scene
    np.testing.assert_allclose(distance(np.array([0.0, 1.0, 2.5, 10.0]), sc), [30, 20, 5, 5])


def test_truth_uses_mid_exposure_distance():
    cfg = override(default_config(), scene={"speed_mps": 11.1})
    t = Scene(cfg).truth([0, 1000])
    np.testing.assert_allclose(t.z_m, [30 - 11.1 * 0.0005, 30 - 11.1 * 1.0005])
    np.testing.assert_allclose(t.disparity_px, 3500 * 0.25 / t.z_m)


def test_vibration_is_smooth_common_with_given_rms():
    vib = Vibration(0.8, seed=3)
    t = np.arange(0, 20.0, 1e-3)
    s = vib(t)
    assert np.sqrt((s ** 2).mean(axis=0)) == pytest.approx([0.8, 0.8], rel=0.25)
    assert np.diff(s, axis=0).std() < 0.2 * 0.8  # smooth at 1000 fps (white noise: 1.4x rms)
    assert np.array_equal(vib(t[:5]), Vibration(0.8, seed=3)(t[:5]))


def test_jitter_is_fresh_per_frame_independent_per_camera_and_random_access():
    a, b = Jitter(0.3, 5, 0), Jitter(0.3, 5, 1)
    f = np.arange(20_000)
    ja, jb = a(f), b(f)
    assert ja.std(axis=0) == pytest.approx([0.3, 0.3], rel=0.05)
    assert abs(np.corrcoef(ja[:, 0], jb[:, 0])[0, 1]) < 0.03
    assert abs(np.corrcoef(ja[1:, 0], ja[:-1, 0])[0, 1]) < 0.03
    np.testing.assert_array_equal(Jitter(0.3, 5, 0)(np.array([12345, 7])), ja[[12345, 7]])


def test_shifts_move_the_spots_in_truth():
    cfg = override(default_config(), scene={"vibration_px": 0.5, "jitter_px": 0.2})
    s = Scene(cfg)
    t = s.truth(np.arange(0, 3000, 3))
    still = Scene(default_config()).truth(np.arange(0, 3000, 3))
    dl = t.u_left - still.u_left
    np.testing.assert_allclose(dl, np.repeat(t.shift_left[:, :1], 64, axis=1))
    common = (t.shift_left + t.shift_right) / 2
    diff = t.shift_left - t.shift_right
    assert diff.std() == pytest.approx(0.2 * np.sqrt(2), rel=0.15)
    assert common.std() > 0.3
    np.testing.assert_allclose(t.disparity_px, still.disparity_px)
