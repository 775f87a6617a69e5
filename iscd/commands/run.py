"""``iscd run``: the daemon."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any


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
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: run until stopped)")
    p.add_argument("--out", help="JSON Lines output file (rotated at [daemon] rotate_mb)")
    p.add_argument("--calibration", help="stereo calibration YAML (default: the ideal rig of [camera])")
    p.add_argument("--socket", metavar="ENDPOINT",
                   help="also publish records on a ZeroMQ PUB socket, e.g. tcp://127.0.0.1:5556")
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
        print("stats " + " ".join(f"{k}={r.get(k)}" for k in keys), file=sys.stderr, flush=True)

    def close(self) -> None:
        pass


def run(args: argparse.Namespace) -> int:
    from iscd import config as C
    from iscd.cli import UserError
    from iscd.daemon import Daemon

    from drivers.registry import check_stereo_config

    cfg = C.load(args.config)
    C.check_extra_sections(cfg)
    check_stereo_config(cfg)  # refuse a bad camera/board config before spawning anything
    if args.duration is not None and args.duration <= 0:
        raise UserError("--duration must be > 0 seconds")
    rerun = None
    if args.connect is not None or args.serve or args.save:
        rerun = {"connect": args.connect, "serve": args.serve, "save": args.save}
    d = Daemon(cfg, out=args.out, duration_s=args.duration, rerun=rerun, socket=args.socket,
               calibration=args.calibration)
    if not getattr(args, "quiet", False):
        d.extra_outputs = [_Console()]
    final = d.run()
    print(json.dumps({k: final.get(k) for k in ("pairs_decoded", "frames_dropped", "packets_ok",
                                                 "packets_bad", "ranges", "latency_ms_p50",
                                                 "latency_ms_p99")}))
    return 0
