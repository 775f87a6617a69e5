"""The exposure integral (SPEC section 3): exact on-time == brute-force integration."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.core.airinterface import duty
from iscd.sim.exposure import LedClock, brute_force_on_time, on_time, partial_on_time


def _duty_source(levels_m: int, n_leds: int, seed: int):
    rng = np.random.default_rng(seed)
    table = rng.integers(1, levels_m + 1, size=(4096, n_leds))

    def duty_of(k0: int, k1: int) -> np.ndarray:
        k = np.arange(k0, k1)
        lv = np.where((k >= 0)[:, None], table[np.clip(k, 0, None) % 4096], 1)
        return duty(lv, levels_m)

    return duty_of


@pytest.mark.parametrize("levels_m,pwm_hz,phase,drift", [
    (8, 50_000.0, 0.3e-3, 100.0),
    (8, 3_170.0, 1.7e-3, -200.0),   # carrier period not a divisor of the symbol period
    (2, 1_000.0, 0.0, 0.0),         # OOK with a slow carrier
    (16, 7_919.0, 0.95e-3, 57.0),
])
def test_exact_matches_brute_force(levels_m, pwm_hz, phase, drift):
    clock = LedClock(1 / 500, pwm_hz, phase, drift)
    duty_of = _duty_source(levels_m, 5, seed=levels_m)
    rng = np.random.default_rng(7)
    t0 = np.sort(rng.uniform(0, 0.05, 25))
    t0[0] = 0.0  # starts before symbol 0: dark part
    exact = on_time(t0, 1e-3, clock, duty_of)
    for i, t in enumerate(t0):
        ref = brute_force_on_time(float(t), 1e-3, clock, duty_of, samples_per_pwm_period=400)
        dt = 1e-3 / np.ceil(1e-3 * pwm_hz * 400)
        edges = 2 * (1e-3 * pwm_hz + 2)
        np.testing.assert_allclose(exact[i], ref, atol=edges * dt / 2 + 1e-12)


def test_straddling_window_mixes_two_symbols():
    # even symbols at duty 1, odd ones at duty 0: a 1 ms window starting 0.4 ms before the
    # end of an even symbol integrates exactly 0.4 ms; 0.25 ms before an odd one ends, 0.75 ms.
    clock = LedClock(2e-3, 50_000.0, 0.0, 0.0)

    def duty_of(k0, k1):
        k = np.arange(k0, k1)
        return np.where(k % 2 == 0, 1.0, 0.0)[:, None]

    t0 = np.array([2e-3 - 0.4e-3, 4e-3 - 0.25e-3, 0.5e-3])
    got = on_time(t0, 1e-3, clock, duty_of)[:, 0]
    np.testing.assert_allclose(got, [0.4e-3, 0.75e-3, 1e-3], atol=1e-12)


def test_inside_one_symbol_is_duty_times_exposure_whatever_the_phase():
    # 50 carrier periods in 1 ms: any window inside a symbol integrates duty * exposure.
    clock = LedClock(2e-3, 50_000.0, 0.123e-3, 0.0)
    d = np.array([[0.0, 1 / 7, 3 / 7, 1.0]])

    def duty_of(k0, k1):
        return np.repeat(d, k1 - k0, axis=0)

    t0 = 0.123e-3 + np.linspace(0, 1e-3, 11)  # windows within symbol 0
    got = on_time(t0, 1e-3, clock, duty_of)
    np.testing.assert_allclose(got, np.repeat(d * 1e-3, 11, axis=0), atol=1e-15)


def test_drift_stretches_time():
    # a +1000 ppm LED clock: a fully-on LED still gives exposure on-time (camera clock).
    clock = LedClock(2e-3, 50_000.0, 0.0, 1000.0)
    got = on_time(np.array([10e-3]), 1e-3, clock, lambda a, b: np.ones((b - a, 1)))
    assert got[0, 0] == pytest.approx(1e-3, rel=1e-12)


def test_partial_on_time_formula():
    # tau = 2.5 carrier periods at duty 0.3: 2 * 0.3 + min(0.5, 0.3) = 0.9 periods
    assert partial_on_time(np.array(2.5e-3), 0.3, 1000.0) == pytest.approx(0.9e-3)
    assert partial_on_time(np.array(2.2e-3), 0.3, 1000.0) == pytest.approx(0.8e-3)
