"""Residual packet error rate of air interface v2's codes against the symbol error rate.

Symbol errors are injected into the decided data levels of encoded packets (no physics:
the code's view of the channel), the packets decoded by
:meth:`iscd.core.airinterface_v2.AirInterfaceV2.decode_data`, and the outcomes counted:
delivered (payload exact), lost (reported failed) and wrong (delivered but not the
payload: must never happen; the CRC-32 is there for it).

Impairments: ``uniform`` -- every data symbol independently wrong with probability SER, the
wrong level drawn uniformly from the M - 1 others; ``dark_led`` -- one LED of the array at
level 1 for the whole packet, plus the uniform errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from iscd.core.airinterface_v2 import FEC_MODES, AirInterfaceV2


def inject_symbol_errors(levels: np.ndarray, m: int, ser: float, rng: np.random.Generator) -> np.ndarray:
    """Levels with each symbol replaced, with probability ``ser``, by one of the M - 1
    other levels drawn uniformly.

    Parameters
    ----------
    levels : ndarray
        Levels 1..M, any shape.
    m : int
        M.
    ser : float
        Symbol error rate, 0..1.
    rng : numpy.random.Generator
        The randomness.

    Returns
    -------
    ndarray
        A copy with the errors (uint8).
    """
    lv = np.array(levels, dtype=np.uint8, copy=True)
    hit = rng.random(lv.shape) < ser
    shift = rng.integers(1, m, size=lv.shape)
    lv[hit] = ((lv[hit].astype(np.int64) - 1 + shift[hit]) % m + 1).astype(np.uint8)
    return lv


@dataclass
class PerPoint:
    """Outcome counts of ``packets`` packets of one mode at one SER."""

    fec: str
    impairment: str
    ser: float
    packets: int
    lost: int
    wrong: int
    corrected_mean: float

    @property
    def per(self) -> float:
        """Residual packet error rate (lost + wrong) / packets."""
        return (self.lost + self.wrong) / self.packets


def residual_per(fec: str, ser: float, packets: int, seed: int, impairment: str = "uniform",
                 levels: int = 16, rows: int = 8, cols: int = 8, data_symbols: int = 600,
                 dark_led: int = 27) -> PerPoint:
    """Residual PER of one FEC mode at one SER (module docstring).

    Parameters
    ----------
    fec : str
        A mode of :data:`iscd.core.airinterface_v2.FEC_MODES`.
    ser : float
        Injected symbol error rate.
    packets : int
        Packets to send.
    seed : int
        Seed of the payloads and the errors.
    impairment : str
        ``uniform`` or ``dark_led``.
    levels, rows, cols, data_symbols : int
        The packet (the default: 8x8 PWM-16, F = 600, a full packet of ~19 kB coded).
    dark_led : int
        The LED that is dark in ``dark_led``.

    Returns
    -------
    PerPoint
        Lost and wrong packets.
    """
    if impairment not in ("uniform", "dark_led"):
        raise ValueError(f"impairment must be uniform or dark_led, got {impairment!r}")
    air = AirInterfaceV2.for_capacity(data_symbols, levels=levels, rows=rows, cols=cols, fec=fec)
    rng = np.random.default_rng(seed)
    lost = wrong = 0
    corr = 0
    for _ in range(packets):
        payload = rng.integers(0, 256, air.payload_len, dtype=np.uint8).tobytes()
        lv = inject_symbol_errors(air.encode_data(payload), levels, ser, rng)
        if impairment == "dark_led":
            lv[:, dark_led] = 1
        res = air.decode_data(lv)
        corr += res.corrected
        if res.payload is None:
            lost += 1
        elif res.payload != payload:
            wrong += 1
    return PerPoint(fec, impairment, ser, packets, lost, wrong, corr / max(packets, 1))


def per_curve(sers: list[float], packets: int, seed: int = 0, impairments: tuple[str, ...] = ("uniform", "dark_led"),
              modes: tuple[str, ...] = tuple(FEC_MODES)) -> list[PerPoint]:
    """:func:`residual_per` for every mode, impairment and SER (one seed per point)."""
    return [residual_per(m, s, packets, seed + 1000 * i + j, imp)
            for i, imp in enumerate(impairments) for m in modes for j, s in enumerate(sers)]
