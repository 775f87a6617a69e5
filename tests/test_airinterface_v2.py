"""Air interface v2 (iscd.core.airinterface_v2): the PHY header and the coded data.

Properties (hypothesis, derandomized in CI): encode -> corrupt up to the code's limit
(errors, erasures, a mix; spread by the interleaver) -> decode returns the payload exactly;
past the limit the packet is reported failed or corrected, never delivered wrong; the
header decodes under a dark LED, a straddled symbol time and noise, and a corrupted header
(or none: v1 training, garbage) is rejected with HeaderError, never misread; any garbage
input gives AirInterfaceError, never another exception. The residual-PER check of the
strong mode (SER 1e-2 uniform; one dark LED of 8x8) on two seeds.
"""

from __future__ import annotations

import numpy as np
import pytest
from fuzzing import fuzz
from hypothesis import given
from hypothesis import strategies as st

from iscd.core import airinterface_v2 as v2
from iscd.core.airinterface import AirInterface, AirInterfaceError
from iscd.eval.fec import inject_symbol_errors, residual_per

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")


def _air(levels: int, rows: int, cols: int, fec: str, payload_len: int, k: int = 4) -> v2.AirInterfaceV2:
    return v2.AirInterfaceV2(levels=levels, rows=rows, cols=cols, training_symbols=k, fec=fec,
                             payload_len=payload_len)


airs = st.builds(_air, st.sampled_from([2, 4, 8, 16]), st.integers(1, 8), st.integers(1, 8),
                 st.sampled_from(list(v2.FEC_MODES)), st.integers(0, 2000))


def _payload(air: v2.AirInterfaceV2, seed: int) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, air.payload_len, dtype=np.uint8).tobytes()


# --------------------------------------------------------------------------- packet layout
def test_packet_layout_and_v1_parts() -> None:
    air = v2.AirInterfaceV2(levels=8, rows=8, cols=8, training_symbols=40, fec="rs255_223",
                            payload_len=1000, idle_symbols=3)
    v1 = AirInterface(levels=8, n_leds=64, training_symbols=40, data_symbols=air.data_symbols, idle_symbols=3)
    pk = air.packet(_payload(air, 0))
    assert pk.shape == (air.period_symbols, 64) and air.header_symbols == 9
    assert np.array_equal(pk[:13], v1.header())
    assert np.array_equal(pk[air.training_offset:air.data_offset], v1.training())
    hdr = pk[13:air.training_offset]
    assert set(np.unique(hdr).tolist()) == {1, 8}  # OOK
    assert 0.3 < (hdr == 8).mean() < 0.7  # whitened: no steady light
    assert (pk[air.packet_symbols:] == 1).all()
    assert air.coded_bytes == 1004 + air.codewords * 32
    assert air.data_symbols == -(-air.coded_bytes * 8 // (64 * 3))


@pytest.mark.parametrize("fec,payload_len,goodput_min", [("rs255_239", 17964, 108e3), ("rs255_223", 16732, 101e3),
                                                         ("rs255_191", 14321, 86e3)])
def test_full_8x8_pwm16_packet(fec: str, payload_len: int, goodput_min: float) -> None:
    """F = 600 (v1's default) holds these payloads; goodput at 500 symbols/s."""
    air = v2.AirInterfaceV2.for_capacity(600, levels=16, rows=8, cols=8, fec=fec)
    assert air.payload_len == payload_len and air.data_symbols == 600
    assert air.payload_len * 8 / (air.packet_symbols / 500) > goodput_min
    bigger = v2.AirInterfaceV2(levels=16, rows=8, cols=8, fec=fec, payload_len=payload_len + 1)
    assert bigger.data_symbols > 600


@fuzz(60)
@given(airs, st.integers(0, 2**32 - 1))
def test_round_trip(air: v2.AirInterfaceV2, seed: int) -> None:
    p = _payload(air, seed)
    pk = air.packet(p)
    hdr = v2.parse_header(v2.header_soft(pk[13:air.training_offset], air.levels), air.n_leds)
    rx = v2.AirInterfaceV2.from_header(hdr)
    assert rx == air
    res = rx.decode_data(pk[air.data_offset:air.packet_symbols])
    assert res.crc_ok and res.payload == p and res.corrected == 0 and res.failed_codewords == 0


# --------------------------------------------------------------------------- the code's limit
def _corrupt_codewords(air: v2.AirInterfaceV2, lv: np.ndarray, per_cw: list[tuple[int, int]],
                       rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Corrupt (e errors, f erasures) bytes of each codeword c through the data symbols:
    an error changes every symbol of a byte (a byte error), an erasure marks them."""
    k = air.bits_per_symbol
    lay = air._layout
    lv = lv.copy().reshape(-1)
    er = np.zeros(lv.size, bool)
    for c, (e, f) in enumerate(per_cw):
        stream_pos = np.flatnonzero(lay.cw == c)
        pick = rng.choice(stream_pos, e + f, replace=False)
        for j, b in enumerate(pick):
            syms = np.arange(8 * b // k, (8 * b + 7) // k + 1)
            if j < e:
                lv[syms] = (lv[syms] % air.levels) + 1
            else:
                er[syms] = True
                lv[syms] = rng.integers(1, air.levels + 1, syms.size)
    shape = (air.data_symbols, air.n_leds)
    return lv.reshape(shape), er.reshape(shape)


def _budget(air: v2.AirInterfaceV2, seed: int, over: int) -> list[tuple[int, int]]:
    """Per codeword (e, f) with 2e + f = nsym + over (a symbol may span two bytes, so the
    byte budget is halved for M = 8 and M = 2's bytes span no extra one)."""
    rng = np.random.default_rng(seed)
    nsym = air.mode.nsym
    spans_two = 8 % air.bits_per_symbol != 0  # a corrupted byte's symbols may touch a neighbour
    lim = nsym // 3 if spans_two else nsym  # room for the neighbours' collateral
    out = []
    for _ in range(air.codewords):
        f = int(rng.integers(0, lim + 1))
        out.append(((lim - f) // 2, f))
    return out


@fuzz(40)
@given(airs.filter(lambda a: a.mode.nsym > 0 and a.payload_len > 0), st.integers(0, 2**32 - 1))
def test_decodes_up_to_the_limit(air: v2.AirInterfaceV2, seed: int) -> None:
    p = _payload(air, seed)
    rng = np.random.default_rng(seed)
    lv, er = _corrupt_codewords(air, air.encode_data(p), _budget(air, seed, 0), rng)
    res = air.decode_data(lv, er)
    assert res.crc_ok and res.payload == p and res.failed_codewords == 0


@fuzz(40)
@given(airs.filter(lambda a: a.mode.nsym > 0 and a.payload_len > 0), st.integers(0, 2**32 - 1))
def test_past_the_limit_never_delivers_wrong(air: v2.AirInterfaceV2, seed: int) -> None:
    """One codeword one byte past 2e + f = nsym (errors only and a mix): failed, or (rarely)
    corrected; never a payload that is not the one sent."""
    p = _payload(air, seed)
    rng = np.random.default_rng(seed)
    nsym = air.mode.nsym
    f = int(rng.integers(0, nsym + 1))
    per = [(0, 0)] * air.codewords
    per[int(rng.integers(0, air.codewords))] = ((nsym - f) // 2 + 1, f)
    lv, er = _corrupt_codewords(air, air.encode_data(p), per, rng)
    res = air.decode_data(lv, er)
    assert res.payload is None or res.payload == p
    assert res.crc_ok == (res.payload is not None)


def test_past_the_limit_is_reported_failed() -> None:
    air = v2.AirInterfaceV2(levels=16, rows=8, cols=8, fec="rs255_223", payload_len=5000)
    p = _payload(air, 1)
    per = [(0, 0)] * air.codewords
    per[3] = (17, 0)
    lv, er = _corrupt_codewords(air, air.encode_data(p), per, np.random.default_rng(2))
    res = air.decode_data(lv, er)
    assert res.payload is None and not res.crc_ok and res.failed_codewords == 1
    per[3] = (16, 0)
    lv, er = _corrupt_codewords(air, air.encode_data(p), per, np.random.default_rng(2))
    res = air.decode_data(lv, er)
    assert res.payload == p and res.corrected == 16


def test_erasures_double_what_is_corrected() -> None:
    """A dark LED for the whole packet plus four straddled symbol times on every LED: as
    errors the high-rate mode fails, marked as erasures it decodes."""
    air = v2.AirInterfaceV2.for_capacity(600, levels=16, rows=8, cols=8, fec="rs255_239")
    p = _payload(air, 5)
    lv = air.encode_data(p)
    bad = lv.copy()
    bad[:, 9] = 1
    bad[100:104] = (bad[100:104] % 16) + 1
    er = np.zeros(lv.shape, bool)
    er[:, 9] = True
    er[100:104] = True
    assert air.decode_data(bad).payload is None
    res = air.decode_data(bad, er)
    assert res.payload == p and res.erased > 0


# --------------------------------------------------------------------------- PHY header
def _soft(air: v2.AirInterfaceV2) -> np.ndarray:
    return v2.header_soft(v2.header_levels(air.phy_header), air.levels)


@fuzz(60)
@given(airs, st.integers(0, 2**32 - 1))
def test_header_survives_dark_led_straddle_and_noise(air: v2.AirInterfaceV2, seed: int) -> None:
    rng = np.random.default_rng(seed)
    y = _soft(air) + rng.normal(0, 0.05, _soft(air).shape)  # (M = 16 data: SER ~ 0.5)
    if air.n_leds >= 16:  # (with fewer, one dark LED is more than the data survives)
        y[:, rng.integers(air.n_leds)] = 0.0  # a dark LED
    y[rng.integers(y.shape[0])] = 0.5  # one symbol time straddled on every LED
    y[rng.integers(y.shape[0]), rng.integers(air.n_leds)] = np.nan  # a missing sample
    assert v2.parse_header(y, air.n_leds) == air.phy_header


@fuzz(60)
@given(airs, st.integers(1, 8), st.integers(0, 2**32 - 1))
def test_corrupted_header_is_rejected(air: v2.AirInterfaceV2, n_bits: int, seed: int) -> None:
    """Every copy of 1..8 header bits flipped (the soft combiner sees a clean, wrong bit):
    the CRC-32 rejects it."""
    rng = np.random.default_rng(seed)
    y = _soft(air)
    idx, _ = v2._header_map(air.n_leds)
    for b in rng.choice(v2.HEADER_BITS, n_bits, replace=False):
        y[idx == b] = 1.0 - y[idx == b]
    with pytest.raises(v2.HeaderError):
        v2.parse_header(y, air.n_leds)


@fuzz(100)
@given(st.sampled_from([1, 4, 64]), st.sampled_from(["float", "uniform", "bits", "v1"]), st.integers(0, 2**32 - 1))
def test_no_header_is_rejected(n: int, kind: str, seed: int) -> None:
    """Garbage, random OOK, and v1's training after the Barker are never read as a header."""
    rng = np.random.default_rng(seed)
    shape = (v2.header_symbols(n), n)
    if kind == "float":
        y = rng.choice(np.array([np.nan, np.inf, -np.inf, -1e300, 0.0, 1.0, 0.5]), shape)
    elif kind == "uniform":
        y = rng.random(shape)
    elif kind == "bits":
        y = rng.integers(0, 2, shape).astype(float)
    else:
        m = int(rng.choice([2, 4, 8, 16]))
        v1 = AirInterface(levels=m, n_leds=n, training_symbols=shape[0], data_symbols=700)
        y = v2.header_soft(v1.training(), m)
    with pytest.raises(v2.HeaderError):
        v2.parse_header(y, n)


def test_header_wrong_shape_or_type() -> None:
    with pytest.raises(v2.HeaderError):
        v2.parse_header(np.zeros((3, 64)), 64)
    with pytest.raises(v2.HeaderError):
        v2.parse_header(np.full((9, 64), "x", dtype=object), 64)
    with pytest.raises(v2.HeaderError):  # another LED count than the receiver's
        v2.parse_header(_soft(_air(8, 4, 8, "none", 10)), 64)


@fuzz(60)
@given(st.binary(min_size=17, max_size=17))
def test_unpack_any_bytes(data: bytes) -> None:
    try:
        h = v2.PhyHeader.unpack(data)
    except v2.HeaderError:
        return
    assert h.pack() == data


# --------------------------------------------------------------------------- garbage in
@fuzz(100)
@given(st.integers(-5, 300), st.integers(-5, 300), st.integers(-5, 300), st.integers(-5, 2**25),
       st.sampled_from(["none", "rs255_223", "bogus", ""]), st.integers(-5, 70000), st.integers(-2, 70000))
def test_any_geometry(levels: int, rows: int, cols: int, payload_len: int, fec: str, k: int, f: int) -> None:
    try:
        air = v2.AirInterfaceV2(levels=levels, rows=rows, cols=cols, fec=fec, payload_len=payload_len,
                                training_symbols=k, data_symbols=max(f, 0))
    except AirInterfaceError:
        return
    assert air.packet_symbols > air.data_offset > air.training_offset and air.phy_header.pack()


@fuzz(60)
@given(airs, st.sampled_from(["wide", "float", "shape", "erasures"]), st.integers(0, 2**32 - 1))
def test_decode_any_levels(air: v2.AirInterfaceV2, kind: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    shape = (air.data_symbols, air.n_leds)
    er = None
    if kind == "wide":
        lv = rng.integers(-2**40, 2**40, shape)
    elif kind == "float":
        lv = rng.choice(np.array([np.nan, np.inf, -np.inf, 0.5, 1e300, 3.0]), shape)
    elif kind == "shape":
        lv = rng.integers(1, 3, (shape[0] + 1, shape[1]))
    else:
        lv = rng.integers(1, air.levels + 1, shape)
        er = rng.random((shape[0], shape[1] + int(rng.integers(0, 2)))) < 0.5
    try:
        res = air.decode_data(lv, er)
    except AirInterfaceError:
        assert kind in ("shape", "erasures")
        return
    assert isinstance(res, v2.DataResult) and len(res.raw) == air.payload_len
    assert res.payload is None or res.crc_ok


# --------------------------------------------------------------------------- residual PER
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("impairment", ["uniform", "dark_led"])
def test_strong_mode_loses_nothing_at_ser_1e_2(impairment: str, seed: int) -> None:
    pt = residual_per("rs255_191", 1e-2, 6, seed, impairment)
    assert pt.lost == 0 and pt.wrong == 0 and pt.corrected_mean > 100
    weak = residual_per("none", 1e-2, 2, seed, impairment)  # the impairment is real
    assert weak.lost == 2 and weak.wrong == 0


def test_inject_symbol_errors_rate() -> None:
    lv = np.ones((600, 64), np.uint8) * 3
    out = inject_symbol_errors(lv, 16, 1e-2, np.random.default_rng(0))
    rate = (out != lv).mean()
    assert 0.008 < rate < 0.012 and out.min() >= 1 and out.max() <= 16
