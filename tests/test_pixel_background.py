"""The per-pixel background (iscd.decode.tracking.luminance.PixelBackground) of the LED following:
its compiled kernel against the numpy reference over consecutive blocks (the state evolves
the same), and what it is for: the light above it stays put when a textured background
moves under the window.

Tolerances as tests/test_frame_kernels.py: positions 1e-4 px, luminance 1e-5 relative;
the background maps are float32 minima of the same pixels (exact) plus the same rises.
"""

from __future__ import annotations

import numpy as np
import pytest

from iscd.decode.tracking.detect import detect_array
from iscd.decode.tracking.follow_kernel import follow_and_measure_compiled
from iscd.decode.tracking.luminance import (PixelBackground, follow_and_measure, gather_patches,
                                     grid_sample)


@pytest.mark.parametrize("subtract", [True, False])
def test_the_kernel_keeps_the_same_background_as_the_reference(rendered_default, subtract: bool) -> None:
    L, R = rendered_default
    fl, fr = detect_array(L[:64], 8, 8), detect_array(R[:64], 8, 8)
    assert fl is not None and fr is not None
    shape = L.shape[1:]
    ref = [PixelBackground(shape), PixelBackground(shape)]
    fast = [PixelBackground(shape), PixelBackground(shape)]
    rng = np.random.default_rng(3)
    for a in range(64, 64 + 5 * 16, 16):
        starts = [fl.centers + rng.normal(0, 0.3, 2), fr.centers + rng.normal(0, 0.3, 2)]
        fr_l, fr_r = L[a:a + 16], R[a:a + 16]
        (a_l, a_r), (la, ra) = follow_and_measure([fr_l, fr_r], starts, 5, [1.2, 1.1],
                                                  use=grid_sample(8, 8), backgrounds=ref,
                                                  subtract=subtract)
        (b_l, b_r), (lb, rb) = follow_and_measure_compiled([fr_l, fr_r], starts, 5, [1.2, 1.1],
                                                           use=grid_sample(8, 8), backgrounds=fast,
                                                           subtract=subtract)
        for x, y in ((a_l, b_l), (a_r, b_r)):
            assert np.abs(x - y).max() < 1e-4
        for x, y in ((la, lb), (ra, rb)):
            assert np.all(np.abs(x - y) <= 1e-5 * np.maximum(np.abs(x), 1.0))
        for p, q in zip(ref, fast):
            np.testing.assert_array_equal(p.bg, q.bg)
            np.testing.assert_array_equal(p.stamp, q.stamp)
    # the maps hold only what the patches covered, there within what the frames showed
    seen = np.isfinite(ref[0].bg)
    assert 0 < seen.sum() < seen.size
    assert np.all(ref[0].bg[seen] >= L[64:144].min(0)[seen])
    assert np.all(ref[0].bg[seen] <= L[64:144].max(0)[seen] + 5 * ref[0].rise_dn)


def test_background_rises_once_per_block_and_follows_the_least_value() -> None:
    bg = PixelBackground((8, 8), rise_dn=0.5)
    fr = np.full((3, 8, 8), 20, np.uint8)
    fr[1, 2:5, 2:5] = 10
    p = gather_patches(fr, np.array([[3.0, 3.0], [3.4, 3.2]]), 1)  # two overlapping patches
    under = bg.update(p)
    assert np.all(under == 10)
    assert np.all(bg.bg[2:5, 2:5] == 10) and np.isinf(bg.bg[0, 0])
    fr[:] = 30
    under = bg.update(gather_patches(fr, np.array([[3.0, 3.0]]), 1))
    assert np.allclose(under, 10.5)  # one rise per block, however many patches cover a pixel
    with pytest.raises(ValueError, match="rise_dn"):
        PixelBackground((4, 4), rise_dn=-1.0)


def test_light_above_the_background_does_not_see_the_texture_the_spot_moves_over() -> None:
    """A steady spot that moves over a static textured background (an approaching LED's
    image moves against a far background; the right camera's disparity grows): the
    Gaussian mean changes with the texture under the window, the light above the
    per-pixel background (learnt from the dark frames) does not."""
    rng = np.random.default_rng(7)
    H = W = 48
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    n = 96
    lit = np.arange(n) % 2 == 0  # on, off, on, off ...
    tex = np.kron(rng.uniform(20, 80, size=(H // 2, W // 2)), np.ones((2, 2)))
    x_of = 20.0 + 4.0 * np.arange(n) / n  # 4 px over the run
    frames = np.empty((n, H, W), np.uint8)
    for f in range(n):
        img = tex.copy()
        if lit[f]:
            img += 100 * np.exp(-((xx - x_of[f]) ** 2 + (yy - 24) ** 2) / (2 * 1.2 ** 2))
        frames[f] = np.clip(np.rint(img), 0, 255)
    plain, above = [], []
    bgs = [PixelBackground((H, W)), PixelBackground((H, W))]
    for a in range(0, n, 16):
        blk = frames[a:a + 16]
        c = np.stack([x_of[a:a + 16], np.full(16, 24.0)], -1)[:, None, :]  # (F, 1, 2)
        _, (lum, _) = follow_and_measure([blk, blk], [c, c], 3, [1.5, 1.5])
        _, (lum_b, _) = follow_and_measure([blk, blk], [c, c], 3, [1.5, 1.5], backgrounds=bgs)
        plain.append(lum[:, 0])
        above.append(lum_b[:, 0])
    plain_on = np.concatenate(plain)[lit]
    above_on = np.concatenate(above)[lit]
    assert above_on.std() < 0.25 * plain_on.std()


def test_spot_size_kernel_matches_reference_and_grows_with_the_spot(rendered_default) -> None:
    """The lit spots' half-maximum area: compiled == reference (the same pixel counts);
    and a spot drawn twice as wide shows about four times the area."""
    L, R = rendered_default
    fl, fr = detect_array(L[:64], 8, 8), detect_array(R[:64], 8, 8)
    starts = [fl.centers, fr.centers]
    for bgs in (None, "bg"):
        b1 = None if bgs is None else [PixelBackground(L.shape[1:]), PixelBackground(L.shape[1:])]
        b2 = None if bgs is None else [PixelBackground(L.shape[1:]), PixelBackground(L.shape[1:])]
        i1, i2 = {}, {}
        follow_and_measure([L[64:96], R[64:96]], starts, 5, [1.2, 1.1], use=grid_sample(8, 8),
                           info=i1, backgrounds=b1, spot_radius_px=2.0)
        follow_and_measure_compiled([L[64:96], R[64:96]], starts, 5, [1.2, 1.1], use=grid_sample(8, 8),
                                    info=i2, backgrounds=b2, spot_radius_px=2.0)
        np.testing.assert_allclose(i1["spot_area"], i2["spot_area"], rtol=1e-12)
        assert np.all(i1["spot_area"] > 1)
    H = W = 40
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    areas = []
    for s in (1.0, 2.0):
        fr_ = np.empty((8, H, W), np.uint8)
        for f in range(8):
            fr_[f] = np.clip(np.rint(10 + 150 * np.exp(-((xx - 20.3) ** 2 + (yy - 19.6) ** 2) / (2 * s * s))
                                     * (f % 2)), 0, 255)
        info: dict = {}
        c = np.array([[20.3, 19.6]])
        follow_and_measure_compiled([fr_, fr_], [c, c], 3, [1.0, 1.0], info=info, spot_radius_px=8.0)
        areas.append(info["spot_area"][0])
    assert 3.0 < areas[1] / areas[0] < 5.0
    from iscd.decode.tracking.luminance import area_sigma

    assert abs(area_sigma(areas[1]) - 2.0) < 0.3


@pytest.mark.parametrize("moving", [False, True])
@pytest.mark.parametrize("spread", [1.0, 3.0])
@pytest.mark.parametrize("subtract", [True, False])
def test_kernel_background_paths_match_the_reference(moving: bool, spread: float, subtract: bool) -> None:
    """The kernel folds a block into the background over the patches' bounding box when
    they stay put and overlap (an array's), else patch by patch: both give the
    reference's maps bit for bit -- patches that move from frame to frame, LEDs spread
    wider than their patches, uint16 frames, a rise that is no binary fraction, pixels
    already at the block's stamp -- and the same centroids and luminance (to the
    reference's float32)."""
    rng = np.random.default_rng(11)
    H, W, F, K = 96, 112, 8, 5
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    gx, gy = np.meshgrid(np.arange(4), np.arange(3))
    centres = np.stack([50 + spread * 6.0 * (gx.ravel() - 1.5), 45 + spread * 6.0 * (gy.ravel() - 1)], -1)
    shape = (H, W)
    ref = [PixelBackground(shape, rise_dn=0.1), PixelBackground(shape, rise_dn=0.1)]
    fast = [PixelBackground(shape, rise_dn=0.1), PixelBackground(shape, rise_dn=0.1)]
    for blk in range(3):
        frames = []
        for cam in range(2):
            fr = rng.uniform(100, 900, (F, H, W))
            for f in range(F):
                for i, (x, y) in enumerate(centres):
                    if (f + i + blk) % 2:
                        fr[f] += 3000 * np.exp(-((xx - x - 0.3 * f) ** 2 + (yy - y) ** 2) / 2.0)
            frames.append(np.rint(fr).astype(np.uint16))
        st = centres + (rng.normal(0, 1.2, (F, len(centres), 2)) if moving else rng.normal(0, 0.3, 2))
        if blk == 2:  # pixels already stamped at this block (left as they are by the rise)
            for b in ref + fast:
                b.stamp[10:30, 20:40] = b.block + 1
        use = np.array([0, 2, 5, 7, 9, 11])
        kw = dict(use=use, subtract=subtract, spot_radius_px=2.0)
        i1: dict = {}
        i2: dict = {}
        (a_l, a_r), (la, ra) = follow_and_measure(frames, [st, st + 0.4], K, [1.0, 1.1], info=i1,
                                                  backgrounds=ref, **kw)
        (b_l, b_r), (lb, rb) = follow_and_measure_compiled(frames, [st, st + 0.4], K, [1.0, 1.1],
                                                           info=i2, backgrounds=fast, **kw)
        for x, y in ((a_l, b_l), (a_r, b_r)):
            assert np.abs(x - y).max() < 1e-4
        for x, y in ((la, lb), (ra, rb)):
            # (the reference sums partly in float32: up to ~2e-5 relative on these uint16 spots)
            assert np.all(np.abs(x - y) <= 1e-4 * np.maximum(np.abs(x), 1.0))
        np.testing.assert_allclose(i1["light"], i2["light"], rtol=1e-9)
        for p, q in zip(ref, fast):
            np.testing.assert_array_equal(p.bg, q.bg)
            np.testing.assert_array_equal(p.stamp, q.stamp)
    assert np.isfinite(fast[0].bg).sum() > 0
