"""``iscd bench``: run the benchmarks (speed as ratios to the camera rate and to in-process baselines)."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import operator
import re
import sys
from dataclasses import dataclass
from pathlib import Path

BENCHES = {
    "mock_rig": "the mock rig delivering 512x512 stereo pairs of the 8x8 scene (pace off)",
    "ringbuffer": "stereo pairs through the shared-memory ring, producer and consumer in two processes",
    "receiver": "the demodulator alone on 8x8 PWM-16 luminance",
    "ranging": "range estimates per second, one LED and an 8x8 array",
    "decode_loop": "the whole decode loop (tracking, luminance, demodulation, ranging every frame)",
    "record": "the recording's writer per mode (full, roi, blackbox), as a ratio to a raw sequential write of the same bytes",
    "fec": "Reed-Solomon encode/decode of a 19 kB v2 packet beside reedsolo, creedsolo and galois; residual PER per code mode",
    "campaign": "iscd campaign of 12 simulated recordings (2000 pairs each) on 1 and on 2 Dask workers: the speed-up",
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench", help="run the speed benchmarks",
        description=("Runs the benchmarks in benchmarks/ and prints, for each, the rate achieved as a "
                     "ratio to the 1000 fps camera rate and to a baseline measured in the same run (the "
                     "machine may be noisy; the ratios drift less than absolute times). Benchmarks: "
                     + "; ".join(f"{k}: {v}" for k, v in BENCHES.items()) + "."))
    p.add_argument("names", nargs="*", choices=[*BENCHES, []], metavar="NAME",
                   help=f"which benchmarks (default: all): {', '.join(BENCHES)}")
    p.add_argument("--quick", action="store_true", help="short runs, to check that they work")
    p.add_argument("--check", action="store_true",
                   help="exit status 1 when a benchmark misses a target it prints (decode_loop: "
                        "realtime ratio >= target; mock_rig: cores <= target; ringbuffer: the ring "
                        "lines >= 1x target; campaign: speed-up >= target), or prints no target line; the verdicts go to stderr")
    p.set_defaults(func=run)


_OPS = {">=": operator.ge, "<=": operator.le, ">": operator.gt, "<": operator.lt}

CHECKS: dict[str, list[tuple[str, re.Pattern[str]]]] = {
    # (what, pattern with groups value, op, target) per benchmark, matched on its stdout lines
    "decode_loop": [("realtime ratio", re.compile(
        r"(?P<value>[\d.]+) x the \d+ fps camera rate \(target (?P<op>>=|<=|>|<) (?P<target>[\d.]+)\)"))],
    "mock_rig": [("cores at the camera rate", re.compile(
        r"(?P<value>[\d.]+) cores \(target (?P<op>>=|<=|>|<) (?P<target>[\d.]+)"))],
    "ringbuffer": [("ring pairs/s over the camera rate", re.compile(
        r"^ring -> .*?(?P<value>[\d.]+)x target(?P<op>)(?P<target>)"))],
    "campaign": [("speed-up from 1 to 2 workers", re.compile(
        r"speed-up (?P<value>[\d.]+) x from 1 to 2 workers \(target (?P<op>>=|<=|>|<) (?P<target>[\d.]+)\)"))],
}
"""The targets that ``--check`` reads from each benchmark's output (receiver and ranging
print ratios without a stated target: they are not checked)."""


@dataclass(frozen=True)
class TargetResult:
    """One target line of a benchmark's output, checked."""

    bench: str
    what: str
    value: float
    op: str
    target: float
    line: str

    @property
    def ok(self) -> bool:
        return _OPS[self.op](self.value, self.target)

    def __str__(self) -> str:
        verdict = "ok" if self.ok else "MISSED"
        return f"{self.bench}: {self.what} {self.value:g} (target {self.op} {self.target:g}): {verdict}"


def check_targets(name: str, text: str) -> list[TargetResult]:
    """Every target line of benchmark ``name`` in its output ``text``, checked. A pattern
    without a stated operator (ringbuffer's "N.NNx target") means ">= 1"."""
    out: list[TargetResult] = []
    for what, pat in CHECKS.get(name, []):
        for line in text.splitlines():
            m = pat.search(line)
            if m is None:
                continue
            op = m.group("op") or ">="
            target = float(m.group("target")) if m.group("target") else 1.0
            out.append(TargetResult(name, what, float(m.group("value")), op, target, line.strip()))
    return out


class _Tee(io.TextIOBase):
    """Writes to the real stdout and keeps a copy."""

    def __init__(self, out: io.TextIOBase) -> None:
        self.out, self.buf = out, io.StringIO()

    def write(self, s: str) -> int:
        self.buf.write(s)
        return self.out.write(s)

    def flush(self) -> None:
        self.out.flush()


def benchmarks_root() -> Path | None:
    """The source checkout whose ``benchmarks/`` folder holds the benchmarks (the folder
    beside the ``iscd`` package of an editable install), or None for an installed wheel,
    which ships only ``iscd``."""
    import iscd

    root = Path(iscd.__file__).resolve().parents[1]
    return root if (root / "benchmarks" / "__init__.py").is_file() else None


def run(args: argparse.Namespace) -> int:
    from iscd.core.errors import UserError

    names = args.names or list(BENCHES)
    checkout = benchmarks_root()
    if checkout is None:
        raise UserError("the benchmarks are not installed with iscd (only the package is): run "
                        "'iscd bench' from a source checkout installed with 'pip install -e .'")
    if str(checkout) not in sys.path:
        sys.path.insert(0, str(checkout))
    rc = 0
    for name in names:
        try:
            mod = importlib.import_module(f"benchmarks.bench_{name}")
        except ModuleNotFoundError as e:
            raise UserError(f"benchmark {name!r} could not be loaded from {checkout}/benchmarks ({e})") from None
        print(f"== {name}: {BENCHES[name]}", flush=True)
        tee = _Tee(sys.stdout)
        with contextlib.redirect_stdout(tee):
            rc |= int(mod.main(["--quick"] if args.quick else []) or 0)
        if getattr(args, "check", False) and name in CHECKS:
            results = check_targets(name, tee.buf.getvalue())
            if not results:
                print(f"iscd bench: {name}: no target line in its output: cannot check", file=sys.stderr)
                rc |= 1
            for r in results:
                print(f"iscd bench: {r}", file=sys.stderr)
                if not r.ok:
                    rc |= 1
    return rc
