"""Keys bicubic interpolation (dissertation eqs. 3.1-3.3)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from iscd.decode.ranging.bicubic import interp_matrix, keys_kernel, sample_positions, upsample


def eq_3_3(u: np.ndarray) -> np.ndarray:
    """S(u) typed in from the dissertation, piece by piece."""
    x = np.abs(u)
    out = np.zeros_like(x)
    a = x <= 1
    b = (x > 1) & (x <= 2)
    out[a] = 1 - 2.5 * u[a] ** 2 + 1.5 * x[a] ** 3
    out[b] = 2 - 4 * x[b] + 2.5 * u[b] ** 2 - 0.5 * x[b] ** 3
    return out


def test_kernel_equals_equation_3_3() -> None:
    u = np.linspace(-3, 3, 6001)
    np.testing.assert_allclose(keys_kernel(u), eq_3_3(u), atol=1e-12)
    # interpolating kernel: 1 at 0, 0 at the other integers; continuous at |u| = 1 and 2
    np.testing.assert_allclose(keys_kernel(np.array([0.0, 1.0, -1.0, 2.0, -2.0, 2.5])), [1, 0, 0, 0, 0, 0], atol=1e-12)
    eps = 1e-9
    for knot in (1.0, 2.0):
        assert abs(keys_kernel(knot - eps) - keys_kernel(knot + eps)) < 1e-7


def test_weights_sum_to_one_and_a_changes_the_kernel() -> None:
    delta = np.linspace(0, 1, 101, endpoint=False)
    h = np.arange(-1, 3)
    for a in (-0.5, -0.75):
        np.testing.assert_allclose(keys_kernel(h[None, :] - delta[:, None], a).sum(axis=1), 1.0, atol=1e-12)
    assert abs(keys_kernel(0.5, -0.5) - keys_kernel(0.5, -0.75)) > 0.01


def test_dissertation_mapping_keeps_input_samples() -> None:
    """Eq. 3.1: x_bic = alpha x, so every alpha-th output pixel is an input pixel."""
    rng = np.random.default_rng(0)
    g = rng.uniform(0, 255, (5, 16, 12))
    up = upsample(g, 3)
    assert up.shape == (5, 48, 36)
    np.testing.assert_allclose(up[:, ::3, ::3], g, atol=1e-9)
    np.testing.assert_allclose(sample_positions(4, 3)[:4], [0, 1 / 3, 2 / 3, 1])


def test_reproduces_quadratics_like_keys_and_not_cubics() -> None:
    """Keys (1981): a = -1/2 reproduces polynomials up to degree 2 exactly (away from the
    border), which no other a does; cubics are not reproduced."""
    n = 20
    x = np.arange(n, dtype=np.float64)
    xs = sample_positions(n, 3)
    inner = (xs >= 1) & (xs <= n - 3)
    for coeffs in ([3.0, -2.0, 0.7], [0.0, 1.0, 0.0], [5.0, 0.0, 0.0]):
        p = np.polynomial.Polynomial(coeffs)
        got = interp_matrix(n, 3) @ p(x)
        np.testing.assert_allclose(got[inner], p(xs[inner]), atol=1e-9)
    quad = np.polynomial.Polynomial([3.0, -2.0, 0.7])
    err_075 = np.abs(interp_matrix(n, 3, a=-0.75) @ quad(x) - quad(xs))[inner].max()
    assert err_075 > 1e-3
    cubic = np.polynomial.Polynomial([0.0, 0.0, 0.0, 1.0])
    err_cubic = np.abs(interp_matrix(n, 3) @ cubic(x) - cubic(xs))[inner].max()
    assert err_cubic > 1e-3


def test_2d_separable_matches_direct_equation_3_2() -> None:
    """The two matrix products equal the 16-neighbour double sum of eq. 3.2."""
    rng = np.random.default_rng(1)
    g = rng.uniform(0, 255, (9, 11))
    up = upsample(g, 3)
    for yb, xb in [(4, 7), (13, 20), (10, 2), (25, 31)]:
        y, dy = divmod(yb, 3)
        x, dx = divmod(xb, 3)
        dy, dx = dy / 3, dx / 3
        val = 0.0
        for h in range(-1, 3):
            for v in range(-1, 3):
                xi = min(max(x + h, 0), g.shape[1] - 1)
                yi = min(max(y + v, 0), g.shape[0] - 1)
                val += g[yi, xi] * keys_kernel(h - dx) * keys_kernel(v - dy)
        assert abs(up[yb, xb] - val) < 1e-9


def test_differs_from_cv2_inter_cubic_which_is_a_minus_075() -> None:
    rng = np.random.default_rng(2)
    img = rng.uniform(0, 255, (16, 16))
    cv = cv2.resize(img, (48, 48), interpolation=cv2.INTER_CUBIC)
    # same machinery with OpenCV's constant and pixel-centre mapping reproduces cv2 ...
    np.testing.assert_allclose(upsample(img, 3, a=-0.75, mapping="center"), cv, atol=2e-3)
    # ... and the dissertation's kernel does not
    assert np.abs(upsample(img, 3, a=-0.5, mapping="center") - cv).max() > 1.0


def test_batched_equals_single_and_bad_input() -> None:
    rng = np.random.default_rng(3)
    g = rng.uniform(0, 255, (4, 8, 10))
    b = upsample(g, 3)
    for i in range(4):
        np.testing.assert_allclose(b[i], upsample(g[i], 3), atol=1e-12)
    with pytest.raises(ValueError, match="alpha"):
        upsample(g, 0)
    with pytest.raises(ValueError, match="alpha"):
        upsample(g, 2.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="shape"):
        upsample(np.zeros(5), 3)
    with pytest.raises(ValueError, match="mapping"):
        upsample(g, 3, mapping="corner")  # type: ignore[arg-type]
