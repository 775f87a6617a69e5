"""The receiver's compiled kernels agree with their pure-numpy references.

Tolerances (what each kernel can differ by, and why):

* ``ChannelModel._fine`` (lookup tables): bit-identical (same float64 arithmetic, cast).
* ``clean_costs``: bit-identical costs for the Gaussian and Euclidean models (same float32
  operations); for the Student-t model the kernel's float32 log1p is correctly rounded and
  numpy's (libm log1pf) may be 1 ulp off: costs agree to ~1e-7 relative.
* ``decide_span`` with straddling frames: the straddle's float32 log-variance is correctly
  rounded in the kernel and numpy's vectorized log may be 1 ulp off, so costs and margins
  agree to ~1e-6 relative (asserted: |d margin| <= 1e-4 max(|margin|, 1)); the decisions
  are identical.
* ``refine_clock``, ``estimate_iscd``, ``_match_gain``: sums in sample order instead of
  numpy's pairwise order -> u0, p, centroids and variances agree to 1e-9 relative (seen:
  ~1e-13).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.decode.comms.channel import ChannelModel, ChannelTrack, estimate_iscd, estimate_iscd_reference
from iscd.decode.comms.decide import clean_costs, clean_costs_reference, decide_span, decide_span_reference
from iscd.decode.comms.demod import (_match_gain, _match_gain_reference, clean_samples, demodulate_packet,
                                 known_levels)
from iscd.decode.comms.settings import ReceiverConfig
from iscd.decode.comms.synth import SynthCamera, synth_recording
from iscd.decode.comms.timing import SymbolClock, refine_clock, refine_clock_reference


def _setup(peak: float = 40.0, seed: int = 0, n_leds: int = 6, levels: int = 8, nan_frac: float = 0.0):
    air = AirInterface(levels=levels, n_leds=n_leds, data_symbols=200)
    cams = [SynthCamera(peak_dn=peak), SynthCamera(peak_dn=peak / 4)]
    rec = synth_recording(air, cams, n_packets=1, phase_s=0.00061, drift_ppm=50.0, seed=seed,
                          lead_symbols=7)
    L = rec.L.copy()
    if nan_frac:
        rng = np.random.default_rng(seed)
        L[rng.random(L.shape) < nan_frac] = np.nan
    clock = SymbolClock(rec.packet_starts_s[0] * 1000.0, 2.0)
    truth = rec.levels[7:7 + air.packet_symbols].astype(np.int64) - 1
    return air, L, clock, truth


def _margins_close(a: np.ndarray, b: np.ndarray) -> None:
    """|a - b| <= 1e-4 max(|b|, 1) (a float32 ulp of the costs), equal infinities allowed."""
    same = a == b
    with np.errstate(invalid="ignore"):
        near = np.abs(a - b) <= 1e-4 * np.maximum(np.abs(b), 1.0)
    assert np.all(same | near)


@pytest.mark.parametrize("kind", ["gauss", "t", "euclid"])
@pytest.mark.parametrize("nan_frac", [0.0, 0.05])
def test_decide_span_matches_reference(kind: str, nan_frac: float) -> None:
    air, L, clock, truth = _setup(seed=3, nan_frac=nan_frac)
    y, lv = clean_samples(L, clock, 1.0, truth, 0)
    model = dataclasses.replace(estimate_iscd_reference(y, lv, 8), kind=kind, nu=8.0)
    n0, P = air.data_offset, air.packet_symbols
    a = clean_costs(L, clock, 1.0, n0, P, model)
    b = clean_costs_reference(L, clock, 1.0, n0, P, model)
    if kind == "t":
        np.testing.assert_allclose(a.costs, b.costs, rtol=1e-6, atol=1e-6)
    else:
        np.testing.assert_array_equal(a.costs, b.costs)
    np.testing.assert_array_equal(a.n_obs, b.n_obs)
    np.testing.assert_array_equal(a.valid_obs, b.valid_obs)
    ctx = truth.copy()
    ctx[n0 + 30:n0 + 40] = -1  # some unknown neighbours
    for cand in (4, 0, 1):
        for edge in ((), (0,), (0, 7)):
            for straddle in (True, False):
                d = decide_span(L, clock, 1.0, n0, P, model, ctx, 0, straddle, 0.02, cand, None, edge)
                r = decide_span_reference(L, clock, 1.0, n0, P, model, ctx, 0, straddle, 0.02, cand, None, edge)
                np.testing.assert_array_equal(d.levels, r.levels)
                np.testing.assert_array_equal(d.n_obs, r.n_obs)
                _margins_close(d.margin, r.margin)


def test_decide_span_symbols_without_clean_frames() -> None:
    """Symbols seen only in straddles are decided over all M levels (the full-cost path)."""
    air, L, clock, truth = _setup(seed=4)
    y, lv = clean_samples(L, clock, 1.0, truth, 0)
    model = estimate_iscd_reference(y, lv, 8, kind="t", nu=8.0)
    n0, P = air.data_offset, air.packet_symbols
    a = clean_costs(L, clock, 1.0, n0, P, model)
    L2 = L.copy()
    L2[:, a.k[a.alpha >= 1.0][::7]] = np.nan  # every 7th clean frame lost
    d = decide_span(L2, clock, 1.0, n0, P, model, truth, 0, True, 0.02, 4)
    r = decide_span_reference(L2, clock, 1.0, n0, P, model, truth, 0, True, 0.02, 4)
    np.testing.assert_array_equal(d.levels, r.levels)
    np.testing.assert_array_equal(d.n_obs, r.n_obs)
    _margins_close(d.margin, r.margin)


@pytest.mark.parametrize("levels", [2, 8, 16])
def test_fine_tables_bit_identical(levels: int) -> None:
    rng = np.random.default_rng(levels)
    m = ChannelModel(mu=np.cumsum(rng.gamma(2, 10, (2, 5, levels)), -1), var=rng.gamma(2, 3, (2, 5, levels)))
    for a, b in zip(m._fine, m._fine_reference()):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("nan_frac", [0.0, 0.1])
def test_estimate_iscd_matches_reference(nan_frac: float) -> None:
    air, L, clock, truth = _setup(seed=5, nan_frac=nan_frac)
    y, lv = clean_samples(L, clock, 1.0, truth, 0)
    lv = lv.copy()
    lv[::11, 0] = -1  # unlabelled samples
    y = y.copy()
    y[0, 5, 1] += 500.0  # a gross outlier (dropped and refitted)
    for M_used in (8,):
        a = estimate_iscd(y, lv, M_used, kind="t", nu=8.0)
        b = estimate_iscd_reference(y, lv, M_used, kind="t", nu=8.0)
        np.testing.assert_allclose(a.mu, b.mu, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(a.var, b.var, rtol=1e-9)
    # a camera without samples, and levels never seen
    y2 = y.copy()
    y2[1] = np.nan
    lv2 = np.where(lv == 3, -1, lv)
    a = estimate_iscd(y2, lv2, 8)
    b = estimate_iscd_reference(y2, lv2, 8)
    np.testing.assert_allclose(a.mu, b.mu, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(a.var, b.var, rtol=1e-9)


def test_refine_clock_matches_reference() -> None:
    air, L, clock, truth = _setup(seed=6)
    y, lv = clean_samples(L, clock, 1.0, truth, 0)
    model = estimate_iscd(y, lv, 8, kind="t", nu=8.0)
    off = SymbolClock(clock.u0 + 0.07, clock.p * (1 + 40e-6))
    lev = truth.copy()
    lev[100:110] = -1
    track = ChannelTrack((0, 100), (model, dataclasses.replace(model, mu=model.mu * 1.01)))
    for m in (model, track):
        for fit_p in (True, False):
            a, na = refine_clock(L, off, 1.0, lev, 0, m, 2.0, 6e-4, fit_p=fit_p)
            b, nb = refine_clock_reference(L, off, 1.0, lev, 0, m, 2.0, 6e-4, fit_p=fit_p)
            assert na == nb
            assert a.u0 == pytest.approx(b.u0, rel=1e-9, abs=1e-9)
            assert a.p == pytest.approx(b.p, rel=1e-9)


def _gap_setup():
    """Exposure 0.9 frames; boundaries start in the dark gap and drift (-150 ppm) into the
    windows: (luminance, clock at the true phase with the nominal period, true levels, model)."""
    air = AirInterface(levels=8, n_leds=3, data_symbols=200)
    rec = synth_recording(air, [SynthCamera(peak_dn=80), SynthCamera(peak_dn=20)], n_packets=1,
                          phase_s=0.000948, drift_ppm=-150.0, seed=9, exposure_s=0.9e-3)
    clock = SymbolClock(rec.packet_starts_s[0] * 1000.0, 2.0)
    truth = rec.levels[7:7 + air.packet_symbols].astype(np.int64) - 1
    y, lv = clean_samples(rec.L, clock, 0.9, truth, 0)
    return np.ascontiguousarray(rec.L), clock, truth, estimate_iscd(y, lv, 8, kind="t", nu=8.0)


def test_refine_clock_matches_reference_with_a_dark_gap() -> None:
    """The period search (:func:`iscd.decode.comms.timing._clock_cost` on a grid) and the
    Gauss-Newton steps agree in the kernel and the reference."""
    L, clock, truth, model = _gap_setup()
    for fit_p in (True, False):
        a, na = refine_clock(L, clock, 0.9, truth, 0, model, 2.0, 6e-4, fit_p=fit_p)
        b, nb = refine_clock_reference(L, clock, 0.9, truth, 0, model, 2.0, 6e-4, fit_p=fit_p)
        assert na == nb and (na > 0 or not fit_p)
        assert a.u0 == pytest.approx(b.u0, rel=1e-9, abs=1e-9)
        assert a.p == pytest.approx(b.p, rel=1e-9)


def test_clock_cost_matches_reference() -> None:
    from iscd.decode.comms.channel import ChannelTrack
    from iscd.decode.comms.timing import _clock_cost, clock_cost_reference

    L, clock, truth, model = _gap_setup()
    track = ChannelTrack.single(model)
    mu_t, var_t, err_t = track.tables
    for p in (2.0, 2.0003, 1.9996):
        for log_var in (False, True):
            a = _clock_cost(L, 0, L.shape[1], clock.u0, p, 0.9, truth, 0, np.zeros(1, np.int64),
                            mu_t, var_t, err_t, 0.02, 3.0, log_var)
            b = clock_cost_reference(L, 0, L.shape[1], clock.u0, p, 0.9, truth, 0, track, 0.02, 3.0,
                                     log_var)
            assert a == pytest.approx(b, rel=1e-9) and (a > 0 or log_var)


def test_match_gain_matches_reference() -> None:
    air, L, clock, truth = _setup(seed=7, nan_frac=0.02)
    y, lv = clean_samples(L, clock, 1.0, truth, 0)
    model = estimate_iscd(y, lv, 8, kind="t", nu=8.0)
    dim = dataclasses.replace(model, mu=model.mu[:, :, :1] + 0.9 * (model.mu - model.mu[:, :, :1]))
    a = _match_gain(dim, L, clock, 1.0, truth, 60, 120)
    b = _match_gain_reference(dim, L, clock, 1.0, truth, 60, 120)
    np.testing.assert_allclose(a.mu, b.mu, rtol=1e-9)


def test_demodulate_packet_same_decisions() -> None:
    """The whole packet with all kernels: the same levels as before, to the bit; the clock
    and quality figures within rounding."""
    import iscd.decode.comms.channel as ch
    import iscd.decode.comms.decide as de
    import iscd.decode.comms.demod as dm
    import iscd.decode.comms.timing as ti

    air, L, clock, truth = _setup(peak=25.0, seed=8)
    cfg = ReceiverConfig()
    got = demodulate_packet(L, clock.u0 + 0.2, air, 1.0, 2.0, 2.0, 6e-4, cfg)
    patched = [(de, "clean_costs", de.clean_costs_reference), (de, "decide_span", de.decide_span_reference),
               (dm, "decide_span", de.decide_span_reference), (dm, "clean_costs", de.clean_costs_reference),
               (ch, "estimate_iscd", ch.estimate_iscd_reference), (dm, "estimate_iscd", ch.estimate_iscd_reference),
               (ti, "refine_clock", ti.refine_clock_reference), (dm, "refine_clock", ti.refine_clock_reference),
               (dm, "_match_gain", dm._match_gain_reference)]
    saved = [(mod, name, getattr(mod, name)) for mod, name, _ in patched]
    try:
        for mod, name, fn in patched:
            setattr(mod, name, fn)
        ref = demodulate_packet(L, clock.u0 + 0.2, air, 1.0, 2.0, 2.0, 6e-4, cfg)
    finally:
        for mod, name, fn in saved:
            setattr(mod, name, fn)
    np.testing.assert_array_equal(got.levels, ref.levels)
    assert got.crc_ok == ref.crc_ok
    assert got.u0 == pytest.approx(ref.u0, rel=1e-9)
    assert got.p == pytest.approx(ref.p, rel=1e-9)
    _margins_close(got.margins, ref.margins)
    assert (got.levels.astype(np.int64) - 1 == truth[air.data_offset:]).mean() > 0.99


def test_camera_tops_is_nanmax_of_cameras_with_a_finite_value() -> None:
    """Each camera's brightest value (the light match's cap): NaN skipped, infinities kept,
    NaN for a camera without any finite value (all NaN, all -inf, inf and NaN only, none)."""
    from iscd.decode.comms.demod import _camera_tops

    def loop(L: np.ndarray) -> np.ndarray:  # the specification, value by value
        out = np.full(L.shape[0], np.nan)
        for c in range(L.shape[0]):
            v = L[c].ravel()
            fin = np.isfinite(v)
            if fin.any():
                out[c] = np.max(v[~np.isnan(v)])
        return out

    rng = np.random.default_rng(0)
    a = rng.random((5, 20, 4)) * 200
    a[0, 3, 1] = np.inf  # with finite values: +inf is the top
    a[1] = np.nan
    a[1, 2, 2] = np.inf  # inf and NaN only: no finite value
    a[2] = -np.inf
    a[3, :5] = np.nan
    for L in (a, np.zeros((2, 0, 3)), a[:, ::2, 1:]):
        np.testing.assert_array_equal(_camera_tops(L), loop(L))
    assert _camera_tops(a)[0] == np.inf and np.isnan(_camera_tops(a)[1:3]).all()
