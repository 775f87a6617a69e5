"""Following moving LED spots frame by frame (iscd.decode.tracking.luminance.refine_centres) and
the Gaussian-weighted luminance window (gauss_mean), against spots rendered at known
sub-pixel positions (pixel-integrated Gaussians, so the pixel phase is real)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iscd.decode.tracking.luminance import box_cover, gauss_mean, refine_centres, roi_mean


def _integrated_spots(centres: np.ndarray, amp: np.ndarray, shape: tuple[int, int], sigma: float,
                      background: float = 20.0, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """float frames (F, H, W): LED i of frame f is a Gaussian of RMS ``sigma`` px integrated
    over each pixel, centred at centres[f, i] (x, y), with total light amp[f, i] (DN px^2)."""
    F, N, _ = centres.shape
    H, W = shape
    erf = np.vectorize(math.erf)

    def cover(c: np.ndarray, n: int) -> np.ndarray:  # (F, N, n) pixel integrals along one axis
        edges = np.arange(n + 1) - 0.5
        cdf = 0.5 * (1 + erf((edges[None, None, :] - c[..., None]) / (sigma * math.sqrt(2))))
        return np.diff(cdf, axis=-1)

    gx, gy = cover(centres[..., 0], W), cover(centres[..., 1], H)
    img = background + np.einsum("fn,fny,fnx->fyx", amp, gy, gx)
    if noise:
        img = img + noise * np.random.default_rng(seed).standard_normal(img.shape)
    return img


def _grid(rows: int, pitch: float, x0: float = 20.0, y0: float = 18.0) -> np.ndarray:
    r, c = np.mgrid[0:rows, 0:rows]
    return np.stack([x0 + c.ravel() * pitch, y0 + r.ravel() * pitch], axis=1)


def test_box_cover_covers_the_box_exactly() -> None:
    c = np.array([3.0, 3.25, 3.5, 3.99])
    px = np.broadcast_to(np.arange(8, dtype=np.float32), (4, 8))
    w = box_cover(c, px, 3)
    np.testing.assert_allclose(w.sum(-1), 3.0, rtol=1e-6)
    # the weighted mean of the pixel positions is the box centre
    np.testing.assert_allclose((px * w).sum(-1) / 3.0, c, atol=1e-5)


def test_gauss_mean_is_the_same_at_every_sub_pixel_phase() -> None:
    """An LED moving across a pixel: the Gaussian window's value stays within 0.5 %, a
    3x3 ROI snapped to whole pixels changes by several %."""
    phases = np.linspace(0.0, 1.0, 21)
    centres = np.stack([30.0 + phases, 25.0 + 0.5 * phases], -1)[:, None, :]  # (F, 1, 2)
    frames = _integrated_spots(centres, np.full((phases.size, 1), 400.0), (50, 60), sigma=0.85,
                               background=0.0)
    g = gauss_mean(frames, centres, 0.85)[:, 0]
    box = roi_mean(frames, centres, 3)[:, 0]
    print(f"gauss {np.ptp(g) / g.mean():.4f}, 3x3 box {np.ptp(box) / box.mean():.4f}")
    assert np.ptp(g) / g.mean() < 5e-3
    assert np.ptp(box) / box.mean() > 10 * np.ptp(g) / g.mean()


def test_gauss_mean_matches_a_direct_weighted_sum() -> None:
    rng = np.random.default_rng(3)
    frames = rng.integers(0, 256, size=(4, 30, 40)).astype(np.uint8)
    centres = rng.uniform(3, 26, size=(4, 5, 2))
    got = gauss_mean(frames, centres, 1.2, radius=3)
    for f in range(4):
        for i in range(5):
            cx, cy = centres[f, i]
            xs = np.rint(cx) + np.arange(-3, 4)
            ys = np.rint(cy) + np.arange(-3, 4)
            w = np.exp(-((ys[:, None] - cy) ** 2 + (xs[None, :] - cx) ** 2) / (2 * 1.2 ** 2))
            pix = frames[f][np.ix_(ys.astype(int), xs.astype(int))].astype(float)
            assert got[f, i] == pytest.approx((w * pix).sum() / w.sum(), rel=1e-5)
    with pytest.raises(ValueError, match="sigma"):
        gauss_mean(frames, centres, 0.0)


@pytest.mark.parametrize("pitch", [4.2, 7.0])
def test_refine_centres_recovers_each_frames_shift_and_scale(pitch: float) -> None:
    """An 8x8 array whose frames are shifted (vibration, up to 0.6 px) and scaled (an
    approach, +-2 %) against the grid the tracker knows: refined to 0.02 px RMS, from
    0.3-0.5 px."""
    rng = np.random.default_rng(7)
    base = _grid(8, pitch)
    F = 24
    shift = rng.normal(0.0, 0.3, size=(F, 2))
    scale = 1.0 + rng.uniform(-0.02, 0.02, size=F)
    ctr = base.mean(0)
    true = ctr + (base - ctr)[None] * scale[:, None, None] + shift[:, None, :]
    amp = rng.integers(0, 8, size=(F, 64)) / 7.0 * 600.0  # PWM-8 levels, some LEDs dark
    frames = _integrated_spots(true, amp, (80, 80), sigma=0.85, noise=1.0, seed=1)
    got = refine_centres(frames, base, 3)
    err0 = np.sqrt(((base[None] - true) ** 2).sum(-1).mean())
    err = np.sqrt(((got - true) ** 2).sum(-1).mean())
    assert err0 > 0.3
    assert err < 0.02, (err0, err)


def test_refine_centres_single_led_and_dark_frames() -> None:
    """One LED: its shift alone (no scale); a frame without light keeps its centres."""
    true = np.array([[[20.3, 15.6]], [[19.8, 15.1]], [[20.0, 15.0]]])
    amp = np.array([[500.0], [300.0], [0.0]])
    frames = _integrated_spots(true, amp, (32, 40), sigma=0.9, noise=0.5)
    start = np.array([[20.0, 15.0]])
    got = refine_centres(frames, start, 3)
    np.testing.assert_allclose(got[:2], true[:2], atol=0.03)
    np.testing.assert_array_equal(got[2], start)
    with pytest.raises(ValueError, match="frames"):
        refine_centres(frames[0], start)


def test_a_dark_stretch_does_not_walk_the_centres_away() -> None:
    """A block in which every LED is dark (zero padding, a dark symbol run): with the light
    of a lit LED remembered from an earlier block, noise moves no LED (without it, a
    tenth of the block's own 90th percentile is noise, and the centres wander)."""
    base = _grid(8, 4.2)
    F = 16
    levels = np.random.default_rng(4).integers(0, 8, size=(F, 64)) / 7.0  # PWM-8 data, dark ones too
    lit = _integrated_spots(np.broadcast_to(base, (F, 64, 2)).copy(), levels * 600.0, (80, 80),
                            sigma=0.85, noise=1.0, seed=2)
    info: dict = {}
    from iscd.decode.tracking.luminance import gather_patches, refine_in_patches

    p = gather_patches(lit, base, 3)
    refine_in_patches(p, np.broadcast_to(base, (F, 64, 2)), 3, info=info)
    dark = _integrated_spots(np.broadcast_to(base, (F, 64, 2)).copy(), np.zeros((F, 64)), (80, 80),
                             sigma=0.85, noise=1.0, seed=3)
    start = base + 0.2
    pd = gather_patches(dark, start, 3)
    held = refine_in_patches(pd, np.broadcast_to(start, (F, 64, 2)), 3, lit_light=info["light"])
    np.testing.assert_array_equal(held, np.broadcast_to(start, (F, 64, 2)))
    wander = refine_in_patches(pd, np.broadcast_to(start, (F, 64, 2)), 3)
    assert np.abs(wander - start).max() > 0.05


def test_all_dark_frames_over_a_textured_background_do_not_move_the_leds() -> None:
    """A header's dark symbols over a textured background (the failure the 60 s daemon run
    found: the texture's own 'centroids' moved the LEDs by a pixel): the background is
    each pixel's least value over the block, so a dark frame keeps its centres and the lit
    frames are still followed."""
    rng = np.random.default_rng(5)
    base = _grid(8, 7.0)
    F = 16
    amp = rng.integers(0, 8, size=(F, 64)) / 7.0 * 3000.0
    amp[[4, 5, 11]] = 0.0  # three frames with every LED dark
    shift = rng.normal(0.0, 0.2, size=(F, 2))
    true = base[None] + shift[:, None, :]
    texture = rng.uniform(20.0, 80.0, size=(90, 90))
    frames = _integrated_spots(true, amp, (90, 90), sigma=1.2, background=0.0, noise=1.0, seed=6) + texture
    got = refine_centres(frames, base, 5)
    dark = [4, 5, 11]
    np.testing.assert_allclose(got[dark], np.broadcast_to(base, (3, 64, 2)), atol=1e-9)
    lit = [f for f in range(F) if f not in dark]
    assert np.sqrt(((got[lit] - true[lit]) ** 2).sum(-1).mean()) < 0.05  # texture +-30 DN per pixel
