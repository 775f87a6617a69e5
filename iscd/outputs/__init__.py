"""The daemon's outputs: JSON Lines files, a ZeroMQ socket, and the Rerun live view.

- :class:`~iscd.outputs.jsonl.JsonlWriter` — SPEC section 7 records, rotated, flushed so a
  killed daemon loses at most ``flush_interval_s`` of them.
- :class:`~iscd.outputs.socket.ZmqPublisher` — the same records on a ZeroMQ PUB socket
  (loopback by default) for other in-car software.
- :class:`~iscd.outputs.rerun_view.RerunView` — images with LED boxes, luminance, levels,
  range, counters in the Rerun viewer (``--connect``, ``--serve``, ``--save FILE.rrd``).
- :class:`Outputs` — one ``write(record)`` for all of them; never raises.

The config sections ``[output]`` and ``[rerun]`` are :class:`OutputConfig` and
:class:`RerunConfig` (docs/outputs.md). Submodules are imported lazily so that importing
this package does not load pyzmq or rerun-sdk.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from iscd.outputs.base import (OutputConfig, OutputError, RerunConfig, output_config,  # noqa: F401
                               rerun_config)

if TYPE_CHECKING:
    from iscd.core.config import Config
    from iscd.outputs.jsonl import JsonlWriter
    from iscd.outputs.rerun_view import RerunView
    from iscd.outputs.socket import ZmqPublisher

log = logging.getLogger(__name__)


class Outputs:
    """Fan-out of records to the enabled outputs; :meth:`write` never raises.

    Any of ``jsonl``, ``zmq``, ``rerun`` may be None. An exception from one output is
    logged (rate-limited) and counted in :attr:`errors`; the others still get the record.
    """

    def __init__(self, jsonl: "JsonlWriter | None" = None, zmq: "ZmqPublisher | None" = None,
                 rerun: "RerunView | None" = None) -> None:
        self.jsonl, self.zmq, self.rerun = jsonl, zmq, rerun
        self.errors = 0

    def _each(self) -> list[tuple[str, Any]]:
        return [(n, o) for n, o in (("jsonl", self.jsonl), ("zmq", self.zmq), ("rerun", self.rerun))
                if o is not None]

    def write(self, record: dict[str, Any]) -> None:
        for name, out in self._each():
            try:
                if name == "rerun":
                    out.log_record(record)
                else:
                    out.write(record)
            except Exception as e:  # noqa: BLE001 - an output must never stop the daemon
                self.errors += 1
                if self.errors <= 5 or self.errors % 100 == 0:
                    log.error("output %s failed: %s (error %d)", name, e, self.errors)

    def maybe_flush(self) -> None:
        if self.jsonl is not None:
            self.jsonl.maybe_flush()

    def counters(self) -> dict[str, int]:
        """Drop and error counters of every output, for the stats record."""
        out: dict[str, int] = {"output_errors": self.errors}
        for _, o in self._each():
            out.update(o.counters())
        return out

    def close(self) -> None:
        for name, out in self._each():
            try:
                out.close()
            except Exception as e:  # noqa: BLE001
                log.error("closing output %s failed: %s", name, e)


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


__all__ = ["JsonlWriter", "OutputConfig", "OutputError", "Outputs", "RerunConfig", "RerunView",
           "ZmqPublisher", "output_config", "rerun_config"]
