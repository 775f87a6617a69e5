"""Board protocol v1, pure layer: CRC, COBS, frames, the stream deframer, message layouts."""

from __future__ import annotations

import re
import zlib
from pathlib import Path

import numpy as np
import pytest

from iscd.drivers.board import protocol as P

DOC = Path(__file__).resolve().parents[1] / "docs" / "board-protocol.md"


def test_crc16_is_ccitt_false_with_its_check_value() -> None:
    assert P.crc16(b"123456789") == 0x29B1
    # independent bitwise reference (the C code of the docs) on random data
    rng = np.random.default_rng(1)
    for n in (0, 1, 7, 263):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        crc = 0xFFFF
        for b in data:
            crc ^= b << 8
            for _ in range(8):
                crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        assert P.crc16(data) == crc


# The examples of the COBS paper / Wikipedia's COBS article.
COBS_VECTORS = [
    (b"\x00", b"\x01\x01"),
    (b"\x00\x00", b"\x01\x01\x01"),
    (b"\x00\x11\x00", b"\x01\x02\x11\x01"),
    (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
    (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
    (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
    (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),
    (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255))),
    (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
    (bytes(range(2, 256)) + b"\x00", b"\xff" + bytes(range(2, 256)) + b"\x01\x01"),
    (bytes(range(3, 256)) + b"\x00\x01", b"\xfe" + bytes(range(3, 256)) + b"\x02\x01"),
]


@pytest.mark.parametrize("raw,enc", COBS_VECTORS)
def test_cobs_reference_vectors(raw: bytes, enc: bytes) -> None:
    assert P.cobs_encode(raw) == enc
    assert P.cobs_decode(enc) == raw


def test_cobs_round_trip_random_and_zero_heavy() -> None:
    rng = np.random.default_rng(7)
    for n in list(range(0, 600, 37)) + [253, 254, 255, 508, 509]:
        for p_zero in (0.0, 0.01, 0.5, 1.0):
            data = rng.integers(1, 256, n, dtype=np.uint8)
            data[rng.random(n) < p_zero] = 0
            raw = data.tobytes()
            enc = P.cobs_encode(raw)
            assert b"\0" not in enc
            assert len(enc) <= P.cobs_max_encoded(n)
            assert P.cobs_decode(enc) == raw


@pytest.mark.parametrize("bad", [b"\x00", b"\x05\x11\x22", b"\x03\x11\x00"])
def test_cobs_decode_rejects_malformed(bad: bytes) -> None:
    with pytest.raises(P.CobsError):
        P.cobs_decode(bad)


def test_frame_round_trip_and_bounds() -> None:
    for payload in (b"", b"\x00\x00", bytes(range(256))):
        wire = P.encode_frame(P.Command.LOAD_PAYLOAD, 200, payload)
        assert wire[0] == 0 and wire[-1] == 0 and b"\0" not in wire[1:-1]
        assert len(wire) - 2 <= P.MAX_ENCODED
        f = P.parse_body(P.cobs_decode(wire[1:-1]))
        assert (f.version, f.type, f.seq, f.payload) == (1, P.Command.LOAD_PAYLOAD, 200, payload)
    with pytest.raises(P.ProtocolError):
        P.encode_frame(P.Command.LOAD_PAYLOAD, 0, bytes(P.MAX_PAYLOAD + 1))


def test_every_single_bit_error_is_detected() -> None:
    body = P.pack_body(P.Command.SET_CONFIG, 9, P.BoardConfig().pack())
    arr = np.frombuffer(body, dtype=np.uint8)
    for bit in range(arr.size * 8):
        bad = arr.copy()
        bad[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(P.FrameError) as e:
            P.parse_body(bad.tobytes())
        assert e.value.code in (P.NakCode.BAD_CRC, P.NakCode.BAD_LENGTH)


def test_parse_body_length_errors_carry_the_seq() -> None:
    with pytest.raises(P.FrameError) as e:
        P.parse_body(b"\x01\x05")
    assert e.value.code is P.NakCode.BAD_LENGTH and e.value.seq is None
    with pytest.raises(P.FrameError) as e:
        P.parse_body(b"\x01\x05\x07\x00")
    assert e.value.code is P.NakCode.BAD_LENGTH and e.value.seq == 7
    # a length field that lies, with a valid CRC over the lie
    head = bytes([1, P.Command.START, 3, 10, 0])
    body = head + P.crc16(head).to_bytes(2, "little")
    with pytest.raises(P.FrameError) as e:
        P.parse_body(body)
    assert e.value.code is P.NakCode.BAD_LENGTH and e.value.seq == 3


def test_deframer_resyncs_after_garbage_partial_frames_and_overflow() -> None:
    rng = np.random.default_rng(3)
    frames = [P.encode_frame(P.Command.GET_STATUS, s, bytes([s]) * s) for s in range(20)]
    noise = rng.integers(1, 256, 40, dtype=np.uint8).tobytes()  # zero-free: no delimiter of its own
    partial = frames[5][: len(frames[5]) // 2]
    overlong = rng.integers(1, 256, 3 * P.MAX_ENCODED, dtype=np.uint8).tobytes()
    stream = (frames[0] + noise + frames[1] + partial + frames[2] + b"\0" + overlong + b"\0"
              + b"".join(frames[3:]))
    d = P.Deframer()
    got = []
    # feed in irregular pieces, a byte at a time for part of it
    i = 0
    while i < len(stream):
        step = int(rng.integers(1, 50)) if i > 100 else 1
        got += d.feed(stream[i:i + step])
        i += step
        assert d.pending <= P.MAX_ENCODED
    seqs = [P.parse_body(b).seq for b in got]
    # frame 0 .. 19 each exactly once; the partial copy of frame 5 is lost with the noise
    assert seqs == list(range(20))
    assert d.stats.overflows >= 1
    assert d.stats.garbage_bytes >= len(overlong)


def test_deframer_counts_invalid_cobs_and_keeps_going() -> None:
    d = P.Deframer()
    good = P.encode_frame(P.Command.START, 1)
    out = d.feed(b"\x05\x01\x00" + good)  # "05 01" claims 4 bytes but has 1
    assert [P.parse_body(b).seq for b in out] == [1]
    assert d.stats.dropped == 1 and d.stats.garbage_bytes == 2


def test_message_layouts_round_trip_and_reject_bad_lengths() -> None:
    cfg = P.BoardConfig(levels=16, rows=4, cols=2, symbol_rate_mhz=123_456, pwm_hz=40_000,
                        training_symbols=7, data_symbols=99, idle_symbols=3)
    assert P.BoardConfig.unpack(cfg.pack()) == cfg
    with pytest.raises(P.MessageError):
        P.BoardConfig.unpack(cfg.pack() + b"\0")  # commands do not grow silently
    info = P.BoardInfo(1, 1, (2, 3, 4), b"ABCDEFGH", 64, 16, 128, 4096, 1_000_000, 100_000)
    assert P.BoardInfo.unpack(info.pack()) == info
    # replies may grow: a v1 host reads its fields and ignores appended ones
    assert P.BoardInfo.unpack(info.pack() + b"v2 extra") == info
    st = P.BoardStatus(P.State.RUNNING, P.Content.LEVELS, P.Fault.LED_OPEN | P.Fault.UNDERRUN,
                       2**32 - 1, 5, 6, 7, 8, 9)
    assert P.BoardStatus.unpack(st.pack()) == st
    with pytest.raises(P.MessageError):
        P.BoardStatus.unpack(st.pack()[:-1])
    with pytest.raises(P.MessageError):
        P.BoardStatus.unpack(bytes([9]) + st.pack()[1:])  # unknown state
    ch = P.LoadChunk(1000, 19196, b"\x00\x01" * 100)
    assert P.LoadChunk.unpack(ch.pack()) == ch
    with pytest.raises(P.ProtocolError):
        P.LoadChunk(0, 1000, bytes(P.MAX_CHUNK + 1)).pack()
    assert P.Nak.unpack(P.Nak(P.Command.START, P.NakCode.BUSY, 70000).pack()) == P.Nak(5, 5, 70000)
    with pytest.raises(P.ProtocolError):
        P.BoardConfig(rows=300).pack()


def test_board_config_from_transmitter_config() -> None:
    from iscd.core.config import default_config

    tx = default_config().transmitter
    c = P.BoardConfig.from_transmitter(tx)
    assert (c.levels, c.n_leds, c.symbol_rate_hz, c.pwm_hz) == (tx.levels, tx.n_leds, tx.symbol_rate_hz, tx.pwm_hz)
    assert (c.training_symbols, c.data_symbols, c.idle_symbols) == (40, 600, 0)


def test_documented_example_frames_match_the_code() -> None:
    text = DOC.read_text(encoding="utf-8")
    hexes = r"((?:[0-9a-f]{2} )*[0-9a-f]{2})"
    bodies = re.findall("body " + hexes, text)
    wires = re.findall("wire " + hexes, text)
    assert len(bodies) == len(wires) == 6
    for body_hex, wire_hex in zip(bodies, wires):
        body, wire = bytes.fromhex(body_hex), bytes.fromhex(wire_hex)
        f = P.parse_body(body)  # CRC and length are right
        assert P.encode_frame(f.type, f.seq, f.payload, f.version) == wire
        assert P.pack_body(f.type, f.seq, f.payload) == body
    # the CRC check value quoted in the docs
    assert "0x29B1" in text and zlib.crc32(b"") == 0
