"""The ``iscd`` console command: ``iscd <subcommand> --help`` explains each one."""

from __future__ import annotations

import os

# One BLAS thread: the daemon runs acquisition and decoding as two processes on two cores,
# and multi-threaded BLAS on small batches is slower here (docs/ranging.md). Must be set
# before numpy is first imported; a value set by the user wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from iscd import __version__
from iscd.cli.commands import COMMANDS
from iscd.core.errors import UserError

__all__ = ["UserError", "build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="iscd",
        description=(
            "Image-sensor-communication daemon: decodes data sent by road LEDs (PWM-M) from two "
            "synchronized 1000 fps cameras and measures the distance to them by stereo vision. "
            "With no hardware, 'iscd run' runs the embedded mock rig."),
        epilog="See 'iscd <command> --help' for each command's options.")
    parser.add_argument("--version", action="version", version=f"iscd {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"iscd.cli.commands.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"iscd.cli.commands.{name}":
                continue  # not implemented yet
            raise
        mod.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING if args.quiet else (logging.INFO if args.verbose <= 1 else logging.DEBUG)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from iscd.core.config import ConfigError

    try:
        return int(args.func(args) or 0)
    except (UserError, ConfigError) as e:
        print(f"iscd {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"iscd {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader of stdout went away ('iscd config --describe | head'): no traceback, and
        # none from the interpreter's final flush either (stdout goes to /dev/null)
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):
            pass
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
