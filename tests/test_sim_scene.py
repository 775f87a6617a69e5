"""The rendered scene against its own ground truth (fixed seeds, noise off unless noted)."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.core.config import default_config
from iscd.sim import ArraySource, Scene, Truth
from iscd.sim.optics import spot_size_px
from iscd.sim.presets import override, single_led

DARK = 2.0  # sensor.dark_dn default


def _led_scene(distance_m: float, level: int, *, noise: bool = False, **scene) -> Scene:
    cfg = single_led(default_config(), distance_m, background="none", distractors=[],
                     led_phase_s=0.0, led_drift_ppm=0.0, **scene)
    return Scene(cfg, ArraySource(np.full((1, 1), level), repeat=True), noise=noise)


def _window(img: np.ndarray, u: float, v: float, half: int = 9) -> tuple[np.ndarray, int, int]:
    x0, y0 = int(round(u)) - half, int(round(v)) - half
    return img[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1].astype(np.float64) - DARK, x0, y0


def _centroid(img: np.ndarray, u: float, v: float) -> tuple[float, float]:
    w, x0, y0 = _window(img, u, v)
    w = np.clip(w, 0, None)
    ys, xs = np.mgrid[:w.shape[0], :w.shape[1]]
    return x0 + (w * xs).sum() / w.sum(), y0 + (w * ys).sum() / w.sum()


def test_truth_disparity_is_fb_over_z():
    s = _led_scene(20.0, 3)
    t = s.truth(np.arange(5))
    np.testing.assert_allclose(t.disparity_px, 105.0)
    np.testing.assert_allclose(t.u_left - t.u_right, 105.0)
    assert t.u_left[0, 0] == pytest.approx(255.5)  # on axis: the image centre


@pytest.mark.parametrize("distance_m,lateral_m,vertical_m", [
    (20.0, 0.0113, -0.0071), (23.7, -0.2, 0.05), (41.3, 0.31, 0.13), (58.9, -0.05, -0.4)])
def test_rendered_centroid_disparity_matches_truth(distance_m, lateral_m, vertical_m):
    # level 3 of 8 keeps the spot unsaturated at every distance
    s = _led_scene(distance_m, 3, lateral_m=lateral_m, vertical_m=vertical_m)
    t = s.truth([4])
    left, right = s.render_pair(4)
    ul, vl = _centroid(left, t.u_left[0, 0], t.v_left[0, 0])
    ur, vr = _centroid(right, t.u_right[0, 0], t.v_right[0, 0])
    assert left.max() < 255
    assert ul == pytest.approx(t.u_left[0, 0], abs=0.05)
    assert vl == pytest.approx(t.v_left[0, 0], abs=0.05)
    assert ul - ur == pytest.approx(t.disparity_px[0], abs=0.05)
    assert vl - vr == pytest.approx(0.0, abs=0.05)


def test_centroid_with_noise_averaged_over_frames():
    s = _led_scene(37.1, 3, noise=True, lateral_m=0.137)
    t = s.truth(np.arange(0, 200, 2))
    d = []
    for i, n in enumerate(t.frames):
        left, right = s.render_pair(int(n))
        d.append(_centroid(left, t.u_left[i, 0], t.v_left[i, 0])[0]
                 - _centroid(right, t.u_right[i, 0], t.v_right[i, 0])[0])
    assert np.mean(d) == pytest.approx(t.disparity_px[0], abs=0.05)


def _spot_side(img: np.ndarray, u: float, v: float) -> tuple[float, float]:
    w = _window(img, u, v)[0]
    peak = w.max()
    return float(np.sqrt((w > 0.1 * peak).sum())), float(peak)


@pytest.mark.parametrize("distance_m,lo,hi", [(20.0, 5.0, 7.0), (60.0, 2.5, 3.9)])
def test_spot_size(distance_m, lo, hi):
    # "spot size": side of the square with the area of the pixels above 10 % of the peak
    # (unsaturated spot, background subtracted); the continuous profile's full width at
    # 10 % agrees.
    level = 2 if distance_m < 30 else 4
    s = _led_scene(distance_m, level)
    t = s.truth([6])
    left, _ = s.render_pair(6)
    side, peak = _spot_side(left, t.u_left[0, 0], t.v_left[0, 0])
    assert peak + DARK < 250
    assert lo <= side <= hi
    cont = spot_size_px(float(s.led_radius_fn(distance_m)), s.cams[0].sigma_core)
    assert lo <= cont <= hi + 0.2


def test_saturated_spot_is_wider():
    # clipped at 255 the bright spot's flanks and glare spread: more pixels above half its
    # (clipped) peak and above a fixed grey level than an unsaturated spot
    for distance_m in (20.0, 30.0):
        lo, hi = _led_scene(distance_m, 2), _led_scene(distance_m, 8)
        t = lo.truth([6])
        u, v = t.u_left[0, 0], t.v_left[0, 0]
        w_lo = _window(lo.render_pair(6)[0], u, v)[0]
        w_hi = _window(hi.render_pair(6)[0], u, v)[0]
        assert w_hi.max() + DARK == 255 and w_lo.max() + DARK < 200
        assert (w_hi >= 0.5 * w_hi.max()).sum() > 1.3 * (w_lo >= 0.5 * w_lo.max()).sum()
        assert (w_hi > 25).sum() > 1.3 * (w_lo > 25).sum()


def test_f8_gives_a_quarter_of_f4():
    cfg = single_led(default_config(), 25.0, background="flat", distractors=[], led_phase_s=0.0,
                     led_drift_ppm=0.0)
    cfg = override(cfg, camera={"f_number_right": 8.0})
    s = Scene(cfg, ArraySource(np.full((1, 1), 3), repeat=True), noise=False)
    t = s.truth([6])
    left, right = s.render_pair(6)
    fl = (_window(left, t.u_left[0, 0], t.v_left[0, 0], 8)[0]
          - _window(left, t.u_left[0, 0], t.v_left[0, 0] + 40, 8)[0])  # background subtracted
    fr = (_window(right, t.u_right[0, 0], t.v_right[0, 0], 8)[0]
          - _window(right, t.u_right[0, 0], t.v_right[0, 0] + 40, 8)[0])
    assert left.max() < 255
    assert fr.sum() / fl.sum() == pytest.approx(0.25, rel=0.03)
    # the flat background scales the same way
    assert (np.median(right) - DARK) / (np.median(left) - DARK) == pytest.approx(0.25, rel=0.05)


def test_signal_is_linear_in_on_time():
    # random levels, unsynchronized clock: frames straddle symbols; flux ∝ on_fraction
    cfg = single_led(default_config(), 40.0, background="none", distractors=[],
                     led_phase_s=0.37e-3, led_drift_ppm=150.0)
    cfg = override(cfg, camera={"f_number_right": 8.0})  # never saturates
    rng = np.random.default_rng(3)
    s = Scene(cfg, ArraySource(rng.integers(1, 9, size=(200, 1))), noise=False)
    frames = np.arange(2, 300, 3)
    t = s.truth(frames)
    flux = np.array([np.clip(_window(s.render_pair(int(n))[1], t.u_right[i, 0],
                                     t.v_right[i, 0])[0], 0, None).sum()
                     for i, n in enumerate(frames)])
    f = t.on_fraction[:, 0]
    assert f.min() == 0.0 and f.max() == 1.0 and (~t.clean).sum() > 10
    k = (flux @ f) / (f @ f)
    assert np.abs(flux - k * f).max() < 0.01 * k + 15  # rounding of ~20 px, no saturation
    assert np.corrcoef(flux, f)[0, 1] > 0.999


def test_random_access_is_deterministic():
    cfg = override(default_config(), scene={"jitter_px": 0.2, "vibration_px": 0.5})
    a = Scene(cfg)
    b = Scene(cfg)
    for n in (0, 700, 3):
        a.render_pair(n)
    la, ra = a.render_pair(1234)
    lb, rb = b.render_pair(1234)
    assert np.array_equal(la, lb) and np.array_equal(ra, rb)
    l2, _ = a.render_pair(1235)
    assert not np.array_equal(la, l2)  # fresh noise every frame


def test_noise_statistics_and_no_visible_window():
    cfg = override(default_config(), transmitter={"rows": 2, "cols": 2},
                   camera={"f_number_right": 4.0},
                   scene={"background": "flat", "background_dn": 40.0, "distractors": []})
    s = Scene(cfg, ArraySource(np.ones((1, 4), int), repeat=True))  # LEDs dark
    frames = [s.render_pair(n)[0].astype(float) for n in range(0, 40)]
    stack = np.stack(frames)
    # temporal noise of one pixel: shot + read + quantization
    k = 255 / cfg.sensor.full_well_e
    expect = np.sqrt(40 * k + (cfg.sensor.read_noise_e * k) ** 2 + 1 / 12)
    inside = stack[:, 250:262, 250:262]  # rendered window around the (dark) LEDs
    outside = stack[:, 100:140, 100:140]  # from the background bank
    assert inside.std(axis=0).mean() == pytest.approx(expect, rel=0.15)
    assert outside.std(axis=0).mean() == pytest.approx(expect, rel=0.15)
    assert inside.mean() == pytest.approx(outside.mean(), abs=0.3)
    # PRNU: fixed pattern across frames, ~1 % of 40 DN
    fpn = stack.mean(axis=0)[100:200, 100:200].std()
    assert 0.25 < fpn < 0.6


def test_distractors_appear_and_are_steady():
    cfg = override(default_config(), scene={
        "background": "none", "distractors": [
            {"x_m": 2.0, "y_m": -1.0, "z_m": 40.0, "diameter_m": 0.1, "brightness_dn": 150.0},
            {"x_m": -2.0, "y_m": 1.0, "z_m": 30.0, "diameter_m": 0.1, "brightness_dn": 150.0,
             "flicker_hz": 100.0}]})
    s = Scene(cfg, noise=False)
    steady, flick = s.meta()["distractors"]
    vals = {"steady": [], "flicker": []}
    for n in (0, 2, 4, 6, 500):
        left, right = s.render_pair(n)
        for name, d in (("steady", steady), ("flicker", flick)):
            ul = left[int(round(d["v"])), int(round(d["u_left"]))]
            ur = right[int(round(d["v"])), int(round(d["u_right"]))]
            vals[name].append((int(ul), int(ur)))
    assert len(set(vals["steady"])) == 1 and vals["steady"][0][0] > 100  # bright, constant
    assert vals["steady"][0][1] > 20  # seen by the f/8 camera at its own disparity
    lv = [v[0] for v in vals["flicker"]]
    assert max(lv) - min(lv) > 50  # 100 Hz flicker sampled at 1000 fps


def test_truth_levels_carry_the_payload_and_start_dark():
    cfg = override(default_config(), scene={"led_phase_s": 5e-3, "led_drift_ppm": 0.0})
    s = Scene(cfg)
    air = AirInterface.from_config(cfg.transmitter)
    t = s.truth(np.arange(0, 4 * air.period_symbols + 20))  # 2 frames per symbol
    assert t.symbol_index[0] < 0 and (t.levels[t.symbol_index < 0] == 1).all()
    assert (t.on_fraction[t.t_s + cfg.camera.exposure_s <= 5e-3] == 0).all()
    assert t.symbol_t_s[t.symbol_index == 0][0] == pytest.approx(5e-3)
    assert list(t.packet_start_symbol[:2]) == [0, air.period_symbols]
    for p, payload in zip(t.packet_index[:2], t.payloads[:2]):
        k0 = int(p) * air.period_symbols + air.data_offset
        body, ok = air.decode_data(t.levels_of(k0, k0 + air.data_symbols))
        assert ok and body == payload
    assert t.payloads[0] != t.payloads[1]  # random payload per packet


def test_truth_save_load_roundtrip(tmp_path):
    s = Scene(override(default_config(), scene={"jitter_px": 0.1}))
    t = s.truth(np.arange(100, 160))
    t.save(tmp_path)
    back = Truth.load(tmp_path)
    assert back == t
    assert back.meta["config"]["transmitter"]["rows"] == 8


def test_clean_frames_integrate_the_duty_of_their_symbol():
    cfg = override(default_config(), scene={"led_drift_ppm": 100.0, "seed": 4})
    s = Scene(cfg)
    t = s.truth(np.arange(0, 1500))
    M = cfg.transmitter.levels
    clean = t.clean
    assert 0.3 < clean.mean() < 0.7  # 1 ms frames, 2 ms symbols, random phase
    lv = t.levels[t.symbol_mid[clean] - t.symbol_index[0]]
    np.testing.assert_allclose(t.on_fraction[clean], (lv - 1) / (M - 1), atol=1e-3)
    # a straddling frame lies between its two symbols' duties
    i = np.flatnonzero(~clean)[5]
    k = t.symbol_mid[i] - t.symbol_index[0]
    d = (t.levels[k - 1:k + 2].astype(float) - 1) / (M - 1)
    lo, hi = d.min(axis=0) - 1e-9, d.max(axis=0) + 1e-9
    assert ((t.on_fraction[i] >= lo) & (t.on_fraction[i] <= hi)).all()


def test_noise_free_window_is_invisible_and_edges_do_not_crash():
    cfg = override(default_config(), scene={"background": "texture", "distractors": []})
    s = Scene(cfg, ArraySource(np.ones((1, 64), int), repeat=True), noise=False)
    a, b = s.render_pair(3)
    c, d = s.render_pair(900)
    assert np.array_equal(a, c) and np.array_equal(b, d)  # dark LEDs: only the background
    # arrays half outside, fully outside and very close
    for scene in ({"lateral_m": 2.3}, {"lateral_m": 40.0}, {"vertical_m": -2.2},
                  {"distance_m": 2.5}):
        cfg2 = override(default_config(), scene=scene)
        left, right = Scene(cfg2).render_pair(60)
        assert left.shape == (512, 512)


def test_background_has_its_own_disparity():
    import cv2

    cfg = override(default_config(), camera={"f_number_right": 4.0},
                   scene={"distractors": [], "background_distance_m": 150.0})
    s = Scene(cfg, ArraySource(np.ones((1, 64), int), repeat=True), noise=False)
    left, right = s.render_pair(0)
    win = cv2.createHanningWindow((512, 512), cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(right.astype(np.float64), left.astype(np.float64), win)
    assert dx == pytest.approx(3500 * 0.25 / 150.0, abs=0.1) and abs(dy) < 0.1
    assert 30 < left.mean() < 50 and left.std() > 5  # textured, mean ~ background_dn + dark
