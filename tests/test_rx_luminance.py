"""LED luminance: ROI mean (3.10) against a plain loop; the spot estimator against truth."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.decode.tracking.luminance import SpotLuminance, gather_windows, roi_mean
from iscd.decode.comms.synth import render_spots


def _loop_roi_mean(frames: np.ndarray, centres: np.ndarray, size: int) -> np.ndarray:
    F, H, W = frames.shape
    out = np.full((F, centres.shape[-2]), np.nan)
    for f in range(F):
        c = centres if centres.ndim == 2 else centres[f]
        for i, (x, y) in enumerate(c):
            x0 = int(np.rint(x - (size - 1) / 2))
            y0 = int(np.rint(y - (size - 1) / 2))
            vals = [frames[f, r, q] for r in range(y0, y0 + size) for q in range(x0, x0 + size)
                    if 0 <= r < H and 0 <= q < W]
            if vals:
                out[f, i] = np.mean(vals)
    return out


@pytest.mark.parametrize("size", [1, 3, 4, 5])
def test_roi_mean_matches_a_loop_including_borders(size: int) -> None:
    rng = np.random.default_rng(size)
    frames = rng.integers(0, 256, size=(4, 20, 30), dtype=np.uint8)
    centres = np.array([[5.2, 6.7], [0.2, 0.4], [29.4, 19.6], [14.5, 10.5], [-10.0, 5.0]])
    got = roi_mean(frames, centres, size)
    want = _loop_roi_mean(frames, centres, size)
    np.testing.assert_allclose(got, want)
    assert np.isnan(got[:, 4]).all()  # entirely outside the image


def test_roi_mean_with_tracked_centres_per_frame() -> None:
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 256, size=(6, 16, 16), dtype=np.uint8)
    centres = rng.uniform(2, 13, size=(6, 3, 2))
    np.testing.assert_allclose(roi_mean(frames, centres, 3), _loop_roi_mean(frames, centres, 3))
    with pytest.raises(ValueError):
        roi_mean(frames, centres[:5], 3)
    pix, valid = gather_windows(frames, centres, (3, 5))
    assert pix.shape == (6, 3, 5, 3) and valid.shape == (6, 3, 5, 3)


def _grid(n: int, pitch: float, x0: float = 10.3, y0: float = 9.6) -> np.ndarray:
    g = np.arange(n)
    return np.stack(np.meshgrid(g * pitch + x0, g * pitch + y0), -1).reshape(-1, 2)


def _spacing_over_noise(L: np.ndarray, x: np.ndarray, M: int) -> float:
    """Median over LEDs of (level spacing of a linear fit L ~ x) / residual RMS."""
    out = []
    for i in range(x.shape[1]):
        A = np.c_[np.ones(len(x)), x[:, i]]
        co = np.linalg.lstsq(A, L[:, i], rcond=None)[0]
        out.append(co[1] / (M - 1) / (L[:, i] - A @ co).std())
    return float(np.median(out))


def test_spot_luminance_removes_crosstalk_of_an_array_at_4px_pitch() -> None:
    rng = np.random.default_rng(7)
    M, F = 16, 500
    centres = _grid(8, 4.2)
    x = (rng.integers(1, M + 1, (F, 64)) - 1) / (M - 1)
    frames = render_spots(x, centres, (50, 50), peak_dn=80, sigma_px=0.9, rng=rng)
    assert frames.max() < 255  # crosstalk only, no saturation
    roi = _spacing_over_noise(roi_mean(frames, centres, 5), x, M)
    spot = _spacing_over_noise(SpotLuminance(centres, 5).fit(frames[:300])(frames), x, M)
    # neighbours' light in the 5x5 ROI is interference; the template fit separates it
    assert spot > 1.5 * roi
    assert spot > 5.0


def test_spot_luminance_is_linear_where_the_roi_mean_saturates() -> None:
    rng = np.random.default_rng(3)
    M, F = 8, 400
    centres = _grid(2, 9.0)
    x = (rng.integers(1, M + 1, (F, 4)) - 1) / (M - 1)
    frames = render_spots(x, centres, (30, 30), peak_dn=900, sigma_px=1.0, rng=rng)
    assert (frames == 255).mean() > 0.005  # the cores clip
    L_roi = roi_mean(frames, centres, 5)
    L_spot = SpotLuminance(centres, 5).fit(frames)(frames)
    # per level means: the ROI mean bends over (top levels merge), the spot estimate does not
    lv = np.rint(x * (M - 1)).astype(int)
    steps_roi, steps_spot = [], []
    for i in range(4):
        m_roi = np.array([L_roi[lv[:, i] == s, i].mean() for s in range(M)])
        m_spot = np.array([L_spot[lv[:, i] == s, i].mean() for s in range(M)])
        steps_roi.append(np.diff(m_roi))
        steps_spot.append(np.diff(m_spot))
    steps_roi, steps_spot = np.array(steps_roi), np.array(steps_spot)
    assert (steps_roi[:, -1] / steps_roi[:, 0]).max() < 0.5  # ROI mean saturates
    ratio = steps_spot[:, -1] / steps_spot[:, 0]
    assert ratio.min() > 0.8 and ratio.max() < 1.25  # spot estimate stays linear
    assert _spacing_over_noise(L_spot, x, M) > 2 * _spacing_over_noise(L_roi, x, M)


def test_spot_luminance_needs_fit_and_a_block() -> None:
    s = SpotLuminance(np.array([[5.0, 5.0]]), 3)
    with pytest.raises(RuntimeError):
        s(np.zeros((2, 10, 10), np.uint8))
    with pytest.raises(ValueError):
        s.fit(np.zeros((3, 10, 10), np.uint8))


def test_spot_luminance_of_a_fully_saturated_window_is_not_dark() -> None:
    rng = np.random.default_rng(4)
    centres = np.array([[10.2, 10.4], [20.1, 10.7]])
    x = (rng.integers(1, 9, (300, 2)) - 1) / 7
    frames = render_spots(x, centres, (22, 30), peak_dn=20000, sigma_px=1.0, rng=rng)
    L = SpotLuminance(centres, 3).fit(frames)(frames)
    dark, lit = x == 0, x > 0
    # every lit frame saturates the whole 3x3 window: no information about the level is
    # left, but the estimate must stay far above the dark level (never collapse to 0)
    assert (frames[:, 9:12, 9:12][lit[:, 0]] == 255).all()
    assert L[lit].min() > 5 * L[dark].max()
