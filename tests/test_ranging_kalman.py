"""The optional constant-velocity Kalman filter on range and closing speed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iscd.decode.ranging.kalman import RangeKalman
from iscd.decode.ranging.range import range_sigma

F_PX, B = 3500.0, 0.6


def approach(seconds: float = 2.0, fps: float = 1000.0, z0: float = 60.0, speed: float = 11.1,
             sigma_px: float = 0.08, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Car closing in at ``speed`` m/s from ``z0``; per-frame ranges with disparity noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * fps)) / fps
    z = z0 - speed * t
    d = F_PX * B / z + rng.normal(0, sigma_px, t.size)
    zm = F_PX * B / d
    sig = range_sigma(zm, sigma_px, F_PX, B)
    return t, z, zm, sig


def run(kf: RangeKalman, t: np.ndarray, zm: np.ndarray, sig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    out = [kf.update(float(a), float(b), float(c)) for a, b, c in zip(t, zm, sig)]
    return np.array([s.z_m for s in out]), np.array([s.closing_speed_mps for s in out])


def test_filter_reduces_noise_on_an_approach() -> None:
    t, z, zm, sig = approach()
    zf, vf = run(RangeKalman(), t, zm, sig)
    settled = t > 0.5
    raw_rmse = np.sqrt(np.mean((zm - z)[settled] ** 2))
    kf_rmse = np.sqrt(np.mean((zf - z)[settled] ** 2))
    assert raw_rmse > 0.05                                # there is noise to remove
    assert kf_rmse < raw_rmse / 5
    assert abs(vf[-1] - 11.1) < 0.3                        # closing speed, m/s
    assert abs(np.mean(zf[settled] - z[settled])) < 0.02   # no lag bias at constant speed


def test_outliers_are_gated_and_counted() -> None:
    t, z, zm, sig = approach(seed=1)
    rng = np.random.default_rng(2)
    bad = rng.random(t.size) < 0.05
    bad[:5] = False
    zm = np.where(bad, zm + rng.choice([-15.0, 20.0], t.size), zm)
    kf = RangeKalman()
    zf, _ = run(kf, t, zm, sig)
    assert kf.rejected_total >= 0.9 * bad.sum()
    assert np.sqrt(np.mean((zf - z)[t > 0.5] ** 2)) < 0.05


def test_missing_measurements_only_predict_and_a_lost_track_restarts() -> None:
    kf = RangeKalman(max_rejects=5)
    for i in range(200):
        kf.update(i / 1000, 40.0 - 10 * i / 1000, 0.02)
    s = kf.update(0.2, math.nan, 0.02)                 # no measurement: prediction only
    assert not s.accepted and s.z_m == pytest.approx(38.0, abs=0.05)
    # the target is now really at 25 m (e.g. another transmitter took over the track)
    states = [kf.update(0.201 + i / 1000, 25.0, 0.02) for i in range(10)]
    assert not states[0].accepted
    assert states[-1].z_m == pytest.approx(25.0, abs=0.05)


def test_time_must_not_go_backwards_and_bad_parameters() -> None:
    kf = RangeKalman()
    kf.update(1.0, 30.0, 0.1)
    with pytest.raises(ValueError, match="backwards"):
        kf.update(0.5, 30.0, 0.1)
    with pytest.raises(ValueError):
        RangeKalman(accel_psd=0)
    first = RangeKalman().update(0.0, math.nan, 0.1)
    assert not first.accepted and math.isnan(first.z_m)
