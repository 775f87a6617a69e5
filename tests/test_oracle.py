"""The oracle decodings (iscd.eval.oracle) and the motion suite (issue 12)."""

from __future__ import annotations

import json
import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from iscd.cli.main import main
from iscd.core.config import default_config
from iscd.eval import oracle
from iscd.eval.oracle import (CHAIN, FLOOR, SPLIT, STAGES, error_profile, genie_sum, nearest_dark,
                              pool, profile_bins, run_oracle, true_clock)
from iscd.eval.suites import MOTION_CASES, EvalPlan, chapter3_cfg, motion_cfg, run_plan
from iscd.sim.presets import override


# ----------------------------------------------------------------------------- pure parts

@pytest.mark.parametrize("F,N,bins", [(600, 1, 8), (600, 64, 8), (120, 1, 8), (7, 3, 8), (5, 1, 8), (600, 1, 1)])
def test_profile_bins_cover_every_data_symbol_exactly_once(F: int, N: int, bins: int) -> None:
    b = profile_bins(F, N, bins)
    assert b.shape == (F, N)
    flat = b.ravel()  # data order: symbol time major (SPEC section 3)
    assert flat.min() >= 0 and flat.max() <= bins - 1
    assert np.all(np.diff(flat) >= 0)  # contiguous stretches along the packet
    counts = np.bincount(flat, minlength=bins)
    assert counts.sum() == F * N  # every data symbol in exactly one bin
    if F * N >= bins:
        assert counts.min() >= 1 and counts.max() - counts.min() <= 1


def test_error_profile_counts_every_error_in_its_stretch() -> None:
    rng = np.random.default_rng(3)
    sent = rng.integers(1, 9, size=(600, 4))
    got = sent.copy()
    got[590:, 2] = (got[590:, 2] % 8) + 1  # 10 errors at the packet's end
    got[0, 0] = (got[0, 0] % 8) + 1  # one at its start
    e, n = error_profile(sent, got, 8)
    assert e.sum() == 11 and n.sum() == 2400 and np.all(n == 300)
    assert e[0] == 1 and e[-1] == 10 and e[1:-1].sum() == 0
    with pytest.raises(ValueError):
        error_profile(sent, got[:10], 8)


def test_true_clock_is_the_line_through_the_symbol_starts() -> None:
    fps, p_true, u0 = 1000.0, 2.0 / (1 + 100e-6), 17.37
    t = (u0 + p_true * np.arange(653)) / fps
    clk = true_clock(t, fps, frame0=10)
    assert clk.u0 == pytest.approx(u0 - 10, abs=1e-9) and clk.p == pytest.approx(p_true, rel=1e-12)
    assert clk.drift_ppm(2.0) == pytest.approx(100.0, abs=1e-6)


def test_genie_sum_is_the_light_above_the_background_within_the_radius() -> None:
    H = W = 32
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    cx, cy, sig, flux = 15.3, 16.7, 0.9, 400.0
    spot = flux * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sig * sig)) / (2 * np.pi * sig * sig)
    bg = 20.0 + 0.5 * xx  # a sloping background, per pixel
    frames = np.stack([bg + spot, bg + 2 * spot, bg])
    c = np.broadcast_to(np.array([[cx, cy]]), (3, 1, 2))
    g = genie_sum(frames, c, np.full(3, 4.0), np.broadcast_to(bg, frames.shape))
    assert g[:, 0] == pytest.approx([flux, 2 * flux, 0.0], abs=0.5)
    # without the background the sum is biased by the window's pixels
    g0 = genie_sum(frames, c, np.full(3, 4.0), np.zeros_like(frames))
    assert g0[2, 0] > 100


def test_nearest_dark_frames() -> None:
    idx = nearest_dark(np.array([3, 10, 50, 51]), np.array([0, 30, 52]), 2)
    assert sorted(idx[0].tolist()) == [0, 1] and sorted(idx[2].tolist()) == [2, 3]
    assert set(idx[1].tolist()) == {1, 2}


def _one_led_packet(peak_dn: float):  # type: ignore[no-untyped-def]
    """One synthetic one-LED PWM-8 packet seen by two cameras (2.5 DN read noise, 80 ppm
    drift): (air interface, recording, its first symbol, the true symbol clock)."""
    from iscd.core.airinterface import AirInterface
    from iscd.core.config import TransmitterConfig
    from iscd.decode.comms.synth import SynthCamera, synth_recording

    air = AirInterface.from_config(TransmitterConfig(rows=1, cols=1, levels=8))
    rec = synth_recording(air, [SynthCamera(peak_dn=peak_dn, read_noise_dn=2.5)] * 2, n_packets=1, drift_ppm=80,
                          phase_s=0.0021, seed=6)
    k0 = int(rec.packet_symbol0[0])
    T, rate = 1.0 / 500.0, 1 + 80e-6
    t_sym = (k0 + np.arange(air.packet_symbols + 1)) * T / rate + 0.0021
    return air, rec, k0, true_clock(t_sym, rec.fps)


def test_demod_hooks_fix_the_clock_and_replace_the_channel() -> None:
    """``demodulate_packet(clock=, channel=)``: the clock given is the clock used (no fits),
    and every channel estimate comes from ``channel(clock, a, b)`` over stretches that
    cover the packet; a true-level channel does not do worse than the estimate."""
    from iscd.decode.comms.demod import PacketResult, demodulate_packet
    from iscd.decode.comms.settings import ReceiverConfig

    air, rec, k0, clock = _one_led_packet(40.0)
    cfg = ReceiverConfig()
    base = demodulate_packet(rec.L, clock.u0 + 0.3, air, 1.0, 2.0, 2.0, 2.0 * 300e-6, cfg)
    fixed = demodulate_packet(rec.L, clock.u0 + 0.3, air, 1.0, 2.0, 2.0, 2.0 * 300e-6, cfg, clock=clock)
    assert isinstance(base, PacketResult) and isinstance(fixed, PacketResult)
    assert (fixed.u0, fixed.p) == (clock.u0, clock.p) and math.isnan(fixed.header_r2)
    assert base.u0 != clock.u0  # the receiver fits its own
    true_lev = rec.levels[k0:k0 + air.packet_symbols].astype(np.int64) - 1
    spans: list[tuple[int, int]] = []
    genie = oracle.genie_channel(rec.L, 1.0, true_lev, 8, cfg, 96)

    def channel(clk, a, b):  # type: ignore[no-untyped-def]
        assert clk == clock
        spans.append((a, b))
        return genie(clk, a, b)
    g = demodulate_packet(rec.L, clock.u0, air, 1.0, 2.0, 2.0, 2.0 * 300e-6, cfg, clock=clock, channel=channel)
    assert isinstance(g, PacketResult)
    covered = np.zeros(air.packet_symbols, bool)
    for a, b in spans:
        covered[a:b] = True
    assert covered[13 + air.training_symbols:].all()
    sent = true_lev[13 + air.training_symbols:] + 1
    assert 0 < np.count_nonzero(fixed.levels != sent) < 30  # low SNR: a few errors (3 of 600 when written)
    assert np.count_nonzero(g.levels != sent) <= np.count_nonzero(fixed.levels != sent)


def test_the_labels_hook_feeds_the_channel_fits_only() -> None:
    """``demodulate_packet(labels=)`` (the ``+true labels`` row): the decision-directed
    channel fits read the levels given, the decisions stay the receiver's. With the true
    levels a clean packet is delivered as without them; levels that are wrong (the sent ones
    shifted along the packet) wreck the channel and with it the decisions -- so the fits did
    read them; a wrong shape is one clear error. (On a noisy packet true labels need not
    give fewer errors than the receiver's own: a fit to its own decisions can suit that
    noise better, 0 against 1 error at 50 DN.)"""
    from iscd.decode.comms.demod import PacketResult, demodulate_packet
    from iscd.decode.comms.settings import ReceiverConfig

    air, rec, k0, clock = _one_led_packet(60.0)
    cfg = ReceiverConfig()
    true_lev = rec.levels[k0:k0 + air.packet_symbols].astype(np.int64) - 1
    sent = true_lev[air.data_offset:] + 1

    def errors(**kw):  # type: ignore[no-untyped-def]
        r = demodulate_packet(rec.L, clock.u0, air, 1.0, 2.0, 2.0, 2.0 * 300e-6, cfg, clock=clock, **kw)
        assert isinstance(r, PacketResult)
        return int(np.count_nonzero(r.levels != sent)) + (0 if r.crc_ok else 10_000)

    assert errors() == 0  # a clean packet (the receiver's own decisions)
    assert errors(labels=true_lev) == 0
    wrong = true_lev.copy()
    wrong[air.data_offset:] = np.roll(wrong[air.data_offset:], 7, axis=0)
    assert errors(labels=wrong) > 10_000 + 100
    with pytest.raises(ValueError, match="labels"):
        errors(labels=true_lev[:-1])


# ----------------------------------------------------------------------------- simulated

def _short(cfg):  # type: ignore[no-untyped-def]
    return override(cfg, transmitter={"data_symbols": 120})


def test_static_clean_scene_every_stage_is_error_free() -> None:
    cfg = _short(chapter3_cfg(default_config(), 30.0, 8, 5))
    res = run_oracle(cfg, 2)
    assert res.notes == []  # among others: the oracle's window is the receiver's
    assert res.receiver.found == 2 and res.receiver.exact == 2
    assert set(res.stages) == set(STAGES)
    assert len(res.common()) == 2
    for s in res.stages:
        assert all(p.stages[s].found and p.stages[s].crc_ok for p in res.packets), s
        assert res.ser(s) == 0.0, s
        assert np.all(res.profile(s) == 0.0), s
        assert res.counts(s) == (0, 2 * 120)
    sp = res.split()
    assert sp == {"receiver": 0.0, "following": 0.0, "timing": 0.0, "channel": 0.0, FLOOR: 0.0}
    # the luminance the stages decoded: the receiver's and the true-position one agree on a
    # still scene (the same window, the LEDs followed to within a small fraction of a pixel)
    lr, lt = res.luminance["receiver"], res.luminance["true positions"]
    ok = np.isfinite(lr) & np.isfinite(lt)
    assert ok.sum() > 1000 and np.allclose(lr[ok], lt[ok], rtol=0.02, atol=0.5)
    d = json.loads(json.dumps(res.as_dict()))  # JSON-ready
    assert d["ser"]["receiver"] == 0.0 and d["common_packets"] == [0, 1]


@pytest.fixture(scope="module")
def approach() -> oracle.OracleResult:
    """One LED closing at 40 km/h from 50 to 25 m with 0.5 px vibration, decoded without the
    per-pixel background (``background_one_led = false``, the receiver before issue 12's
    session 11), without list decoding (session 21, which delivers its packets even so) and
    without the symbol-by-symbol attempt (session 25; since session 27's survivors it
    delivers them too), without the sub-pixel phase attempt (session 33, which delivers
    them too) and with one LED's growth from each block's starts (before session 33; from the
    block's followed frames this scene decodes at SER 0): the receiver fails (with the background, this scene decodes at SER 0)."""
    from iscd.decode.comms import demod, listdecode, pixelphase

    cfg = chapter3_cfg(default_config(), 50.0, 8, 7, speed_mps=40 / 3.6, vibration_px=0.5, min_distance_m=25.0)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(listdecode, "LIST_DECODE", False)
        mp.setattr(demod, "SEQUENTIAL_RETRY", False)
        mp.setattr(pixelphase, "PHASE_RETRY", False)
        return run_oracle(cfg.with_keys("tracking", background_one_led=False, growth_from_block=False), 2)


def test_true_everything_is_not_worse_than_the_receiver_on_an_approach(approach: oracle.OracleResult) -> None:
    res = approach
    assert res.notes == []
    assert res.common(), "no packet that every stage demodulated"
    rx = res.ser("receiver")
    assert rx > 0  # a perturbed scene: the receiver makes errors
    assert res.ser("+true channel") <= rx
    assert res.ser("genie luminance +true channel") <= rx
    # the split telescopes: following + timing + channel + floor = receiver, every term bounded
    sp = res.split()
    assert sum(sp[name] for name, _, _ in SPLIT) + sp[FLOOR] == pytest.approx(sp["receiver"], abs=1e-12)
    for name, _, _ in SPLIT:
        assert -1.0 <= sp[name] <= 1.0
    for s in res.stages:
        assert 0.0 <= res.ser(s) <= 1.0
        # the profile's bins hold exactly the stage's errors and symbols
        sc = [p.stages[s] for p in res.common() if p.stages[s].found]
        e, n = res.counts(s)
        assert sum(int(x.profile_errors.sum()) for x in sc) == e
        assert sum(int(x.profile_symbols.sum()) for x in sc) == n
    # the receiver's errors grow along the packet (the symptom)
    prof = res.profile("receiver")
    assert prof[-4:].mean() > prof[:4].mean()


def test_pool_adds_the_seeds(approach: oracle.OracleResult) -> None:
    both = pool([approach, approach])
    assert both.receiver.packets_sent == 2 * approach.receiver.packets_sent
    assert len(both.packets) == 2 * len(approach.packets)
    for s in CHAIN:
        assert both.ser(s) == pytest.approx(approach.ser(s))


def test_oracle_of_a_recording_is_the_oracle_of_its_scene(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """A recording written by ``iscd simulate`` (frames + truth + config) gives the same
    decodings as rendering the scene: the oracle runs on another renderer's recordings."""
    from iscd.sim.tomlout import config_to_toml

    cfg = override(_short(chapter3_cfg(default_config(), 40.0, 8, 9, vibration_px=0.3)),
                   camera={"width": 192, "height": 96})  # small frames: a small recording
    (tmp_path / "in.toml").write_text(config_to_toml(cfg))
    from iscd.eval.sweeps import frames_for_packets
    from iscd.sim.scene import Scene
    from iscd.core.airinterface import AirInterface

    n = frames_for_packets(Scene(cfg), AirInterface.from_config(cfg.transmitter), 2)
    rec = tmp_path / "rec"
    assert main(["simulate", "--config", str(tmp_path / "in.toml"), "--out", str(rec), "--frames", str(n)]) == 0
    a = oracle.oracle_of_recording(rec)
    b = run_oracle(cfg, 2)
    assert len(a.packets) == len(b.packets) == 2 and b.receiver.found >= 1 and len(b.common()) >= 1
    for s in a.stages:
        assert a.counts(s) == b.counts(s), s
    assert a.receiver.as_dict() | {"seconds": 0} == b.receiver.as_dict() | {"seconds": 0}
    # and from the command line: the report's motion tables for the recording
    out = tmp_path / "rep"
    assert main(["eval", "--recording", str(rec), "--out", str(out)]) == 0
    assert "**Oracle split**" in capsys.readouterr().out  # printed too
    md = (out / "report.md").read_text()
    data = json.loads((out / "results.json").read_text())
    (row,) = data["motion"]
    assert row["case"] == "rec" and row["ser"] == a.as_dict()["ser"]
    assert "rec: 1x1 PWM-8, 0 km/h from 40 m, 0.3 px" in md and "**Oracle split**" in md
    assert main(["eval", "--recording", str(tmp_path / "nothing"), "--out", str(out)]) == 2


# ----------------------------------------------------------------------------- the suite

def test_motion_cfg_takes_scene_keys_and_the_optional_randomizer(monkeypatch: pytest.MonkeyPatch) -> None:
    base = default_config()
    case = next(c for c in MOTION_CASES if c.leds == 64)
    cfg, note = motion_cfg(base, case, 11, quick=True)
    assert cfg.transmitter.n_leds == 64 and cfg.camera.f_number_right == 8.0
    assert cfg.scene.speed_mps == pytest.approx(40 / 3.6) and cfg.scene.min_distance_m == 25.0
    assert cfg.transmitter.data_symbols == 120 and note == ""
    cfg2, _ = motion_cfg(base, case, 11, scene={"vibration_px": 0.7})
    assert cfg2.scene.vibration_px == 0.7 and cfg2.transmitter.data_symbols == 600
    with pytest.raises(ValueError):
        motion_cfg(base, case, 11, scene={"no_such_key": 1})
    # the randomizer absent: the case runs without it and says so
    monkeypatch.setitem(sys.modules, "iscd.sim.randomize", None)
    cfg3, note = motion_cfg(base, case, 11, randomize=True)
    assert "not available" in note and cfg3 == motion_cfg(base, case, 11)[0]
    # present: every case goes through it with its seed
    seen: list[int] = []
    fake = types.ModuleType("iscd.sim.randomize")

    def randomized(c, seed):  # type: ignore[no-untyped-def]
        seen.append(seed)
        return override(c, scene={"vibration_px": 0.4})
    fake.randomized = randomized  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "iscd.sim.randomize", fake)
    cfg4, note = motion_cfg(base, case, 11, randomize=True)
    assert seen == [11] and cfg4.scene.vibration_px == 0.4 and "randomized" in note
    # one that takes the motion to keep: the case's speed and vibration are passed
    kept: list[dict] = []

    def randomized_m(c, seed, *, motion=None):  # type: ignore[no-untyped-def]
        kept.append(dict(motion or {}))
        return c
    fake.randomized = randomized_m  # type: ignore[attr-defined]
    motion_cfg(base, case, 11, randomize=True, scene={"jitter_px": 0.01})
    assert kept[0]["vibration_px"] == case.vibration_px and kept[0]["jitter_px"] == 0.01
    assert kept[0]["speed_mps"] == pytest.approx(case.speed_kmh / 3.6)


def test_motion_suite_report_table_and_json(tmp_path: Path) -> None:
    keys = ("1led-still-0.5px", "1led-40kmh-0.3px")
    res = run_plan(default_config(), EvalPlan(suites=("motion",), quick=True, motion_cases=keys))
    assert [r.case.key for r in res.motion] == list(keys)
    from iscd.eval.report import write_report

    md = write_report(res, tmp_path).read_text()
    data = json.loads((tmp_path / "results.json").read_text())
    assert "## Motion" in md and "vibration 0.3 px" in md and "vibration 0.5 px" in md
    for r, row in zip(res.motion, data["motion"]):
        assert r.case.label in md and row["case"] == r.case.key
        assert row["receiver"]["packets_sent"] == 2
        assert set(row["split"]) == {"receiver", "following", "timing", "channel", FLOOR}
        assert len(row["profile"]["receiver"]) == 8
    assert data["settings"]["motion_seeds"] == 1 and data["settings"]["motion_cases"] == list(keys)


def test_motion_cli_bad_scene_key_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "--suite", "motion", "--quick", "--scene", "no_such_key=3", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "no_such_key" in err and "Traceback" not in err
    assert main(["eval", "--suite", "motion", "--cases", "nope", "--out", str(tmp_path)]) == 2


@pytest.mark.slow
def test_motion_suite_quick_form_has_every_case(tmp_path: Path) -> None:
    rc = main(["eval", "--suite", "motion", "--quick", "--out", str(tmp_path)])
    assert rc == 0
    data = json.loads((tmp_path / "results.json").read_text())
    assert [r["case"] for r in data["motion"]] == [c.key for c in MOTION_CASES]
    md = (tmp_path / "report.md").read_text()
    for c in MOTION_CASES:
        assert md.count(c.label) >= 3  # split table, found table, profile
    assert data["seconds"] < 120
    for r in data["motion"]:
        sp = r["split"]
        if sp["receiver"] is not None and all(sp[k] is not None for k in sp):
            assert math.isclose(sp["following"] + sp["timing"] + sp["channel"] + sp[FLOOR], sp["receiver"],
                                abs_tol=1e-12)


def test_one_leds_true_positions_are_measured_as_the_receiver_measures_under_vibration() -> None:
    """One LED closing at 40 km/h with 0.5 px vibration (its background held in the scene's
    frame, its following in the background's frame: issue 12, sessions 17 and 26): the
    "+true positions" window sees the frames as the receiver's luminance does -- the light
    above the registered map at each frame's image shift -- so at the receiver's own centres
    it gives the receiver's luminance (no note), and the stage is the following's cost alone."""
    cfg = _short(chapter3_cfg(default_config(), 50.0, 8, 7, speed_mps=40 / 3.6, vibration_px=0.5,
                              min_distance_m=25.0))
    res = run_oracle(cfg, 2, genie=False)
    assert [n for n in res.notes if n.startswith("+true positions")] == []
    assert res.receiver.found == 2
