"""Following along the LEDs' path through a block (issue 12): iscd.decode.tracking.trajectory
and its compiled twins in iscd.decode.tracking.path_kernel."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.decode.tracking.follow_kernel import follow_and_measure_compiled
from iscd.decode.tracking.luminance import Patches, PixelBackground, follow_and_measure, gather_patches
from iscd.decode.tracking.path_kernel import path_block_compiled
from iscd.decode.tracking.trajectory import (FINAL_LIT_SHARE, LIT_SHARE, REACH_SIGMAS, SIGMA_FRAMES,
                                             follow_path, frame_weights, held_floor, path_block,
                                             smooth_path)
from test_rx_follow import _integrated_spots

SIZE = 5
SIGMA = 0.9


def _bump_block(F: int = 32, amp_px: float = 3.0, seed: int = 0, sway_px: float = 0.4,
                texture_dn: float = 6.0):
    """One LED that a road bump carries ``amp_px`` px up within the block (a damped 12 Hz
    ring), switched as PWM symbols (2 frames a symbol, some dark, some partial), over a
    textured background; returns uint8 frames, the true centres (F, 1, 2) and the on share."""
    rng = np.random.default_rng(seed)
    t = np.arange(F) / 1000.0
    y = 24.0 + amp_px * (1 - np.exp(-t / 0.012) * np.cos(2 * np.pi * 12 * t))
    x = 25.3 + sway_px * np.sin(2 * np.pi * 9 * t)
    centres = np.stack([x, y], axis=-1)[:, None, :]
    on = np.repeat(rng.choice([0.0, 0.3, 0.6, 1.0], size=(F + 1) // 2), 2)[:F]
    on[:4] = 1.0  # lit at the start (the block starts where the last one ended, on the spot)
    img = _integrated_spots(centres, 900.0 * on[:, None], (48, 48), SIGMA, background=30.0,
                            noise=1.0, seed=seed)
    tex = texture_dn * np.sin(np.arange(48)[None, :] / 2.3) * np.cos(np.arange(48)[:, None] / 3.1)
    frames = np.clip(img + tex[None], 0, 255).round().astype(np.uint8)
    return frames, centres, on


def _follow(frames, start, passes, compiled=True):
    follow = follow_and_measure_compiled if compiled else follow_and_measure
    st = [start, start]
    if passes == 0:
        (c, _), (lum, _) = follow([frames, frames], st, SIZE, [SIGMA, SIGMA])
        return c, lum
    res = follow_path(follow, [frames, frames], st, SIZE, [SIGMA, SIGMA], [None, None],
                      [start, start], passes=passes, compiled=compiled)
    return res.centres[0], res.luminance[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_bump_of_3px_within_a_block_is_followed_on_every_lit_frame(seed: int) -> None:
    frames, truth, on = _bump_block(seed=seed)
    start = truth[0]
    err = lambda c: np.linalg.norm(c[:, 0] - truth[:, 0], axis=-1)  # noqa: E731
    lit, dark = on >= 0.6, on == 0
    one = err(_follow(frames, start, 0)[0])
    assert one[lit].max() > 1.0  # one pass from the block's start cannot reach (1.5 px per pass)
    c, _ = _follow(frames, start, 3)
    e = err(c)
    # the box centroid over this texture is biased by ~0.1 px where the spot stands still
    # (the block's first frames, one pass alike)
    assert e[lit].max() < 0.25
    assert e[dark].max() < 0.4  # bridged on the path, not left at the block's start
    assert np.median(e[dark]) < 0.25


def test_reference_and_compiled_follow_path_agree_on_rendered_frames() -> None:
    frames, truth, _ = _bump_block(seed=4)
    c1, l1 = _follow(frames, truth[0], 3, compiled=True)
    c2, l2 = _follow(frames, truth[0], 3, compiled=False)
    # the reference's patches are float32, the kernel's sums float64 (as for one pass)
    np.testing.assert_allclose(c1, c2, atol=1e-3)
    np.testing.assert_allclose(l1, l2, rtol=1e-4, atol=1e-3)


def test_a_still_led_needs_no_further_pass_and_keeps_its_luminance() -> None:
    """A spot that does not move (over a flat background: a texture biases a dim frame's box
    centroid by tenths of a px, one pass alike): the path settles at once (no second pass)
    and the lit frames' luminance is the one pass's own."""
    frames, truth, _ = _bump_block(amp_px=0.0, seed=5, sway_px=0.0, texture_dn=0.0)
    frames = frames.copy()
    st = [truth[0], truth[0]]
    res = follow_path(follow_and_measure_compiled, [frames, frames], st, SIZE, [SIGMA, SIGMA],
                      [None, None], [None, None])
    assert res.passes == 0
    (c, _), (lum, _) = follow_and_measure_compiled([frames, frames], st, SIZE, [SIGMA, SIGMA])
    moved = np.abs(c - truth[0]).max(axis=(1, 2)) > 0
    np.testing.assert_allclose(res.luminance[0][moved], lum[moved], rtol=0.01)


def test_smooth_path_follows_a_line_through_dark_stretches_without_lag() -> None:
    """Lit frames on one side of a frame do not drag it back (a locally linear fit), and
    a dark stretch is bridged linearly, from the anchor at the block's start."""
    F = 30
    t = np.arange(F, dtype=float)
    true = np.stack([10 + 0.2 * t, 5 - 0.1 * t], axis=-1)[:, None, :]
    w = np.ones(F)
    w[8:16] = 0  # dark in the middle
    w[:3] = 0  # and at the start
    anchor = true[0] - np.array([[0.2, -0.1]])  # frame -1
    p = smooth_path(true, w, anchor)
    np.testing.assert_allclose(p, true, atol=1e-9)
    assert np.allclose(smooth_path(true, np.zeros(F), anchor), anchor[None])
    np.testing.assert_allclose(smooth_path(true, np.zeros(F)), true)


def test_frame_weights_count_only_lit_leds_above_the_floor() -> None:
    lum = np.array([[10.0, 10.0], [110.0, 12.0], [60.0, 10.0], [20.0, np.nan]])
    w = frame_weights(lum, np.array([10.0, 10.0]), lit_share=0.25)
    # LED 0: 90th percentile 85 -> lit above 21.25 (frames 1, 2); LED 1 p90 1.4 -> frame 1
    np.testing.assert_allclose(w, [0.0, 100.0 + 2.0, 50.0, 0.0])
    np.testing.assert_allclose(frame_weights(lum, np.array([10.0, 10.0]), np.array([1])), [0, 2, 0, 0])


def test_held_floor_takes_the_lowest_and_rises_slowly() -> None:
    f = held_floor(None, np.array([[5.0], [3.0]]))
    assert f.tolist() == [3.0]
    assert held_floor(f, np.array([[9.0]]), rise_dn=1.0).tolist() == [4.0]
    assert held_floor(f, np.array([[2.0]])).tolist() == [2.0]


def test_compiled_path_block_equals_the_reference() -> None:
    rng = np.random.default_rng(7)
    worst = 0.0
    kw = dict(lit_share=LIT_SHARE, final_share=FINAL_LIT_SHARE, sigma_frames=SIGMA_FRAMES,
              reach_sigmas=REACH_SIGMAS)
    for _ in range(200):
        F, N, G = int(rng.integers(1, 40)), int(rng.integers(1, 6)), int(rng.integers(1, 3))
        cs, lums, curs, floors, anchors = [], [], [], [], []
        for _g in range(G):
            c = rng.normal(50, 2, (F, N, 2))
            cur = c + rng.normal(0, 0.5, (F, N, 2))
            dark = rng.random(F) < 0.3
            c[dark] = cur[dark]  # frames the following did not refine
            lum = rng.uniform(0, 200, (F, N))
            lum[rng.random((F, N)) < 0.2] = np.nan
            cs.append(c), curs.append(cur), lums.append(lum), floors.append(rng.uniform(0, 50, N))
            anchors.append(None if rng.random() < 0.3 else rng.normal(50, 2, (N, 2)))
        use = None if rng.random() < 0.5 else np.sort(rng.choice(N, int(rng.integers(1, N + 1)), replace=False))
        p1, m1, f1, x1 = path_block(cs, lums, curs, floors, anchors, use, **kw)
        p2, m2, f2, x2 = path_block_compiled(cs, lums, curs, floors, anchors, use, **kw)
        worst = max(worst, abs(m1 - m2), abs(x1 - x2), *(np.abs(a - b).max() for a, b in zip(p1, p2)),
                    *(np.abs(a - b).max() for a, b in zip(f1, f2)))
    assert worst < 1e-9


def test_a_background_folded_again_for_the_same_block_is_not_relaxed_twice() -> None:
    """Later passes give the backgrounds the block again (new_block=False): the map is the
    one a single fold gives."""
    frames, truth, _ = _bump_block(seed=3)
    a, b = PixelBackground(frames.shape[1:], 0.5), PixelBackground(frames.shape[1:], 0.5)
    p = gather_patches(frames, truth, 6)
    for _ in range(2):
        a.update(Patches(p.pix, p.x0, p.y0))
        b.update(Patches(p.pix, p.x0, p.y0))
        b.update(Patches(p.pix, p.x0, p.y0), new_block=False)
    np.testing.assert_array_equal(a.bg, b.bg)
    assert a.block == b.block == 2


def test_the_path_of_stabilized_frames_is_smoothed_in_image_positions() -> None:
    """Frames held still by whole-pixel image shifts (iscd.decode.tracking.stabilize; one LED,
    issue 12 session 26): a bump that carries the spot 3 px moves it smoothly in the image,
    but in the stabilized frames its sub-pixel rest jumps by 1 px wherever the rounded shift
    steps. With ``offsets`` the path is smoothed in image positions: the dark frames'
    bridged centres are as close to the truth as when the image itself is followed; smoothed
    in the stabilized frames' positions they are further off."""
    from iscd.decode.tracking.stabilize import stabilize_into

    frames, truth, on = _bump_block(seed=3, texture_dn=0.0)
    F = frames.shape[0]
    shifts = np.zeros((F, 2), np.int64)
    shifts[:, 1] = np.rint(truth[:, 0, 1] - truth[0, 0, 1]).astype(np.int64)
    assert len(set(shifts[:, 1].tolist())) >= 3  # the rounded shift steps within the block
    stab = stabilize_into(frames, shifts, (0, 0, 48, 48), np.zeros_like(frames)).copy()
    start = truth[0]
    dark = on == 0

    def image_err(offsets):
        res = follow_path(follow_and_measure_compiled, [stab, stab], [start, start], SIZE, [SIGMA, SIGMA],
                          [None, None], [start, start], offsets=offsets)
        c = res.centres[0] + shifts[:, None, :]
        return np.linalg.norm(c[:, 0] - truth[:, 0], axis=-1), res

    with_off, res = image_err([shifts, shifts])
    without, _ = image_err(None)
    direct = np.linalg.norm(_follow(frames, start, 3)[0][:, 0] - truth[:, 0], axis=-1)
    print(f"dark frames' worst error: offsets {with_off[dark].max():.2f} px, stabilized positions "
          f"{without[dark].max():.2f} px, the image followed {direct[dark].max():.2f} px")
    assert with_off[on >= 0.6].max() < 0.25
    assert with_off[dark].max() <= direct[dark].max() + 0.1
    assert without[dark].max() > with_off[dark].max() + 0.2
    # the path's end is an image position (the next block's anchor)
    assert np.abs(res.path_end[0] - truth[-1]).max() < 0.5
