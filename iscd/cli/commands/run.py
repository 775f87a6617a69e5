"""``iscd run``: the daemon."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Any


def positive_seconds(text: str) -> float:
    """argparse type of ``--duration``: a finite number of seconds > 0 (not nan, not inf)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds > 0, got {text!r}")
    return v


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run", help="run the daemon (default: the embedded mock rig, no hardware)",
        description=(
            "Runs the image-sensor-communication daemon: reads the stereo cameras chosen in the "
            "config's [rig] (with no --config: the embedded default, a mock rig of two simulated "
            "1000 fps cameras watching an 8x8 PWM-8 LED array at 30 m), decodes every packet and "
            "measures the range every frame, and writes JSON Lines records (packet, range, stats; "
            "SPEC section 7). A stats line is printed every second. Stops after --duration, or on "
            "SIGINT/SIGTERM, with a final stats record."),
        epilog="Examples: iscd run --duration 10 --out run.jsonl;  "
               "iscd run --config /etc/iscd/iscd.toml --out /var/lib/iscd/iscd.jsonl --save live.rrd")
    p.add_argument("--config", help="TOML config file (default: the embedded mock-rig config; see 'iscd config --describe')")
    p.add_argument("--duration", type=positive_seconds,
                   help="stop after this many seconds, a finite number > 0 (default: run until stopped)")
    p.add_argument("--out", help="JSON Lines output file (rotated at [daemon] rotate_mb)")
    add_calibration_options(p, "the [camera] width x height")
    p.add_argument("--record", metavar="DIR",
                   help="record the stereo pairs into DIR (a run-YYYYmmdd-HHMMSS folder per run, with the "
                        "config and calibration; replay it with 'iscd replay DIR/run-...'); [record] in the config")
    p.add_argument("--record-mode", choices=("full", "roi", "blackbox"),
                   help="full: every pair whole; roi: the windows the decoder reads (default); blackbox: the "
                        "last [record] pre_s seconds in memory, written on SIGUSR1, a failed packet or a lost "
                        "transmitter, with post_s seconds after")
    p.add_argument("--socket", metavar="ENDPOINT",
                   help="also publish records on a ZeroMQ PUB socket, e.g. tcp://127.0.0.1:5556")
    p.add_argument("--control", metavar="ENDPOINT",
                   help="take commands on a ZeroMQ REP socket, e.g. tcp://127.0.0.1:5557: 'blackbox' "
                        "writes the blackbox recording (--record-mode blackbox), 'ping' answers 'pong' "
                        "([daemon] control)")
    g = p.add_argument_group("Rerun live view (optional)")
    g.add_argument("--connect", nargs="?", const="", metavar="URL",
                   help="stream to a running Rerun viewer (default URL: the local viewer)")
    g.add_argument("--serve", action="store_true", help="serve the recording for a web viewer")
    g.add_argument("--save", metavar="FILE.rrd", help="save the Rerun recording to a file")
    p.set_defaults(func=run)


class _Console:
    """Prints one compact line per stats record on stderr."""

    def write(self, r: dict[str, Any]) -> None:
        if r.get("type") != "stats":
            return
        keys = ("uptime_s", "pairs_decoded", "frames_dropped", "packets_ok", "packets_bad", "ranges",
                "latency_ms_p50", "latency_ms_p99", "cpu_cores", "rss_mb")
        if "record_written" in r:
            keys += ("record_written", "record_dropped", "record_mb_per_s")
        print("stats " + " ".join(f"{k}={r.get(k)}" for k in keys), file=sys.stderr, flush=True)

    def close(self) -> None:
        pass


def check_out_path(path: str, what: str = "--out") -> None:
    """Raise UserError (one line) unless a JSON Lines file can be written at ``path``: its
    folder exists or can be made, and the file can be created (or appended to). Leaves no
    file behind (a folder it had to make stays, as the daemon would make it)."""
    from iscd.core.errors import UserError

    p = Path(path)
    if p.is_dir():
        raise UserError(f"{what} {path}: is a folder; give a file name such as run.jsonl")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        if p.exists():
            with open(p, "ab"):
                pass
        else:
            fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".check", dir=p.parent)
            os.close(fd)
            os.unlink(tmp)
    except OSError as e:
        raise UserError(f"{what} {path}: cannot write there: {e.strerror or e}") from None


def check_record_dir(path: str, what: str = "--record") -> None:
    """Raise UserError (one line) unless recordings can be written under folder ``path``:
    it is a folder or can be made, and a file can be created in it (none is left behind)."""
    from iscd.core.errors import UserError

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UserError(f"{what} {path}: is a file; give a folder")
    try:
        p.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".iscd-record.", suffix=".check", dir=p)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise UserError(f"{what} {path}: cannot write there: {e.strerror or e}") from None


def add_calibration_options(p: argparse.ArgumentParser, size: str) -> None:
    """``--calibration`` and ``--scale-calibration`` (run and replay), for images of ``size``."""
    p.add_argument("--calibration", help="stereo calibration YAML (default: the ideal rig of [camera]); it must "
                                          f"be for {size}, else it is refused")
    p.add_argument("--scale-calibration", action="store_true",
                   help="use a calibration made at another resolution of the same view (binning): its "
                        f"focal lengths and principal points are scaled to {size} (same aspect ratio only)")


def checked_calibration(path: str, width: int, height: int, *, scale: bool, what: str) -> tuple[Any, bool]:
    """(calibration, scaled): the calibration at ``path`` for ``width`` x ``height`` images
    (scaled to it with ``scale``, then ``scaled`` is True), or UserError naming the file and,
    for a size mismatch, both sizes."""
    from iscd.calibration.io import CalibrationError, check_image_size, load_calibration, scale_calibration
    from iscd.core.errors import UserError

    try:
        cal = load_calibration(path)
        if cal.image_size == (width, height):
            return cal, False
        if not scale:
            try:
                check_image_size(cal, width, height, path)
            except CalibrationError as e:
                raise CalibrationError(
                    f"{e} ({what}); recalibrate at {width}x{height}, or pass --scale-calibration if "
                    f"the images are the same view resampled") from None
        scaled = scale_calibration(cal, width, height)
    except CalibrationError as e:
        msg = str(e)
        raise UserError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    print(f"iscd: calibration {path} for {cal.image_width}x{cal.image_height} px scaled to "
          f"{width}x{height} px (--scale-calibration)", file=sys.stderr)
    return scaled, True


def run(args: argparse.Namespace) -> int:
    from iscd.core import config as C
    from iscd.core.errors import UserError
    from iscd.service.daemon import Daemon, DaemonSettings

    from iscd.drivers.registry import check_stereo_config

    import iscd.cli.sections  # noqa: F401  (every section's owner, to validate them all)

    cfg = C.load(args.config)
    if args.record:
        cfg = cfg.with_keys("record", dir=args.record)
    if args.record_mode:
        cfg = cfg.with_keys("record", mode=args.record_mode)
    C.check_sections(cfg)
    check_stereo_config(cfg)  # refuse a bad camera/board config before spawning anything
    # the inputs the daemon would only read after starting its processes are checked here
    settings = C.section(cfg, DaemonSettings)
    out = args.out or settings.out or None
    if out:
        check_out_path(out, "--out" if args.out else "daemon.out")
    from iscd.recording.recorder import RecordSettings

    record = C.section(cfg, RecordSettings)
    if record.dir:
        check_record_dir(record.dir, "--record" if args.record else "record.dir")
    elif args.record_mode:
        raise UserError("--record-mode needs --record DIR (or [record] dir in the config)")
    cal_path = args.calibration or settings.calibration or None
    tmp_dir = None
    if cal_path:
        cal, scaled = checked_calibration(cal_path, cfg.camera.width, cfg.camera.height,
                                          scale=args.scale_calibration, what="[camera] width/height")
        if scaled:
            # the daemon reads a calibration file: hand it the scaled one
            from iscd.calibration.io import save_calibration

            tmp_dir = tempfile.TemporaryDirectory(prefix="iscd-cal-")
            cal_path = str(Path(tmp_dir.name) / "scaled.yml")
            save_calibration(cal, cal_path)
    rerun = None
    if args.connect is not None or args.serve or args.save:
        rerun = {"connect": args.connect, "serve": args.serve, "save": args.save}
    try:
        d = Daemon(cfg, out=out, duration_s=args.duration, rerun=rerun, socket=args.socket,
                   calibration=cal_path, control=args.control)
        if not getattr(args, "quiet", False):
            d.extra_outputs = [_Console()]
        final = d.run()
    finally:
        if tmp_dir is not None:
            tmp_dir.cleanup()
    print(json.dumps({**{k: final.get(k) for k in ("pairs_decoded", "frames_dropped", "packets_ok",
                                                    "packets_bad", "ranges", "latency_ms_p50",
                                                    "latency_ms_p99", "latency_run_ms_p50",
                                                    "latency_run_ms_p99", "latency_run_ms_max")},
                      **{k: final[k] for k in ("record_written", "record_dropped", "record_mb") if k in final}}))
    return 0
