"""``iscd config``: show, check or describe configuration files."""

from __future__ import annotations

import argparse
import json

from iscd.core import config as C


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "config", help="check a config file, show the effective config, or list every key",
        description=("Without options, prints the effective configuration (the embedded default "
                     "mock-rig config if no FILE) as JSON. --check validates FILE and names any bad "
                     "key; --describe lists every section and key with its default and meaning."))
    p.add_argument("file", nargs="?", help="a TOML config file (default: the embedded default)")
    p.add_argument("--check", action="store_true", help="only validate FILE; exit 2 on error")
    p.add_argument("--describe", action="store_true", help="list all sections and keys with defaults")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import iscd.cli.sections  # noqa: F401  (every section's owner, for --describe and --check)

    if args.describe:
        print(C.describe())
        return 0
    cfg = C.load(args.file)
    C.check_sections(cfg)
    if args.check:
        print(f"{args.file or '<embedded default>'}: OK")
        return 0
    print(json.dumps(C.to_dict(cfg), indent=2))
    return 0
