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
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from iscd.errors import UserError

if TYPE_CHECKING:
    from iscd.config import Config
    from iscd.outputs.jsonl import JsonlWriter
    from iscd.outputs.rerun_view import RerunView
    from iscd.outputs.socket import ZmqPublisher

log = logging.getLogger(__name__)


class OutputError(UserError):
    """An output cannot be set up (file not writable, endpoint refused or in use). One line."""


def _f(default: Any, *, lo: float | None = None, hi: float | None = None,
       choices: tuple[Any, ...] | None = None, doc: str = "") -> Any:
    """A config field in iscd.config's style (validated by ``iscd.config.build_section``)."""
    return field(default=default,
                 metadata={"lo": lo, "hi": hi, "lo_open": False, "choices": choices, "doc": doc})


@dataclass(frozen=True)
class OutputConfig:
    """``[output]``: how the JSON Lines files and the ZeroMQ socket behave (docs/outputs.md).

    Where they go is ``[daemon]``'s business (``out``, ``rotate_mb``, ``socket``) and the
    command line's (``--out``, ``--socket``).
    """

    keep: int = _f(10, lo=0, doc="rotated files kept (FILE.1 ... FILE.keep); older ones are deleted")
    flush_interval_s: float = _f(0.5, lo=0, hi=60,
                                 doc="longest a record waits in memory (what a killed daemon loses), s")
    fsync_interval_s: float = _f(5.0, lo=0, doc="force the file to disk this often (power cuts), s")
    zmq_hwm: int = _f(10_000, lo=1, doc="messages queued per subscriber before records are dropped")
    zmq_allow_remote: bool = _f(False, doc="allow binding the socket to a non-loopback address")


@dataclass(frozen=True)
class RerunConfig:
    """``[rerun]``: the Rerun live view (the command-line flags override these)."""

    connect: str = _f("", doc="stream to a running viewer at this URL "
                              "(rerun+http://127.0.0.1:9876/proxy); empty = off")
    serve: bool = _f(False, doc="host a gRPC server that viewers connect to")
    serve_bind: str = _f("127.0.0.1", doc="--serve: address to bind (0.0.0.0 = every interface)")
    serve_port: int = _f(9876, lo=1, hi=65535, doc="--serve: port")
    server_memory_limit: str = _f("256MiB", doc="--serve: data kept for late viewers")
    save: str = _f("", doc="write a .rrd recording here; empty = off")
    image_every: int = _f(50, lo=1, doc="log one image pair every this many frames")
    image_scale: float = _f(0.5, lo=0.05, hi=1.0, doc="image downscale factor for the view")
    jpeg_quality: int = _f(0, lo=0, hi=100, doc="JPEG-compress logged images (0 = raw pixels)")


def output_config(cfg: "Config") -> OutputConfig:
    """The validated ``[output]`` section of ``cfg`` (defaults when absent)."""
    from iscd.config import build_section

    return build_section(OutputConfig, cfg.extra.get("output", {}), "output")


def rerun_config(cfg: "Config") -> RerunConfig:
    """The validated ``[rerun]`` section of ``cfg`` (defaults when absent)."""
    from iscd.config import build_section

    return build_section(RerunConfig, cfg.extra.get("rerun", {}), "rerun")


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
