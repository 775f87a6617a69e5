"""What the outputs share, below each of them: their error type and their config sections
(``[output]``: :class:`OutputConfig`, ``[rerun]``: :class:`RerunConfig`, docs/outputs.md).
The package face (:mod:`iscd.outputs`) re-exports them and builds the fan-out."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from iscd.core.config import config_section, section
from iscd.core.errors import UserError

if TYPE_CHECKING:
    from iscd.core.config import Config


class OutputError(UserError):
    """An output cannot be set up (file not writable, endpoint refused or in use). One line."""


def _f(default: Any, *, lo: float | None = None, hi: float | None = None,
       choices: tuple[Any, ...] | None = None, doc: str = "") -> Any:
    """A config field in iscd.core.config's style (validated by ``iscd.core.config.build_section``)."""
    return field(default=default,
                 metadata={"lo": lo, "hi": hi, "lo_open": False, "choices": choices, "doc": doc})


class Output:
    """What every output of the daemon is (picamera2's ``Output``): it takes SPEC section 7
    records one by one; :class:`~iscd.outputs.Outputs` fans each record out to all of them.

    Subclasses implement :meth:`write`; :meth:`counters` (numbers for the stats record) and
    :meth:`close` (idempotent) default to nothing."""

    def write(self, record: dict[str, Any]) -> None:
        """Take one record (it may raise: the fan-out counts and logs it)."""
        raise NotImplementedError

    def counters(self) -> dict[str, int]:
        """Drop and error counters for the daemon's stats record."""
        return {}

    def close(self) -> None:
        """Flush and release; called once at the end, must be safe to call again."""


@config_section("output")
@dataclass(frozen=True)
class OutputConfig:
    """How the JSON Lines files and the ZeroMQ socket behave (docs/outputs.md).

    Where they go is ``[daemon]``'s business (``out``, ``rotate_mb``, ``socket``) and the
    command line's (``--out``, ``--socket``).
    """

    keep: int = _f(10, lo=0, doc="rotated files kept (FILE.1 ... FILE.keep); older ones are deleted")
    flush_interval_s: float = _f(0.5, lo=0, hi=60,
                                 doc="longest a record waits in memory (what a killed daemon loses), s")
    fsync_interval_s: float = _f(5.0, lo=0, doc="force the file to disk this often (power cuts), s")
    zmq_hwm: int = _f(10_000, lo=1, doc="messages queued per subscriber before records are dropped")
    zmq_allow_remote: bool = _f(False, doc="allow binding the socket to a non-loopback address")


@config_section("rerun")
@dataclass(frozen=True)
class RerunConfig:
    """The Rerun live view (the command-line flags override these)."""

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
    return section(cfg, OutputConfig)


def rerun_config(cfg: "Config") -> RerunConfig:
    """The validated ``[rerun]`` section of ``cfg`` (defaults when absent)."""
    return section(cfg, RerunConfig)
