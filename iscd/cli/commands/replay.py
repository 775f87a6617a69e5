"""``iscd replay``: offline decode + ranging of a recorded stereo pair."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from iscd.cli.commands.run import add_calibration_options


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay", help="decode and range a recorded stereo pair offline",
        description=(
            "Decodes the packets and measures the range of the transmitter in a recorded stereo "
            "pair, with the same pipeline as the daemon, and writes JSON Lines records (SPEC "
            "section 7: packet, range, stats). LEFT and RIGHT may each be an .iscr file, a Photron "
            ".cih/.cihx (with its .mraw beside it) or a folder of PNG/TIFF frames; frames are paired "
            "by frame id. A recording made by 'iscd simulate' holds left.iscr, right.iscr, config.toml "
            "and calibration.yml: give the folder as LEFT and omit RIGHT, --config and --calibration. "
            "A recording made by 'iscd run --record' (a run folder of stereo .iscr files, any mode, "
            "or one of its files) is given alone as LEFT: it is decoded in the blocks the live "
            "daemon decoded, with the config and calibration stored beside it, and gives the "
            "live run's packet records."),
        epilog="Example: iscd replay sim/left.iscr sim/right.iscr --config sim/config.toml "
               "--calibration sim/calibration.yml --out sim.jsonl")
    p.add_argument("left", help="left-camera recording (or a simulate output folder, or an 'iscd run --record' "
                                "run folder or file)")
    p.add_argument("right", nargs="?", help="right-camera recording")
    p.add_argument("--config", help="TOML config with the [camera] (and the [transmitter]) the recording shows; "
                                    "without a [transmitter] table the receiver infers the array's shape and "
                                    "reads v1 packets with the SPEC's M, K, F (v2 packets say their own)")
    add_calibration_options(p, "the recording's image size")
    p.add_argument("--allow-mismatch", action="store_true",
                   help="decode even when the recording's size or frame rate differ from [camera], or "
                        "when the recordings' metadata say LEFT and RIGHT are swapped "
                        "(a warning instead of an error)")
    p.add_argument("--out", required=True, help="JSON Lines output file")
    p.add_argument("--block", type=int, default=64, help="frames per processing block (default 64)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _warn(msg: str) -> None:
    print(f"iscd replay: warning: {msg}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    """Decode the recording with :func:`iscd.eval.replay.replay` (the code a campaign's
    recording tasks run too), with a progress bar on a terminal."""
    from iscd.eval.replay import SUMMARY_KEYS, ReplayInputs, replay

    inp = ReplayInputs(left=Path(args.left), right=Path(args.right) if args.right else None, config=args.config,
                       calibration=args.calibration, allow_mismatch=args.allow_mismatch, block=args.block)
    bar: list = []

    def progress(n: int, total: int) -> None:
        if not bar:
            from tqdm import tqdm

            bar.append(tqdm(total=total, unit="pair", desc="replay", file=sys.stderr))
        bar[0].update(n)

    def calibration(path: str, width: int, height: int) -> object:
        from iscd.cli.commands.run import checked_calibration

        return checked_calibration(path, width, height, scale=args.scale_calibration,
                                   what="the recording's size")[0]
    try:
        stats = replay(inp, args.out, warn=_warn, calibration=calibration,
                       progress=progress if not args.no_progress and sys.stderr.isatty() else None).stats
    finally:
        if bar:
            bar[0].close()
    print(json.dumps({k: stats[k] for k in SUMMARY_KEYS}), file=sys.stderr)
    return 0
