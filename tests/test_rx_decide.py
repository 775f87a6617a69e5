"""Symbol decisions: clean frames (3.12), straddling frames, missing frames."""

from __future__ import annotations

import numpy as np

from iscd.core.airinterface import AirInterface
from iscd.decode.comms.channel import estimate_dissertation, estimate_iscd
from iscd.decode.comms.decide import decide_span
from iscd.decode.comms.demod import clean_samples, known_levels
from iscd.decode.comms.synth import SynthCamera, synth_recording
from iscd.decode.comms.timing import SymbolClock, clean_frame, frame_map


def _setup(peak: float, seed: int = 0, n_leds: int = 4, levels: int = 8):
    air = AirInterface(levels=levels, n_leds=n_leds, data_symbols=600)
    cams = [SynthCamera(peak_dn=peak), SynthCamera(peak_dn=peak)]
    rec = synth_recording(air, cams, n_packets=1, phase_s=0.00061, drift_ppm=0.0, seed=seed,
                          lead_symbols=7)
    clock = SymbolClock(rec.packet_starts_s[0] * 1000.0, 2.0)  # the true clock
    truth = rec.levels[7:7 + air.packet_symbols].astype(np.int64) - 1
    y, lv = clean_samples(rec.L, clock, 1.0, truth, 0)  # genie channel from all symbols
    return air, rec, clock, truth, y, lv


def test_dissertation_rule_is_the_argmin_of_3_12_on_clean_frames() -> None:
    air, rec, clock, truth, _, _ = _setup(60.0)
    n0 = air.data_offset
    yt, lt = clean_samples(rec.L, clock, 1.0, known_levels(air)[13:], 13)
    model = estimate_dissertation(yt, lt, 8)
    d = decide_span(rec.L, clock, 1.0, n0, air.packet_symbols, model, straddle=False)
    k = np.arange(n0, air.packet_symbols)
    n = clean_frame(k, clock, 1.0)  # exactly one clean frame per symbol here
    L = rec.L[:, n, :]  # (2, S, N)
    want = ((L[..., None] - model.mu[:, None]) ** 2).sum(0).argmin(-1)
    np.testing.assert_array_equal(d.levels, want)


def test_straddling_frames_cut_the_symbol_errors() -> None:
    air, rec, clock, truth, y, lv = _setup(18.0, seed=1)
    model = estimate_iscd(y, lv, 8, kind="gauss")
    n0, P = air.data_offset, air.packet_symbols
    clean = decide_span(rec.L, clock, 1.0, n0, P, model, straddle=False)
    ser_clean = (clean.levels != truth[n0:]).mean()
    ctx = truth.copy()
    ctx[n0:] = clean.levels
    ic = decide_span(rec.L, clock, 1.0, n0, P, model, ctx, 0, straddle=True)
    ser_ic = (ic.levels != truth[n0:]).mean()
    assert 2e-3 < ser_clean < 0.1  # a noisy channel
    assert ser_ic < 0.5 * ser_clean
    # margins: wrong decisions have small margins
    wrong = ic.levels != truth[n0:]
    assert np.median(ic.margin[wrong]) < 0.2 * np.median(ic.margin[~wrong])


def test_missing_frames_decided_from_the_other_camera_or_erased() -> None:
    air, rec, clock, truth, y, lv = _setup(100.0, seed=2)
    model = estimate_iscd(y, lv, 8)
    n0, P = air.data_offset, air.packet_symbols
    L = rec.L.copy()
    frames = np.arange(L.shape[1])
    k, alpha = frame_map(frames, clock, 1.0)
    # symbol n0 + 10: left camera frames lost; symbol n0 + 20: every frame touching it lost
    L[0, (k == n0 + 10) | ((k + 1 == n0 + 10) & (alpha < 1))] = np.nan
    lost = (k == n0 + 20) | ((k + 1 == n0 + 20) & (alpha < 1))
    L[:, lost] = np.nan
    ctx = truth.copy()
    ctx[n0:] = -1
    d = decide_span(L, clock, 1.0, n0, P, model, ctx, 0, straddle=True)
    assert (d.levels[10] == truth[n0 + 10]).all()
    assert (d.n_obs[20] == 0).all() and (d.n_obs[10] > 0).all()
    ok = np.ones(P - n0, bool)
    ok[20] = False
    assert (d.levels[ok] == truth[n0:][ok]).all()
