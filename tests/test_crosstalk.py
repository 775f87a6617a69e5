"""An array's neighbours' light in each LED's luminance (iscd.decode.comms.crosstalk):
neighbour indices, the estimate against known fractions, the cancellation, and packets of an
8x8 array with crosstalk that fail without it and decode with it."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.core.config import TransmitterConfig
from iscd.decode.comms.crosstalk import (DIRECTIONS, MIN_CROSSTALK, cancel_crosstalk, estimate_crosstalk,
                                         grid_neighbours)
from iscd.decode.comms.packets import Packet, PacketAssembler
from iscd.decode.comms.synth import SynthCamera, SynthRecording, synth_recording


def _with_crosstalk(L: np.ndarray, coef: np.ndarray, nb: np.ndarray, dark_dn: float) -> np.ndarray:
    """L (C, n, N) plus coef[c, d] x the light above dark of neighbour d (0 past the edge)."""
    out = L.astype(np.float64).copy()
    for d in range(nb.shape[0]):
        ok = nb[d] >= 0
        out[:, :, ok] += coef[:, d, None, None] * (L[:, :, nb[d][ok]] - dark_dn)
    return out


def test_neighbours_of_a_3_by_4_array() -> None:
    nb = grid_neighbours(3, 4)
    assert nb.shape == (len(DIRECTIONS), 12)
    up, down, left, right = nb
    assert (up[0], down[0], left[0], right[0]) == (-1, 4, -1, 1)  # top-left corner
    assert (up[5], down[5], left[5], right[5]) == (1, 9, 4, 6)  # row 1, column 1
    assert (up[11], down[11], left[11], right[11]) == (7, -1, 10, -1)  # bottom-right corner
    # every link goes both ways
    for d, back in ((0, 1), (2, 3)):
        for i in range(12):
            if nb[d, i] >= 0:
                assert nb[back, nb[d, i]] == i
    with pytest.raises(ValueError, match="grid"):
        grid_neighbours(0, 4)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_estimate_recovers_known_fractions(seed: int) -> None:
    """Random levels on an 8x8 array, per-LED gains and offsets, known fractions that differ
    per camera and direction, noise: the estimate within 0.002 of each."""
    rng = np.random.default_rng(seed)
    M, N, n = 8, 64, 600
    nb = grid_neighbours(8, 8)
    lev = rng.integers(0, M, size=(n, N))
    gain = rng.uniform(15.0, 20.0, size=(2, N)) * np.array([1.0, 0.25])[:, None]
    x = 30.0 + gain[:, None, :] * lev[None]  # (C, n, N)
    truth = np.array([[0.03, 0.025, 0.02, 0.035], [0.01, 0.0, 0.015, 0.02]])
    y = _with_crosstalk(x, truth, nb, 30.0) + rng.normal(0.0, 1.0, size=x.shape)
    y[0, 5, 7] = np.nan  # a missing sample is skipped
    got = estimate_crosstalk(y, lev, M, nb)
    assert got.shape == (2, 4)
    np.testing.assert_allclose(got, truth, atol=0.002)


def test_no_crosstalk_is_estimated_as_none() -> None:
    rng = np.random.default_rng(4)
    nb = grid_neighbours(8, 8)
    lev = rng.integers(0, 8, size=(600, 64))
    y = (20.0 + 18.0 * lev + rng.normal(0.0, 1.0, size=lev.shape))[None]
    assert np.abs(estimate_crosstalk(y, lev, 8, nb)).max() < MIN_CROSSTALK


def test_cancelling_leaves_each_led_its_own_light() -> None:
    """Noise-free: after cancelling, an LED's luminance differs from its own light by a
    per-LED constant and second-order terms (a^2 of the light) only."""
    rng = np.random.default_rng(5)
    nb = grid_neighbours(8, 8)
    lev = rng.integers(0, 8, size=(400, 64))
    x = (30.0 + 18.0 * lev)[None]
    a = np.full((1, 4), 0.04)
    y = _with_crosstalk(x, a, nb, 30.0)
    out = cancel_crosstalk(y, a, nb)
    resid = out - x
    resid -= resid.mean(axis=1, keepdims=True)  # the per-LED constant
    before = y - x
    before -= before.mean(axis=1, keepdims=True)
    assert np.abs(before).max() > 10.0  # the neighbours' light: several DN
    assert np.abs(resid).max() < 4 * 0.04 ** 2 * 18 * 7 * 4  # second order
    assert out.flags.c_contiguous and out.dtype == np.float64
    with pytest.raises(ValueError, match="do not fit"):
        cancel_crosstalk(y, np.zeros((2, 4)), nb)


def _decode(tx: TransmitterConfig, rec: SynthRecording, L: np.ndarray, grid: bool) -> list[Packet]:
    asm = PacketAssembler(tx, rec.fps, rec.exposure_s)
    assert asm.grid == (8, 8)
    if not grid:
        asm.grid = None
    out: list[Packet] = []
    for a in range(0, rec.t_s.size, 250):
        i = np.arange(a, min(a + 250, rec.t_s.size))
        out += asm.push(i, rec.t_s[i], L[0][i], L[1][i])
    return out + asm.flush()


@pytest.mark.parametrize("a,seed", [(0.03, 1), (0.05, 2)])
def test_an_arrays_packets_with_crosstalk_decode_once_it_is_cancelled(a: float, seed: int) -> None:
    """The training's neighbours send the LED's own level (above and below) or one off
    (beside): fitted there, the centroids are biased for random data. Without the
    cancellation the packets fail their CRC; with it they decode bit-exact."""
    tx = TransmitterConfig(rows=8, cols=8, levels=8, data_symbols=600, idle_symbols=0)
    air = AirInterface.from_config(tx)
    cams = [SynthCamera(peak_dn=60, read_noise_dn=1.0), SynthCamera(peak_dn=15, read_noise_dn=1.0)]
    rec = synth_recording(air, cams, n_packets=2, drift_ppm=80, phase_s=0.0011, seed=seed)
    L = _with_crosstalk(rec.L, np.full((2, 4), a), grid_neighbours(8, 8), 10.0)
    without = _decode(tx, rec, L, grid=False)
    assert len(without) == 2 and not any(p.crc_ok for p in without)
    got = _decode(tx, rec, L, grid=True)
    assert len(got) == 2
    for p in got:
        j = int(np.argmin(np.abs(rec.packet_starts_s - p.t_s)))
        assert p.crc_ok and p.payload == rec.payloads[j]


def test_one_led_and_shapeless_transmitters_have_no_grid() -> None:
    one = TransmitterConfig(rows=1, cols=1, levels=8, data_symbols=100, idle_symbols=0)
    assert PacketAssembler(one, 1000.0, 1e-3).grid is None
    wide = TransmitterConfig(rows=2, cols=4, levels=8, data_symbols=100, idle_symbols=0)
    assert PacketAssembler(wide, 1000.0, 1e-3).grid == (2, 4)
