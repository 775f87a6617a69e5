"""The daemon's outputs: JSON Lines files, a ZeroMQ socket, and the Rerun live view.

- :class:`~iscd.outputs.jsonl.JsonlWriter` — SPEC section 7 records, rotated, flushed so a
  killed daemon loses at most ``flush_interval_s`` of them.
- :class:`~iscd.outputs.socket.ZmqPublisher` — the same records on a ZeroMQ PUB socket
  (loopback by default) for other in-car software.
- :class:`~iscd.outputs.rerun_view.RerunView` — images with LED boxes, luminance, levels,
  range, counters in the Rerun viewer (``--connect``, ``--serve``, ``--save FILE.rrd``).
- :class:`Outputs` — one ``write(record)`` for all of them (each an
  :class:`~iscd.outputs.base.Output`); never raises.

The config sections ``[output]`` and ``[rerun]`` are :class:`OutputConfig` and
:class:`RerunConfig` (docs/outputs.md). Submodules are imported lazily so that importing
this package does not load pyzmq or rerun-sdk.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from iscd.outputs.base import (Output, OutputConfig, OutputError, RerunConfig, output_config,  # noqa: F401
                               rerun_config)

if TYPE_CHECKING:
    from iscd.core.config import Config
    from iscd.outputs.jsonl import JsonlWriter
    from iscd.outputs.rerun_view import RerunView
    from iscd.outputs.socket import ZmqPublisher

log = logging.getLogger(__name__)


class Outputs:
    """Fan-out of records to the enabled outputs (picamera2's encoder -> outputs); never raises.

    Each output is an :class:`~iscd.outputs.base.Output` (``write(record)``, ``counters()``,
    ``close()``; duck-typed objects with only ``write`` are fine). An exception from one output
    is logged (rate-limited) and counted in :attr:`errors` (``output_errors`` in the stats);
    the others still get the record: an output never stops the decoding.
    """

    def __init__(self, outputs: "Iterable[Output]" = ()) -> None:
        self.outputs: list[Any] = list(outputs)
        self.errors = 0

    def write(self, record: dict[str, Any]) -> None:
        """One record to every output."""
        for out in self.outputs:
            try:
                out.write(record)
            except Exception as e:  # noqa: BLE001 - an output must never stop the daemon
                self.errors += 1
                if self.errors <= 5 or self.errors % 100 == 0:
                    log.error("output %s failed: %s (error %d)", type(out).__name__, e, self.errors)

    def counters(self) -> dict[str, int | float]:
        """``output_errors`` and every output's own numeric counters, for the stats record."""
        out: dict[str, int | float] = {"output_errors": self.errors}
        for o in self.outputs:
            c = getattr(o, "counters", None)
            if callable(c):
                out.update({k: v for k, v in c().items() if isinstance(v, (int, float))})
        return out

    def close(self) -> None:
        """Close every output (each once; an error is logged, the rest still close)."""
        for o in self.outputs:
            close = getattr(o, "close", None)
            if not callable(close):
                continue
            try:
                close()
            except Exception as e:  # noqa: BLE001
                log.error("closing output %s failed: %s", type(o).__name__, e)


def __getattr__(name: str) -> Any:
    if name == "JsonlWriter":
        from iscd.outputs.jsonl import JsonlWriter

        return JsonlWriter
    if name == "ZmqPublisher":
        from iscd.outputs.socket import ZmqPublisher

        return ZmqPublisher
    if name == "RerunView":
        from iscd.outputs.rerun_view import RerunView

        return RerunView
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["JsonlWriter", "Output", "OutputConfig", "OutputError", "Outputs", "RerunConfig", "RerunView",
           "ZmqPublisher", "output_config", "rerun_config"]
