"""The compiled one-LED core refill against :func:`declip_cells`' numpy reference, on
rendered single-LED patches and on synthetic clipped spots."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.decode.ranging.declip_kernel import declip_one_cell
from iscd.decode.ranging.projected import declip_cells, led_cells


def _spots(n: int, h: int, w: int, peak: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, h, w) Gaussian spots of random centre, width and brightness clipped at 255 DN,
    plus noise; and the clipped mask."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    out = np.empty((n, h, w))
    for f in range(n):
        cx, cy = (w - 1) / 2 + rng.uniform(-1.5, 1.5), (h - 1) / 2 + rng.uniform(-1.5, 1.5)
        s = rng.uniform(1.2, 2.5)
        a = peak * rng.uniform(0.3, 1.5)
        out[f] = a * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s)) + rng.normal(0, 1.0, (h, w))
    out = np.clip(out, 0, 255)
    return out, out >= 254.5


@pytest.mark.parametrize("h, w, peak, seed", [(14, 14, 900.0, 1), (22, 22, 3000.0, 2), (15, 21, 400.0, 3)])
def test_refill_matches_the_reference(h: int, w: int, peak: float, seed: int) -> None:
    p, sat = _spots(32, h, w, peak, seed)
    cells = led_cells(h, w, np.array([[(w - 1) / 2, (h - 1) / 2]]))
    assert cells.index.shape[0] == 1
    rng = np.random.default_rng(seed + 10)
    top = 255.0 - rng.uniform(0, 5, 32)           # per frame (the pedestal taken off)
    tmap = -rng.uniform(0, 3, (32, h, w))         # a background per pixel
    for tm in (None, tmap, tmap[0]):
        ref, ref_ok = declip_cells(p, sat, top, cells, tm)
        got, got_ok = declip_cells(p, sat, top, cells, tm, compiled=True)
        assert ref_ok.any() and (ref_ok == got_ok).all()
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9)
        assert (got[~sat] == p[~sat]).all()       # only clipped pixels change
    # the direct call, a scalar top
    a, _ = declip_cells(p, sat, 250.0, cells)
    b, _ = declip_one_cell(p, sat, 250.0, cells.index[0], cells.member[0])
    np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-9)


def test_nothing_clipped_and_too_few_pixels() -> None:
    p, sat = _spots(4, 14, 14, 100.0, 4)          # dim: nothing clipped
    cells = led_cells(14, 14, np.array([[6.5, 6.5]]))
    got, ok = declip_one_cell(p, np.zeros_like(sat), 255.0, cells.index[0], cells.member[0])
    assert not ok.any() and np.array_equal(got, p)
    # a whole patch clipped: no ring to fit, left as it is (as the reference)
    full = np.full((2, 14, 14), 255.0)
    ref, ref_ok = declip_cells(full, full >= 254.5, 255.0, cells)
    got, ok = declip_cells(full, full >= 254.5, 255.0, cells, compiled=True)
    assert not ok.any() and not ref_ok.any() and np.array_equal(got, ref)


def test_live_ranging_of_a_bright_single_led_is_unchanged() -> None:
    """The live StereoRanger on a saturating single LED: compiled and numpy paths give the
    same ranges (the refill is the only numpy-vs-compiled difference on this path)."""
    from fakes import render_pairs
    from iscd.core.config import default_config
    from iscd.decode.ranging.stereo import StereoRanger
    from iscd.decode.tracking.detect import detect_array
    from iscd.sim.presets import single_led

    cfg = single_led(default_config(), 30.0)
    L, R = render_pairs(cfg, 96)
    fl, fr = detect_array(L[:64], 1, 1), detect_array(R[:64], 1, 1)
    assert fl is not None and fr is not None
    from iscd.calibration.io import StereoCalibration

    cal = StereoCalibration.ideal(cfg.camera)
    a, b = StereoRanger(cal, compiled=False), StereoRanger(cal, compiled=True)
    for s in range(64, 96, 16):
        ra = a.measure(L[s:s + 16], R[s:s + 16], fl, fr)
        rb = b.measure(L[s:s + 16], R[s:s + 16], fl, fr)
        assert (L[s:s + 16] == 255).any()  # it does saturate
        np.testing.assert_array_equal(ra.valid, rb.valid)
        assert ra.valid.any()
        np.testing.assert_allclose(rb.disparity_px, ra.disparity_px, rtol=0, atol=1e-6, equal_nan=True)
