"""LED board serial protocol v1: framing, CRC and message layouts (pure functions, no I/O).

The reference for firmware authors is ``docs/board-protocol.md``; this module is its
executable form, shared by the host driver (:mod:`iscd.drivers.board.client`) and the board
emulator (:mod:`iscd.drivers.board.emulator`).

A frame on the wire is ``0x00 || COBS(body) || 0x00`` with

    body = version u8 | type u8 | seq u8 | length u16 | payload (length bytes) | crc u16

All multi-byte integers are little-endian. ``crc`` is CRC-16/CCITT-FALSE (poly 0x1021,
init 0xFFFF, not reflected, no final XOR; check value 0x29B1 for ``b"123456789"``) over
``version .. payload``. ``length <= MAX_PAYLOAD`` (256), so an encoded frame is at most
:data:`MAX_ENCODED` bytes between delimiters: a receiver drops anything longer and
resynchronises at the next ``0x00``.

Everything received is untrusted (wires pick up noise, hosts have bugs): every parser here
checks lengths exactly and raises :class:`FrameError` / :class:`MessageError` with a
one-line reason instead of reading past a buffer.
"""

from __future__ import annotations

import binascii
import enum
import struct
from dataclasses import dataclass

PROTOCOL_VERSION = 1
"""The version byte of every v1 frame."""

MAX_PAYLOAD = 256
"""Largest payload of a frame, bytes."""

HEADER_LEN = 5
CRC_LEN = 2
MAX_BODY = HEADER_LEN + MAX_PAYLOAD + CRC_LEN
"""Largest frame body (before COBS), bytes: 263."""


def cobs_max_encoded(n: int) -> int:
    """Largest COBS encoding of ``n`` bytes: one code byte per started 254-byte block."""
    return n + n // 254 + 1


MAX_ENCODED = cobs_max_encoded(MAX_BODY)
"""Largest COBS-encoded frame between two delimiters, bytes: 265."""

LOAD_HEADER = struct.Struct("<II")
"""LOAD_PAYLOAD / LOAD_LEVELS header: offset u32, total u32; the chunk's bytes follow."""

MAX_CHUNK = MAX_PAYLOAD - LOAD_HEADER.size
"""Largest chunk of a LOAD_PAYLOAD / LOAD_LEVELS command, bytes: 248."""

LOAD_PROGRESS = struct.Struct("<I")
"""ACK data of LOAD_PAYLOAD / LOAD_LEVELS: bytes loaded so far, u32."""


class Command(enum.IntEnum):
    """Host -> board frame types."""

    GET_INFO = 0x01  # a.k.a. HELLO: always executed, resets the duplicate cache
    SET_CONFIG = 0x02
    LOAD_PAYLOAD = 0x03
    LOAD_LEVELS = 0x04
    START = 0x05
    STOP = 0x06
    GET_STATUS = 0x07
    CLEAR_FAULTS = 0x08


HELLO = Command.GET_INFO

READ_ONLY_COMMANDS = frozenset({Command.GET_INFO, Command.GET_STATUS})
"""Commands the board always executes (never answered from the duplicate cache)."""


class ReplyType(enum.IntEnum):
    """Board -> host frame types. 0x82 (EVENT, unsolicited) is reserved for v2."""

    ACK = 0x80
    NAK = 0x81


class NakCode(enum.IntEnum):
    """Why the board refused a command (NAK ``code``); ``arg`` gives detail, see docs."""

    BAD_CRC = 1
    BAD_LENGTH = 2
    UNKNOWN_COMMAND = 3
    BAD_PARAMETER = 4
    BUSY = 5
    WRONG_STATE = 6
    VERSION_MISMATCH = 7
    TOO_LARGE = 8
    BAD_OFFSET = 9


class State(enum.IntEnum):
    """The board's state (GET_STATUS ``state``)."""

    UNCONFIGURED = 0  # after power-on: no SET_CONFIG yet
    CONFIGURED = 1  # configured, no complete payload / level sequence
    READY = 2  # content loaded, LEDs dark (level 1)
    RUNNING = 3  # sending
    FAULT = 4  # a critical fault is set: LEDs dark until CLEAR_FAULTS


class Content(enum.IntEnum):
    """What the board holds (GET_STATUS ``content``)."""

    NONE = 0
    PAYLOAD = 1
    LEVELS = 2


class Fault(enum.IntFlag):
    """Fault flags (GET_STATUS ``faults``); they stay set until CLEAR_FAULTS."""

    OVERTEMP = 0x01
    UNDERVOLTAGE = 0x02
    LED_SHORT = 0x04
    LED_OPEN = 0x08
    UNDERRUN = 0x10  # the symbol clock missed a deadline
    RX_OVERFLOW = 0x20  # a frame longer than MAX_ENCODED arrived
    POWER_ON_RESET = 0x40  # set at boot: tells the host that the board lost its settings


CRITICAL_FAULTS = Fault.OVERTEMP | Fault.UNDERVOLTAGE | Fault.LED_SHORT
"""Faults that stop the output (state FAULT) until cleared."""

ALL_FAULTS = Fault(0x7F)

CONFIG_FIELDS = ("levels", "rows", "cols", "flags", "symbol_rate_mhz", "pwm_hz",
                 "training_symbols", "data_symbols", "idle_symbols")
"""SET_CONFIG fields in wire order; a BAD_PARAMETER NAK's ``arg`` indexes this tuple."""


class ProtocolError(ValueError):
    """Base of framing and message errors (one-line ``str``)."""


class CobsError(ProtocolError):
    """Bytes that are not a valid COBS encoding."""


class FrameError(ProtocolError):
    """A frame body that is too short, too long or fails its CRC.

    ``code`` is the NAK code a board answers with; ``seq`` the frame's sequence number
    if the frame was long enough to have one (a board NAKs BAD_CRC with it, so the host
    can retransmit at once instead of waiting for its timeout).
    """

    def __init__(self, code: NakCode, message: str, seq: int | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.seq = seq


class MessageError(ProtocolError):
    """A payload whose layout does not match its frame type."""

    def __init__(self, code: NakCode, message: str, arg: int = 0) -> None:
        super().__init__(message)
        self.code = code
        self.arg = arg


# --- CRC and COBS ---------------------------------------------------------------------


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (poly 0x1021, init 0xFFFF, no reflection/xorout)."""
    return binascii.crc_hqx(data, crc)


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: ``data`` without any 0x00 byte.

    Each zero-free run of up to 254 bytes is preceded by a code byte (run length + 1);
    a code below 0xFF implies a 0x00 after its run (except at the very end).
    """
    out = bytearray()
    parts = bytes(data).split(b"\0")
    last = len(parts) - 1
    for i, part in enumerate(parts):
        full_blocks = 0
        while len(part) >= 254:
            out.append(0xFF)
            out += part[:254]
            part = part[254:]
            full_blocks += 1
        if i == last and not part and full_blocks:
            break  # a final run of k*254 bytes needs no trailing 0x01
        out.append(len(part) + 1)
        out += part
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`; raises :class:`CobsError` on a malformed input."""
    out = bytearray()
    n = len(data)
    i = 0
    while i < n:
        code = data[i]
        if code == 0:
            raise CobsError(f"COBS: zero byte at {i}")
        end = i + code
        if end > n:
            raise CobsError(f"COBS: block at {i} runs past the end ({end} > {n})")
        block = data[i + 1:end]
        if 0 in block:
            raise CobsError("COBS: zero byte inside a block")
        out += block
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


# --- frames ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Frame:
    """A decoded, CRC-checked frame."""

    version: int
    type: int
    seq: int
    payload: bytes


_HEADER = struct.Struct("<BBBH")


def pack_body(ftype: int, seq: int, payload: bytes = b"", version: int = PROTOCOL_VERSION) -> bytes:
    """Frame body (before COBS): header, payload, CRC-16."""
    if len(payload) > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(payload)} bytes exceeds the frame limit of {MAX_PAYLOAD}")
    head = _HEADER.pack(version & 0xFF, ftype & 0xFF, seq & 0xFF, len(payload)) + bytes(payload)
    return head + struct.pack("<H", crc16(head))


def encode_frame(ftype: int, seq: int, payload: bytes = b"", version: int = PROTOCOL_VERSION) -> bytes:
    """Wire bytes of one frame: ``0x00 || COBS(body) || 0x00``.

    The leading delimiter ends whatever partial frame noise left in the receiver's buffer,
    so that this frame is not lost with it.
    """
    return b"\0" + cobs_encode(pack_body(ftype, seq, payload, version)) + b"\0"


def parse_body(body: bytes) -> Frame:
    """Check and split a COBS-decoded frame body; raises :class:`FrameError`."""
    n = len(body)
    seq = body[2] if n >= 3 else None
    if n < HEADER_LEN + CRC_LEN:
        raise FrameError(NakCode.BAD_LENGTH, f"frame of {n} bytes is shorter than {HEADER_LEN + CRC_LEN}", seq)
    if n > MAX_BODY:
        raise FrameError(NakCode.BAD_LENGTH, f"frame of {n} bytes is longer than {MAX_BODY}", seq)
    (crc,) = struct.unpack_from("<H", body, n - CRC_LEN)
    if crc16(body[: n - CRC_LEN]) != crc:
        raise FrameError(NakCode.BAD_CRC, "frame CRC mismatch", seq)
    version, ftype, seq, length = _HEADER.unpack_from(body)
    if length != n - HEADER_LEN - CRC_LEN:
        raise FrameError(NakCode.BAD_LENGTH,
                         f"length field {length} does not match the {n - HEADER_LEN - CRC_LEN} payload bytes",
                         seq)
    return Frame(version, ftype, seq, bytes(body[HEADER_LEN: n - CRC_LEN]))


@dataclass
class DeframerStats:
    """What a :class:`Deframer` threw away."""

    frames: int = 0
    """COBS-valid frames returned."""
    garbage_bytes: int = 0
    """Bytes dropped: invalid COBS, or runs longer than MAX_ENCODED."""
    overflows: int = 0
    """Runs longer than MAX_ENCODED without a delimiter."""
    dropped: int = 0
    """Runs dropped (invalid COBS or overflow)."""


class Deframer:
    """Splits a byte stream at 0x00 delimiters into COBS-decoded frame bodies.

    Bounded: at most ``max_encoded`` bytes are buffered; a longer run is dropped up to the
    next delimiter (the receiver resynchronises there). Empty frames (``00 00``) are
    ignored: they are the leading delimiters of :func:`encode_frame`.
    """

    def __init__(self, max_encoded: int = MAX_ENCODED) -> None:
        self.max_encoded = max_encoded
        self.stats = DeframerStats()
        self._buf = b""
        self._discarding = False

    def reset(self) -> None:
        """Forget a partial frame (after reopening a port)."""
        self._buf = b""
        self._discarding = False

    def feed(self, data: bytes) -> list[bytes]:
        """Add received bytes; return the frame bodies completed by them."""
        parts = (self._buf + bytes(data)).split(b"\0")
        self._buf = parts.pop()
        out: list[bytes] = []
        for part in parts:
            if self._discarding:
                self.stats.garbage_bytes += len(part)
                self._discarding = False
                continue
            if not part:
                continue
            if len(part) > self.max_encoded:
                self.stats.garbage_bytes += len(part)
                self.stats.overflows += 1
                self.stats.dropped += 1
                continue
            try:
                out.append(cobs_decode(part))
            except CobsError:
                self.stats.garbage_bytes += len(part)
                self.stats.dropped += 1
                continue
            self.stats.frames += 1
        if len(self._buf) > self.max_encoded:
            self.stats.garbage_bytes += len(self._buf)
            self.stats.overflows += 1
            self.stats.dropped += 1
            self._buf = b""
            self._discarding = True
        return out

    @property
    def pending(self) -> int:
        """Bytes of a partial frame waiting for their delimiter."""
        return len(self._buf)


# --- messages -------------------------------------------------------------------------


def _exact(payload: bytes, st: struct.Struct, what: str) -> tuple:
    if len(payload) != st.size:
        raise MessageError(NakCode.BAD_LENGTH, f"{what}: expected {st.size} bytes, got {len(payload)}")
    return st.unpack(payload)


def _at_least(payload: bytes, st: struct.Struct, what: str) -> tuple:
    """Replies may grow in later versions: v1 reads its fields and ignores the rest."""
    if len(payload) < st.size:
        raise MessageError(NakCode.BAD_LENGTH, f"{what}: expected at least {st.size} bytes, got {len(payload)}")
    return st.unpack_from(payload)


_INFO = struct.Struct("<BBBBB8sHBHIII")


@dataclass(frozen=True)
class BoardInfo:
    """GET_INFO reply: what the board is and what it can do."""

    protocol_min: int
    protocol_max: int
    firmware: tuple[int, int, int]
    board_id: bytes  # 8 bytes, e.g. the MCU's unique id
    max_leds: int
    max_levels: int  # largest M
    max_chunk: int  # largest LOAD chunk, bytes
    buffer_bytes: int  # payload / level buffer, bytes
    max_symbol_rate_mhz: int  # mHz
    max_pwm_hz: int  # Hz

    def pack(self) -> bytes:
        return _INFO.pack(self.protocol_min, self.protocol_max, *self.firmware,
                          self.board_id.ljust(8, b"\0")[:8], self.max_leds, self.max_levels,
                          self.max_chunk, self.buffer_bytes, self.max_symbol_rate_mhz, self.max_pwm_hz)

    @classmethod
    def unpack(cls, payload: bytes) -> "BoardInfo":
        v = _at_least(payload, _INFO, "INFO")
        return cls(v[0], v[1], (v[2], v[3], v[4]), v[5], *v[6:])

    def as_dict(self) -> dict[str, object]:
        return {"protocol": [self.protocol_min, self.protocol_max],
                "firmware": ".".join(map(str, self.firmware)), "board_id": self.board_id.hex(),
                "max_leds": self.max_leds, "max_levels": self.max_levels, "max_chunk": self.max_chunk,
                "buffer_bytes": self.buffer_bytes,
                "max_symbol_rate_hz": self.max_symbol_rate_mhz / 1000.0, "max_pwm_hz": self.max_pwm_hz}


_CONFIG = struct.Struct("<BBBBIIHHH")

FLAG_AIR_V2 = 0x01
"""CONFIG ``flags`` bit 0: payloads are sent as air interface v2 (docs/air-interface.md)."""
FLAG_FEC_SHIFT = 1
FLAG_FEC_MASK = 0x06
"""CONFIG ``flags`` bits 1-2 with FLAG_AIR_V2: the code (the PHY header's fec id: 0 none,
1 rs255_239, 2 rs255_223, 3 rs255_191). Every other bit must be 0."""
FEC_IDS = ("none", "rs255_239", "rs255_223", "rs255_191")


@dataclass(frozen=True)
class BoardConfig:
    """SET_CONFIG payload: the air interface geometry and the LED drive timing."""

    levels: int = 8  # M
    rows: int = 8
    cols: int = 8
    flags: int = 0  # 0: air interface v1; FLAG_AIR_V2 | fec id << 1: v2 (boards that speak it)
    symbol_rate_mhz: int = 500_000  # f_sym in millihertz
    pwm_hz: int = 50_000  # f_pwm, Hz
    training_symbols: int = 40  # K
    data_symbols: int = 600  # F
    idle_symbols: int = 0  # G

    @property
    def n_leds(self) -> int:
        return self.rows * self.cols

    @property
    def symbol_rate_hz(self) -> float:
        return self.symbol_rate_mhz / 1000.0

    @property
    def air_interface(self) -> str:
        """``v1``, or ``v2`` when ``flags`` has :data:`FLAG_AIR_V2`."""
        return "v2" if self.flags & FLAG_AIR_V2 else "v1"

    @property
    def fec(self) -> str:
        """v2's code (``flags`` bits 1-2)."""
        return FEC_IDS[(self.flags & FLAG_FEC_MASK) >> FLAG_FEC_SHIFT]

    def pack(self) -> bytes:
        try:
            return _CONFIG.pack(self.levels, self.rows, self.cols, self.flags, self.symbol_rate_mhz,
                                self.pwm_hz, self.training_symbols, self.data_symbols, self.idle_symbols)
        except struct.error as e:
            raise ProtocolError(f"board config does not fit the v1 layout: {e}") from None

    @classmethod
    def unpack(cls, payload: bytes) -> "BoardConfig":
        return cls(*_exact(payload, _CONFIG, "SET_CONFIG"))

    @classmethod
    def from_transmitter(cls, tx: object) -> "BoardConfig":
        """From a :class:`iscd.core.config.TransmitterConfig` (rates rounded to mHz / Hz;
        with ``air_interface = "v2"`` the v2 flags and the F that v2's geometry gives)."""
        flags, data = 0, tx.data_symbols  # type: ignore[attr-defined]
        if getattr(tx, "air_interface", "v1") == "v2":
            from iscd.core.airinterface_v2 import from_config

            flags = FLAG_AIR_V2 | (FEC_IDS.index(tx.fec) << FLAG_FEC_SHIFT)  # type: ignore[attr-defined]
            data = from_config(tx).data_symbols
        return cls(levels=tx.levels, rows=tx.rows, cols=tx.cols, flags=flags,  # type: ignore[attr-defined]
                   symbol_rate_mhz=round(tx.symbol_rate_hz * 1000),  # type: ignore[attr-defined]
                   pwm_hz=round(tx.pwm_hz),  # type: ignore[attr-defined]
                   training_symbols=tx.training_symbols,  # type: ignore[attr-defined]
                   data_symbols=data, idle_symbols=tx.idle_symbols)  # type: ignore[attr-defined]

    def as_dict(self) -> dict[str, object]:
        return {"levels": self.levels, "rows": self.rows, "cols": self.cols,
                "symbol_rate_hz": self.symbol_rate_hz, "pwm_hz": self.pwm_hz,
                "training_symbols": self.training_symbols, "data_symbols": self.data_symbols,
                "idle_symbols": self.idle_symbols, "air_interface": self.air_interface,
                **({"fec": self.fec} if self.flags & FLAG_AIR_V2 else {})}


@dataclass(frozen=True)
class LoadChunk:
    """LOAD_PAYLOAD / LOAD_LEVELS payload: ``data`` goes at ``offset`` of ``total`` bytes."""

    offset: int
    total: int
    data: bytes

    def pack(self) -> bytes:
        if len(self.data) > MAX_CHUNK:
            raise ProtocolError(f"chunk of {len(self.data)} bytes exceeds {MAX_CHUNK}")
        return LOAD_HEADER.pack(self.offset, self.total) + bytes(self.data)

    @classmethod
    def unpack(cls, payload: bytes) -> "LoadChunk":
        if len(payload) < LOAD_HEADER.size:
            raise MessageError(NakCode.BAD_LENGTH,
                               f"LOAD: expected at least {LOAD_HEADER.size} bytes, got {len(payload)}")
        offset, total = LOAD_HEADER.unpack_from(payload)
        return cls(offset, total, bytes(payload[LOAD_HEADER.size:]))


_STATUS = struct.Struct("<BBHIIIIII")


@dataclass(frozen=True)
class BoardStatus:
    """GET_STATUS reply."""

    state: State
    content: Content
    faults: Fault
    symbol_counter: int  # symbols sent since START (u32, wraps)
    packets_sent: int  # whole packets (or level sequences) sent since START
    bytes_loaded: int
    bytes_total: int  # announced total of the current / last load
    rx_frames: int  # valid frames received since power-on
    rx_errors: int  # frames dropped: COBS, length or CRC errors

    def pack(self) -> bytes:
        return _STATUS.pack(int(self.state), int(self.content), int(self.faults),
                            self.symbol_counter & 0xFFFFFFFF, self.packets_sent & 0xFFFFFFFF,
                            self.bytes_loaded, self.bytes_total,
                            self.rx_frames & 0xFFFFFFFF, self.rx_errors & 0xFFFFFFFF)

    @classmethod
    def unpack(cls, payload: bytes) -> "BoardStatus":
        v = _at_least(payload, _STATUS, "STATUS")
        try:
            state, content = State(v[0]), Content(v[1])
        except ValueError as e:
            raise MessageError(NakCode.BAD_PARAMETER, f"STATUS: {e}") from None
        return cls(state, content, Fault(v[2] & int(ALL_FAULTS)), *v[3:])

    def as_dict(self) -> dict[str, object]:
        return {"state": self.state.name, "content": self.content.name,
                "faults": [f.name for f in Fault if f in self.faults],
                "symbol_counter": self.symbol_counter, "packets_sent": self.packets_sent,
                "bytes_loaded": self.bytes_loaded, "bytes_total": self.bytes_total,
                "rx_frames": self.rx_frames, "rx_errors": self.rx_errors}


_NAK = struct.Struct("<BBI")


@dataclass(frozen=True)
class Nak:
    """NAK payload: the refused command, why, and a code-specific detail (see docs)."""

    command: int
    code: int
    arg: int = 0

    def pack(self) -> bytes:
        return _NAK.pack(self.command & 0xFF, int(self.code), self.arg & 0xFFFFFFFF)

    @classmethod
    def unpack(cls, payload: bytes) -> "Nak":
        return cls(*_at_least(payload, _NAK, "NAK"))


FAULT_MASK = struct.Struct("<H")
"""CLEAR_FAULTS payload (faults to clear) and its ACK data (faults still set)."""


def ack_payload(command: int, data: bytes = b"") -> bytes:
    """ACK payload: the acknowledged command, then its reply data."""
    return bytes([command & 0xFF]) + data


def command_name(code: int) -> str:
    """``START`` for 0x05, ``0x2a`` for an unknown code."""
    try:
        return Command(code).name
    except ValueError:
        return f"0x{code:02x}"


def nak_name(code: int) -> str:
    try:
        return NakCode(code).name
    except ValueError:
        return f"code {code}"
