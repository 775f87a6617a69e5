"""Phase-only correlation and sub-pixel peaks (dissertation eqs. 3.5-3.9)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from iscd.decode.ranging.poc import (continuous_peak, cross_power, integer_peak, peak_kernel, poc_surface,
                              sinc_fit)
from iscd.decode.ranging.synth import fourier_shift


def textures(n: int, size: int, seed: int, smooth: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return gaussian_filter(rng.normal(size=(n, size, size)), (0, smooth, smooth), mode="wrap") * 40 + 100


def test_integer_shift_gives_unit_delta_at_plus_shift() -> None:
    """Eq. 3.6: for a pure integer shift the POC is a Kronecker delta of height 1, at
    +(left position - right position) (wrapping for negative shifts)."""
    base = textures(3, 16, 0)
    right = base
    shifts = [(2, 3), (-1, -4), (0, 7)]
    left = np.stack([np.roll(base[i], s, axis=(0, 1)) for i, s in enumerate(shifts)])
    c = poc_surface(left, right)
    iy, ix = integer_peak(c)
    assert list(zip(iy.tolist(), ix.tolist())) == shifts
    for i, (sy, sx) in enumerate(shifts):
        assert c[i, sy % 16, sx % 16] == pytest.approx(1.0, abs=1e-9)
        assert np.sort(np.abs(c[i].ravel()))[-2] < 1e-9


def test_cross_power_is_unit_magnitude_and_beta_zero_is_plain_correlation() -> None:
    rng = np.random.default_rng(1)
    fl, fr = np.fft.fft2(rng.normal(size=(2, 8, 8))), np.fft.fft2(rng.normal(size=(2, 8, 8)))
    np.testing.assert_allclose(np.abs(cross_power(fl, fr)), 1.0, atol=1e-12)
    np.testing.assert_allclose(cross_power(fl, fr, beta=0.0), fl * np.conj(fr))
    assert np.all(cross_power(np.zeros((1, 4, 4), complex), np.zeros((1, 4, 4), complex)) == 0)


@pytest.mark.parametrize("kernel", ["sinc", "dirichlet"])
def test_sinc_fit_recovers_model_peak_to_its_grid_step(kernel: str) -> None:
    """Eqs. 3.8/3.9: sampled peak models at known offsets are fitted to within half the grid
    step (0.01 px grid -> 0.005 px)."""
    w = 32
    deltas = np.array([-0.49, -0.23, 0.0, 0.117, 0.38, 0.5])
    n = deltas.size
    surf = np.zeros((n, w, w))
    cols = np.fft.fftfreq(w) * w                     # signed column offsets
    for i, d in enumerate(deltas):
        surf[i, 0, :] = 0.8 * peak_kernel(cols - (5 + d), w, kernel)
    iy, ix = integer_peak(surf)
    _, dx, amp = sinc_fit(surf, iy, ix, radius=2, step=0.01, kernel=kernel)
    assert np.all(np.abs(dx - (5 + deltas)) <= 0.005 + 1e-9)
    np.testing.assert_allclose(amp, 0.8, atol=0.02)


def test_continuous_peak_is_exact_for_fourier_shifts() -> None:
    base = textures(40, 16, 2)
    rng = np.random.default_rng(3)
    dx, dy = rng.uniform(-3, 3, 40), rng.uniform(-1, 1, 40)
    left = fourier_shift(base, dx, dy)           # left content at +d relative to right
    spec = cross_power(np.fft.fft2(left), np.fft.fft2(base), beta=0.5)
    iy, ix = integer_peak(np.fft.ifft2(spec).real)
    p = continuous_peak(spec, iy, ix)
    np.testing.assert_allclose(p.dx, dx, atol=1e-6)
    np.testing.assert_allclose(p.dy, dy, atol=1e-6)
    np.testing.assert_allclose(p.height, 1.0, atol=1e-6)


def test_continuous_peak_sigma_matches_observed_scatter() -> None:
    """The residual-phase standard deviation predicts the error of noisy shifts: the RMS of
    error/sigma over 400 pairs is near 1 (a wrong sigma by 2x fails)."""
    rng = np.random.default_rng(4)
    n = 400
    base = textures(n, 16, 5, smooth=1.5)
    d = rng.uniform(-2, 2, n)
    left = fourier_shift(base, d) + rng.normal(0, 2.0, (n, 16, 16))
    right = base + rng.normal(0, 2.0, (n, 16, 16))
    spec = cross_power(np.fft.fft2(left), np.fft.fft2(right), beta=0.0)
    iy, ix = integer_peak(np.fft.ifft2(spec).real)
    p = continuous_peak(spec, iy, ix)
    err = p.dx - d
    z = np.sqrt(np.mean((err / p.sigma_x) ** 2))
    print("err/sigma RMS", z)
    assert 0.7 < z < 1.4, z
    assert np.sqrt(np.mean(err ** 2)) > 0.005      # the test has real noise in it


def test_bad_pairs_are_refused() -> None:
    with pytest.raises(ValueError, match="differ in shape"):
        poc_surface(np.zeros((2, 8, 8)), np.zeros((2, 8, 9)))
    with pytest.raises(ValueError, match="NaN"):
        poc_surface(np.full((1, 8, 8), np.nan), np.zeros((1, 8, 8)))
    with pytest.raises(ValueError, match="shape"):
        poc_surface(np.zeros(8), np.zeros(8))


@pytest.mark.parametrize("size", [(16, 16), (15, 17), (12, 21)])
def test_half_spectrum_gives_the_same_peak_as_the_full_one(size: tuple[int, int]) -> None:
    """rfft2 input (each bin standing for its conjugate too) == fft2 input, to rounding."""
    h, w = size
    rng = np.random.default_rng(6)
    base = gaussian_filter(rng.normal(size=(5, h, w)), (0, 1, 1), mode="wrap")
    left = fourier_shift(base, rng.uniform(-2, 2, 5), rng.uniform(-1, 1, 5)) + rng.normal(0, 0.05, (5, h, w))
    full = cross_power(np.fft.fft2(left), np.fft.fft2(base), beta=0.3)
    half = cross_power(np.fft.rfft2(left), np.fft.rfft2(base), beta=0.3)
    iy, ix = integer_peak(np.fft.ifft2(full).real)
    a = continuous_peak(full, iy, ix)
    b = continuous_peak(half, iy, ix, width=w)
    for f in ("dx", "dy", "height", "sigma_x", "sigma_y"):
        np.testing.assert_allclose(getattr(b, f), getattr(a, f), rtol=1e-7, atol=1e-10, err_msg=f)
