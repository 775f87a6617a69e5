"""Property-based fuzzing (hypothesis) of the LED board protocol and the air interface's
packet decoder: any input gives a value or the module's own error type
(:class:`~iscd.drivers.board.protocol.ProtocolError` and its subclasses,
:class:`~iscd.core.airinterface.AirInterfaceError`), never another exception.

Bounds: inputs up to 4 KiB of bytes per call (the protocol's MAX_ENCODED is far less), the
deframer's buffer stays <= its max_encoded whatever arrives; packet geometries up to
64 LEDs x 700 data symbols. CI runs a few dozen cases per target, derandomized; set
``ISCD_FUZZ_EXAMPLES=N`` for a long run (docs/hardening.md).
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from fuzzing import fuzz
from hypothesis import example, given
from hypothesis import strategies as st

from iscd.drivers.board import protocol as P
from iscd.drivers.board.emulator import Board
from iscd.core.airinterface import AirInterface, AirInterfaceError

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")  # e.g. a NaN cast is a finding





blobs = st.binary(max_size=4096)


# --------------------------------------------------------------------------- COBS / frames
@fuzz(200)
@given(blobs)
def test_cobs_decode_any_bytes(data: bytes) -> None:
    try:
        out = P.cobs_decode(data)
    except P.CobsError:
        return
    assert isinstance(out, bytes) and len(out) <= len(data)


@fuzz(200)
@given(blobs)
def test_cobs_round_trip(data: bytes) -> None:
    enc = P.cobs_encode(data)
    assert 0 not in enc
    assert P.cobs_decode(enc) == data


@fuzz(200)
@given(blobs)
@example(b"\x01\x02\x03\x04\x05\x06")
def test_parse_body_any_bytes(body: bytes) -> None:
    try:
        f = P.parse_body(body)
    except P.FrameError as e:
        assert isinstance(e.code, P.NakCode)
        return
    assert P.pack_body(f.type, f.seq, f.payload, f.version) == body


@fuzz(200)
@given(st.integers(0, 255), st.integers(0, 255), st.binary(max_size=P.MAX_PAYLOAD), st.integers(0, 255))
def test_frame_round_trip(ftype: int, seq: int, payload: bytes, version: int) -> None:
    wire = P.encode_frame(ftype, seq, payload, version)
    bodies = P.Deframer().feed(wire)
    assert len(bodies) == 1
    assert P.parse_body(bodies[0]) == P.Frame(version, ftype, seq, payload)


@fuzz(100)
@given(st.lists(st.binary(max_size=1024), max_size=20), st.integers(8, 600))
def test_deframer_bounded(chunks: list[bytes], max_encoded: int) -> None:
    d = P.Deframer(max_encoded=max_encoded)
    for c in chunks:
        for body in d.feed(c):
            assert isinstance(body, bytes)
        assert d.pending <= max_encoded


# --------------------------------------------------------------------------- messages
UNPACKERS = [P.BoardInfo.unpack, P.BoardConfig.unpack, P.LoadChunk.unpack, P.BoardStatus.unpack,
             P.Nak.unpack]


@fuzz(300)
@given(st.sampled_from(UNPACKERS), st.binary(max_size=300))
def test_message_unpack_any_bytes(unpack, payload: bytes) -> None:  # type: ignore[no-untyped-def]
    try:
        msg = unpack(payload)
    except P.MessageError:
        return
    if hasattr(msg, "as_dict"):
        msg.as_dict()


# --------------------------------------------------------------------------- the board (firmware side)
@fuzz(150)
@given(blobs)
def test_board_receive_any_bytes(data: bytes) -> None:
    b = Board()
    out = b.receive(data)
    assert isinstance(out, bytes)
    b.status().pack()


def _config_payloads() -> st.SearchStrategy[bytes]:
    return st.builds(lambda *v: struct.pack("<BBBBIIHHH", *v),
                     st.integers(0, 255), st.integers(0, 255), st.integers(0, 255), st.integers(0, 255),
                     st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1),
                     st.integers(0, 2**16 - 1), st.integers(0, 2**16 - 1), st.integers(0, 2**16 - 1))


def _load_payloads() -> st.SearchStrategy[bytes]:
    return st.builds(lambda off, tot, data: P.LOAD_HEADER.pack(off, tot) + data,
                     st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1), st.binary(max_size=P.MAX_CHUNK))


commands = st.tuples(
    st.sampled_from([int(c) for c in P.Command] + [0, 0x7F, 0xFF]),
    st.integers(0, 255),
    st.one_of(st.binary(max_size=64), _config_payloads(), _load_payloads()))


@fuzz(150)
@given(st.lists(commands, max_size=12), st.integers(0, 100_000))
@example([(int(P.Command.SET_CONFIG), 1, struct.pack("<BBBBIIHHH", 8, 8, 8, 0, 500_000, 50_000, 40, 600, 0)),
          (int(P.Command.LOAD_PAYLOAD), 2, P.LOAD_HEADER.pack(0, 10) + b"0123456789"),
          (int(P.Command.START), 3, b"")], 1000)
def test_board_command_sequences(cmds: list[tuple[int, int, bytes]], symbols: int) -> None:
    """Well-framed commands with arbitrary payloads: the board replies to each (ACK or NAK)
    and its state stays usable (status, levels)."""
    t = [0.0]
    b = Board(clock=lambda: t[0])
    for ftype, seq, payload in cmds:
        out = b.receive(P.encode_frame(ftype, seq, payload[:P.MAX_PAYLOAD]))
        bodies = P.Deframer().feed(out)
        assert len(bodies) <= 1
        for body in bodies:
            reply = P.parse_body(body)
            assert reply.type in (int(P.ReplyType.ACK), int(P.ReplyType.NAK))
        t[0] += 0.01
    b.status().pack()
    if b.config is not None and b.sequence() is not None:
        lv = b.levels(symbols, 4)
        assert lv.shape[0] == 4


# --------------------------------------------------------------------------- air interface
def _air(levels: int, n: int, k: int, f: int, g: int) -> AirInterface | None:
    try:
        return AirInterface(levels=levels, n_leds=n, training_symbols=k, data_symbols=f, idle_symbols=g)
    except AirInterfaceError:  # too small to carry the CRC: not a geometry to decode with
        return None


geometries = st.builds(_air, st.sampled_from([2, 4, 8, 16]), st.integers(1, 64), st.integers(0, 50),
                       st.integers(1, 700), st.integers(0, 10)).filter(lambda a: a is not None)


@fuzz(100)
@given(st.integers(-5, 2**20), st.integers(-5, 100), st.integers(-5, 100), st.integers(-5, 1000),
       st.integers(-5, 100))
def test_air_interface_geometry(levels: int, n: int, k: int, f: int, g: int) -> None:
    try:
        air = AirInterface(levels=levels, n_leds=n, training_symbols=k, data_symbols=f, idle_symbols=g)
    except AirInterfaceError:
        return
    assert air.payload_bytes >= 0 and air.period_symbols >= air.packet_symbols


def test_decode_data_non_finite_levels_regression() -> None:
    """Found by the fuzzer: NaN levels were cast to int64 (undefined value, RuntimeWarning)."""
    air = AirInterface(levels=2, n_leds=1, training_symbols=0, data_symbols=32)
    lv = np.full((32, 1), np.nan)
    lv[0, 0], lv[1, 0] = np.inf, -np.inf
    payload, ok = air.decode_data(lv)
    assert len(payload) == air.payload_bytes and not ok
    with pytest.raises(AirInterfaceError):
        air.decode_data(np.full((32, 1), "x", dtype=object))


@fuzz(150)
@given(geometries, st.data())
def test_decode_data_any_levels(air: AirInterface, data: st.DataObject) -> None:
    shape = data.draw(st.sampled_from([(air.data_symbols, air.n_leds), (air.data_symbols, air.n_leds + 1),
                                       (air.n_leds,), (0, air.n_leds)]))
    kind = data.draw(st.sampled_from(["int", "wide", "float"]))
    n = int(np.prod(shape))
    seed = data.draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    if kind == "int":
        lv = rng.integers(1, air.levels + 1, n).reshape(shape)
    elif kind == "wide":
        lv = rng.integers(-2**40, 2**40, n).reshape(shape)
    else:
        lv = rng.choice(np.array([np.nan, np.inf, -np.inf, 0.5, 1e300, 3.0]), n).reshape(shape)
    try:
        payload, ok = air.decode_data(lv)
    except AirInterfaceError:
        assert shape != (air.data_symbols, air.n_leds)
        return
    assert isinstance(payload, bytes) and len(payload) == air.payload_bytes and isinstance(ok, bool)


@fuzz(100)
@given(geometries, st.binary(max_size=400))
def test_encode_decode_round_trip(air: AirInterface, payload: bytes) -> None:
    try:
        lv = air.encode_data(payload)
    except AirInterfaceError:
        assert len(payload) > air.payload_bytes
        return
    body, ok = air.decode_data(lv)
    assert ok and body == payload.ljust(air.payload_bytes, b"\0")
