"""Air interface v1 (SPEC section 3): payload <-> CRC-32 <-> bits <-> Gray levels <-> packet.

The one implementation of the transmitter <-> receiver contract, used by the simulator,
the LED board driver/emulator and the receiver.

Levels are 1-based: ``s`` in ``1..M``; during a symbol the LED is driven by a PWM carrier
with duty ``(s - 1) / (M - 1)`` (:func:`duty`). A packet, for all N LEDs in lock-step, is

* header: Barker-13 ``+ + + + + - - + + - + - +``, ``+`` = level M, ``-`` = level 1;
* training: K symbol times, LED i at training index k sends ``((k + i) mod M) + 1``;
* data: F symbol times. ``payload || CRC-32(payload)`` (big-endian, ``zlib.crc32``) as bits,
  MSB first; each group of log2(M) bits is a value v, sent as level ``l + 1`` with
  ``l ^ (l >> 1) == v`` (Gray); zero-padded to F*N symbols; data symbol j goes to
  symbol time ``j // N``, LED ``j % N``;

followed by G idle symbol times at level 1. The payload has a fixed length,
``floor(F*N*log2(M)/8) - 4`` bytes (:func:`payload_capacity`).

Decoded payloads are untrusted data: :func:`decode_data` returns bytes of exactly the
capacity and a CRC verdict, nothing else.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

BARKER13 = np.array([1, 1, 1, 1, 1, -1, -1, 1, 1, -1, 1, -1, 1], dtype=np.int8)
HEADER_SYMBOLS = 13
CRC_BYTES = 4


class AirInterfaceError(ValueError):
    """Parameters or payload that the air interface cannot carry."""


def _check_levels(levels: int) -> int:
    if levels < 2 or levels & (levels - 1):
        raise AirInterfaceError(f"levels (M) must be a power of two >= 2, got {levels}")
    return int(math.log2(levels))


def duty(level: np.ndarray | int, levels: int) -> np.ndarray:
    """PWM duty cycle in [0, 1] of 1-based ``level`` for M = ``levels``."""
    return (np.asarray(level, dtype=np.float64) - 1.0) / (levels - 1)


def gray_encode(l: np.ndarray) -> np.ndarray:
    """Gray code of index l: ``l ^ (l >> 1)``."""
    l = np.asarray(l)
    return l ^ (l >> 1)


def gray_decode(v: np.ndarray, bits: int) -> np.ndarray:
    """Index l with ``l ^ (l >> 1) == v`` (inverse Gray code), for ``bits``-bit values."""
    l = np.array(v, copy=True)
    shift = 1
    while shift < bits:
        l = l ^ (l >> shift)
        shift <<= 1
    return l


class PacketFraming:
    """What v1 and v2 packets share: the training, and a packet as header, training, data
    and idle (subclasses give ``levels``, ``n_leds``, ``training_symbols``,
    ``idle_symbols``, ``header()`` and ``encode_data()``)."""

    levels: int
    n_leds: int
    training_symbols: int
    idle_symbols: int

    def header(self) -> np.ndarray:  # pragma: no cover - each version has its own
        raise NotImplementedError

    def encode_data(self, payload: bytes) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def training(self) -> np.ndarray:
        """(K, N) training levels: ((k + i) mod M) + 1."""
        k = np.arange(self.training_symbols)[:, None]
        i = np.arange(self.n_leds)[None, :]
        return (((k + i) % self.levels) + 1).astype(np.uint8)

    def packet(self, payload: bytes) -> np.ndarray:
        """(header + K + F + G, N) levels of one packet, idle symbols included."""
        idle = np.ones((self.idle_symbols, self.n_leds), dtype=np.uint8)
        return np.concatenate([self.header(), self.training(), self.encode_data(payload), idle])

    def packets(self, payloads: list[bytes]) -> np.ndarray:
        """Back-to-back packets, ``(len(payloads) * period_symbols, N)`` levels."""
        if not payloads:
            return np.zeros((0, self.n_leds), dtype=np.uint8)
        return np.concatenate([self.packet(p) for p in payloads])


@dataclass(frozen=True)
class AirInterface(PacketFraming):
    """Packet geometry: M levels, N LEDs, K training, F data, G idle symbol times."""

    levels: int = 8
    n_leds: int = 64
    training_symbols: int = 40
    data_symbols: int = 600
    idle_symbols: int = 0

    def __post_init__(self) -> None:
        _check_levels(self.levels)
        if self.n_leds < 1 or self.data_symbols < 1 or self.training_symbols < 0 or self.idle_symbols < 0:
            raise AirInterfaceError(f"invalid packet geometry {self}")
        if self.payload_bytes < 0:
            raise AirInterfaceError(
                f"{self.data_symbols} data symbols x {self.n_leds} LEDs cannot carry the CRC-32")

    @classmethod
    def from_config(cls, tx: object) -> "AirInterface":
        """From a :class:`iscd.core.config.TransmitterConfig`."""
        if tx.rows * tx.cols == 0:  # type: ignore[attr-defined]
            raise AirInterfaceError('transmitter rows and cols are "auto": only the receiver infers '
                                    "them; a packet's geometry needs the numbers")
        return cls(levels=tx.levels, n_leds=tx.rows * tx.cols,  # type: ignore[attr-defined]
                   training_symbols=tx.training_symbols,  # type: ignore[attr-defined]
                   data_symbols=tx.data_symbols, idle_symbols=tx.idle_symbols)  # type: ignore[attr-defined]

    @property
    def bits_per_symbol(self) -> int:
        return _check_levels(self.levels)

    @property
    def payload_bytes(self) -> int:
        """Fixed payload length in bytes: floor(F*N*log2(M)/8) - 4."""
        return payload_capacity(self.data_symbols, self.n_leds, self.levels)

    @property
    def packet_symbols(self) -> int:
        """Symbol times per packet without idle: 13 + K + F (653 by default)."""
        return HEADER_SYMBOLS + self.training_symbols + self.data_symbols

    @property
    def period_symbols(self) -> int:
        """Symbol times from one packet start to the next: 13 + K + F + G."""
        return self.packet_symbols + self.idle_symbols

    @property
    def data_offset(self) -> int:
        """Symbol time of the first data symbol within a packet: 13 + K."""
        return HEADER_SYMBOLS + self.training_symbols

    def header(self) -> np.ndarray:
        """(13, N) header levels."""
        return barker_levels(self.levels, self.n_leds)

    def encode_data(self, payload: bytes) -> np.ndarray:
        """(F, N) data levels for ``payload`` (shorter payloads are zero-padded)."""
        if len(payload) > self.payload_bytes:
            raise AirInterfaceError(
                f"payload of {len(payload)} bytes exceeds the capacity of {self.payload_bytes} bytes "
                f"(M={self.levels}, N={self.n_leds}, F={self.data_symbols})")
        body = bytes(payload).ljust(self.payload_bytes, b"\0")
        framed = body + zlib.crc32(body).to_bytes(CRC_BYTES, "big")
        return bytes_to_levels(framed, self.levels, self.data_symbols * self.n_leds).reshape(
            self.data_symbols, self.n_leds)

    def decode_data(self, levels: np.ndarray) -> tuple[bytes, bool]:
        """Payload and CRC verdict from (F, N) decided levels (1..M).

        Out-of-range levels are clipped to 1..M (they can only come from a broken
        decision stage, and must not crash the decoder).
        """
        lv = np.asarray(levels)
        if lv.shape != (self.data_symbols, self.n_leds):
            raise AirInterfaceError(
                f"expected ({self.data_symbols}, {self.n_leds}) data levels, got {lv.shape}")
        framed = levels_to_bytes(lv, self.levels, self.payload_bytes + CRC_BYTES)
        body, crc = framed[: self.payload_bytes], framed[self.payload_bytes:]
        return body, zlib.crc32(body) == int.from_bytes(crc, "big")



def barker_levels(levels: int, n_leds: int) -> np.ndarray:
    """(13, N) levels of the Barker-13: ``+`` = M, ``-`` = 1 on every LED."""
    col = np.where(BARKER13 > 0, levels, 1).astype(np.uint8)
    return np.repeat(col[:, None], n_leds, axis=1)


def bytes_to_levels(data: bytes, levels: int, n_symbols: int) -> np.ndarray:
    """Levels 1..M of ``data``: bits MSB first, log2(M) at a time as Gray values, zero-padded
    to ``n_symbols`` symbols (SPEC section 3, shared by v1 and v2).

    Parameters
    ----------
    data : bytes
        At most ``n_symbols * log2(M) / 8`` bytes.
    levels : int
        M, a power of two.
    n_symbols : int
        Symbols to fill.

    Returns
    -------
    ndarray
        (n_symbols,) uint8 levels.
    """
    k = _check_levels(levels)
    bits = np.unpackbits(np.frombuffer(bytes(data), dtype=np.uint8))
    if bits.size > n_symbols * k:
        raise AirInterfaceError(f"{len(data)} bytes do not fit in {n_symbols} symbols of M={levels}")
    padded = np.zeros(n_symbols * k, dtype=np.uint8)
    padded[: bits.size] = bits
    weights = (1 << np.arange(k - 1, -1, -1)).astype(np.uint16)
    values = padded.reshape(n_symbols, k).astype(np.uint16) @ weights
    return (gray_decode(values, k) + 1).astype(np.uint8)


def level_indices(levels_in: np.ndarray, levels: int) -> np.ndarray:
    """0-based level indices (int64, flat) of decided levels, clipped to 1..M; NaN and
    infinities are clipped too (they can only come from a broken decision stage and must
    not crash the decoder).

    Raises
    ------
    AirInterfaceError
        If the levels are not numbers.
    """
    lv = np.asarray(levels_in)
    if lv.dtype.kind not in "iub":  # floats (NaN, inf) or objects: clip before the cast
        try:
            lv = np.nan_to_num(np.asarray(lv, dtype=np.float64), nan=1.0, posinf=levels, neginf=1.0)
        except (TypeError, ValueError):
            raise AirInterfaceError(f"data levels must be numbers, got dtype {lv.dtype}") from None
        lv = np.clip(lv, 1, levels)
    return np.clip(lv.astype(np.int64), 1, levels).reshape(-1) - 1


def levels_to_bytes(levels_in: np.ndarray, levels: int, n_bytes: int) -> bytes:
    """The first ``n_bytes`` bytes that decided levels 1..M carry (inverse of
    :func:`bytes_to_levels`; out-of-range levels clipped, :func:`level_indices`)."""
    k = _check_levels(levels)
    values = gray_encode(level_indices(levels_in, levels))
    bits = ((values[:, None] >> np.arange(k - 1, -1, -1)[None, :]) & 1).astype(np.uint8).reshape(-1)
    return np.packbits(bits[: n_bytes * 8]).tobytes()


def payload_capacity(data_symbols: int, n_leds: int, levels: int) -> int:
    """Payload bytes of a packet: floor(F*N*log2(M)/8) - 4 (SPEC section 3)."""
    return (data_symbols * n_leds * _check_levels(levels)) // 8 - CRC_BYTES


def random_payload(air: AirInterface, rng: np.random.Generator) -> bytes:
    """A full-length random payload."""
    return rng.integers(0, 256, size=air.payload_bytes, dtype=np.uint8).tobytes()
