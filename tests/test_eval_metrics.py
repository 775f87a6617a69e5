"""The evaluation's pure metrics, checked against the air interface and direct computation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.eval.metrics import (bit_errors, error_stats, goodput_kbps, match_packets, symbol_errors,
                               throughput_kbps)


@pytest.mark.parametrize("levels", [2, 8, 16])
def test_bit_errors_agree_with_the_air_interface_decoder(levels: int) -> None:
    """Corrupt some payload symbols of a real packet: the bit errors counted from the levels
    (Gray mapping) equal the bits that differ in the payload the air interface decodes."""
    rng = np.random.default_rng(levels)
    air = AirInterface(levels=levels, n_leds=4, training_symbols=40, data_symbols=120)
    payload = rng.integers(0, 256, air.payload_bytes, dtype=np.uint8).tobytes()
    sent = air.encode_data(payload)  # (F, N) levels
    got = sent.copy()
    flat = got.reshape(-1)
    payload_syms = air.payload_bytes * 8 // air.bits_per_symbol
    idx = rng.choice(payload_syms, size=25, replace=False)
    flat[idx] = rng.integers(1, levels + 1, size=idx.size)
    decoded, crc_ok = air.decode_data(got)
    want = int(np.unpackbits(np.frombuffer(payload, np.uint8) ^ np.frombuffer(decoded, np.uint8)).sum())
    assert want > 0 and not crc_ok
    assert bit_errors(sent, got, levels) == want
    assert symbol_errors(sent, got) == int(np.count_nonzero(sent != got))


def test_a_one_level_slip_is_one_bit_and_shape_mismatch_is_an_error() -> None:
    lv = np.arange(1, 16)
    assert bit_errors(lv, lv + 1, 16) == lv.size
    assert bit_errors(lv, lv, 16) == 0
    with pytest.raises(ValueError):
        bit_errors(np.ones(3), np.ones(4), 8)
    with pytest.raises(ValueError):
        bit_errors(np.ones(3), np.ones(3), 6)
    with pytest.raises(ValueError):
        symbol_errors(np.ones(3), np.ones((3, 1)))


def test_throughput_4_4_reproduces_the_error_free_numbers_of_the_spec() -> None:
    dt = 653 / 500.0
    assert throughput_kbps(8, 64, 600, dt, 0.0) == pytest.approx(88.2, abs=0.01)
    assert throughput_kbps(16, 64, 600, dt, 0.0) == pytest.approx(117.6, abs=0.02)
    assert throughput_kbps(16, 64, 600, dt, 0.25) == pytest.approx(0.75 * 117.6, abs=0.02)
    assert math.isnan(throughput_kbps(8, 64, 600, dt, float("nan")))
    with pytest.raises(ValueError):
        throughput_kbps(8, 64, 600, 0.0, 0.0)


def test_goodput_counts_only_delivered_payload_bits() -> None:
    dt = 653 / 500.0
    assert goodput_kbps(4, 221, 4, dt) == pytest.approx(8 * 221 / dt / 1000)
    assert goodput_kbps(1, 221, 4, dt) == pytest.approx(8 * 221 / (4 * dt) / 1000)
    assert goodput_kbps(0, 221, 4, dt) == 0.0
    assert math.isnan(goodput_kbps(0, 221, 0, dt))


def test_match_packets_pairs_nearest_within_tolerance() -> None:
    truth = [0.0012, 1.3072, 2.6132]
    dec = [0.0013, 2.6140, 1.9, 1.3069]
    assert match_packets(dec, truth, 1e-3).tolist() == [0, 2, -1, 1]
    assert match_packets([], truth, 1e-3).size == 0
    assert match_packets([0.5], [], 1e-3).tolist() == [-1]


def test_error_stats_against_direct_computation() -> None:
    rng = np.random.default_rng(5)
    truth = rng.uniform(20, 60, 500)
    est = truth + rng.normal(0.03, 0.1, 500)
    est[[3, 77]] = np.nan
    s = error_stats(est, truth)
    e = (est - truth)[np.isfinite(est)]
    assert s.n == 498 and s.failed == 2
    assert s.mae == pytest.approx(np.mean(np.abs(e)))
    assert s.bias == pytest.approx(np.mean(e))
    assert s.rmse == pytest.approx(np.sqrt(np.mean(e ** 2)))
    assert s.rmse >= s.mae >= abs(s.bias)
    none = error_stats(np.full(3, np.nan), np.zeros(3))
    assert none.n == 0 and none.failed == 3 and math.isnan(none.mae)


def test_reference_numbers_are_the_specs() -> None:
    """The report quotes SPEC section 5: table 4.2 and fig. 3.8's bounds."""
    from iscd.eval import reference as ref

    assert ref.table_4_2(None, 4.0, "single", 8) == 74.29 and ref.table_4_2(None, 4.0, "single", 16) == 44.4
    assert ref.table_4_2(4.0, 4.0, "diversity", 16) == 98.33
    assert ref.table_4_2(4.0, 8.0, "hdr", 8) == 88.02 and ref.table_4_2(4.0, 16.0, "hdr", 16) == 105.17
    assert ref.table_4_2(4.0, 2.0, "hdr", 8) is None and ref.table_4_2(4.0, 8.0, "hdr", 4) is None
    assert ref.fig_3_8_ser(8, 55.0)[1] == 0.0 and ref.fig_3_8_ser(8, 60.0)[1] == 6e-3
    assert ref.fig_3_8_ser(2, 60.0)[1] is None
    assert ref.TABLE_4_2_ERROR_FREE_KBPS[8] == pytest.approx(throughput_kbps(8, 64, 600, 653 / 500, 0.0), abs=0.01)
