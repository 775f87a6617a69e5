"""One LED followed in the background's own frame (issue 12; iscd.decode.tracking.stabilize and
RegisteredBackground.predict_shifts): the stabilizing copy against its numpy reference, the
predicted shifts against known ones with the map's state left untouched, and, on randomized
motion scenes the receiver was not tuned on, the following and the packets against the
simulator's truth with the setting on and off."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from iscd.decode.tracking.registered_background import (RegisteredBackground, measure_block,
                                                        measure_block_reference, window_half)
from iscd.decode.tracking.stabilize import _stabilize_kernel, stabilize_into, stabilize_reference
from scenes import assert_delivered_only_with, following_errors, motion_scene

H = W = 64


# ----------------------------------------------------------------------------- the copy

@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_the_kernel_matches_the_reference_and_writes_only_the_box(dtype) -> None:
    rng = np.random.default_rng(7)
    frames = rng.integers(0, 250, (5, 40, 48)).astype(dtype)
    shifts = rng.integers(-8, 9, (5, 2))
    shifts[0] = (0, 0)
    shifts[1] = (-8, 8)  # reads past the frame's edges: the nearest edge pixel
    for box in [(3, 5, 30, 33), (-4, -6, 60, 50), (40, 2, 48, 40)]:
        a = np.full((7, 40, 48), 77, dtype)
        b = a.copy()
        stabilize_into(frames, shifts, box, a)
        stabilize_reference(frames, shifts, box, b)
        np.testing.assert_array_equal(a, b)
        x0, y0, x1, y1 = max(box[0], 0), max(box[1], 0), min(box[2], 48), min(box[3], 40)
        outside = np.ones((40, 48), bool)
        outside[y0:y1, x0:x1] = False
        assert (a[:, outside] == 77).all() and (a[5:] == 77).all()
    # frame 0 unshifted: its box is the frame itself; frame 1's pixel (x, y) is frame (x - 8, y + 8)
    np.testing.assert_array_equal(a[0, 2:40, 40:48], frames[0, 2:40, 40:48])
    np.testing.assert_array_equal(a[1, 2:32, 40:48], frames[1, 10:40, 32:40])
    np.testing.assert_array_equal(a[1, 32:40, 40:48], np.broadcast_to(frames[1, 39:40, 32:40], (8, 8)))
    assert _stabilize_kernel.signatures


def test_bad_buffers_are_refused_with_a_clear_message() -> None:
    fr = np.zeros((2, 8, 8), np.uint8)
    with pytest.raises(ValueError, match="out: expected dtype"):
        stabilize_into(fr, np.zeros((2, 2), np.int64), (0, 0, 8, 8), np.zeros((2, 8, 8), np.uint16))
    with pytest.raises(ValueError, match="out: expected at least"):
        stabilize_into(fr, np.zeros((2, 2), np.int64), (0, 0, 8, 8), np.zeros((1, 8, 8), np.uint8))
    with pytest.raises(ValueError, match="shifts: expected"):
        stabilize_into(fr, np.zeros((3, 2), np.int64), (0, 0, 8, 8), np.zeros((2, 8, 8), np.uint8))


# ----------------------------------------------------------------------------- predicted shifts

def _moving_texture(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A textured background with one dim LED at (32.4, 31.6), the whole image moved by a
    known whole-pixel vibration (n, 2); frames, centres (n, 1, 2), shifts."""
    rng = np.random.default_rng(seed)
    m = 12
    tex = gaussian_filter(rng.normal(size=(H + 2 * m, W + 2 * m)), 1.2)
    tex = 40.0 + 25.0 * tex / tex.std()
    t = np.arange(n)
    ph = rng.uniform(0, 2 * np.pi, 2)
    sh = np.rint(np.stack([1.5 * np.sin(2 * np.pi * t / 37.0 + ph[0]),
                           1.3 * np.sin(2 * np.pi * t / 23.0 + ph[1])], axis=1)).astype(np.int64)
    ys, xs = np.mgrid[0:H, 0:W]
    frames = np.empty((n, H, W), np.uint8)
    centres = np.empty((n, 1, 2))
    lv = rng.integers(0, 8, n)
    lv[::8] = 0
    for f in range(n):
        sx, sy = sh[f]
        img = tex[m - sy:m - sy + H, m - sx:m - sx + W].copy()
        cx, cy = 32.4 + sx, 31.6 + sy
        img += 15.0 * lv[f] * np.exp(-((xs - cx) ** 2 + (ys - cy) ** 2) / (2 * 0.9 ** 2))
        frames[f] = np.clip(np.rint(img + rng.normal(0, 1.0, img.shape)), 0, 255).astype(np.uint8)
        centres[f, 0] = cx, cy
    return frames, centres, sh


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_predicted_shifts_are_the_known_ones_and_change_nothing(seed: int) -> None:
    """After a few blocks have built the map, the shifts predicted for the next blocks from
    where the LED was (the last block's last centre, not where it is) are the true image
    shifts (relative to the map's origin) in >= 95 % of the frames; the map, the last
    shift, the running level and the hint state are as they were; the measurement of the
    same block then finds the same shifts in >= 95 % of its frames."""
    n = 256
    frames, centres, sh = _moving_texture(n, seed)
    bg = RegisteredBackground((H, W))
    for s in range(0, 64, 16):
        bg.measure(frames[s:s + 16], centres[s:s + 16], 1.0)
    origin = sh[0]
    agree_pred = agree_meas = 0
    for s in range(64, n, 16):
        before = copy.deepcopy(bg.__dict__)
        guess = np.broadcast_to(centres[s - 1], (16, 1, 2))
        pred = bg.predict_shifts(frames[s:s + 16], guess, 1.0)
        for k, v in before.items():
            now = getattr(bg, k)
            if isinstance(v, np.ndarray):
                np.testing.assert_array_equal(now, v, err_msg=k)  # (NaN equal to NaN)
            else:
                assert now == v, k
        _, got = bg.measure(frames[s:s + 16], centres[s:s + 16], 1.0)
        truth = sh[s:s + 16] - origin
        agree_pred += int((pred == truth).all(axis=1).sum())
        agree_meas += int((pred == got).all(axis=1).sum())
    total = n - 64
    print(f"predicted = truth in {agree_pred}/{total} frames, = measured in {agree_meas}/{total}")
    assert agree_pred >= 0.95 * total
    assert agree_meas >= 0.95 * total
    assert (np.abs(sh[64:] - origin) >= 1).any()  # the image did move


def test_the_shifts_only_kernel_matches_the_reference_and_leaves_the_map() -> None:
    frames, centres, _ = _moving_texture(48, 4)
    bg = RegisteredBackground((H, W))
    bg.measure(frames[:32], centres[:32], 1.0)
    outs = []
    for fn in (measure_block, measure_block_reference):
        b, st = bg.bg.copy(), bg.stamp.copy()
        shift, level = bg.shift.copy(), bg.level.copy()
        lum = np.full((16, 1), -5.0)
        shifts = np.zeros((16, 2), np.int64)
        fn(frames[32:], np.ascontiguousarray(centres[32:]), 1.0, window_half(1.0), 3, b, st, bg.block + 1,
           0.25, 8, shift, level, lum, shifts, np.zeros((0, 2), np.int64), np.full(16, np.nan), False,
           False, np.zeros((16, 2)))
        np.testing.assert_array_equal(b, bg.bg)
        np.testing.assert_array_equal(st, bg.stamp)
        assert (lum == -5.0).all()  # not written
        outs.append((shifts, shift, level))
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_array_equal(outs[0][1], outs[1][1])
    np.testing.assert_allclose(outs[0][2], outs[1][2], rtol=1e-9)


# ----------------------------------------------------------------------------- rendered scenes

def _motion_cfg(key: str, seed: int, model: str, stabilized: bool):
    # the stereo hold (session 34) puts a camera that walks off back beside the other one;
    # these tests measure the following itself, as when they were written, over a background
    # read at whole pixels only (with the residual shift fitted, session 36, 919376006 is
    # delivered followed in the image too)
    return motion_scene(key, seed, model, stabilized_following=stabilized, stereo_hold=False,
                        registered_subpixel=False)


_following_errors = following_errors


def test_a_dim_led_beside_a_texture_edge_is_followed_in_the_backgrounds_frame() -> None:
    """Randomized scene 957526840 of set 60001 (one LED closing from 100 m at 100 km/h, engine
    vibration 0.5 px RMS; issue 12, session 26): an 18 DN texture edge runs 3 px above the
    LED. Followed in the image, the light the image-indexed background leaves above that
    edge as the image moves pulled both cameras' centroids onto it (3.8 px off for 10
    frames, lit ones among them); followed in the background's own frame, every frame of
    the first 400 in which the LED is on for at least a quarter of the exposure is within
    1 px of the truth, and fewer frames of any kind are more than 1 px off. (The frames
    still off are dark or at level 2 of 8, at the ends of blocks: the path's extrapolation.)"""
    n = 400
    on, lit = _following_errors(_motion_cfg("1led-100kmh-0.5px", 957526840, "engine", True), n)
    off, lit_off = _following_errors(_motion_cfg("1led-100kmh-0.5px", 957526840, "engine", False), n)
    np.testing.assert_array_equal(lit, lit_off)
    bright = lit >= 0.25
    print(f"stabilized: worst {on.max():.2f} px ({on[:, bright].max():.2f} lit), > 1 px {(on > 1).mean():.3f}; "
          f"in the image: worst {off.max():.2f} px ({off[:, bright].max():.2f} lit), > 1 px {(off > 1).mean():.3f}")
    assert on.shape[1] >= 300 and bright.sum() >= 150
    assert on[:, bright].max() <= 1.0
    assert off[:, bright].max() >= 3.0  # the failure is there without it
    assert (on > 1).mean() < 0.5 * (off > 1).mean()


def test_a_road_bump_between_two_fits_is_taken_out_by_the_image_shifts(monkeypatch: pytest.MonkeyPatch) -> None:
    """Randomized scene 2103417577 of set 62001 (one LED from 100 m at 100 km/h, road bumps
    0.5 px RMS; issue 12, session 26): a bump moved the image from +3.1 to -1.4 px within 32
    frames, so the followed LED was 4.4 px from the last grid fit (an average over the
    frames before the bump), beyond what counts as lost (2.8 px with the fits' own swing),
    and following restarted at that stale fit, 5 px off, for two blocks. Compared in the
    background's frame (the followed centres less their frame's image shift, the fit less
    its interval's mean shift: StreamDecoder._still_distance) the LED had not moved: every
    lit frame (on for >= 1/4 of the exposure) of frames 64-480 within 1 px of the truth,
    against >= 3 px without that comparison."""
    from iscd.decode.stream import StreamDecoder

    cfg = _motion_cfg("1led-100kmh-0.5px", 2103417577, "bumps", True)
    on, lit = _following_errors(cfg, 480)
    monkeypatch.setattr(StreamDecoder, "_still_distance", lambda self, side, prev, fit: float("inf"))
    off, _ = _following_errors(cfg, 480)
    bright = lit >= 0.25
    print(f"with: worst lit {on[:, bright].max():.2f} px; without: {off[:, bright].max():.2f} px")
    assert bright.sum() >= 150
    assert on[:, bright].max() <= 1.0
    assert off[:, bright].max() >= 3.0


@pytest.mark.parametrize("key, seed, model", [
    ("1led-100kmh-0.5px", 957526840, "engine"),
    pytest.param("1led-100kmh-0.5px", 2103417577, "bumps", marks=pytest.mark.slow),
    pytest.param("1led-40kmh-0.3px", 919376006, "smooth", marks=pytest.mark.slow)])
def test_packets_lost_to_the_texture_under_a_dim_led_are_delivered(key: str, seed: int, model: str) -> None:
    """Three randomized scenes of sets 60001 and 62001 that lost a packet to the following
    (the oracle's "+true positions" stage decoded them; 919376006: centres 1-3 px off in dim
    frames over a high-contrast texture; 2103417577: the road bump above): with the
    following in the background's own frame both packets are bit-exact; followed in the
    image, one is lost."""
    assert_delivered_only_with(_motion_cfg(key, seed, model, True), _motion_cfg(key, seed, model, False),
                               "the stabilized following")


def test_one_leds_live_path_compiles_nothing_after_the_warm_up() -> None:
    """One LED under road bumps, decoded as the daemon does after iscd.core.jit.warm_up()
    (writable block buffers): the stabilized following and the shift prediction run (the
    registered background's shifts are set) and no kernel compiles again."""
    from iscd.core import jit
    from iscd.core.config import default_config
    from iscd.decode.stream import StreamDecoder
    from iscd.sim.presets import override, single_led
    from iscd.sim.scene import Scene

    cfg = override(single_led(default_config(), 40.0), scene={"vibration_model": "bumps", "vibration_px": 0.5})
    sc = Scene(cfg)
    dec = StreamDecoder(cfg)
    jit.warm_up()
    before = jit.signatures()
    bl = np.empty((16, sc.height, sc.width), np.uint8)
    br = np.empty_like(bl)
    for s in range(0, 320, 16):
        for i in range(16):
            sc.render_pair_into(s + i, bl[i], br[i])
        ids = np.arange(s, s + 16)
        dec.push(ids, ids / sc.fps, bl, br)
    assert dec.track is not None and dec.image_shifts[0] is not None
    after = jit.signatures()
    assert {k: v for k, v in after.items() if v != before.get(k)} == {}
    dec.close()
