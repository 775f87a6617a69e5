"""Luminance traces: what a receiver's packet assembler was fed in one scene, kept so that the
demodulation alone can run again -- with other ``[receiver]`` settings or a changed
demodulator -- without rendering, following or measuring the scene again.

``iscd eval --suite motion --traces DIR`` writes one trace per scene
(``DIR/<case>-<seed>[-<scene keys>].npz``); ``python -m iscd.eval.lumtrace FILE|DIR...
[--receiver KEY=VALUE]`` demodulates them again and prints, per scene and in all, the packets
delivered bit-exact against those of the run that wrote them: about half a second per
two-packet one-LED scene, where the oracle spends about 7.5 s (session 31 tried a dozen
channel variants this way on 324 scenes, docs/eval.md).

A trace holds, in order, the assembler's calls (``push`` with the frame ids, times and the
per-LED luminance of each camera; ``reset``; ``flush``), the transmitter and receiver settings,
the camera rate and exposure, the truth's sent packets (header start, data levels) and how
the run that wrote it scored them. What the front end did (detection, following, the
luminance window) is fixed in it; the demodulator is the code that reads it. Units: times
s, luminance DN, levels 1 .. M.
"""

from __future__ import annotations

import argparse
import json
import sys
import zipfile
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from iscd.core.config import TransmitterConfig
from iscd.decode.comms.packets import PacketAssembler
from iscd.decode.comms.settings import ReceiverConfig

FORMAT = 1
"""Version of the file layout (``meta["format"]``)."""


class TraceError(ValueError):
    """A trace file that cannot be read (missing, truncated, another format)."""


@dataclass(frozen=True)
class SentPacket:
    """A packet the transmitter sent: its index in the scene, header start (s) and data
    levels (F, N), 1 .. M."""

    index: int
    t_s: float
    levels: np.ndarray


@dataclass(frozen=True)
class PacketScore:
    """How one sent packet came out: ``found`` (a packet was decoded at its time),
    ``crc_ok`` and the wrong data ``errors`` (symbols)."""

    index: int
    found: bool
    crc_ok: bool = False
    errors: int = 0

    @property
    def delivered(self) -> bool:
        """Bit-exact with a valid CRC."""
        return self.found and self.crc_ok and self.errors == 0


@dataclass
class Trace:
    """One scene's assembler input and truth (module docstring)."""

    label: str
    transmitter: TransmitterConfig
    receiver: ReceiverConfig
    fps: float
    exposure_s: float
    sent: list[SentPacket]
    steps: list[tuple[Any, ...]] = field(default_factory=list)
    """("new",) (a fresh assembler: the decoder's new track), ("push", ids (n,), t_s (n,),
    L_left (n, N) or None, L_right (n, N) or None, centres or None), ("reset",) or
    ("flush",), in call order; centres: one LED's (left, right) followed centres (n, 1, 2)
    px, each or both None (a trace written before they were kept has none)"""
    captured: list[PacketScore] = field(default_factory=list)
    """the scores of the run that wrote the trace"""

    @property
    def tolerance_s(self) -> float:
        """Largest distance between a decoded and a sent header start that still matches, s
        (half a symbol, as ``iscd eval`` scores)."""
        return 0.5 / self.transmitter.symbol_rate_hz


class TracingAssembler(PacketAssembler):
    """A :class:`PacketAssembler` that also keeps a copy of every call's input in
    ``steps`` (what a :class:`Trace` holds), after a ``("new",)`` for itself: a decoder
    that starts a new assembler for a new track hands each the same list."""

    def __init__(self, *a: Any, steps: list[tuple[Any, ...]] | None = None, **k: Any) -> None:
        self.steps: list[tuple[Any, ...]] = [] if steps is None else steps
        self.steps.append(("new",))
        super().__init__(*a, **k)

    def push(self, frame_ids: np.ndarray, t_s: np.ndarray, L_left: np.ndarray | None,
             L_right: np.ndarray | None = None,
             centres: tuple[np.ndarray | None, np.ndarray | None] | None = None) -> list[Any]:
        kept = None if centres is None else tuple(None if c is None else np.array(c) for c in centres)
        self.steps.append(("push", np.array(frame_ids), np.array(t_s),
                           None if L_left is None else np.array(L_left),
                           None if L_right is None else np.array(L_right), kept))
        return super().push(frame_ids, t_s, L_left, L_right, centres)

    def reset(self) -> list[Any]:
        self.steps.append(("reset",))
        return super().reset()

    def flush(self) -> list[Any]:
        self.steps.append(("flush",))
        return super().flush()


# ----------------------------------------------------------------------------- scoring

def score(packets: Sequence[Any], sent: Sequence[SentPacket], tolerance_s: float) -> list[PacketScore]:
    """Per sent packet the best decoded one within ``tolerance_s`` of its header start.

    Parameters
    ----------
    packets : sequence
        Decoded packets (``t_s`` s, ``levels`` (F, N) or flat 1 .. M, ``crc_ok``), objects
        or records.
    sent : sequence of SentPacket
        The truth.
    tolerance_s : float
        Match window, s.

    Returns
    -------
    list of PacketScore
        In the order of ``sent``; a packet with several matches scores its fewest errors.
    """
    best: dict[int, PacketScore] = {p.index: PacketScore(p.index, False) for p in sent}
    if not sent:
        return []
    starts = np.array([p.t_s for p in sent])
    for pk in packets:
        get = pk.get if isinstance(pk, dict) else (lambda k, pk=pk: getattr(pk, k))
        j = int(np.argmin(np.abs(starts - float(get("t_s")))))
        if abs(starts[j] - float(get("t_s"))) > tolerance_s:
            continue
        want = sent[j]
        got = np.asarray(get("levels")).reshape(want.levels.shape)
        sc = PacketScore(want.index, True, bool(get("crc_ok")), int(np.count_nonzero(got != want.levels)))
        old = best[want.index]
        if not old.found or (sc.delivered, -sc.errors) > (old.delivered, -old.errors):
            best[want.index] = sc
    return [best[p.index] for p in sent]


def redemodulate(trace: Trace, receiver: ReceiverConfig | None = None) -> list[PacketScore]:
    """Feed a trace's steps to fresh assemblers (one per ``("new",)``, as the run had them)
    with ``receiver`` (default the trace's own) and score every packet they return.

    Parameters
    ----------
    trace : Trace
        What to demodulate again.
    receiver : ReceiverConfig, optional
        Receiver settings instead of the trace's.

    Returns
    -------
    list of PacketScore
        Per sent packet, as :func:`score`.
    """
    rx = receiver or trace.receiver

    def new() -> PacketAssembler:
        return PacketAssembler(trace.transmitter, fps=trace.fps, exposure_s=trace.exposure_s, cfg=rx)

    asm = new()  # (a trace written by TracingAssembler starts with ("new",) anyway)
    out: list[Any] = []
    for step in trace.steps:
        if step[0] == "new":
            asm = new()
        elif step[0] == "push":
            out += asm.push(*step[1:])
        elif step[0] == "reset":
            out += asm.reset()
        elif step[0] == "flush":
            out += asm.flush()
    out += asm.flush()
    return score(out, trace.sent, trace.tolerance_s)


# ----------------------------------------------------------------------------- files

def save(trace: Trace, path: str | Path) -> Path:
    """Write ``trace`` as one ``.npz`` (arrays, and the rest as JSON in ``meta``); written to
    a temporary name first, so that a crash leaves no partial file under ``path``."""
    path = Path(path)
    arrays: dict[str, np.ndarray] = {}
    steps: list[list[Any]] = []
    for i, st in enumerate(trace.steps):
        if st[0] == "push":
            arrays[f"ids{i}"], arrays[f"t{i}"] = np.asarray(st[1]), np.asarray(st[2], dtype=np.float64)
            cl, cr = st[5] if len(st) > 5 and st[5] is not None else (None, None)
            for side, a in (("l", st[3]), ("r", st[4]), ("cl", cl), ("cr", cr)):
                if a is not None:
                    arrays[f"{side}{i}"] = np.asarray(a, dtype=np.float64)
            steps.append(["push", st[3] is not None, st[4] is not None, cl is not None, cr is not None])
        else:
            steps.append([st[0]])
    for j, p in enumerate(trace.sent):
        arrays[f"sent{j}"] = np.asarray(p.levels, dtype=np.int64)
    meta = {"format": FORMAT, "label": trace.label, "transmitter": asdict(trace.transmitter),
            "receiver": asdict(trace.receiver), "fps": trace.fps, "exposure_s": trace.exposure_s,
            "steps": steps, "sent": [[p.index, p.t_s] for p in trace.sent],
            "captured": [[s.index, s.found, s.crc_ok, s.errors] for s in trace.captured]}
    arrays["meta"] = np.array(json.dumps(meta))
    tmp = path.with_name(path.name + ".part")
    try:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _dataclass_from(cls: Any, d: dict[str, Any], what: str) -> Any:
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
        raise TraceError(f"{what}: unknown key {unknown[0]!r} (written by another version?)")
    return cls(**d)


def _check_settings(meta: dict[str, Any], path: Path) -> None:
    """The transmitter and camera settings of a trace checked as a config's ``[transmitter]``
    and ``[camera]`` are (levels, shape, fps, exposure...): a damaged value is one line
    naming it, not an exception in the demodulator."""
    from iscd.core.config import CameraConfig, ConfigError, build_section

    try:
        if not isinstance(meta["transmitter"], dict):
            raise ConfigError(f"transmitter: expected a table, got {meta['transmitter']!r}")
        build_section(TransmitterConfig, meta["transmitter"], "transmitter")
        build_section(CameraConfig, {"fps": meta["fps"], "exposure_s": meta["exposure_s"]}, "camera")
    except ConfigError as e:
        raise TraceError(f"{path}: a damaged trace ({e})") from None


def _receiver_from(table: Any, path: Path) -> ReceiverConfig:
    from iscd.core.config import ConfigError
    from iscd.decode.comms.settings import receiver_config

    try:
        return receiver_config(table=table)
    except ConfigError as e:
        raise TraceError(f"{path}: {e}") from None


def load(path: str | Path) -> Trace:
    """Read a trace written by :func:`save`.

    Raises
    ------
    TraceError
        The file is missing, truncated or not a trace of this format (one line saying which).
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise TraceError(f"{path}: no such file") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise TraceError(f"{path}: not a readable trace ({type(e).__name__}: {e})") from None
    if "meta" not in data:
        raise TraceError(f"{path}: not a trace (no meta)")
    try:
        meta = json.loads(str(data["meta"]))
        if meta.get("format") != FORMAT:
            raise TraceError(f"{path}: trace format {meta.get('format')!r}, this version reads {FORMAT}")
        tx = _dataclass_from(TransmitterConfig, meta["transmitter"], f"{path}: transmitter")
        rx = _receiver_from(meta["receiver"], path)
        _check_settings(meta, path)
        steps: list[tuple[Any, ...]] = []
        for i, st in enumerate(meta["steps"]):
            if st[0] == "push":
                cl = data[f"cl{i}"] if len(st) > 3 and st[3] else None
                cr = data[f"cr{i}"] if len(st) > 4 and st[4] else None
                steps.append(("push", data[f"ids{i}"], data[f"t{i}"],
                              data[f"l{i}"] if st[1] else None, data[f"r{i}"] if st[2] else None,
                              None if cl is None and cr is None else (cl, cr)))
            elif st[0] in ("new", "reset", "flush"):
                steps.append((st[0],))
            else:
                raise TraceError(f"{path}: unknown step {st[0]!r}")
        sent = [SentPacket(int(ix), float(t), data[f"sent{j}"]) for j, (ix, t) in enumerate(meta["sent"])]
        captured = [PacketScore(int(a), bool(b), bool(c), int(d)) for a, b, c, d in meta["captured"]]
        return Trace(str(meta["label"]), tx, rx, float(meta["fps"]), float(meta["exposure_s"]), sent, steps,
                     captured)
    except TraceError:
        raise
    except (KeyError, IndexError, TypeError, ValueError) as e:
        raise TraceError(f"{path}: a damaged trace ({type(e).__name__}: {e})") from None


# ----------------------------------------------------------------------------- command line

def _with_receiver_keys(base: ReceiverConfig, items: Sequence[str]) -> ReceiverConfig:
    """``base`` with ``KEY=VALUE`` items over it (values read as TOML values, bare words as
    strings), validated as a ``[receiver]`` table: a bad key or value is one line naming it."""
    import tomllib

    from iscd.core.config import ConfigError
    from iscd.decode.comms.settings import receiver_config

    table: dict[str, Any] = asdict(base)
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise TraceError(f"--receiver {item!r}: expected KEY=VALUE")
        try:
            table[key] = tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError:
            table[key] = value
    try:
        return receiver_config(table=table)
    except ConfigError as e:
        raise TraceError(f"--receiver: {e}") from None


def _files(args: Sequence[str]) -> list[Path]:
    out: list[Path] = []
    for a in args:
        p = Path(a)
        if p.is_dir():
            found = sorted(p.glob("*.npz"))
            if not found:
                raise TraceError(f"{p}: no trace (*.npz) in it")
            out += found
        else:
            out.append(p)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m iscd.eval.lumtrace",
        description="Demodulate luminance traces again (written by iscd eval --suite motion --traces DIR) "
                    "and compare the packets delivered bit-exact with the run that wrote them. The front end "
                    "(detection, following, luminance) is the one recorded; the demodulator is this code.")
    ap.add_argument("paths", nargs="+", metavar="FILE|DIR", help="trace files, or directories of them")
    ap.add_argument("--receiver", metavar="KEY=VALUE", action="append", default=[],
                    help="a [receiver] setting over each trace's own (repeatable), e.g. channel_window_symbols=64")
    args = ap.parse_args(argv)
    try:
        files = _files(args.paths)
        total = [0, 0, 0]
        for i, f in enumerate(files):
            tr = load(f)
            rx = _with_receiver_keys(tr.receiver, args.receiver)
            new = redemodulate(tr, rx)
            old = {s.index: s for s in tr.captured}
            n_new = sum(s.delivered for s in new)
            n_old = sum(old[s.index].delivered for s in new if s.index in old)
            total[0] += n_new
            total[1] += n_old
            total[2] += len(new)
            changed = [f"p{s.index} {'gained' if s.delivered else 'lost'}" for s in new
                       if s.index in old and s.delivered != old[s.index].delivered]
            print(f"[{i + 1}/{len(files)}] {tr.label}: {n_new} of {len(new)} delivered (captured {n_old})"
                  + (f"; {', '.join(changed)}" if changed else ""), flush=True)
        print(f"in all: {total[0]} of {total[2]} delivered bit-exact (the runs that wrote the traces: {total[1]})")
    except TraceError as e:
        print(f"lumtrace: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
