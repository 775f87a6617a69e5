"""``iscd bench``: run the benchmarks (speed as ratios to the camera rate and to in-process baselines)."""

from __future__ import annotations

import argparse
import importlib

BENCHES = {
    "mock_rig": "the mock rig delivering 512x512 stereo pairs of the 8x8 scene (pace off)",
    "ringbuffer": "stereo pairs through the shared-memory ring, producer and consumer in two processes",
    "receiver": "the demodulator alone on 8x8 PWM-16 luminance",
    "ranging": "range estimates per second, one LED and an 8x8 array",
    "decode_loop": "the whole decode loop (tracking, luminance, demodulation, ranging every frame)",
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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from iscd.cli import UserError

    names = args.names or list(BENCHES)
    rc = 0
    for name in names:
        try:
            mod = importlib.import_module(f"benchmarks.bench_{name}")
        except ModuleNotFoundError as e:
            raise UserError(f"benchmark {name!r} is not installed ({e}); run from a source checkout "
                            "installed with 'pip install -e .'") from None
        print(f"== {name}: {BENCHES[name]}", flush=True)
        rc |= int(mod.main(["--quick"] if args.quick else []) or 0)
    return rc
