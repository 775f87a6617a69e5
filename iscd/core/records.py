"""The output records (SPEC section 7), typed: one dataclass per record ``type``.

Every record has ``type``, ``tx`` (transmitter index), ``frame`` (left-camera frame index)
and ``t_s`` (s, camera time). The producers (the decoder, the daemon, ``iscd replay``) build
these and hand on ``to_json()``: a plain dict of JSON types, keys in the order below, which the
outputs (JSON Lines, ZeroMQ, Rerun) write as they are. :func:`check_record` tells whether a
dict read back (a file, the socket) has what SPEC section 7 promises for its type.

Fields are stable (SPEC section 7: "keep these stable; extend them freely"): new ones are
added, none renamed. A record's own extras (a packet's quality metrics, the stats' counters)
go in ``extra`` and are written after the fixed fields.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar

__all__ = ["PacketRecord", "RangeFilteredRecord", "RangeLedsRecord", "RangeRecord", "RECORD_TYPES",
           "RecordError", "StatsRecord", "check_record"]


class RecordError(ValueError):
    """A dict that is not a record of its type (a key missing or of the wrong type)."""


_FIELDS: dict[type, tuple[str, ...]] = {}


@dataclass(frozen=True, slots=True)
class _Record:
    TYPE: ClassVar[str] = ""
    tx: int
    frame: int
    t_s: float | None
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def spec_fields(cls) -> tuple[str, ...]:
        """The fields of this type after ``type``, ``tx``, ``frame``, ``t_s`` (``extra`` aside)."""
        return tuple(f.name for f in dataclasses.fields(cls) if f.name not in ("tx", "frame", "t_s", "extra"))

    def to_json(self) -> dict[str, Any]:
        """The record as written: ``type`` first, then the fields in order, then ``extra``."""
        names = _FIELDS.get(type(self))
        if names is None:
            names = _FIELDS[type(self)] = tuple(f.name for f in dataclasses.fields(self) if f.name != "extra")
        out: dict[str, Any] = {"type": self.TYPE}
        for n in names:
            out[n] = getattr(self, n)
        if self.extra:
            out.update(self.extra)
        return out


@dataclass(frozen=True, slots=True)
class RangeRecord(_Record):
    """``range``: the transmitter's distance on one frame (SPEC section 7)."""

    TYPE: ClassVar[str] = "range"
    z_m: float = float("nan")
    """distance along the left camera's optical axis, m"""
    disparity_px: float = float("nan")
    """stereo disparity, px"""
    sigma_m: float = float("nan")
    """the estimator's standard deviation of z_m, m"""

    @staticmethod
    def json_of(tx: int, frame: int, t_s: float | None, z_m: float, disparity_px: float,
                sigma_m: float) -> dict[str, Any]:
        """``RangeRecord(...).to_json()`` without the record object: the decoder makes one
        per frame (1000 a second), and the object costs more than the dict."""
        return {"type": "range", "tx": tx, "frame": frame, "t_s": t_s, "z_m": z_m,
                "disparity_px": disparity_px, "sigma_m": sigma_m}


@dataclass(frozen=True, slots=True)
class PacketRecord(_Record):
    """``packet``: one packet found (SPEC section 7); ``extra`` holds the quality metrics."""

    TYPE: ClassVar[str] = "packet"
    crc_ok: bool = False
    payload_hex: str = ""
    """the payload, hex ('' unless the CRC holds: light is an untrusted channel)"""
    levels: list[int] = field(default_factory=list)
    """the F·N decided data levels 1..M, symbol time major"""


@dataclass(frozen=True, slots=True)
class RangeLedsRecord(_Record):
    """``range_leds``: one range per LED of an array (``[ranging] per_led``); None where an
    LED has no valid range."""

    TYPE: ClassVar[str] = "range_leds"
    n_valid: int = 0
    z_m: list[float | None] = field(default_factory=list)
    sigma_m: list[float | None] = field(default_factory=list)


@dataclass(frozen=True, slots=True)
class RangeFilteredRecord(_Record):
    """``range_filtered``: Kalman-filtered range and closing speed (``[ranging] kalman``)."""

    TYPE: ClassVar[str] = "range_filtered"
    z_m: float = float("nan")
    sigma_m: float = float("nan")
    closing_speed_mps: float = float("nan")
    """positive when the transmitter comes closer, m/s"""
    accepted: bool = True
    """False when the measurement was gated out as an outlier"""


@dataclass(frozen=True, slots=True)
class StatsRecord(_Record):
    """``stats``: every ``stats_interval_s`` of a run and once at its end (SPEC section 7);
    ``extra`` holds every finer counter."""

    TYPE: ClassVar[str] = "stats"
    frames_in: int = 0
    frames_dropped: int = 0
    pairs_decoded: int = 0
    packets_ok: int = 0
    packets_bad: int = 0
    latency_ms_p50: float | None = None
    latency_ms_p99: float | None = None


RECORD_TYPES: dict[str, type[_Record]] = {c.TYPE: c for c in
                                          (RangeRecord, PacketRecord, RangeLedsRecord, RangeFilteredRecord, StatsRecord)}

def _json_types(tp: Any) -> tuple[type, ...]:
    """The JSON value types a field of annotation ``tp`` is read back as: a float may come as
    an int, or as null (the JSON Lines writer writes non-finite numbers as null)."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return tuple(dict.fromkeys(t for a in typing.get_args(tp) for t in _json_types(a)))
    if tp is float:
        return (int, float, type(None))
    if typing.get_origin(tp) is list:
        return (list,)
    return (type(None),) if tp is type(None) else (tp,)


def _schema(cls: type[_Record]) -> dict[str, tuple[type, ...]]:
    hints = typing.get_type_hints(cls)
    return {f.name: _json_types(hints[f.name]) for f in dataclasses.fields(cls) if f.name != "extra"}


_CHECKS: dict[str, dict[str, tuple[type, ...]]] = {k: _schema(c) for k, c in RECORD_TYPES.items()}
"""Per record type, each SPEC field and the JSON types it may hold (from the dataclasses)."""


def check_record(record: dict[str, Any]) -> str:
    """The record's type, after checking that it has every field SPEC section 7 promises
    for it, of the right JSON type. Raises :class:`RecordError` naming the field."""
    kind = record.get("type")
    if kind not in _CHECKS:
        raise RecordError(f"record type {kind!r} unknown (known: {', '.join(_CHECKS)})")
    for key, ok in _CHECKS[kind].items():
        if key not in record:
            raise RecordError(f"{kind} record: no {key!r}")
        v = record[key]
        if not isinstance(v, ok) or (isinstance(v, bool) and bool not in ok):
            raise RecordError(f"{kind} record: {key} = {v!r} is not {' or '.join(t.__name__ for t in ok)}")
    return kind
