"""Several transmitters and PWM-dimmed blinkers in one simulated scene (issue 15, simulator).

``[[scene.transmitters]]`` adds transmitters beside the main one, each with its own
geometry, LED clock and packets; ``[[scene.distractors]] waveform = "square"`` is a
PWM-dimmed lamp. Checked: each transmitter's truth agrees with the light in its own LED
windows, blinkers follow their square wave, payloads differ, ``start_s``/``stop_s``, config
errors name the key, and single-transmitter scenes render the frames of before.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from iscd.cli.main import main
from iscd.core.config import ConfigError, default_config, load, loads
from iscd.sim import Scene, Truth
from iscd.sim.background import square_on_fraction
from iscd.sim.presets import override
from iscd.sim.tomlout import config_to_toml

EXAMPLE = Path(__file__).resolve().parents[1] / "iscd" / "data" / "examples" / "three_tx.toml"

MULTI = """
[transmitter]
rows = 8
cols = 8
levels = 8
[scene]
distance_m = 40
led_drift_ppm = 100
seed = 3
[[scene.transmitters]]
distance_m = 30
lateral_m = -1.2
led_drift_ppm = -100
[[scene.transmitters]]
distance_m = 55
lateral_m = 1.5
vertical_m = -1.0
led_drift_ppm = 100
[[scene.distractors]]
x_m = 1.0
y_m = 0.5
z_m = 25
diameter_m = 0.08
brightness_dn = 150
flicker_hz = 200
waveform = "square"
duty = 0.3
[[scene.distractors]]
x_m = -0.8
y_m = 0.6
z_m = 35
diameter_m = 0.08
brightness_dn = 150
flicker_hz = 1300
waveform = "square"
duty = 0.25
"""

FRAMES = np.arange(0, 400)


@pytest.fixture(scope="module")
def multi() -> tuple[Scene, list[Truth], np.ndarray, np.ndarray]:
    """The scene, its truths and the right camera's frames 0..399 (f/8: nothing saturates)."""
    scene = Scene(loads(MULTI))
    truths = scene.truths(FRAMES)
    left = np.empty((FRAMES.size, 512, 512), np.uint8)
    right = np.empty_like(left)
    for j, n in enumerate(FRAMES):
        scene.render_pair_into(int(n), left[j], right[j])
    return scene, truths, left, right


def _box_sum(frames: np.ndarray, u: float, v: float, half: int = 1) -> np.ndarray:
    """(F,) sum of the (2 half + 1)^2 pixels around pixel-centre coordinates (u, v) px."""
    x, y = int(round(u)), int(round(v))
    return frames[:, y - half:y + half + 1, x - half:x + half + 1].reshape(len(frames), -1).sum(1,
                                                                                         dtype=np.float64)


def test_each_transmitters_truth_follows_the_light_in_its_own_windows(multi):
    scene, truths, left, right = multi
    assert scene.n_transmitters == 3 and len(truths) == 3
    assert truths[0] == scene.truth(FRAMES)  # index 0 is the main transmitter's truth
    assert [t.meta["tx_index"] for t in truths] == [0, 1, 2]
    assert [t.on_fraction.shape[1] for t in truths] == [64, 1, 1]
    np.testing.assert_allclose([t.z_m[0] for t in truths], [40, 30, 55])
    for t, drift in zip(truths, (100, -100, 100)):
        assert t.present.all() and t.meta["led_drift_ppm"] == drift
        # its own clock: symbols last T / (1 + drift) on the camera clock
        np.testing.assert_allclose(np.diff(t.symbol_t_s), 2e-3 / (1 + drift * 1e-6), rtol=1e-9)
        np.testing.assert_allclose(t.disparity_px, 3500 * 0.25 / t.z_m)
    # the single LEDs: the light around each centre follows its own on-fraction, not the others'
    for k in (1, 2):
        t = truths[k]
        assert t.u_left[0, 0] == pytest.approx(255.5 + 3500 * t.meta["lateral_m"] / t.z_m[0])
        for frames, u, v in ((left, t.u_left, t.v_left), (right, t.u_right, t.v_right)):
            light = _box_sum(frames, u[0, 0], v[0, 0], half=2)  # 5x5: f/4 saturates the core
            assert np.corrcoef(light, t.on_fraction[:, 0])[0, 1] > 0.9
            other = truths[3 - k].on_fraction[:, 0]
            assert abs(np.corrcoef(light, other)[0, 1]) < 0.3
    # the 8x8 array (right camera, unsaturated): per LED a 3x3 box around its centre
    t = truths[0]
    corr = [np.corrcoef(_box_sum(right, t.u_right[0, i], t.v_right[0, i]), t.on_fraction[:, i])[0, 1]
            for i in range(64)]
    assert min(corr) > 0.9, min(corr)


def test_square_blinkers_follow_their_on_fraction(multi):
    scene, truths, left, right = multi
    gains = scene.distractor_gains(FRAMES)
    assert gains.shape == (FRAMES.size, 2)
    assert 0 <= gains.min() and gains.max() <= 1
    # exact: the same as integrating the wave over each exposure numerically
    t0 = FRAMES / 1000.0
    phase = scene.flicker_phase
    for j, (f, duty) in enumerate(((200, 0.3), (1300, 0.25))):
        off = phase[j] / (2 * np.pi * f)
        np.testing.assert_allclose(gains[:, j], square_on_fraction(t0, 1e-3, f, duty, off))
        ts = t0[:50, None] + (np.arange(20000) + 0.5) / 20000 * 1e-3
        brute = (((ts + off) * f) % 1.0 < duty).mean(1)
        np.testing.assert_allclose(gains[:50, j], brute, atol=2e-4)
        assert gains[:, j].mean() == pytest.approx(duty, abs=0.03)
    for j, d in enumerate(scene.meta()["distractors"]):
        assert d["waveform"] == "square"
        for frames, u in ((left, d["u_left"]), (right, d["u_right"])):
            light = _box_sum(frames, u, d["v"], half=2)
            assert np.corrcoef(light, gains[:, j])[0, 1] > 0.9
            assert abs(np.corrcoef(light, gains[:, 1 - j])[0, 1]) < 0.3


def test_transmitters_send_their_own_payloads(multi):
    scene, truths, _, _ = multi
    first = [t.payloads[0] for t in truths]
    assert len(set(first)) == 3
    assert len(first[0]) == 14396 and len(first[1]) == len(first[2]) == 221  # SPEC section 3
    assert {t.meta["payload_seed"] for t in truths[1:]} == {3 + 4096, 3 + 2 * 4096}
    # the levels are those of their own packets: a header (Barker-13, level M = 8) at their own
    # packet start
    for t in truths:
        k0 = int(t.packet_start_symbol[0])
        if t.symbol_index[0] <= k0 and k0 + 13 <= t.symbol_index[-1]:
            barker = np.array([1, 1, 1, 1, 1, 0, 0, 1, 1, 0, 1, 0, 1]) * 7 + 1
            np.testing.assert_array_equal(t.levels_of(k0, k0 + 13)[:, 0], barker)
    assert len({t.meta["led_phase_s"] for t in truths}) == 3  # independent clocks


def test_transmitters_and_blinkers_do_not_share_windows(multi):
    """In the must-show scene every source has a window of its own in both cameras (no
    overlap), and all of them lie inside the 512 x 512 image."""
    scene, _, _, _ = multi
    ex = Scene(load(EXAMPLE))
    for s in (scene, ex):
        assert s.n_transmitters == 3
        for c in s.cams:
            st, i = s._chunk(0)
            plan = s._plan(c, st, i)
            keys = sorted(sp.key for g in plan for sp in g.sets)
            assert keys == ["flicker", "flicker", "on_fraction", "on_fraction@1", "on_fraction@2"]
            assert all(not g.empty and g.clip == g.box for g in plan)


def test_start_stop_renders_nothing_outside_and_the_truth_says_when(tmp_path):
    base = loads(MULTI)
    sc = base.scene
    entry = {"distance_m": 35, "lateral_m": 0.9, "vertical_m": 0.9, "led_drift_ppm": 40.0,
             "start_s": 0.1005, "stop_s": 0.25}
    cfg = override(base, scene={"transmitters": [*[_entry(t) for t in sc.transmitters], entry]})
    with_it, without = Scene(cfg), Scene(base)
    assert with_it.n_transmitters == 4
    frames = np.arange(60, 300)
    t = with_it.truths(frames)[3]
    # frame n exposes [n, n + 1] ms: in view from frame 100 (the last 0.5 ms of it) to 249
    np.testing.assert_array_equal(t.present, (frames >= 100) & (frames <= 249))
    assert t.meta["start_s"] == 0.1005 and t.meta["stop_s"] == 0.25
    assert not t.on_fraction[~t.present].any()
    # inside, the light is that of the same transmitter always in view, clipped to the interval
    always = Scene(override(cfg, scene={"transmitters": [*[_entry(x) for x in sc.transmitters],
                                                         {**entry, "start_s": 0.0, "stop_s": None}]}))
    full = always.truths(frames)[3].on_fraction
    inside = (frames >= 101) & (frames <= 249)
    np.testing.assert_allclose(t.on_fraction[inside], full[inside], rtol=1e-9, atol=1e-12)
    i100 = int(np.searchsorted(frames, 100))
    assert 0 <= t.on_fraction[i100, 0] <= full[i100, 0] + 1e-12
    # outside its interval the frames are those of the scene without it, bit for bit
    for n in (60, 99, 250, 299):
        assert all(np.array_equal(a, b) for a, b in zip(with_it.render_pair(n), without.render_pair(n)))
    for n in (150, 200):
        a, b = with_it.render_pair(n), without.render_pair(n)
        assert not np.array_equal(a[0], b[0])  # it is there
    # simulate writes each transmitter's truth: truth.* for tx 0, truth_tx1.* ... for the others
    (tmp_path / "c.toml").write_text(config_to_toml(cfg))
    out = tmp_path / "rec"
    assert main(["simulate", "--config", str(tmp_path / "c.toml"), "--out", str(out),
                 "--frames", "6"]) == 0
    names = sorted(p.name for p in out.glob("truth*"))
    assert names == ["truth.json", "truth.npz", *[f"truth_tx{k}.{e}" for k in (1, 2, 3)
                                                  for e in ("json", "npz")]]
    back = [Truth.load(out)] + [Truth.load(out, f"truth_tx{k}") for k in (1, 2, 3)]
    assert back == with_it.truths(np.arange(6))
    assert not back[3].present.any() and back[1].present.all()


def _entry(t: object) -> dict:
    from iscd.core.config import to_dict

    return {k: v for k, v in to_dict(t).items() if v is not None}


@pytest.mark.parametrize("text, key", [
    ("[[scene.transmitters]]\ndistance_m = 30\n[[scene.transmitters]]\ndistance_m = -3\n",
     "scene.transmitters[1].distance_m"),
    ("[[scene.transmitters]]\nlevels = 6\n", "scene.transmitters[0].levels"),
    ("[[scene.transmitters]]\nrows = 0\n", "scene.transmitters[0].rows"),
    ("[[scene.transmitters]]\nstart_s = 0.5\nstop_s = 0.2\n", "scene.transmitters[0].stop_s"),
    ("[[scene.transmitters]]\nled_drift = 3\n", "scene.transmitters[0].led_drift"),
    ("[[scene.transmitters]]\n[[scene.transmitters]]\nair_interface = \"v2\"\ndata_symbols = 1\n",
     "scene.transmitters[1].data_symbols"),
    ("[scene]\ntransmitters = 3\n", "scene.transmitters"),
    ("[[scene.distractors]]\nwaveform = \"triangle\"\n", "scene.distractors[0].waveform"),
    ("[[scene.distractors]]\nflicker_hz = 500\nwaveform = \"square\"\nduty = 1.5\n",
     "scene.distractors[0].duty"),
])
def test_a_bad_entry_names_its_key(text, key):
    with pytest.raises(ConfigError) as e:
        loads(text)
    assert str(e.value).startswith(key + ":"), str(e.value)


def test_a_bad_fixed_payload_names_its_key():
    cfg = loads('[[scene.transmitters]]\npayload_source = "hex"\npayload_value = "zz"\n')
    with pytest.raises(ConfigError, match=r"^scene\.transmitters\[0\]\.payload_value:"):
        Scene(cfg)


def test_extra_transmitters_inherit_the_main_ones_keys_and_round_trip():
    cfg = loads(MULTI)
    tx1 = cfg.scene.transmitters[0].transmitter(cfg.transmitter, 0)
    assert (tx1.rows, tx1.cols, tx1.levels, tx1.led_diameter_m, tx1.data_symbols) == (1, 1, 8, 0.03, 600)
    assert loads(config_to_toml(cfg)) == cfg  # keys left out stay left out (None)
    assert load(EXAMPLE).scene.transmitters[1].seed == 202
    v2 = loads('[[scene.transmitters]]\nlevels = 4\nair_interface = "v2"\nfec = "rs255_239"\n')
    t = Scene(v2).truths([0, 1])[1]
    assert t.meta["air_interface"] == "v2" and t.meta["fec"] == "rs255_239" and t.meta["levels"] == 4


# From the code before [[scene.transmitters]] existed (commit 4f26059 of this repository),
# rendered on the development machine: sha256 of frames 0, 1, 2, 777, 1500 (left then right
# of each) of the embedded default config, first 16 hex digits. Also equal for compiled=False.
DEFAULT_FRAMES_SHA = "7cc7e1e7a086b2ff"


def test_a_single_transmitter_scene_renders_the_frames_of_before():
    m = hashlib.sha256()
    scene = Scene(default_config())
    for n in (0, 1, 2, 777, 1500):
        left, right = scene.render_pair(n)
        m.update(left.tobytes())
        m.update(right.tobytes())
    assert m.hexdigest()[:16] == DEFAULT_FRAMES_SHA
    assert scene.n_transmitters == 1 and len(scene.truths([0, 5])) == 1


def test_adding_a_transmitter_changes_only_its_own_window():
    """An empty [[scene.transmitters]] list is no change; a further transmitter whose window
    overlaps nothing changes the pixels of its window only (the main transmitter's window
    keeps its noise draws)."""
    base = override(default_config(), scene={"vibration_px": 0.0})
    a = Scene(base)
    b = Scene(override(base, scene={"transmitters": []}))
    c = Scene(override(base, scene={"transmitters": [{"lateral_m": -1.3, "distance_m": 25}]}))
    for n in (0, 333):
        fa, fb, fc = a.render_pair(n), b.render_pair(n), c.render_pair(n)
        assert all(np.array_equal(x, y) for x, y in zip(fa, fb))
        for cam, (x, z) in enumerate(zip(fa, fc)):
            ys, xs = np.nonzero(x != z)
            t = c.truths([n])[1]
            u = (t.u_left if cam == 0 else t.u_right)[0, 0]
            assert xs.size and np.abs(xs - u).max() <= 12 and np.abs(ys - t.v_left[0, 0]).max() <= 12


def test_overlapping_transmitters_share_one_window():
    """Two transmitters whose windows overlap are rendered in one window (background and
    noise once, their light added): the same pixels as rendering their light separately
    without noise, up to rounding."""
    cfg = override(default_config(), scene={"background": "flat", "distractors": [],
                                            "transmitters": [{"lateral_m": 0.3, "distance_m": 30}]})
    s = Scene(cfg, noise=False)
    st, i = s._chunk(10)
    plan = s._plan(s.cams[0], st, i)
    assert len(plan) == 1 and sorted(sp.key for sp in plan[0].sets) == ["on_fraction", "on_fraction@1"]
    both = s.render_pair(10)[0].astype(int)
    only_main = Scene(override(cfg, scene={"transmitters": []}), noise=False).render_pair(10)[0].astype(int)
    away = {"lateral_m": 10.0}  # the main transmitter out of the image
    bg = Scene(override(cfg, scene={"transmitters": [], **away}), noise=False).render_pair(10)[0].astype(int)
    only_extra = Scene(override(cfg, scene=away), noise=False).render_pair(10)[0].astype(int)
    added = only_main + only_extra - bg
    unsat = (both < 250) & (added < 250)
    assert np.abs(both - added)[unsat].max() <= 1
