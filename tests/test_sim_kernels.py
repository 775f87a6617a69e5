"""The compiled render kernels (iscd/sim/kernels.py) against their numpy references.

Tolerances: the cores and the sensor read-out are the same float32/float64 operations in the
same order as the references, the Gaussian draws the same cv2.randn stream, so the rendered
uint8 frames must be equal; only the glare's matrix products may round differently
(float64), so canvases agree to 1e-9 relative and a frame may differ by at most 1 grey level
in at most 1 pixel in 10^5 (where a signal sits on a rounding boundary; not seen so far).
"""

from __future__ import annotations

import numpy as np
import pytest

from iscd.core.config import default_config
from iscd.sim import ArraySource, Scene, kernels, sensor
from iscd.sim.presets import override, single_led

FRAMES = (0, 3, 511, 512, 1777)


def _configs() -> dict:
    d = default_config()
    return {
        "default": d,
        "moving": override(d, scene={"speed_mps": 11.0, "jitter_px": 0.3, "vibration_px": 0.5}),
        "flicker": override(d, scene={"distractors": [  # one overlapping the LED array
            {"x_m": 0.1, "y_m": 0.05, "z_m": 30.0, "diameter_m": 0.1, "brightness_dn": 200.0,
             "flicker_hz": 100.0},
            {"x_m": -2.0, "y_m": 0.5, "z_m": 35.0, "diameter_m": 0.2, "brightness_dn": 150.0,
             "flicker_hz": 120.0}]}),
        "edge": override(d, scene={"lateral_m": 2.2, "distance_m": 25.0}),  # clipped window
        "single_close": single_led(d, 4.0),
        "no_glare": override(d, optics={"glare_fraction": 0.0}),
        # the spot and motion models of issue 12: each through both paths
        "moffat": override(d, optics={"psf_model": "moffat", "psf_beta": 2.2,
                                      "right_defocus_px": 0.7}),
        "diffuser": override(d, optics={"diffuser_falloff": 0.6}),
        "power_glare": override(d, optics={"glare_model": "power", "glare_power": 1.8,
                                           "glare_fraction": 0.08}),
        "blooming": override(d, sensor={"blooming": 0.4}, scene={"distance_m": 12.0}),
        "blooming_single": override(single_led(d, 5.0), sensor={"blooming": 0.5}),
        "bumps_lateral": override(d, scene={"vibration_model": "bumps", "vibration_px": 0.4,
                                            "jitter_px": 0.05, "speed_mps": 20.0,
                                            "lateral_speed_mps": 0.8}),
        "engine": override(d, scene={"vibration_model": "engine", "vibration_px": 0.3}),
        "everything": override(d, optics={"psf_model": "moffat", "diffuser_falloff": 0.4,
                                          "glare_model": "power"},
                               sensor={"blooming": 0.3},
                               scene={"vibration_model": "bumps", "vibration_px": 0.3,
                                      "speed_mps": 11.0, "distractors": [
                                          {"x_m": 0.1, "y_m": 0.05, "z_m": 30.0,
                                           "diameter_m": 0.1, "brightness_dn": 200.0,
                                           "flicker_hz": 100.0}]}),
    }


def _assert_frames_agree(a: np.ndarray, b: np.ndarray) -> None:
    d = np.abs(a.astype(np.int16) - b.astype(np.int16))
    assert d.max() <= 1
    assert np.count_nonzero(d) <= max(1, a.size // 100_000)


@pytest.mark.parametrize("name", list(_configs()))
@pytest.mark.parametrize("noise", [False, True])
def test_compiled_scene_renders_the_reference_frames(name, noise):
    cfg = _configs()[name]
    fast = Scene(cfg, noise=noise)
    ref = Scene(cfg, noise=noise, compiled=False)
    for n in FRAMES:
        for a, b in zip(fast.render_pair(n), ref.render_pair(n)):
            _assert_frames_agree(a, b)
    if noise:  # fresh noise: frame n twice is the same, frame n + 1 is not
        np.testing.assert_array_equal(fast.render_pair(5)[0], fast.render_pair(5)[0])
        assert not np.array_equal(fast.render_pair(5)[0], fast.render_pair(6)[0])


def test_compiled_noise_statistics_in_the_window():
    # the temporal noise of pixels inside the LED window (fresh draws every frame, through
    # the compiled read-out) is shot + read + quantization, like the bank outside it
    cfg = override(default_config(), scene={"background": "flat", "distractors": []})
    s = Scene(cfg, ArraySource(np.ones((1, 64), int), repeat=True))  # level 1: dark LEDs
    g = s._plan(s.cams[0], *s._chunk(0))[0]
    X0, Y0, X1, Y1 = g.clip
    stack = np.stack([s.render_pair(n)[0] for n in range(400)]).astype(np.float64)
    inside = stack[:, Y0 + 5:Y1 - 5, X0 + 5:X1 - 5]
    outside = stack[:, 20:60, 20:60]
    k = 255 / cfg.sensor.full_well_e
    expect = np.sqrt(40 * k + (cfg.sensor.read_noise_e * k) ** 2 + 1 / 12)
    assert inside.std(axis=0).mean() == pytest.approx(expect, rel=0.1)
    assert inside.mean() == pytest.approx(outside.mean(), abs=0.05)
    # the bank repeats 16 realizations: its std over many frames is sqrt(15/16) of the true
    assert (outside.std(axis=0).mean() / np.sqrt(15 / 16)
            == pytest.approx(inside.std(axis=0).mean(), rel=0.05))
    z = (inside - inside.mean(axis=0)) / inside.std(axis=0)  # Gaussian-shaped (quantized)
    assert np.mean(np.abs(z) > 2) == pytest.approx(0.0455, abs=0.012)


def test_copy_frame_matches_numpy():
    src = np.random.default_rng(1).integers(0, 256, (40, 50), dtype=np.uint8)
    for oy, ox in ((0, 0), (3, 7), (8, 10)):
        a = np.empty((32, 40), np.uint8)
        b = np.empty((32, 40), np.uint8)
        kernels.copy_frame(a, src, oy, ox)
        kernels.copy_frame_ref(b, src, oy, ox)
        np.testing.assert_array_equal(a, b)


def _window_args(grid: bool, glare: bool, noise: bool) -> tuple:
    rng = np.random.default_rng(7)
    H, W, k = 30, 34, 5
    n = 6
    kern = rng.uniform(0, 1, (n, k, k)).astype(np.float32)
    ix = rng.integers(0, W - k, n)
    iy = rng.integers(0, H - k, n)
    w = rng.uniform(0, 1, n)
    m, q = (2, 3) if grid else (n, n)
    gy = rng.uniform(0, 0.2, (H, m)) if glare else np.zeros((H, 0))
    gy[gy < 0.02] = 0.0  # exact zeros are skipped
    gxt = rng.uniform(0, 0.2, (q, W)) if glare else np.zeros((0, W))
    bg = rng.uniform(0, 60, (H + 10, W + 10)).astype(np.float32)
    prnu = rng.normal(1, 0.01, (H + 10, W + 10)).astype(np.float32)
    z = rng.standard_normal((H - 4, W - 6)).astype(np.float32)
    sensor = kernels.sensor_constants(255 / 20000, 20 * 255 / 20000, 2.0, 255)
    return (1, 2, np.full((H, W), 3.0), 2, 3, True, kern, ix, iy, w, 300.0, 0.9, 1.7, gy, gxt,
            q if grid else 0, bg, prnu, 4, 5, z, noise, sensor)


@pytest.mark.parametrize("grid,glare,noise", [(True, True, True), (False, True, True),
                                              (True, False, False), (False, True, False)])
def test_render_window_matches_reference(grid, glare, noise):
    args = _window_args(grid, glare, noise)
    acc_a, acc_b = args[2].copy(), args[2].copy()
    out_a = np.zeros((40, 45), np.uint8)
    out_b = out_a.copy()
    kernels.render_window(out_a, args[0], args[1], acc_a, *args[3:])
    kernels.render_window_ref(out_b, args[0], args[1], acc_b, *args[3:])
    _assert_frames_agree(out_a, out_b)
    assert out_a.max() > 0
    # the canvases agree on the rows read out (the fused kernel adds the glare only there)
    h = args[20].shape[0]
    np.testing.assert_allclose(acc_a[2:2 + h], acc_b[2:2 + h], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("grid", [True, False])
def test_add_sources_matches_reference(grid):
    a = _window_args(grid, True, True)
    acc = [np.full(a[2].shape, 3.0) for _ in range(4)]
    for clear in (True, False):
        kernels.add_sources(acc[0 + 2 * (not clear)], clear, *a[6:16])
        kernels.add_sources_ref(acc[1 + 2 * (not clear)], clear, *a[6:16])
    np.testing.assert_allclose(acc[0], acc[1], rtol=1e-12)
    np.testing.assert_allclose(acc[2], acc[3], rtol=1e-12)
    np.testing.assert_allclose(acc[2] - acc[0], 3.0, rtol=1e-9)  # clear=False adds


@pytest.mark.parametrize("shape", [(30, 12), (7, 3), (1, 5)])
def test_bloom_columns_matches_reference(shape):
    rng = np.random.default_rng(3)
    acc = rng.uniform(0, 600, shape)
    acc[rng.uniform(size=shape) < 0.5] = 0.0
    coef = sensor.bloom_coefficients(0.4, 2.0)
    assert 2 * coef.sum() == pytest.approx(0.4)
    a, b = acc.copy(), acc.copy()
    kernels.bloom_columns(a, 255.0, 0.4, coef)
    kernels.bloom_columns_ref(b, 255.0, 0.4, coef)
    np.testing.assert_array_equal(a, b)
    # charge moves only from pixels above full well, only along columns
    ex = np.maximum(acc - 255.0, 0.0)
    lost = 0.4 * ex.sum()
    gained = (a - acc + 0.4 * ex).sum()
    assert gained <= lost + 1e-9
    quiet = ex.sum(axis=0) == 0
    np.testing.assert_array_equal(a[:, quiet], acc[:, quiet])


def test_blooming_scene_warm_up_compiles_its_kernel():
    cfg = _configs()["blooming"]
    s = Scene(cfg)
    s.warm_up()
    n = len(kernels.bloom_columns.signatures)
    assert n >= 1
    s.render_pair(3)
    assert len(kernels.bloom_columns.signatures) == n


def test_warm_up_compiles_what_the_scene_calls():
    # after Scene.warm_up() rendering compiles nothing new (a paced mock rig must not stall
    # on its first frames): the warm-up arguments have the types the scene passes
    fs = (kernels.copy_frame, kernels.add_sources, kernels.expose_window, kernels.render_window)
    Scene(default_config()).warm_up()
    before = [len(f.signatures) for f in fs]
    assert all(before)  # compiled (or loaded from the cache)
    for name in ("default", "moving", "flicker"):
        for noise in (False, True):
            Scene(_configs()[name], noise=noise).render_pair(3)
    assert [len(f.signatures) for f in fs] == before
