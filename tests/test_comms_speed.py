"""The demodulator's fast paths (issue 11: less CPU per block and per packet) give exactly
what the paths they replace give: the compiled outlier test of the channel estimate, the
candidate selection, decisions and margins, the quality summary, Gray demapping, the
frame map, the interpolation error bound; the packet assembler's direct append of the
usual block and its copy-free trimming; and nothing compiles after the warm-up."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.core.config import TransmitterConfig
from iscd.decode.comms import channel, decide, demod
from iscd.decode.comms.packets import PacketAssembler
from iscd.decode.comms.settings import ReceiverConfig
from iscd.decode.comms.synth import SynthCamera, synth_recording
from iscd.decode.comms.timing import SymbolClock, frame_map, frame_map_range


def _bits(x: object) -> np.ndarray:
    return np.asarray(x, dtype=np.float64).view(np.int64)


def test_outliers_match_the_exact_medians() -> None:
    """:func:`channel._outliers` (medians bracketed by exponent histograms) drops exactly the
    samples :func:`channel._outliers_exact` (every median selected) drops."""
    rng = np.random.default_rng(5)
    seen_bad = 0
    for t in range(1500):
        n, N, M = int(rng.integers(1, 60)), int(rng.integers(1, 10)), int(rng.integers(2, 10))
        kind = t % 5
        if kind == 0:
            r = np.abs(rng.standard_cauchy((n, N)))
        elif kind == 1:
            r = np.abs(rng.normal(0, 1, (n, N)))
        elif kind == 2:
            r = np.abs(np.round(rng.normal(0, 2, (n, N))))  # ties and zeros
        elif kind == 3:
            r = np.abs(rng.normal(0, 1, (n, N))) * 10.0 ** rng.integers(-300, 300, (n, N))
        else:
            r = np.abs(rng.normal(0, 1, (n, N)))
            r[rng.random((n, N)) < 0.1] *= rng.uniform(2, 20)  # near the threshold
        r[rng.random((n, N)) < 0.05] = np.nan
        y = rng.normal(0, 1, (n, N))
        lev = rng.integers(-1, M + 2, (n, N))
        ok = np.isfinite(r) & (lev >= 0)
        cnt = np.bincount(np.minimum(lev[ok], M - 1), minlength=M).astype(np.int64)
        floor = float(rng.choice([0.3, 1e-9]))
        a = channel._outliers(y, lev, M, r, cnt, floor, 6.0)
        b = channel._outliers_exact(y, lev, M, r, cnt, floor, 6.0)
        assert a[1] == b[1]
        np.testing.assert_array_equal(a[0], b[0])
        seen_bad += b[1]
    assert seen_bad > 100


@pytest.mark.parametrize("M", [4, 5, 8, 16])
def test_select_candidates_is_numpys_argpartition(M: int) -> None:
    rng = np.random.default_rng(M)
    for t in range(200):
        S, N = int(rng.integers(1, 40)), int(rng.integers(1, 70))
        T = int(rng.integers(1, M))
        c = rng.normal(0, 1, (S, N, M)).astype(np.float32)
        if t % 2 == 0:
            c = np.round(c * 3).astype(np.float32)  # many equal costs
        if t % 5 == 0:
            c[rng.random(c.shape) < 0.05] = np.nan
        if t % 7 == 0:
            c[rng.random((S, N)) < 0.3] = 0.0  # NaN observations cost nothing
        np.testing.assert_array_equal(decide.select_candidates(c, T),
                                      np.argpartition(c, T - 1, axis=-1)[..., :T])


def test_finish_kernels_match_numpy() -> None:
    """Argmin (first of equal minima), runner-up margins and runner-up levels:
    :func:`decide._finish_kernel`, :func:`decide.clean_levels` and :func:`decide._finish_span`
    as numpy's :func:`decide._finish`."""
    rng = np.random.default_rng(2)
    for t in range(300):
        S, N, M = int(rng.integers(1, 6)), int(rng.integers(1, 6)), int(rng.integers(1, 9))
        c = rng.normal(0, 1, (S, N, M)).astype(np.float32)
        if t % 3 == 0:
            c = np.round(c * 2).astype(np.float32) / 2
        ref = decide._finish(0, c, np.zeros((S, N), np.int64))
        lev, mar, run = decide._finish_kernel(c)
        np.testing.assert_array_equal(lev, ref.levels)
        np.testing.assert_array_equal(run, ref.runner_up)
        if M >= 2:  # the runner-up is another level, of the least cost but the decision's
            assert (run != lev).all()
            got = np.take_along_axis(c, run[..., None], -1)[..., 0]
            np.testing.assert_array_equal(got - np.take_along_axis(c, lev[..., None], -1)[..., 0],
                                          mar.astype(np.float32))
        np.testing.assert_array_equal(mar, ref.margin)  # (numpy's partition may order -0, +0 otherwise)
        np.testing.assert_array_equal(decide.clean_levels(c), ref.levels)
        if M >= 2:
            T = int(rng.integers(1, M + 1))
            cand = np.ascontiguousarray(np.argsort(rng.random((S, N, M)), -1)[..., :T])
            extra = rng.normal(0, 1, (S, N, T)).astype(np.float32)
            full = rng.normal(0, 1, (S, N, M)).astype(np.float32)
            n_obs = rng.integers(0, 3, (S, N))
            no_clean = n_obs == 0
            lv, mr, nob, ru = decide._finish_span(c, cand, extra, full, n_obs, n_obs, no_clean, True)
            r1 = decide._finish(0, np.take_along_axis(c, cand, -1) + extra, n_obs)
            r2 = decide._finish(0, c + full, n_obs)
            want_lev = np.where(no_clean, r2.levels, np.take_along_axis(cand, r1.levels[..., None], -1)[..., 0])
            np.testing.assert_array_equal(lv, want_lev)
            np.testing.assert_array_equal(mr, np.where(no_clean, r2.margin, r1.margin))
            np.testing.assert_array_equal(nob, 2 * n_obs)
            want_run = np.where(no_clean, r2.runner_up,
                                np.take_along_axis(cand, r1.runner_up[..., None], -1)[..., 0])
            np.testing.assert_array_equal(ru, want_run)


def test_margin_summary_is_numpys() -> None:
    rng = np.random.default_rng(3)
    for t in range(1500):
        n = int(rng.choice([1, 2, 3, 5, 100, 101, 1000, 38400, int(rng.integers(1, 5000))]))
        kind = t % 6
        if kind == 0:
            m = np.abs(rng.normal(0, 20, n))
        elif kind == 1:
            m = np.round(np.abs(rng.normal(0, 5, n)))
        elif kind == 2:
            m = np.abs(rng.standard_cauchy(n)) * 10.0 ** rng.integers(-5, 5)
        elif kind == 3:
            m = np.full(n, 7.25)
        elif kind == 4:
            m = rng.exponential(30, n).astype(np.float32).astype(np.float64)
        else:
            m = np.abs(rng.normal(0, 20, n))
            m[rng.random(n) < 0.1] = rng.choice([np.inf, np.nan, -1.0, -0.0, 0.0])
        if t % 2:
            m = m.reshape(-1, 1)
        with np.errstate(invalid="ignore"):
            want = (m.min(), np.percentile(m, 1), np.median(m))
            got = demod.margin_summary(m)
        np.testing.assert_array_equal(_bits(got[:3]), _bits(want))
        assert got[3] == int((m < 4.0).sum())
    assert demod.margin_summary(np.zeros((0, 4))) == (0.0, 0.0, 0.0, 0)


def test_decode_data_is_the_air_interfaces() -> None:
    rng = np.random.default_rng(4)
    for M in (2, 4, 8, 16, 32):
        for N, F in ((1, 37), (3, 21), (64, 600)):
            air = AirInterface(levels=M, n_leds=N, data_symbols=F)
            good = air.encode_data(rng.integers(0, 256, air.payload_bytes, dtype=np.uint8).tobytes())
            assert demod.decode_data(air, good) == air.decode_data(good)
            assert demod.decode_data(air, good)[1]
            for lo, hi in ((1, M + 1), (0, M + 3)):  # out of range: clipped
                lv = rng.integers(lo, hi, (F, N)).astype(np.uint8)
                assert demod.decode_data(air, lv) == air.decode_data(lv)


def test_frame_map_range_is_frame_map() -> None:
    rng = np.random.default_rng(6)
    for _ in range(3000):
        clock = SymbolClock(float(rng.uniform(-50, 3000)),
                            float(rng.choice([2.0, 2.0002, 2 / (1 + 1e-4), 2.5, 3.0])))
        e = float(rng.choice([1.0, 0.5, 0.999, rng.uniform(0.01, 1)]))
        lo = int(rng.integers(0, 3000))
        hi = lo + int(rng.integers(-3, 200))
        k1, a1 = frame_map(np.arange(lo, hi), clock, e)
        k2, a2 = frame_map_range(lo, hi, clock, e)
        np.testing.assert_array_equal(k1, k2)
        np.testing.assert_array_equal(_bits(a1), _bits(a2))


def test_interp_error_kernel_is_the_numpy_formula() -> None:
    rng = np.random.default_rng(7)
    for t in range(300):
        M = int(rng.integers(2, 17))
        mu = np.cumsum(rng.normal(5, 3, (2, 3, M)), -1)
        if t % 7 == 0:
            mu = np.round(mu)
        s = np.diff(mu, axis=-1)
        ds = np.abs(np.diff(s, axis=-1))
        pad = np.zeros(ds.shape[:-1] + (1,))
        want = 0.125 * np.maximum(np.concatenate([pad, ds], -1), np.concatenate([ds, pad], -1))
        np.testing.assert_array_equal(_bits(channel.ChannelModel(mu, np.ones_like(mu)).interp_error),
                                      _bits(want))


def _stream(monkeypatch: pytest.MonkeyPatch | None, fast: bool, cfg: ReceiverConfig | None = None,
            gaps: bool = False, nan: bool = False):
    tx = TransmitterConfig(rows=2, cols=2, levels=8, data_symbols=120)
    air = AirInterface.from_config(tx)
    cams = [SynthCamera(peak_dn=120, read_noise_dn=1.5), SynthCamera(peak_dn=60, read_noise_dn=1.5)]
    rec = synth_recording(air, cams, n_packets=9, drift_ppm=80.0, seed=11)
    L = rec.L.copy()
    rng = np.random.default_rng(12)
    if nan:
        L[rng.random(L.shape) < 0.01] = np.nan
    ids = np.arange(rec.t_s.size)
    if gaps:
        ids = ids[rng.random(ids.size) > 0.02]
    asm = PacketAssembler(tx, rec.fps, rec.exposure_s, cfg)
    if not fast:
        monkeypatch.setattr(asm, "_fast_push", lambda *a: False)
    out = []
    for a in range(0, ids.size, 16):
        i = ids[a:a + 16]
        out += asm.push(i + 500, rec.t_s[i], L[0][i], L[1][i])
    out += asm.flush()
    return out, asm


@pytest.mark.parametrize("gaps,nan,cameras", [(False, False, "both"), (True, True, "both"),
                                              (False, True, "left")])
def test_fast_push_and_trim_give_the_same_packets(monkeypatch: pytest.MonkeyPatch, gaps: bool,
                                                  nan: bool, cameras: str) -> None:
    """The direct append of a consecutive block and the copy-free trim: the same packets,
    statistics and buffered luminance as the general path (over ~10 trims and the moves of
    the buffer to the front of its allocation)."""
    cfg = ReceiverConfig(cameras=cameras)
    a, asm_a = _stream(None, True, cfg, gaps, nan)
    b, asm_b = _stream(monkeypatch, False, cfg, gaps, nan)
    assert len(a) == len(b) >= 7
    for p, q in zip(a, b):
        assert (p.frame, p.crc_ok, p.payload, p.raw) == (q.frame, q.crc_ok, q.payload, q.raw)
        assert p.t_s == q.t_s and p.u0_frames == q.u0_frames
        np.testing.assert_array_equal(p.levels, q.levels)
        np.testing.assert_array_equal(p.margins, q.margins)
        assert p.quality == q.quality
    assert asm_a.stats == asm_b.stats
    assert (asm_a._n, asm_a._base) == (asm_b._n, asm_b._base)
    np.testing.assert_array_equal(asm_a._L[:, :asm_a._n], asm_b._L[:, :asm_b._n])
    np.testing.assert_array_equal(asm_a._t[:asm_a._n], asm_b._t[:asm_b._n])


def test_the_assembler_compiles_nothing_after_the_warm_up() -> None:
    """After :func:`iscd.core.jit.warm_up` the packet assembler (both cameras, one camera,
    gaps and NaN luminance, the static channel) needs no new compiled signature."""
    from iscd.core import jit

    jit.warm_up()
    before = jit.signatures()
    tx = TransmitterConfig(rows=8, cols=8, levels=8)
    air = AirInterface.from_config(tx)
    cams = [SynthCamera(peak_dn=500, led_gain_spread=0.05, read_noise_dn=2),
            SynthCamera(peak_dn=125, led_gain_spread=0.05, read_noise_dn=2)]
    rec = synth_recording(air, cams, n_packets=2, drift_ppm=100.0, seed=1)
    rng = np.random.default_rng(3)
    for cfg, drop in ((ReceiverConfig(), False), (ReceiverConfig(cameras="left"), False),
                      (ReceiverConfig(), True), (ReceiverConfig(channel_window_symbols=0), False)):
        asm = PacketAssembler(tx, rec.fps, rec.exposure_s, cfg)
        L = rec.L.copy()
        ids = np.arange(rec.t_s.size)
        if drop:
            L[rng.random(L.shape) < 0.01] = np.nan
            ids = ids[rng.random(ids.size) > 0.02]
        got = []
        for a in range(0, ids.size, 16):
            i = ids[a:a + 16]
            got += asm.push(i, rec.t_s[i], L[0][i], L[1][i])
        got += asm.flush()
        assert got
    after = jit.signatures()
    grown = {k: v for k, v in after.items() if v != before.get(k) and ".comms." in k}
    assert grown == {}
