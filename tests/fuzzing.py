"""Hypothesis settings shared by the fuzz tests (tests/test_fuzz_*.py).

CI runs ``ci_examples`` derandomized cases per target (deterministic, no example database);
``ISCD_FUZZ_EXAMPLES=N`` runs N random cases per target instead (the long run,
docs/hardening.md).
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

LONG = os.environ.get("ISCD_FUZZ_EXAMPLES")


def fuzz(ci_examples: int) -> settings:
    """``ci_examples`` derandomized cases in CI, ISCD_FUZZ_EXAMPLES random ones in a long run."""
    if LONG:
        return settings(max_examples=int(LONG), deadline=None, database=None,
                        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    return settings(max_examples=ci_examples, deadline=None, database=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
