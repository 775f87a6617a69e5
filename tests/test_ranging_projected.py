"""The fast 1-D project method ("iscd-fast", iscd.decode.ranging.projected) against known shifts."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

from iscd.decode.ranging.estimators import get_estimator
from iscd.decode.ranging.projected import (ProjectedShift, correlate_1d, declip_cells, led_cells, make_plan,
                                    row_weights)
from iscd.decode.ranging.synth import disk_spots, fourier_shift, gaussian_spots, sensor

SHIFTS = np.array([-2.73, -1.5, -0.31, 0.0, 0.47, 1.25, 2.62])   # left position - right position, px
N = SHIFTS.size


def profiles(n: int, w: int, seed: int, smooth: float = 1.2) -> np.ndarray:
    """Random smooth 1-D profiles under a Gaussian envelope (like a projected LED patch)."""
    rng = np.random.default_rng(seed)
    x = np.arange(w) - (w - 1) / 2
    return gaussian_filter1d(rng.normal(size=(n, w)), smooth, axis=1, mode="wrap") * np.exp(-x ** 2 / (2 * (w / 6) ** 2)) * 50


def test_correlate_1d_is_exact_for_fourier_shifts() -> None:
    base = profiles(N, 24, 1)
    left = fourier_shift(base[:, None, :], SHIFTS)[:, 0, :]       # content at +shift in the left one
    for beta in (0.0, 0.5, 1.0):
        p = correlate_1d(left, base, beta=beta, band_cutoff=0.12)
        np.testing.assert_allclose(p.dx, SHIFTS, atol=1e-6)
        np.testing.assert_allclose(p.height, 1.0, atol=1e-6)


def test_correlate_1d_sigma_matches_observed_scatter() -> None:
    """The residual-phase sigma predicts the scatter of noisy 1-D shifts (a sigma wrong by 2x fails)."""
    rng = np.random.default_rng(2)
    n, w = 500, 24
    base = profiles(n, w, 3)
    d = rng.uniform(-2, 2, n)
    left = fourier_shift(base[:, None, :], d)[:, 0, :] + rng.normal(0, 1.5, (n, w))
    right = base + rng.normal(0, 1.5, (n, w))
    p = correlate_1d(left, right, beta=0.0, band_cutoff=None)
    err = p.dx - d
    z = np.sqrt(np.mean((err / p.sigma) ** 2))
    assert 0.7 < z < 1.4, z
    assert np.sqrt(np.mean(err ** 2)) > 0.01                         # real noise in the test


def test_search_limit_keeps_a_periodic_array_on_the_right_led() -> None:
    """Eight LEDs 4.2 px apart, shifts up to 1.8 px: limited to half the pitch, the peak
    search never matches one LED off (an error of 4.2 px)."""
    w = 48
    x = np.arange(w, dtype=float)
    centres = 6 + 4.2 * np.arange(8)
    rng = np.random.default_rng(5)
    d = rng.uniform(-1.8, 1.8, 200)
    spot = lambda c: np.exp(-0.5 * ((x[None, None, :] - c[..., None]) / 0.9) ** 2).sum(axis=1) * 80  # noqa: E731
    left = spot(centres[None, :] + d[:, None] / 2) + rng.normal(0, 3, (200, w))
    right = spot(centres[None, :] - d[:, None] / 2) + rng.normal(0, 3, (200, w))
    p = correlate_1d(left, right, max_shift_px=2.1)
    assert np.abs(p.dx).max() <= 2.1 + 0.5
    assert np.abs(p.dx - d).max() < 0.25


@pytest.mark.parametrize("kind,size", [("gauss", 1.0), ("gauss", 1.3), ("disk", 1.0), ("disk", 1.5)])
@pytest.mark.parametrize("peak", [200.0, 640.0], ids=["unsaturated", "saturated"])
def test_rendered_spots_to_001px_like_the_2d_method(kind: str, size: float, peak: float) -> None:
    render = gaussian_spots if kind == "gauss" else disk_spots
    left = np.minimum(render(N, (16, 16), 7.6 + SHIFTS / 2, 7.3, size, peak=peak) + 12, 255.0)
    right = np.minimum(render(N, (16, 16), 7.6 - SHIFTS / 2, 7.3, size, peak=peak) + 12, 255.0)
    assert (left >= 255).any() == (peak > 255)
    fast = get_estimator("iscd-fast").estimate(left, right)
    two_d = get_estimator("iscd").estimate(left, right)
    assert np.abs(fast.dx - SHIFTS).max() <= 0.01
    assert np.abs(fast.dx - SHIFTS).max() <= np.abs(two_d.dx - SHIFTS).max() + 0.002
    assert np.all(fast.dy == 0) and np.all(np.isnan(fast.sigma_y_px))   # dy is not measured


def test_declip_refills_clipped_cores_of_an_array() -> None:
    """Nine clipped Gaussian spots 6 px apart: each core is back within 10 % of the truth,
    unsaturated pixels are untouched, and cells never share a pixel."""
    g = (np.arange(3) - 1) * 6.0
    gx, gy = np.meshgrid(g, g)
    cx, cy = 12.3 + gx.ravel(), 11.8 + gy.ravel()
    truth = gaussian_spots(2, (24, 24), np.tile(cx, (2, 1)), np.tile(cy, (2, 1)), 1.1, peak=900)
    clipped = np.minimum(truth, 255.0)
    sat = clipped >= 255
    cells = led_cells(24, 24, np.stack([cx, cy], 1), pitch_px=6.0, spot_px=3.0)
    owners = cells.owner[cells.index[cells.member]]
    assert np.array_equal(owners, np.repeat(np.arange(9), cells.member.sum(axis=(1, 2))))
    out, refilled = declip_cells(clipped, sat, 255.0, cells)
    assert refilled.all()
    rel = np.abs(out[sat] - truth[sat]) / truth[sat]
    assert rel.max() < 0.1
    assert np.array_equal(out[~sat], clipped[~sat])


def test_row_weights_follow_the_led_rows() -> None:
    w = row_weights(20, [5.0, 11.0], 1.0)
    assert w.shape == (20,) and w.max() == pytest.approx(1.0)
    assert w[5] > 0.99 and w[11] > 0.99 and w[8] < 0.03 and w[0] < 1e-3


def test_plan_limits_the_search_for_arrays_only() -> None:
    one = make_plan(16, 16, [[7.5, 7.5]], [[6.9, 7.5]])
    arr = make_plan(40, 40, np.c_[np.arange(8) * 4.2 + 5, np.full(8, 20.0)],
                    np.c_[np.arange(8) * 4.2 + 4, np.full(8, 20.0)], pitch_px=4.2, spot_px=3.0)
    assert one.max_shift_px is None and one.cells_left.index.shape[0] == 1
    assert arr.max_shift_px == pytest.approx(2.1) and arr.cells_left.index.shape[0] == 8


def test_background_and_noise() -> None:
    """A textured background with its own disparity is removed by the background argument;
    noise-only pairs give a finite (meaningless) shift, flat ones NaN."""
    rng = np.random.default_rng(9)
    n = 60
    d = rng.uniform(-1.5, 1.5, n)
    bg_l = gaussian_filter1d(gaussian_filter1d(rng.normal(size=(n, 16, 16)), 1.2, axis=1), 1.2, axis=2) * 60 + 60
    bg_r = np.roll(bg_l, 5, axis=2)
    left = sensor(bg_l + gaussian_spots(n, (16, 16), 7.5 + d / 2, 7.5, 1.0, peak=60), rng, 0, 0.26, 78)
    right = sensor(bg_r + gaussian_spots(n, (16, 16), 7.5 - d / 2, 7.5, 1.0, peak=60), rng, 0, 0.26, 78)
    est = ProjectedShift()
    plain = np.abs(est.estimate(left, right).dx - d).mean()
    sub = np.abs(est.estimate(left, right, background=(bg_l, bg_r)).dx - d).mean()
    assert sub < 0.05 and plain > 3 * sub
    flat = est.estimate(np.full((2, 16, 16), 40.0), np.full((2, 16, 16), 40.0))
    assert np.isnan(flat.dx).all() and np.all(flat.quality == 0)
    with pytest.raises(ValueError, match="differ in shape"):
        est.estimate(np.zeros((2, 16, 16)), np.zeros((3, 16, 16)))
    with pytest.raises(ValueError, match="beta"):
        get_estimator("iscd-fast", beta=2.0)
