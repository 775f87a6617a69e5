"""Air interface v2: a self-describing PHY header and Reed-Solomon forward error correction.

v2 keeps v1's physical layer (SPEC section 3: PWM levels 1..M, the Barker-13 in levels 1
and M, the training sequence, Gray mapping, symbol j at symbol time j // N, LED j % N) and
adds, for all N LEDs in lock-step (``docs/air-interface.md``)::

    Barker-13 | PHY header (H symbol times, OOK) | training (K) | data (F) | idle (G)

* **PHY header** (:class:`PhyHeader`, 17 bytes = 136 bits): version 2, FEC mode, log2(M),
  rows - 1, cols - 1, K, F, G, payload length, then the CRC-32 of those 13 bytes. Sent in
  OOK (level 1 = dark, level M = fully on: the Barker's two levels, whatever M), each bit
  on at least :data:`HEADER_COPIES` slots on pairwise different LEDs and symbol times,
  whitened by PRBS-9 so that it is never steady light and never a second Barker. The
  receiver averages the copies' normalized luminance (soft combining) and accepts the
  header only if its CRC-32 and every field check out (:func:`parse_header`).
  H = max(8, ceil(4 B' / N)) symbol times (9 for 8x8; :func:`header_symbols`).
* **Data**: ``payload || CRC-32(payload)`` (big-endian), split into n_cw shortened
  Reed-Solomon codewords over GF(256) of ``nsym`` parity bytes each (:mod:`iscd.core.fec`),
  interleaved byte by byte across codewords (:func:`iscd.core.fec.interleave_order`), then
  Gray-mapped to levels exactly like v1 and zero-padded to F N symbols. F is the fewest
  symbol times that hold the coded bytes unless the transmitter asks for more.
* **FEC modes** (:data:`FEC_MODES`): ``none`` (CRC only), ``rs255_239`` (t = 8, rate 0.94,
  the high-rate mode), ``rs255_223`` (t = 16, rate 0.87, the CCSDS code), ``rs255_191``
  (t = 32, rate 0.75, the strong mode).

Decoded payloads are untrusted data: :meth:`AirInterfaceV2.decode_data` returns a
payload only when every codeword decoded and the CRC-32 holds; otherwise ``None``.
Invalid parameters and malformed input raise :class:`AirInterfaceError` (or its
:class:`HeaderError`), never another exception.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from iscd.core.airinterface import (CRC_BYTES, HEADER_SYMBOLS, AirInterface, AirInterfaceError, PacketFraming,
                                    _check_levels, barker_levels, bytes_to_levels, level_indices,
                                    levels_to_bytes)
from iscd.core.fec import N_MAX, RSCode, codeword_count, interleave_order, split_lengths

VERSION = 2
HEADER_BYTES = 17
"""PHY header: 13 bytes of fields + CRC-32."""
HEADER_BITS = 8 * HEADER_BYTES
HEADER_COPIES = 4
"""Each header bit is sent at least this often (soft-combined by the receiver)."""
HEADER_MIN_SYMBOLS = 8


@dataclass(frozen=True)
class FecMode:
    """A code mode: its id in the PHY header and its parity bytes per codeword."""

    name: str
    code_id: int
    nsym: int

    @property
    def k(self) -> int:
        """Data bytes per full codeword (255 - nsym; no code: 255)."""
        return N_MAX - self.nsym

    @property
    def rate(self) -> float:
        return self.k / N_MAX

    @property
    def t(self) -> int:
        """Errors corrected per codeword (or 2t erasures)."""
        return self.nsym // 2


FEC_MODES: dict[str, FecMode] = {m.name: m for m in (
    FecMode("none", 0, 0), FecMode("rs255_239", 1, 16), FecMode("rs255_223", 2, 32),
    FecMode("rs255_191", 3, 64))}
"""The code modes by name."""
_BY_ID = {m.code_id: m for m in FEC_MODES.values()}


class HeaderError(AirInterfaceError):
    """A PHY header that does not check out (CRC, version, fields): rejected, never read."""


def fec_mode(name: str) -> FecMode:
    """The :class:`FecMode` called ``name`` (AirInterfaceError naming the choices)."""
    try:
        return FEC_MODES[name]
    except (KeyError, TypeError):
        raise AirInterfaceError(f"fec must be one of {', '.join(FEC_MODES)}, got {name!r}") from None


# ---------------------------------------------------------------------------- PHY header
@dataclass(frozen=True)
class PhyHeader:
    """The fields of the v2 PHY header (all that a receiver needs to know)."""

    levels: int
    rows: int
    cols: int
    training_symbols: int
    data_symbols: int
    idle_symbols: int
    fec: str
    payload_len: int
    version: int = VERSION

    def pack(self) -> bytes:
        """The 17 header bytes: fields (big-endian) then their CRC-32.

        Layout: ``version << 4 | fec id``, ``log2(M) << 4`` (low nibble reserved, 0),
        ``rows - 1``, ``cols - 1``, K (2 bytes), F (2 bytes), G (2 bytes), payload
        length (3 bytes), CRC-32 (4 bytes).
        """
        _check_fields(self)
        body = bytes([(self.version << 4) | FEC_MODES[self.fec].code_id,
                      _check_levels(self.levels) << 4, self.rows - 1, self.cols - 1])
        body += (self.training_symbols.to_bytes(2, "big") + self.data_symbols.to_bytes(2, "big")
                 + self.idle_symbols.to_bytes(2, "big") + self.payload_len.to_bytes(3, "big"))
        return body + zlib.crc32(body).to_bytes(CRC_BYTES, "big")

    @classmethod
    def unpack(cls, data: bytes) -> "PhyHeader":
        """Fields from 17 header bytes; :class:`HeaderError` unless the CRC-32 and every
        field check out."""
        if len(data) != HEADER_BYTES:
            raise HeaderError(f"a PHY header has {HEADER_BYTES} bytes, got {len(data)}")
        body, crc = data[:-CRC_BYTES], data[-CRC_BYTES:]
        if zlib.crc32(body) != int.from_bytes(crc, "big"):
            raise HeaderError("PHY header CRC-32 fails")
        version, code = body[0] >> 4, body[0] & 15
        if version != VERSION or code not in _BY_ID or body[1] & 15 or not 1 <= body[1] >> 4 <= 8:
            raise HeaderError(f"PHY header fields out of range (version {version}, fec {code})")
        hdr = cls(levels=1 << (body[1] >> 4), rows=body[2] + 1, cols=body[3] + 1,
                  training_symbols=int.from_bytes(body[4:6], "big"),
                  data_symbols=int.from_bytes(body[6:8], "big"),
                  idle_symbols=int.from_bytes(body[8:10], "big"), fec=_BY_ID[code].name,
                  payload_len=int.from_bytes(body[10:13], "big"), version=version)
        try:
            _check_fields(hdr)
        except AirInterfaceError as e:
            raise HeaderError(f"PHY header inconsistent: {e}") from None
        return hdr


def _check_fields(h: PhyHeader) -> None:
    _check_levels(h.levels)
    if h.levels > 256 or not (1 <= h.rows <= 256 and 1 <= h.cols <= 256):
        raise AirInterfaceError(f"M <= 256 and rows, cols in 1..256 required, got {h.levels}, {h.rows}x{h.cols}")
    for name, v, hi in (("training_symbols", h.training_symbols, 0xFFFF),
                        ("data_symbols", h.data_symbols, 0xFFFF), ("idle_symbols", h.idle_symbols, 0xFFFF),
                        ("payload_len", h.payload_len, 0xFFFFFF)):
        if not 0 <= v <= hi:
            raise AirInterfaceError(f"{name} must be in 0..{hi}, got {v}")
    fec_mode(h.fec)
    need = _data_symbols_needed(h.payload_len, h.fec, h.levels, h.rows * h.cols)
    if h.data_symbols < need:
        raise AirInterfaceError(f"payload of {h.payload_len} bytes with fec {h.fec} needs {need} data "
                                f"symbol times, got {h.data_symbols}")


@lru_cache(maxsize=None)
def _prbs9(n: int) -> np.ndarray:
    """The first n bits of PRBS-9 (x^9 + x^5 + 1, all-ones seed), uint8."""
    out = np.zeros(n, np.uint8)
    reg = 0x1FF
    for i in range(min(n, 511)):
        bit = ((reg >> 8) ^ (reg >> 4)) & 1
        out[i] = bit
        reg = ((reg << 1) | bit) & 0x1FF
    if n > 511:
        out[511:] = np.resize(out[:511], n - 511)
    return out


@lru_cache(maxsize=None)
def _header_period(n_leds: int) -> int:
    """B': the length of the cyclic header bit sequence the slots run through, >= 136 and
    >= N, with N / gcd(B', N) >= min(copies, N) so that the copies of one bit lie on
    different LEDs and (B' >= N) different symbol times."""
    b = max(HEADER_BITS, n_leds)
    while n_leds // math.gcd(b, n_leds) < min(HEADER_COPIES, n_leds):
        b += 1
    return b


def header_symbols(n_leds: int) -> int:
    """H, the PHY header's symbol times for N LEDs: max(8, ceil(4 B' / N)) (9 for 8x8,
    544 for one LED).

    Parameters
    ----------
    n_leds : int
        N, LEDs of the array (>= 1).
    """
    if n_leds < 1:
        raise AirInterfaceError(f"n_leds must be >= 1, got {n_leds}")
    return max(HEADER_MIN_SYMBOLS, -(-HEADER_COPIES * _header_period(n_leds) // n_leds))


@lru_cache(maxsize=None)
def _header_map(n_leds: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, N) header bit index of every slot and its whitening bit."""
    H = header_symbols(n_leds)
    s = np.arange(H * n_leds)
    bit = (s % _header_period(n_leds)) % HEADER_BITS
    return bit.reshape(H, n_leds), _prbs9(H * n_leds).reshape(H, n_leds)


def header_levels(hdr: PhyHeader) -> np.ndarray:
    """(H, N) levels of the PHY header: 1 (dark) or M (fully on)."""
    n = hdr.rows * hdr.cols
    bits = np.unpackbits(np.frombuffer(hdr.pack(), np.uint8))
    idx, white = _header_map(n)
    on = bits[idx] ^ white
    return np.where(on == 1, hdr.levels, 1).astype(np.uint8)


def header_soft(levels: np.ndarray, m: int) -> np.ndarray:
    """Soft OOK values of header levels 1..M for :func:`parse_header`: duty (l - 1)/(M - 1)."""
    return (np.asarray(levels, np.float64) - 1.0) / (m - 1)


def parse_header(soft: np.ndarray, n_leds: int, margin: float = 0.05) -> PhyHeader:
    """The PHY header from the receiver's soft OOK values.

    Parameters
    ----------
    soft : ndarray
        (H, N) normalized luminance of the header slots: 0 = dark (level 1), 1 = fully on
        (level M), from the Barker's two levels; NaN where unknown (a missing frame).
    n_leds : int
        N (the receiver's LED count; the header must say the same rows x cols).
    margin : float
        A bit whose combined value lies within ``margin`` of 0.5 (or has no finite copy)
        makes the header rejected rather than guessed.

    Returns
    -------
    PhyHeader
        The header (CRC-32 and all fields checked).

    Raises
    ------
    HeaderError
        If the header is not there, unreadable, inconsistent or for another LED count.
    """
    H = header_symbols(n_leds)
    try:
        y = np.asarray(soft, dtype=np.float64)
    except (TypeError, ValueError):
        raise HeaderError("header values must be numbers") from None
    if y.shape != (H, n_leds):
        raise HeaderError(f"expected ({H}, {n_leds}) header values, got {y.shape}")
    idx, white = _header_map(n_leds)
    with np.errstate(invalid="ignore"):
        y = np.clip(y, 0.0, 1.0)
    v = np.where(white == 1, 1.0 - y, y)
    ok = np.isfinite(v)
    s = np.bincount(idx[ok], weights=v[ok], minlength=HEADER_BITS)
    c = np.bincount(idx[ok], minlength=HEADER_BITS)
    if (c == 0).any():
        raise HeaderError("header bits without any readable copy")
    mean = s / c
    if (np.abs(mean - 0.5) < margin).any():
        raise HeaderError("header bits undecidable")
    hdr = PhyHeader.unpack(np.packbits((mean > 0.5).astype(np.uint8)).tobytes())
    if hdr.rows * hdr.cols != n_leds:
        raise HeaderError(f"header says {hdr.rows}x{hdr.cols} LEDs, the receiver sees {n_leds}")
    return hdr


# ---------------------------------------------------------------------------- data
@dataclass(frozen=True)
class _Layout:
    lengths: np.ndarray  # (n_cw,) codeword lengths (data + parity)
    k: np.ndarray  # (n_cw,) data bytes per codeword
    cw: np.ndarray  # stream byte -> codeword
    pos: np.ndarray  # stream byte -> byte in codeword

    @property
    def coded_bytes(self) -> int:
        return int(self.lengths.sum())


@lru_cache(maxsize=64)
def _layout(payload_len: int, fec: str, levels: int, n_leds: int) -> _Layout:
    mode = fec_mode(fec)
    data = payload_len + CRC_BYTES
    if mode.nsym == 0:
        k = np.array([data], np.int64)
        lengths = k.copy()
    else:
        n_cw = codeword_count(data, mode.k, n_leds * _check_levels(levels))
        k = split_lengths(data, n_cw)
        lengths = k + mode.nsym
    if mode.nsym == 0:
        cw, pos = np.zeros(data, np.int64), np.arange(data)
    else:
        cw, pos = interleave_order(lengths)
    for a in (lengths, k, cw, pos):
        a.flags.writeable = False
    return _Layout(lengths, k, cw, pos)


def _data_symbols_needed(payload_len: int, fec: str, levels: int, n_leds: int) -> int:
    bits = 8 * _layout(payload_len, fec, levels, n_leds).coded_bytes
    return -(-bits // (n_leds * _check_levels(levels)))


@lru_cache(maxsize=None)
def _code(nsym: int) -> RSCode:
    return RSCode(nsym)


@dataclass
class DataResult:
    """What the data of one v2 packet decoded to.

    payload: the payload, ONLY when every codeword decoded and the CRC-32 holds (else
    None); crc_ok: that verdict; corrected: bytes corrected by the code; failed_codewords:
    codewords beyond the code's reach; erased: bytes marked as erasures; raw: the payload
    bytes as decoded whatever the verdict (untrusted, for diagnostics).
    """

    payload: bytes | None
    crc_ok: bool
    corrected: int
    failed_codewords: int
    erased: int
    raw: bytes


@dataclass(frozen=True)
class AirInterfaceV2(PacketFraming):
    """Packet geometry and code of v2: M levels, rows x cols LEDs, K training symbol
    times, FEC mode, payload length (bytes), G idle symbol times, and F data symbol times
    (0: the fewest that hold the coded payload)."""

    levels: int = 16
    rows: int = 8
    cols: int = 8
    training_symbols: int = 40
    fec: str = "rs255_223"
    payload_len: int = 1024
    idle_symbols: int = 0
    data_symbols: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.payload_len, bool) or not isinstance(self.payload_len, int):
            raise AirInterfaceError(f"payload_len must be an integer, got {self.payload_len!r}")
        if self.data_symbols == 0:
            # bounds first: _data_symbols_needed on absurd sizes would be slow
            _check_levels(self.levels)
            if not 0 <= self.payload_len <= 0xFFFFFF or not (1 <= self.rows <= 256 and 1 <= self.cols <= 256):
                raise AirInterfaceError(f"invalid v2 geometry {self}")
            object.__setattr__(self, "data_symbols", _data_symbols_needed(
                self.payload_len, fec_mode(self.fec).name, self.levels, self.rows * self.cols))
        _check_fields(self.phy_header)

    @classmethod
    def for_capacity(cls, data_symbols: int, **kw: object) -> "AirInterfaceV2":
        """The largest payload that F = ``data_symbols`` symbol times carry (other fields
        as ``kw``), with F fixed to it."""
        probe = cls(**{**kw, "payload_len": 0})  # type: ignore[arg-type]
        n, bits = probe.n_leds, _check_levels(probe.levels)
        lo, hi = 0, min(0xFFFFFF, data_symbols * n * bits // 8)
        if _data_symbols_needed(0, probe.fec, probe.levels, n) > data_symbols:
            raise AirInterfaceError(f"{data_symbols} data symbol times cannot carry a v2 packet")
        while lo < hi:  # the largest payload whose coded bytes fit
            mid = (lo + hi + 1) // 2
            if _data_symbols_needed(mid, probe.fec, probe.levels, n) <= data_symbols:
                lo = mid
            else:
                hi = mid - 1
        return replace(probe, payload_len=lo, data_symbols=data_symbols)

    @classmethod
    def from_header(cls, hdr: PhyHeader) -> "AirInterfaceV2":
        """The geometry a received PHY header describes."""
        return cls(levels=hdr.levels, rows=hdr.rows, cols=hdr.cols, training_symbols=hdr.training_symbols,
                   fec=hdr.fec, payload_len=hdr.payload_len, idle_symbols=hdr.idle_symbols,
                   data_symbols=hdr.data_symbols)

    @property
    def n_leds(self) -> int:
        return self.rows * self.cols

    @property
    def payload_bytes(self) -> int:
        """The payload length (v1's name for it: code that sends payloads takes either)."""
        return self.payload_len

    @property
    def bits_per_symbol(self) -> int:
        return _check_levels(self.levels)

    @property
    def mode(self) -> FecMode:
        return fec_mode(self.fec)

    @property
    def phy_header(self) -> PhyHeader:
        return PhyHeader(levels=self.levels, rows=self.rows, cols=self.cols,
                         training_symbols=self.training_symbols, data_symbols=self.data_symbols,
                         idle_symbols=self.idle_symbols, fec=self.fec, payload_len=self.payload_len)

    @property
    def header_symbols(self) -> int:
        """H, the PHY header's symbol times."""
        return header_symbols(self.n_leds)

    @property
    def training_offset(self) -> int:
        """Symbol time of the first training symbol within a packet: 13 + H."""
        return HEADER_SYMBOLS + self.header_symbols

    @property
    def data_offset(self) -> int:
        """Symbol time of the first data symbol: 13 + H + K."""
        return self.training_offset + self.training_symbols

    @property
    def packet_symbols(self) -> int:
        """Symbol times per packet without idle: 13 + H + K + F."""
        return self.data_offset + self.data_symbols

    @property
    def period_symbols(self) -> int:
        return self.packet_symbols + self.idle_symbols

    @property
    def coded_bytes(self) -> int:
        """Bytes sent in the data symbols (payload, CRC-32 and parity)."""
        return self._layout.coded_bytes

    @property
    def codewords(self) -> int:
        return int(self._layout.lengths.size)

    @property
    def _layout(self) -> _Layout:
        return _layout(self.payload_len, self.fec, self.levels, self.n_leds)

    # ---- transmitter (training, packet, packets: as v1, PacketFraming)
    def header(self) -> np.ndarray:
        """(13 + H, N) levels of Barker-13 and PHY header: what precedes the training, all
        known to a receiver that has read the header (v1's ``header()`` is the Barker)."""
        return np.concatenate([barker_levels(self.levels, self.n_leds), header_levels(self.phy_header)])

    def coded_stream(self, payload: bytes) -> bytes:
        """The interleaved coded bytes of ``payload`` (its length must be payload_len)."""
        payload = bytes(payload)
        if len(payload) != self.payload_len:
            raise AirInterfaceError(f"payload of {len(payload)} bytes, the packet says {self.payload_len}")
        lay = self._layout
        data = np.frombuffer(payload + zlib.crc32(payload).to_bytes(CRC_BYTES, "big"), np.uint8)
        words = np.zeros((lay.k.size, int(lay.lengths.max())), np.uint8)
        offs = np.concatenate([[0], np.cumsum(lay.k)])
        for c in range(lay.k.size):
            words[c, :lay.k[c]] = data[offs[c]:offs[c + 1]]
        if self.mode.nsym:
            par = _code(self.mode.nsym).encode(words, lay.k)
            for c in range(lay.k.size):
                words[c, lay.k[c]:lay.lengths[c]] = par[c]
        return words[lay.cw, lay.pos].tobytes()

    def encode_data(self, payload: bytes) -> np.ndarray:
        """(F, N) data levels of ``payload``."""
        return bytes_to_levels(self.coded_stream(payload), self.levels,
                               self.data_symbols * self.n_leds).reshape(self.data_symbols, self.n_leds)

    # ---- receiver
    def byte_erasures(self, symbol_erasures: np.ndarray) -> np.ndarray:
        """(coded_bytes,) bool: the coded bytes that any erased data symbol touches.

        Parameters
        ----------
        symbol_erasures : ndarray
            (F, N) bool, True where the receiver is unsure of the decided level.
        """
        k = self.bits_per_symbol
        n = self.coded_bytes
        er = np.asarray(symbol_erasures, dtype=bool).reshape(-1)
        bits = np.repeat(er, k)[: 8 * n]
        if bits.size < 8 * n:
            bits = np.concatenate([bits, np.zeros(8 * n - bits.size, bool)])
        return bits.reshape(n, 8).any(axis=1)

    def decode_data(self, levels: np.ndarray, erasures: np.ndarray | None = None) -> DataResult:
        """De-interleave, Reed-Solomon decode (errors and erasures), check the CRC-32.

        Parameters
        ----------
        levels : ndarray
            (F, N) decided data levels 1..M (out of range: clipped).
        erasures : ndarray, optional
            (F, N) bool, symbols the receiver marks as uncertain (erasures: with them the
            code corrects 2e + f <= nsym per codeword); or (T, F, N), T candidate sets tried
            in order, each codeword taking the first under which it decodes (the receiver's
            confidence thresholds, mildest first).

        Returns
        -------
        DataResult
            The payload only if every codeword decoded and the CRC-32 holds.

        Raises
        ------
        AirInterfaceError
            If the arrays have the wrong shape or are not numbers.
        """
        shape = (self.data_symbols, self.n_leds)
        lv = np.asarray(levels)
        if lv.shape != shape:
            raise AirInterfaceError(f"expected {shape} data levels, got {lv.shape}")
        masks: list[np.ndarray | None] = [None]
        if erasures is not None:
            try:
                er_sym = np.asarray(erasures, dtype=bool)
            except (TypeError, ValueError):
                raise AirInterfaceError("erasures must be booleans") from None
            if er_sym.shape[-2:] != shape or er_sym.ndim not in (2, 3) or er_sym.shape[0] == 0:
                raise AirInterfaceError(f"expected {shape} erasure flags (or a stack of them), got {er_sym.shape}")
            masks = list(er_sym) if er_sym.ndim == 3 else [er_sym]
        lay = self._layout
        stream = np.frombuffer(levels_to_bytes(level_indices(lv, self.levels) + 1, self.levels,
                                               lay.coded_bytes), np.uint8)
        words = np.zeros((lay.k.size, int(lay.lengths.max())), np.uint8)
        words[lay.cw, lay.pos] = stream
        erased = corrected = 0
        done = np.ones(lay.k.size, bool)
        if self.mode.nsym:
            done[:] = False
            received = words.copy()
            for mask in masks:
                todo = np.flatnonzero(~done)
                w = np.ascontiguousarray(received[todo])
                er = np.zeros(words.shape, bool)
                if mask is not None:
                    er[lay.cw, lay.pos] = self.byte_erasures(mask)
                er = er[todo]
                res = _code(self.mode.nsym).decode(w, lay.lengths[todo], er)
                ok = res >= 0
                words[todo[ok]] = w[ok]
                done[todo[ok]] = True
                corrected += int(res[ok].sum())
                erased += int(er[ok].sum())
                if done.all():
                    break
        failed = int((~done).sum())
        data = b"".join(words[c, :lay.k[c]].tobytes() for c in range(lay.k.size))
        body, crc = data[: self.payload_len], data[self.payload_len:]
        ok = failed == 0 and zlib.crc32(body) == int.from_bytes(crc, "big")
        return DataResult(payload=body if ok else None, crc_ok=ok, corrected=corrected,
                          failed_codewords=failed, erased=erased, raw=body)

def from_config(tx: object) -> AirInterface | AirInterfaceV2:
    """The air interface of a :class:`iscd.core.config.TransmitterConfig`: v1
    (:meth:`AirInterface.from_config`) or v2 (``fec``; ``payload_len`` bytes, or with 0 as
    many as ``data_symbols`` hold).

    Raises
    ------
    AirInterfaceError
        If the geometry cannot carry a packet.
    """
    if getattr(tx, "air_interface", "v1") != "v2":
        return AirInterface.from_config(tx)
    if tx.rows * tx.cols == 0:  # type: ignore[attr-defined]
        raise AirInterfaceError('transmitter rows and cols are "auto": only the receiver infers '
                                "them; a packet's geometry needs the numbers")
    kw = dict(levels=tx.levels, rows=tx.rows, cols=tx.cols,  # type: ignore[attr-defined]
              training_symbols=tx.training_symbols, fec=tx.fec,  # type: ignore[attr-defined]
              idle_symbols=tx.idle_symbols)  # type: ignore[attr-defined]
    if tx.payload_len:  # type: ignore[attr-defined]
        return AirInterfaceV2(payload_len=tx.payload_len, **kw)  # type: ignore[attr-defined, arg-type]
    return AirInterfaceV2.for_capacity(tx.data_symbols, **kw)  # type: ignore[attr-defined, arg-type]
