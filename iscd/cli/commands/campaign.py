"""``iscd campaign``: many recordings or simulated points decoded on Dask (docs/campaign.md)."""

from __future__ import annotations

import argparse
import shlex

DESCRIPTION = """\
Decodes every recording (or simulated point) of MANIFEST as one task on Dask distributed, each
with the code of 'iscd replay' (a simulated point is rendered by 'iscd simulate' on its worker
first), and writes into DIR:
  tasks/NAME.jsonl   the task's records (packet, range, stats), as 'iscd replay --out' writes them
  tasks/NAME.json    its result: status, error, identity, inputs, figures, timings
  summary.parquet    one row per task (also summary.csv): packets found/CRC-valid/delivered, SER
                     and BER where the truth is known, goodput, range statistics, frames
                     dropped, wall time (columns: docs/campaign.md)
  report.md          the table, the failed tasks with their errors, and campaign.svg (packets
                     found/delivered, SER, median range with its MAE per task)

MANIFEST is TOML ([[recording]] with left, right, config, calibration, truth; [[simulate]] with
config, frames, seed, randomize) or CSV (a header row naming the same keys, a 'kind' column for
simulated points); paths are relative to the manifest's folder. The workers open the
recordings by path: no frame goes through the scheduler, so an existing cluster's workers must
see the same paths.

Resumable: a task whose output is complete and whose inputs (content hash), parameters and iscd
version are unchanged is skipped; a failed task is run again. A task that fails (a bad file, a
decoder exception) is a row with status 'failed' and its error, and the campaign goes on;
Ctrl-C keeps every finished task's output (written under a temporary name, then renamed).

Exit status: 0 when every task is ok, 1 when some failed, 2 for bad input (a missing or
malformed manifest, an unknown key, a missing recording path, an unreachable scheduler),
130 after Ctrl-C."""

EPILOG = """\
examples:
  iscd campaign day1.toml --out day1-results
  iscd campaign sweep.csv --out /tmp/sweep --workers 2
  iscd campaign day1.toml --out day1-results --scheduler tcp://cluster-head:8786"""


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("campaign", help="decode many recordings (or simulated points) on Dask, resumable, "
                                        "with a summary table and a report",
                       description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("manifest", metavar="MANIFEST", help="the campaign's manifest, a .toml or .csv file")
    p.add_argument("--out", metavar="DIR", required=True,
                   help="output folder (created if missing; a re-run into it skips the finished tasks)")
    add_runner_options(p)
    p.add_argument("--force", action="store_true",
                   help="run every task again, even those whose outputs are complete and unchanged")
    p.set_defaults(func=run)


def add_runner_options(p: argparse.ArgumentParser,
                       default: str = "default: the cores this process may use") -> None:
    """``--workers`` and ``--scheduler`` (campaign and eval); ``default`` says what happens
    without them."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, metavar="N",
                   help=f"worker processes of a local Dask cluster, one thread each ({default})")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on an existing Dask cluster: its scheduler's address, e.g. tcp://HOST:8786 "
                        "(its workers need iscd installed and the same paths)")


def run(args: argparse.Namespace) -> int:
    from iscd.campaign.campaign import run_campaign

    argv = [args.manifest, "--out", args.out]
    for k in ("workers", "scheduler"):
        if getattr(args, k) is not None:
            argv += [f"--{k}", str(getattr(args, k))]
    command = "iscd campaign " + " ".join(shlex.quote(a) for a in argv + (["--force"] if args.force else []))
    res = run_campaign(args.manifest, args.out, workers=args.workers, scheduler=args.scheduler, command=command,
                       force=args.force, verbose=bool(getattr(args, "verbose", 0)))
    return 1 if res.failed else 0
