"""Channel estimation (3.11 / 4.2 and the project's model) against known channels."""

from __future__ import annotations

import numpy as np

from iscd.decode.comms.channel import ChannelModel, estimate_dissertation, estimate_iscd


def _samples(rng: np.random.Generator, N: int, M: int, n: int, gains: np.ndarray,
             offsets: np.ndarray, sd: np.ndarray, sat: float = np.inf):
    """n samples per LED of levels cycling like a training sequence; response
    min(gain * (s / (M - 1)) * 100, sat) + offset, per-level noise sd (M,)."""
    lev = (np.arange(n)[:, None] + np.arange(N)[None, :]) % M
    clean = np.minimum(gains[None, :] * lev / (M - 1) * 100.0, sat) + offsets[None, :]
    y = clean + sd[lev] * rng.standard_normal(lev.shape)
    truth_mu = np.minimum(gains[:, None] * np.arange(M)[None, :] / (M - 1) * 100.0, sat) + offsets[:, None]
    return y, lev, truth_mu


def test_dissertation_channel_factors_are_3_11() -> None:
    rng = np.random.default_rng(0)
    N, M = 5, 8
    y, lev, _ = _samples(rng, N, M, 40, rng.uniform(0.8, 1.2, N), rng.uniform(5, 15, N), np.full(M, 2.0))
    yy = np.stack([y, y / 4])
    model = estimate_dissertation(yy, lev, M)
    for c in range(2):
        for s in range(M):  # w^s = 1/(s N_s) sum L^s[n], s = 1-based level; centroid = w^s s
            w = yy[c][lev == s].sum() / ((s + 1) * (lev == s).sum())
            np.testing.assert_allclose(model.mu[c, :, s], w * (s + 1))
    assert model.kind == "euclid"
    # decision 3.12: argmin_s sum_c (L_c - w_c^s s)^2
    L = yy[:, :3, :]
    got = model.level_cost(L).argmin(-1)
    want = ((L[..., None] - model.mu[:, None]) ** 2).sum(0).argmin(-1)
    np.testing.assert_array_equal(got, want)


def test_iscd_channel_recovers_per_led_centroids_and_noise() -> None:
    rng = np.random.default_rng(1)
    N, M = 16, 8
    gains = rng.uniform(0.7, 1.3, N)
    offsets = rng.uniform(5, 15, N)
    sd = np.linspace(1.0, 3.0, M)  # noise grows with the level (shot noise)
    y, lev, truth = _samples(rng, N, M, 40, gains, offsets, sd, sat=110.0)
    model = estimate_iscd(y[None], lev, M, kind="gauss")
    err_iscd = np.abs(model.mu[0] - truth)
    err_pooled = np.abs(estimate_dissertation(y[None], lev, M).mu[0] - truth)
    assert np.median(err_iscd) < 0.25 * np.median(err_pooled)
    assert err_iscd.max() < 1.5 * sd.max()
    # per-level noise: within 35 % of the truth
    est_sd = np.sqrt(np.median(model.var[0], axis=0))
    np.testing.assert_allclose(est_sd, sd, rtol=0.35)
    # with 15x more (decision-directed) samples the centroids get closer still
    y2, lev2, _ = _samples(rng, N, M, 600, gains, offsets, sd, sat=110.0)
    model2 = estimate_iscd(y2[None], lev2, M, kind="gauss")
    assert np.median(np.abs(model2.mu[0] - truth)) < 0.6 * np.median(err_iscd)


def test_unseen_levels_interpolated_and_a_dead_camera_ignored() -> None:
    rng = np.random.default_rng(2)
    M = 16
    lev = np.array([0, 15, 0, 15, 5, 5, 10, 10])[:, None]
    y = 10.0 + lev * 3.0 + rng.normal(0, 0.1, lev.shape)
    yy = np.stack([y, np.full_like(y, np.nan)])
    model = estimate_iscd(yy, lev, M)
    np.testing.assert_allclose(model.mu[0, 0], 10 + 3.0 * np.arange(M), atol=0.5)
    assert (model.var[1] > 1e9).all()  # no data: contributes nothing to a decision
    L = np.array([[[10 + 3.0 * 7]], [[np.nan]]])
    assert model.level_cost(L).argmin(-1)[0, 0] == 7


def test_outliers_do_not_drag_the_centroids() -> None:
    rng = np.random.default_rng(3)
    N, M = 4, 4
    y, lev, truth = _samples(rng, N, M, 200, np.ones(N), np.zeros(N), np.full(M, 1.0))
    bad = rng.random(y.shape) < 0.02  # 2 % mislabelled samples (decision errors)
    lev_noisy = np.where(bad, (lev + 2) % M, lev)
    model = estimate_iscd(y[None], lev_noisy, M)
    assert np.abs(model.mu[0] - truth).max() < 1.0
    assert np.sqrt(model.var[0]).max() < 1.6


def test_interp_and_lookup_agree() -> None:
    rng = np.random.default_rng(4)
    mu = np.sort(rng.uniform(0, 200, (2, 3, 8)), axis=-1)
    var = rng.uniform(1, 4, (2, 3, 8))
    m = ChannelModel(mu, var)
    q = rng.uniform(0, 7, (50, 3))
    a, slope = m.interp(mu, q)
    b, v = m.lookup(q)
    np.testing.assert_allclose(a, b, atol=np.abs(np.diff(mu)).max() / 64 + 1e-9)
    q0 = np.floor(q).astype(int).clip(0, 6)
    want = np.take_along_axis(mu, q0.T[None], -1)  # (2, 3, 50)
    np.testing.assert_allclose(slope, np.take_along_axis(mu, q0.T[None] + 1, -1).transpose(0, 2, 1)
                               - want.transpose(0, 2, 1))
