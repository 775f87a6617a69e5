"""The run-long latency histogram (iscd.service.stats.LatencyHistogram) against numpy's
percentiles of the same samples."""

from __future__ import annotations

import numpy as np

from iscd.service.stats import LatencyHistogram


def test_percentiles_within_one_bin_of_numpy() -> None:
    rng = np.random.default_rng(3)
    v = np.concatenate([rng.gamma(4.0, 2.5, 50_000), rng.uniform(100, 600, 300)])  # a tail of spikes
    h = LatencyHistogram(bin_ms=0.1, top_ms=2000.0)
    for chunk in np.array_split(v, 997):  # added block by block, as the daemon does
        h.add(chunk)
    assert h.n == v.size
    for q in (50, 90, 99, 99.9):
        exact = float(np.percentile(v, q, method="inverted_cdf"))
        got = h.percentile(q)
        assert exact <= got <= exact + 0.1 + 1e-9, (q, exact, got)
    assert h.max_ms == v.max()


def test_empty_and_beyond_the_top() -> None:
    h = LatencyHistogram(bin_ms=1.0, top_ms=10.0)
    assert h.percentile(99) is None and h.n == 0
    h.add(np.array([1.5, 2.5, 500.0, 700.0]))
    assert h.percentile(25) == 2.0       # the upper edge of 1.5's bin
    assert h.percentile(99) == 700.0     # above the top: the largest seen
    h.add(np.array([]))
    assert h.n == 4
