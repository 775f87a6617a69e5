"""Pure metrics of the evaluation: decided levels vs the truth, link rates, range errors.

No I/O, no simulation: the sweeps (:mod:`iscd.eval.sweeps`) feed these with decoded packet
records and the simulator's ground truth.

Units: rates in kbit/s (kbps), times in s, distances in m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iscd.core.airinterface import gray_encode

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.int64)


def symbol_errors(sent: ArrayLike, decided: ArrayLike) -> int:
    """Number of symbols (levels 1..M) where ``decided`` differs from ``sent`` (same shape)."""
    s, d = np.asarray(sent), np.asarray(decided)
    if s.shape != d.shape:
        raise ValueError(f"sent {s.shape} and decided {d.shape} levels differ in shape")
    return int(np.count_nonzero(s != d))


def bit_errors(sent: ArrayLike, decided: ArrayLike, levels: int) -> int:
    """Bit errors between two level arrays under the air interface's Gray mapping (SPEC 3):
    level ``l + 1`` carries the bits of ``l ^ (l >> 1)``, so a one-level slip is one bit.

    Levels outside 1..M (never produced by the receiver) are clipped into range.
    """
    if levels < 2 or levels > 256 or levels & (levels - 1):
        raise ValueError(f"levels: expected a power of two in 2..256, got {levels}")
    s = np.clip(np.asarray(sent, dtype=np.int64), 1, levels) - 1
    d = np.clip(np.asarray(decided, dtype=np.int64), 1, levels) - 1
    if s.shape != d.shape:
        raise ValueError(f"sent {s.shape} and decided {d.shape} levels differ in shape")
    return int(_POPCOUNT[gray_encode(s) ^ gray_encode(d)].sum())


def throughput_kbps(levels: int, n_leds: int, data_symbols: int, packet_s: float, ser: float) -> float:
    """The dissertation's throughput (4.4): log2(M) N F / dt (1 - E) / 1000, kbps.

    ``packet_s`` is dt, the whole packet's duration (header + training + data + idle), s;
    ``ser`` is E. With E = 0 this is the raw data-symbol rate (88.2 kbps for 8x8 PWM-8 with
    653-symbol packets at 500 Hz). The dissertation notes that it is not a true throughput
    (see :func:`goodput_kbps`). NaN when ``ser`` is NaN (nothing decoded)."""
    if packet_s <= 0:
        raise ValueError(f"packet_s: expected a duration > 0, got {packet_s}")
    return math.log2(levels) * n_leds * data_symbols / packet_s * (1.0 - ser) / 1000.0


def goodput_kbps(packets_ok: int, payload_bytes: int, packets_sent: int, packet_s: float) -> float:
    """Payload bits of CRC-valid (and bit-exact) packets per second of transmission, kbps:
    ``8 * payload_bytes * packets_ok / (packets_sent * packet_s) / 1000``."""
    if packets_sent <= 0:
        return float("nan")
    return 8.0 * payload_bytes * packets_ok / (packets_sent * packet_s) / 1000.0


def match_packets(decoded_t_s: ArrayLike, truth_t_s: ArrayLike, tolerance_s: float) -> NDArray[np.int64]:
    """For each decoded packet (header start time, s) the index of the truth packet whose
    header starts within ``tolerance_s`` of it (nearest), or -1 when none does."""
    d = np.asarray(decoded_t_s, dtype=np.float64).reshape(-1)
    t = np.asarray(truth_t_s, dtype=np.float64).reshape(-1)
    if t.size == 0 or d.size == 0:
        return np.full(d.size, -1, np.int64)
    j = np.argmin(np.abs(d[:, None] - t[None, :]), axis=1)
    ok = np.abs(t[j] - d) <= tolerance_s
    return np.where(ok, j, -1).astype(np.int64)


@dataclass(frozen=True)
class ErrorStats:
    """Range error statistics of one method at one point (m); ``n`` estimates used,
    ``failed`` frames where the method gave no finite range (not in the statistics)."""

    n: int
    failed: int
    mae: float
    bias: float
    rmse: float
    p95: float

    def as_dict(self) -> dict[str, float | int]:
        return {"n": self.n, "failed": self.failed, "mae_m": self.mae, "bias_m": self.bias,
                "rmse_m": self.rmse, "p95_m": self.p95}


def error_stats(estimate: ArrayLike, truth: ArrayLike) -> ErrorStats:
    """Mean absolute error, bias (mean signed error), RMSE and 95th percentile of the
    absolute error of ``estimate - truth`` (m), over the finite estimates."""
    e = np.asarray(estimate, dtype=np.float64) - np.asarray(truth, dtype=np.float64)
    ok = np.isfinite(e)
    g = e[ok]
    if g.size == 0:
        nan = float("nan")
        return ErrorStats(0, int(e.size), nan, nan, nan, nan)
    return ErrorStats(n=int(g.size), failed=int(e.size - g.size), mae=float(np.mean(np.abs(g))),
                      bias=float(np.mean(g)), rmse=float(np.sqrt(np.mean(g * g))),
                      p95=float(np.percentile(np.abs(g), 95)))
