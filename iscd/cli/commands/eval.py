"""``iscd eval``: simulated sweeps of communication and ranging and the report (docs/eval.md)."""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
from pathlib import Path

DESCRIPTION = """\
Runs simulated sweeps through the real receiver and writes a report beside the dissertation's
numbers: DIR/report.md (Markdown tables), DIR/comms.png, DIR/hdr.png, DIR/ranging.png (plots,
needs matplotlib) and DIR/results.json (every number).

Suites: comms - one LED, OOK and PWM-8, b = 0.6 m, 20-60 m every 5 m: SER, BER, packet error
rate, goodput and the dissertation's throughput (4.4) for single-camera and diversity reception
(fig. 3.8). hdr - 8x8 array, PWM-8 and PWM-16, b = 0.25 m, left f/4 and right f/4, f/8 or f/16,
10-50 m every 10 m: single camera, diversity and HDR reception (table 4.2), and a car
approaching at 40 km/h with rig vibration. ranging - one LED, PWM-8, b = 0.6 m, 20-60 m every
5 m: per-frame mean absolute error, bias and RMSE of the range for every shift estimator on the
same frames (fig. 3.7). motion (not part of all) - a moving car (one LED at 40 km/h from 50 m and
100 km/h from 100 m down to 25 m, 0.3 and 0.5 px vibration, one LED still with vibration, the 8x8
array with HDR at 40 km/h), 3 seeds a case: SER and packets delivered, and the oracle split of
iscd.eval.oracle (what following, timing and the channel estimate cost) with per-packet error
profiles.

Every point has a fixed seed derived from --seed, so a run is reproducible. A full run
(--suite all) takes about ten minutes on two cores; --quick runs a few points in about ten
seconds."""

EPILOG = """\
examples:
  iscd eval --quick --out /tmp/eval
  iscd eval --suite ranging --frames 5000 --out eval-ranging
  iscd eval --suite comms --packets 10 --distances 50,55,60 --out eval-comms
  iscd eval --suite motion --seeds 3 --out eval-motion
  iscd eval --suite motion --quick --out /tmp/motion"""


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("eval", help="simulated sweeps (SER, goodput, range error vs distance) and a report",
                       description=DESCRIPTION, epilog=EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suite", choices=("comms", "hdr", "ranging", "all", "motion", "fec"), default="all",
                   help="which sweep to run (default: all = comms, hdr and ranging; fec: goodput and "
                        "packet loss of air interface v1 against v2, 8x8 PWM-16)")
    p.add_argument("--quick", action="store_true",
                   help="a few points only (comms 20 and 60 m, hdr 50 m with f/8, ranging 30 and 60 m "
                        "with 300 frames, project rule only): small enough for CI")
    p.add_argument("--out", metavar="DIR", default="iscd-eval",
                   help="folder for report.md, results.json and the plots (default: ./iscd-eval)")
    p.add_argument("--frames", type=int, metavar="N",
                   help="frames per ranging point (default 5000 as in the dissertation; 300 with --quick)")
    p.add_argument("--packets", type=int, metavar="P",
                   help="whole packets per communication point (default 4; 2 with --quick)")
    p.add_argument("--seed", type=int, default=1, metavar="S",
                   help="base seed; each point's seed is derived from it (default 1)")
    p.add_argument("--distances", metavar="LIST",
                   help="comma-separated distances in m, replacing every selected suite's own")
    p.add_argument("--methods", metavar="LIST",
                   help="comma-separated ranging methods (default: all of iscd.decode.ranging.estimators.METHODS)")
    p.add_argument("--rules", metavar="LIST",
                   help="decision rules, comma-separated from iscd,dissertation (default both; iscd with --quick)")
    p.add_argument("--seeds", type=int, metavar="N",
                   help="motion suite: seeds per case (default 3; 1 with --quick)")
    p.add_argument("--cases", metavar="LIST",
                   help="motion suite: comma-separated case keys (default all of iscd.eval.suites.MOTION_CASES)")
    p.add_argument("--scene", metavar="KEY=VALUE", action="append",
                   help="motion suite: a [scene] key over every case's (repeatable), e.g. vibration_model=bumps")
    p.add_argument("--randomize", action="store_true",
                   help="motion suite: pass every case through iscd.sim.randomize.randomized(cfg, seed) "
                        "(runs without it, and says so, where that module is not there)")
    p.add_argument("--traces", metavar="DIR",
                   help="motion suite: also write each scene's luminance trace into DIR (what the receiver's "
                        "demodulator was fed, with the truth); python -m iscd.eval.lumtrace DIR demodulates "
                        "them again with other [receiver] settings in a fraction of the time")
    p.add_argument("--recording", metavar="DIR", action="append",
                   help="the oracle split of a recording instead of a suite (repeatable): DIR holds "
                        "left.iscr, right.iscr, truth.npz, truth.json and config.toml as iscd simulate "
                        "writes them (another renderer may write the same files)")
    p.add_argument("--config", metavar="FILE",
                   help="base config (sensor, optics, background, distractors, [receiver], [tracking], "
                        "[ranging]); each suite sets its own transmitter, cameras and distances "
                        "(default: the embedded default config)")
    from iscd.cli.commands.campaign import add_runner_options

    add_runner_options(p, "without --workers or --scheduler the points run one after another in this "
                          "process, as before; the results are the same either way")
    p.set_defaults(func=run)


def _list(text: str, what: str) -> list[str]:
    from iscd.core.errors import UserError

    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise UserError(f"--{what}: expected a comma-separated list, got {text!r}")
    return items


def _distances(text: str) -> tuple[float, ...]:
    from iscd.core.errors import UserError

    out = []
    for t in _list(text, "distances"):
        try:
            d = float(t)
        except ValueError:
            raise UserError(f"--distances: {t!r} is not a number of metres") from None
        if not 1.0 <= d <= 500.0:
            raise UserError(f"--distances: {d:g} m is outside 1..500 m")
        out.append(d)
    return tuple(out)


def build_plan(args: argparse.Namespace) -> "object":
    """The :class:`iscd.eval.suites.EvalPlan` of the command line (UserError on bad input)."""
    from iscd.core.errors import UserError
    from iscd.eval.suites import SUITES, EvalPlan
    from iscd.decode.ranging.estimators import METHODS

    if args.frames is not None and args.frames < 10:
        raise UserError(f"--frames: expected at least 10 frames per ranging point, got {args.frames}")
    if args.packets is not None and args.packets < 1:
        raise UserError(f"--packets: expected at least 1 packet per point, got {args.packets}")
    methods = tuple(METHODS)
    if args.methods:
        methods = tuple(_list(args.methods, "methods"))
        bad = [m for m in methods if m not in METHODS]
        if bad:
            raise UserError(f"--methods: unknown method {bad[0]!r} (known: {', '.join(METHODS)})")
    rules = None
    if args.rules:
        rules = tuple(_list(args.rules, "rules"))
        bad = [r for r in rules if r not in ("iscd", "dissertation")]
        if bad:
            raise UserError(f"--rules: unknown rule {bad[0]!r} (known: iscd, dissertation)")
    d = _distances(args.distances) if args.distances is not None else None
    suites = SUITES if args.suite == "all" else (args.suite,)
    seeds = getattr(args, "seeds", None)
    if seeds is not None and seeds < 1:
        raise UserError(f"--seeds: expected at least 1 seed per case, got {seeds}")
    cases = None
    if getattr(args, "cases", None):
        from iscd.eval.suites import MOTION_CASES

        cases = tuple(_list(args.cases, "cases"))
        known = [c.key for c in MOTION_CASES]
        bad = [c for c in cases if c not in known]
        if bad:
            raise UserError(f"--cases: unknown case {bad[0]!r} (known: {', '.join(known)})")
    scene = tuple(_scene_key(t) for t in (getattr(args, "scene", None) or ()))
    traces = _traces_dir(getattr(args, "traces", None), suites, bool(getattr(args, "recording", None)))
    return EvalPlan(suites=suites, quick=args.quick, seed=args.seed, packets=args.packets,
                    frames=args.frames, rules=rules, methods=methods, comms_distances=d,
                    hdr_distances=d, ranging_distances=d, fec_distances=d, motion_seeds=seeds, motion_cases=cases,
                    motion_scene=scene, motion_randomize=bool(getattr(args, "randomize", False)),
                    motion_traces=traces)


def _traces_dir(text: str | None, suites: tuple[str, ...], recordings: bool = False) -> str | None:
    """--traces: the directory made (absolute: the points may run in other processes), or
    one clear error."""
    from iscd.core.errors import UserError

    if text is None:
        return None
    if recordings:
        raise UserError("--traces: not with --recording (traces are written of the motion suite's scenes)")
    if "motion" not in suites:
        raise UserError("--traces: only with --suite motion (the traces are of its scenes)")
    path = Path(text).expanduser().resolve()
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise UserError(f"--traces: cannot write into {path} ({e.strerror or e})") from None
    return str(path)


SCENE_KEYS_OF_THE_CASES = {
    "distance_m": "each motion case sets its own start distance (choose cases with --cases)",
    "seed": "each scene's seed is derived from --seed",
}
"""``[scene]`` keys that --scene cannot set: the motion suite sets them for every case."""


def _scene_key(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` of --scene: the value as a TOML value (number, boolean, quoted or
    bare string)."""
    import tomllib

    from iscd.core.errors import UserError

    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise UserError(f"--scene: expected KEY=VALUE, got {text!r}")
    if key in SCENE_KEYS_OF_THE_CASES:
        raise UserError(f"--scene {key}: {SCENE_KEYS_OF_THE_CASES[key]}")
    try:
        v = tomllib.loads(f"v = {value.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        v = value.strip()
    return key, v


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from iscd.core.errors import UserError
    from iscd.core.config import load
    from iscd.eval.report import NO_MATPLOTLIB, write_report
    from iscd.eval.suites import run_plan, total_frames

    if not args.out:
        raise UserError("--out: the path is empty; give a folder")
    plan = build_plan(args)
    if getattr(args, "recording", None):
        for name in ("iscd.decode.stream", "iscd.decode.comms", "iscd.decode.tracking"):
            if not getattr(args, "verbose", 0):
                logging.getLogger(name).setLevel(logging.WARNING)
        return _run_recordings(args)
    base = load(args.config)
    _check_sections(base)
    if not getattr(args, "verbose", 0):  # per-decoder acquisition/search logs are noise here (-v shows them)
        for name in ("iscd.decode.stream", "iscd.decode.comms", "iscd.decode.tracking", "matplotlib"):
            logging.getLogger(name).setLevel(logging.WARNING)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out: {out} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"--out: cannot create {out}: {e.strerror or e}") from None
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        print(f"iscd eval: warning: {NO_MATPLOTLIB}", file=sys.stderr)
    try:
        total = total_frames(base, plan)  # type: ignore[arg-type]
    except ValueError as e:  # a --scene key or value the config rejects: one line
        raise UserError(str(e)) from None
    if getattr(args, "workers", None) is not None or getattr(args, "scheduler", None) is not None:
        from iscd.campaign.evalplan import run_plan_on
        from iscd.campaign.runner import Runner

        with Runner(args.workers, args.scheduler, prog="iscd eval", verbose=bool(getattr(args, "verbose", 0))) as r:
            try:
                results = run_plan_on(r, base, plan)  # type: ignore[arg-type]
            except ValueError as e:
                raise UserError(str(e)) from None
        return _finish(args, results, out)
    with tqdm(total=total, unit="frame", desc="eval", disable=None, file=sys.stderr) as bar:
        current = [""]

        def progress(n: int, label: str) -> None:
            if current[0] != label:
                current[0] = label
                bar.set_description(label, refresh=False)
                if bar.disable:  # no terminal (a log, CI): one line per point instead of a bar
                    print(f"iscd eval: {label}", file=sys.stderr, flush=True)
            bar.update(n)
        try:
            results = run_plan(base, plan, progress)  # type: ignore[arg-type]
        except ValueError as e:  # a bad value (a --scene key the config rejects...): one line
            raise UserError(str(e)) from None
    return _finish(args, results, out)


def _check_sections(cfg: "object") -> None:
    """Every owned table of the base config (``[receiver]``, ``[tracking]``, ...) checked
    before the first point: a bad key is one line naming the file and the key (``[rig]``,
    which the simulated points do not use, is not resolved)."""
    import iscd.cli.sections  # noqa: F401  (every section's owner)
    from iscd.core import config as C

    for cls in C.section_owners().values():
        C.section(cfg, cls)  # type: ignore[arg-type]


def _finish(args: argparse.Namespace, results: "object", out: Path) -> int:
    """The report of a suite run (serial or on the runner) and the motion section."""
    from iscd.core.errors import UserError
    from iscd.eval.report import write_report

    command = "iscd eval " + " ".join(shlex.quote(a) for a in _argv_of(args))
    try:
        path = write_report(results, out, command)  # type: ignore[arg-type]
    except OSError as e:
        raise UserError(f"--out: cannot write to {out}: {e.strerror or e}") from None
    print(f"iscd eval: {results.seconds:.0f} s; wrote {path}, {out / 'results.json'} and the plots",  # type: ignore[attr-defined]
          file=sys.stderr)
    _print_motion(results)
    return 0


def _print_motion(results: "object") -> None:
    """The motion section (SER table, oracle split, error profiles per case) on stdout."""
    rows = getattr(results, "motion", None)
    if rows:
        from iscd.eval.report import motion_section

        print("\n".join(motion_section(rows, getattr(results, "settings", {}))).strip())


def _run_recordings(args: argparse.Namespace) -> int:
    """``--recording DIR ...``: the oracle of each recording, in the report's motion section."""
    import time

    from iscd.core.errors import UserError
    from iscd.core.config import ConfigError, load
    from iscd.eval.oracle import oracle_of_recording
    from iscd.eval.report import write_report
    from iscd.eval.suites import EvalResults, MotionCase, MotionRow
    from iscd.recording import RecordingError

    t0 = time.perf_counter()
    results = EvalResults(settings={"suites": ["recording"], "quick": False, "seed": None,
                                    "recordings": list(args.recording), "motion_seeds": 1})
    for d in args.recording:
        path = Path(d)
        try:
            cfg = load(path / "config.toml")
            print(f"iscd eval: oracle of {path}", file=sys.stderr, flush=True)
            res = oracle_of_recording(path)
        except (OSError, ConfigError, RecordingError, ValueError, KeyError) as e:
            raise UserError(f"--recording {d}: {e}") from None
        sc, tx = cfg.scene, cfg.transmitter
        case = MotionCase(key=path.name or str(path), leds=tx.n_leds, speed_kmh=sc.speed_mps * 3.6,
                          start_m=sc.distance_m, end_m=max(sc.min_distance_m, 0.0),
                          vibration_px=sc.vibration_px, packets=res.receiver.packets_sent,
                          title=f"{path.name or path}: {tx.rows}x{tx.cols} PWM-{tx.levels}, "
                                f"{sc.speed_mps * 3.6:g} km/h from {sc.distance_m:g} m, {sc.vibration_px:g} px")
        results.motion.append(MotionRow(case, int(sc.seed), res))
    results.seconds = time.perf_counter() - t0
    out = Path(args.out)
    command = "iscd eval " + " ".join(shlex.quote(a) for a in _argv_of(args))
    try:
        report = write_report(results, out, command)
    except OSError as e:
        raise UserError(f"--out: cannot write to {out}: {e.strerror or e}") from None
    print(f"iscd eval: {results.seconds:.0f} s; wrote {report} and {out / 'results.json'}", file=sys.stderr)
    _print_motion(results)
    return 0


def _argv_of(args: argparse.Namespace) -> list[str]:
    """The options of this run, to reproduce it."""
    a = [f"--suite={args.suite}", f"--seed={args.seed}"]
    if args.quick:
        a.append("--quick")
    for k in ("frames", "packets", "distances", "methods", "rules", "seeds", "cases", "config"):
        v = getattr(args, k, None)
        if v is not None:
            a.append(f"--{k}={v}")
    for t in getattr(args, "scene", None) or ():
        a.append(f"--scene={t}")
    for t in getattr(args, "recording", None) or ():
        a.append(f"--recording={t}")
    if getattr(args, "traces", None):
        a.append(f"--traces={args.traces}")
    if getattr(args, "randomize", False):
        a.append("--randomize")
    for k in ("workers", "scheduler"):
        if getattr(args, k, None) is not None:
            a.append(f"--{k}={getattr(args, k)}")
    a.append(f"--out={args.out}")
    return a
