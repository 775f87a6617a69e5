"""Air interface v1 (SPEC section 3): round trips, payload lengths, header, training, Gray."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from iscd.core.airinterface import (BARKER13, AirInterface, AirInterfaceError, duty, gray_decode,
                               gray_encode, payload_capacity, random_payload)


@pytest.mark.parametrize("levels", [2, 4, 8, 16])
@pytest.mark.parametrize("n_leds", [1, 64])
def test_round_trip_random_payloads(levels: int, n_leds: int) -> None:
    air = AirInterface(levels=levels, n_leds=n_leds)
    rng = np.random.default_rng(levels * 100 + n_leds)
    for _ in range(5):
        payload = random_payload(air, rng)
        assert len(payload) == payload_capacity(600, n_leds, levels)
        data = air.encode_data(payload)
        assert data.shape == (600, n_leds)
        assert data.min() >= 1 and data.max() <= levels
        out, ok = air.decode_data(data)
        assert ok and out == payload


def test_spec_payload_lengths() -> None:
    assert AirInterface(levels=8, n_leds=1).payload_bytes == 221
    assert AirInterface(levels=8, n_leds=64).payload_bytes == 14_396
    assert AirInterface(levels=16, n_leds=64).payload_bytes == 600 * 64 * 4 // 8 - 4
    assert AirInterface(levels=2, n_leds=1).payload_bytes == 600 // 8 - 4


def test_bit_layout_is_msb_first_gray_and_led_interleaved() -> None:
    air = AirInterface(levels=8, n_leds=2, data_symbols=40)
    payload = bytes([0b10100111]) + bytes(air.payload_bytes - 1)
    data = air.encode_data(payload)
    # bits 101 001 11(0) -> values 5, 1, 6 -> Gray indices l with l^(l>>1)=v: 6, 1, 4 -> levels 7, 2, 5
    # data symbol j -> symbol time j // N, LED j % N
    assert data[0, 0] == 7 and data[0, 1] == 2 and data[1, 0] == 5
    # the CRC follows the payload big-endian
    body = payload
    crc = zlib.crc32(body).to_bytes(4, "big")
    out, ok = air.decode_data(data)
    assert ok and out == body
    bits = np.unpackbits(np.frombuffer(body + crc, np.uint8))
    assert bits.size <= 40 * 2 * 3


def test_neighbouring_levels_differ_by_one_bit() -> None:
    for bits in (1, 2, 3, 4, 5):
        l = np.arange(2 ** bits)
        v = gray_encode(l)
        assert np.array_equal(gray_decode(v, bits), l)
        diff = v[1:] ^ v[:-1]
        assert all(bin(int(d)).count("1") == 1 for d in diff)


def test_crc_detects_a_symbol_error() -> None:
    air = AirInterface(levels=16, n_leds=64)
    payload = random_payload(air, np.random.default_rng(3))
    data = air.encode_data(payload)
    data[100, 7] = data[100, 7] % 16 + 1
    _, ok = air.decode_data(data)
    assert not ok


def test_packet_structure() -> None:
    air = AirInterface(levels=8, n_leds=64, idle_symbols=3)
    pkt = air.packet(b"hello")
    assert pkt.shape == (13 + 40 + 600 + 3, 64)
    assert np.array_equal(pkt[:13, 5], np.where(BARKER13 > 0, 8, 1))
    k, i = 7, 9
    assert pkt[13 + k, i] == ((k + i) % 8) + 1
    assert np.all(pkt[-3:] == 1)
    out, ok = air.decode_data(pkt[53:653])
    assert ok and out[:5] == b"hello" and out[5:] == bytes(len(out) - 5)


def test_bad_parameters_and_payloads() -> None:
    with pytest.raises(AirInterfaceError):
        AirInterface(levels=6)
    with pytest.raises(AirInterfaceError):
        AirInterface(levels=2, n_leds=1, data_symbols=8)
    air = AirInterface(levels=8, n_leds=1)
    with pytest.raises(AirInterfaceError, match="exceeds the capacity"):
        air.encode_data(bytes(222))
    with pytest.raises(AirInterfaceError):
        air.decode_data(np.ones((10, 1)))


def test_garbage_levels_do_not_crash_the_decoder() -> None:
    air = AirInterface(levels=8, n_leds=1)
    out, ok = air.decode_data(np.full((600, 1), 99))
    assert len(out) == air.payload_bytes and ok in (True, False)


def test_duty() -> None:
    assert np.allclose(duty(np.arange(1, 9), 8), np.arange(8) / 7)
