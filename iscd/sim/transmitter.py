"""Level sources: what the (simulated) transmitter sends, symbol by symbol.

A level source is any object with ``n_leds`` and ``levels(k0, k1) -> (k1 - k0, N) uint8``
giving the 1-based PWM level of every LED for symbol indices k0 .. k1-1 (LED clock,
symbol 0 = start of the first packet). Negative indices are before the first packet:
level 1 (dark). The simulator only ever asks for short ranges, so sources can be
infinite (generated on demand) and random-access (the same k always gives the same level).

:class:`PacketSource` sends back-to-back packets of :class:`iscd.core.airinterface.AirInterface`
(SPEC section 3) or, with ``[transmitter] air_interface = "v2"``,
:class:`iscd.core.airinterface_v2.AirInterfaceV2` (docs/air-interface.md), with payloads per
``[payload]``; :class:`ArraySource` replays a fixed
level array (e.g. from the LED-board emulator).
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from iscd.core.airinterface import AirInterface, random_payload
from iscd.core.airinterface_v2 import AirInterfaceV2, from_config
from iscd.core.config import ConfigError, PayloadConfig


@runtime_checkable
class LevelSource(Protocol):
    """Anything that gives transmitted levels per symbol index."""

    n_leds: int

    def levels(self, k0: int, k1: int) -> np.ndarray:
        """(k1 - k0, N) uint8 levels 1..M of symbols k0..k1-1 (k < 0: level 1).

        Parameters
        ----------
        k0, k1 : int
            Symbol index range (LED clock), k1 exclusive.

        Returns
        -------
        ndarray of uint8
            (k1 - k0, N) levels.
        """
        ...


def fixed_payload(cfg: PayloadConfig, capacity: int) -> bytes | None:
    """The fixed payload of ``[payload]`` (None for ``source = "random"``).

    Raises ConfigError naming ``payload.value`` if it cannot be read or is too long.

    Parameters
    ----------
    cfg : PayloadConfig
        ``source`` (random, text, hex or file) and ``value``.
    capacity : int
        Payload capacity of a packet, bytes.

    Returns
    -------
    bytes or None
    """
    if cfg.source == "random":
        return None
    if cfg.source == "text":
        data = cfg.value.encode("utf-8")
    elif cfg.source == "hex":
        try:
            data = bytes.fromhex(cfg.value)
        except ValueError:
            raise ConfigError(f"payload.value: not a hex string: {cfg.value[:40]!r}") from None
    else:
        try:
            data = Path(cfg.value).expanduser().read_bytes()
        except OSError as e:
            raise ConfigError(f"payload.value: cannot read payload file {cfg.value!r}: "
                              f"{e.strerror or e}") from None
    if len(data) > capacity:
        raise ConfigError(f"payload.value: {len(data)} bytes exceed the packet capacity of "
                          f"{capacity} bytes")
    return data


class PacketSource:
    """Back-to-back packets (header, training, data, idle) from packet 0 on.

    payload: a fixed payload for every packet, or None for fresh random payloads, packet p
    drawn from ``default_rng([seed, 0x9A7, p])`` (random access, reproducible).
    """

    def __init__(self, air: AirInterface | AirInterfaceV2, payload: bytes | None = None, seed: int = 1,
                 cache_packets: int = 8) -> None:
        self.air = air
        self.n_leds = air.n_leds
        self._fixed = None if payload is None else bytes(payload)
        if self._fixed is not None and len(self._fixed) > air.payload_bytes:
            raise ValueError(f"payload of {len(self._fixed)} bytes exceeds the capacity "
                             f"{air.payload_bytes}")
        self.seed = int(seed)
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._cache_n = max(1, cache_packets)
        self._fixed_packet: np.ndarray | None = None

    @classmethod
    def from_config(cls, cfg: "object") -> "PacketSource":
        """From an :class:`iscd.core.config.Config` (transmitter, payload, scene.seed).

        Parameters
        ----------
        cfg : Config
            The config.

        Returns
        -------
        PacketSource

        References
        ----------
        SPEC section 3.
        """
        air = from_config(cfg.transmitter)  # type: ignore[attr-defined]
        return cls(air, fixed_payload(cfg.payload, air.payload_bytes),  # type: ignore[attr-defined]
                   seed=cfg.scene.seed)  # type: ignore[attr-defined]

    @property
    def period(self) -> int:
        """Symbols from one packet start to the next."""
        return self.air.period_symbols

    def payload(self, p: int) -> bytes:
        """Payload (exactly ``air.payload_bytes`` bytes, zero-padded) of packet ``p`` >= 0.

        Parameters
        ----------
        p : int
            Packet index, >= 0.

        Returns
        -------
        bytes
        """
        if self._fixed is not None:
            return self._fixed.ljust(self.air.payload_bytes, b"\0")
        rng = np.random.default_rng([self.seed & 0xFFFFFFFF, 0x9A7, int(p)])
        return random_payload(self.air, rng)

    def packet(self, p: int) -> np.ndarray:
        """(period, N) levels of packet ``p``.

        Parameters
        ----------
        p : int
            Packet index, >= 0.

        Returns
        -------
        ndarray of uint8
            (period, N) levels 1..M, idle symbols included (a cached array: do not modify).
        """
        if self._fixed is not None:
            if self._fixed_packet is None:
                self._fixed_packet = self.air.packet(self._fixed)
            return self._fixed_packet
        hit = self._cache.get(p)
        if hit is not None:
            self._cache.move_to_end(p)
            return hit
        lv = self.air.packet(self.payload(p))
        self._cache[p] = lv
        if len(self._cache) > self._cache_n:
            self._cache.popitem(last=False)
        return lv

    def levels(self, k0: int, k1: int) -> np.ndarray:
        """(k1 - k0, N) uint8 levels 1..M of symbols k0..k1-1 (k < 0: level 1).

        Parameters
        ----------
        k0, k1 : int
            Symbol index range, k1 exclusive (symbol 0 = start of packet 0).

        Returns
        -------
        ndarray of uint8
            (k1 - k0, N) levels.
        """
        out = np.ones((max(0, k1 - k0), self.n_leds), dtype=np.uint8)
        P = self.period
        k = max(k0, 0)
        while k < k1:
            p, off = divmod(k, P)
            n = min(P - off, k1 - k)
            out[k - k0:k - k0 + n] = self.packet(p)[off:off + n]
            k += n
        return out


class ArraySource:
    """A fixed (n_sym, N) level array sent from symbol 0; level 1 outside it
    (or repeated forever with ``repeat=True``)."""

    def __init__(self, levels: np.ndarray, repeat: bool = False) -> None:
        lv = np.asarray(levels)
        if lv.ndim != 2 or lv.shape[0] == 0:
            raise ValueError(f"expected (n_sym, N) levels, got shape {lv.shape}")
        if lv.min() < 1:
            raise ValueError("levels are 1-based (>= 1)")
        self._lv = lv.astype(np.uint8)
        self.n_leds = lv.shape[1]
        self.repeat = repeat

    def levels(self, k0: int, k1: int) -> np.ndarray:
        """(k1 - k0, N) uint8 levels of symbols k0..k1-1: the array's rows, level 1 outside it
        (unless ``repeat``).

        Parameters
        ----------
        k0, k1 : int
            Symbol index range, k1 exclusive (symbol 0 = the array's first row).

        Returns
        -------
        ndarray of uint8
            (k1 - k0, N) levels.
        """
        k = np.arange(k0, k1)
        n = self._lv.shape[0]
        if self.repeat:
            idx = np.where(k >= 0, k % n, -1)
        else:
            idx = np.where((k >= 0) & (k < n), k, -1)
        out = self._lv[np.maximum(idx, 0)]
        out[idx < 0] = 1
        return out
