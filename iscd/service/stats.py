"""Run statistics: latency percentiles, CPU and memory of the daemon's processes.

Latency is frame-to-record: from the moment a stereo pair's frames reached the host
(``arrival_ns`` in the ring, ``time.monotonic_ns``) to the moment the records computed
from it were handed to the outputs, in ms.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

_CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


@dataclass
class LatencyWindow:
    """Latencies (ms) collected since the last :meth:`take`, bounded to ``cap`` samples."""

    cap: int = 20_000
    _buf: np.ndarray = field(default_factory=lambda: np.empty(0))
    _n: int = 0

    def __post_init__(self) -> None:
        self._buf = np.empty(self.cap, dtype=np.float64)

    def add(self, latencies_ms: np.ndarray) -> None:
        v = np.asarray(latencies_ms, dtype=np.float64).ravel()
        room = self.cap - self._n
        if room <= 0:
            return
        v = v[:room]
        self._buf[self._n:self._n + v.size] = v
        self._n += v.size

    def take(self) -> tuple[float | None, float | None]:
        """(p50, p99) in ms of the samples since the last call, and reset."""
        if self._n == 0:
            return None, None
        v = self._buf[:self._n]
        p50, p99 = np.percentile(v, [50, 99])
        self._n = 0
        return round(float(p50), 3), round(float(p99), 3)


class LatencyHistogram:
    """Every latency (ms) of a whole run, in bins of ``bin_ms`` up to ``top_ms`` (one bin
    above for the rest): the run's percentiles in constant memory, however long it runs.

    A percentile is the upper edge of the bin it falls in (at most ``bin_ms`` above the
    exact value); above ``top_ms`` it is the largest latency seen.
    """

    def __init__(self, bin_ms: float = 0.1, top_ms: float = 2000.0) -> None:
        self.bin_ms = float(bin_ms)
        self.n_bins = int(np.ceil(top_ms / bin_ms))
        self.counts = np.zeros(self.n_bins + 1, np.int64)
        self.max_ms = 0.0

    def add(self, latencies_ms: np.ndarray) -> None:
        v = np.asarray(latencies_ms, dtype=np.float64).ravel()
        if v.size == 0:
            return
        idx = np.clip((v / self.bin_ms).astype(np.int64), 0, self.n_bins)
        np.add.at(self.counts, idx, 1)
        self.max_ms = max(self.max_ms, float(v.max()))

    @property
    def n(self) -> int:
        return int(self.counts.sum())

    def percentile(self, q: float) -> float | None:
        """The q-th percentile (0-100) of every latency added, ms (None before any)."""
        n = self.n
        if n == 0:
            return None
        k = int(np.searchsorted(np.cumsum(self.counts), np.ceil(q / 100.0 * n)))
        if k >= self.n_bins:
            return round(self.max_ms, 3)
        return round(min((k + 1) * self.bin_ms, self.max_ms), 3)


def process_usage(pid: int | None = None) -> tuple[float, int]:
    """(CPU seconds user+system, RSS bytes) of a process (Linux /proc; (0, 0) elsewhere)."""
    p = pid or os.getpid()
    try:
        with open(f"/proc/{p}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        cpu = (int(fields[11]) + int(fields[12])) / _CLK_TCK
        with open(f"/proc/{p}/statm", "rb") as f:
            rss = int(f.read().split()[1]) * _PAGE
        return cpu, rss
    except (OSError, IndexError, ValueError):
        return 0.0, 0


class CpuMeter:
    """CPU share (1.0 = one core) of a set of processes between calls to :meth:`sample`."""

    def __init__(self) -> None:
        self._last: dict[int, tuple[float, float]] = {}
        self.shares: dict[int, float] = {}
        """per process id, its CPU share (cores) between the last two samples"""

    def sample(self, pids: list[int]) -> tuple[float, int]:
        """(CPU share since the last sample, total RSS bytes) of ``pids``; each process's
        own share is left in :attr:`shares`."""
        now = time.monotonic()
        share = 0.0
        rss_total = 0
        self.shares = {}
        for pid in pids:
            if not os.path.exists(f"/proc/{pid}/stat"):  # gone (stopped): no share, no negative jump
                self._last.pop(pid, None)
                continue
            cpu, rss = process_usage(pid)
            rss_total += rss
            prev = self._last.get(pid)
            if prev is not None and now > prev[0]:
                one = (cpu - prev[1]) / (now - prev[0])
                self.shares[pid] = round(one, 3)
                share += one
            self._last[pid] = (now, cpu)
        return round(share, 3), rss_total
