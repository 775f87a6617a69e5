"""Spot optics: the profile, its table, footprints and flux bookkeeping."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import ncx2

from iscd.sim.optics import (Canvas, add_glare, disk_blur_profile, footprint, make_table, render,
                             source_box, spot_size_px)


def test_profile_is_disk_convolved_with_gaussian():
    # brute force: a finely sampled disk convolved with a Gaussian, evaluated at a few radii
    R, s = 2.1, 0.7
    h = 0.02
    g = np.arange(-R, R + h, h)
    X, Y = np.meshgrid(g, g)
    inside = X ** 2 + Y ** 2 <= R ** 2
    xs, ys = X[inside], Y[inside]
    for r in (0.0, 1.0, 2.1, 3.0):
        ref = np.exp(-((xs - r) ** 2 + ys ** 2) / (2 * s * s)).sum() * h * h / (2 * np.pi * s * s)
        assert disk_blur_profile(np.array([r]), R, s)[0] == pytest.approx(ref, abs=0.01)
    assert disk_blur_profile(np.array([0.0]), 10.0, 0.5)[0] == pytest.approx(1.0)
    np.testing.assert_allclose(disk_blur_profile(np.array([0.3, 2.0]), R, s),
                               ncx2.cdf(R * R / s / s, 2, np.array([0.3, 2.0]) ** 2 / s / s))


def test_table_lookup_matches_profile():
    tab = make_table(1.9, 0.66)
    r = np.random.default_rng(0).uniform(0, tab.r_cut * 0.99, 2000)
    looked = tab.table[(r * r / tab.step).astype(int)]
    np.testing.assert_allclose(looked, disk_blur_profile(r, 1.9, 0.66), atol=2e-3)
    assert tab.half == math.ceil(tab.r_cut)
    assert disk_blur_profile(np.array([tab.r_cut + 0.05]), 1.9, 0.66)[0] < 3e-5


def test_footprint_render_conserves_flux_and_centroid():
    # two sources, one with subpixel offsets: each integrates to pi R^2 * amp (the disk's
    # flux) and has its centroid at (u, v)
    R, s = 1.6, 0.67
    tab = make_table(R, s)
    u = np.array([20.3, 41.77])
    v = np.array([30.61, 28.05])
    x0, y0, x1, y1 = source_box(u, v, tab.half)
    fp = footprint(x0, y0, (y1 - y0, x1 - x0), u, v, tab)
    for i in range(2):
        amp = np.zeros(2)
        amp[i] = 100.0
        img = render(fp, amp)
        assert img.sum() == pytest.approx(100.0 * math.pi * R * R, rel=2e-3)
        ys, xs = np.mgrid[y0:y1, x0:x1]
        assert (img * xs).sum() / img.sum() == pytest.approx(u[i], abs=0.01)
        assert (img * ys).sum() / img.sum() == pytest.approx(v[i], abs=0.01)


def test_grid_glare_equals_general_glare():
    tab = make_table(1.0, 0.6)
    cols, rows = np.meshgrid(10 + 4.3 * np.arange(3), 12 + 4.1 * np.arange(2))
    u, v = cols.ravel(), rows.ravel()
    flux = np.arange(1.0, 7.0)
    x0, y0, x1, y1 = source_box(u, v, 9)
    a = render(footprint(x0, y0, (y1 - y0, x1 - x0), u, v, tab, 2.6, grid=(2, 3)),
               np.zeros(6), flux)
    c = Canvas(x0, y0, np.zeros((y1 - y0, x1 - x0)))
    add_glare(c, u, v, flux, 2.6)
    np.testing.assert_allclose(a, c.data, atol=1e-12)
    assert a.sum() == pytest.approx(flux.sum(), rel=0.01)  # ~3.5 sigma margin


def test_spot_size_grows_with_the_disk():
    assert spot_size_px(5.0, 0.5) > spot_size_px(2.0, 0.5) > spot_size_px(0.5, 0.5)
    assert spot_size_px(0.01, 1.0) == pytest.approx(2 * math.sqrt(2 * math.log(10)), rel=0.01)
