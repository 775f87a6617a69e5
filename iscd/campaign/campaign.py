"""A whole campaign: read the manifest, skip the tasks whose outputs are complete and whose
inputs have not changed, run the others on the runner, write the summary and the report.
"""

from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from iscd import __version__
from iscd.campaign.identity import stamps_unchanged, task_identity
from iscd.campaign.manifest import TaskSpec, load_manifest
from iscd.campaign.tasks import TASKS_DIR, is_complete, one_line, read_result, run_task
from iscd.core.errors import UserError

NOT_RUN = "not run: the campaign was interrupted (run it again to finish it)"


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


@dataclass
class CampaignResult:
    """What :func:`run_campaign` did: ``results`` one per task in manifest order (see
    :func:`iscd.campaign.tasks.run_task`), ``submitted`` the names of the tasks sent to the
    workers (the others were reused without any work), ``seconds`` its wall time, s,
    ``summary`` the summary's rows."""

    results: list[dict[str, Any]]
    submitted: list[str] = field(default_factory=list)
    seconds: float = 0.0
    summary: list[dict[str, Any]] = field(default_factory=list)
    tasks_seconds: float = 0.0
    """wall time from the first task's submission to the last one's result, s"""

    @property
    def failed(self) -> list[dict[str, Any]]:
        return [r for r in self.results if r.get("status") != "ok"]


def reusable(spec: TaskSpec, out: Path, version: str = __version__) -> dict[str, Any] | None:
    """The finished result of ``spec`` when it can stand without any work.

    It can when it is complete (:func:`iscd.campaign.tasks.is_complete`), every input file
    is at its recorded path with its recorded stamp, and the identity is the same for this
    version and these parameters.

    Parameters
    ----------
    spec : TaskSpec
        The task.
    out : Path
        The campaign's output folder.
    version : str
        The iscd version of this run.

    Returns
    -------
    dict or None
        The result with ``reused`` True, or None (the task must go to a worker).
    """
    old = read_result(out, spec.name)
    if not is_complete(out, old) or not stamps_unchanged(old.get("inputs") or {}, spec.inputs()):  # type: ignore[union-attr]
        return None
    if task_identity(spec.params(), old["inputs"], version) != old.get("identity"):  # type: ignore[index]
        return None
    return {**old, "reused": True}  # type: ignore[dict-item]


def _finished_on_disk(spec: TaskSpec, out: Path) -> dict[str, Any] | None:
    """The result a worker wrote for ``spec`` in this run, when it is complete and valid
    (:func:`reusable`), as done in this run; else None."""
    r = reusable(spec, out)
    return None if r is None else {**r, "reused": False}


def clean_parts(out: Path) -> int:
    """Remove what an interrupted run left under temporary names (``tasks/*.part-*``).

    Parameters
    ----------
    out : Path
        The campaign's output folder.

    Returns
    -------
    int
        Files and folders removed.
    """
    n = 0
    for p in (out / TASKS_DIR).glob("*.part-*"):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        n += 1
    return n


def run_campaign(manifest: str | Path, out: str | Path, *, workers: int | None = None, scheduler: str | None = None,
                 command: str = "iscd campaign", force: bool = False, say: Callable[[str], None] = _stderr,
                 verbose: bool = False, runner: Any = None) -> CampaignResult:
    """Run a campaign (docs/campaign.md).

    Parameters
    ----------
    manifest : str or Path
        The TOML or CSV manifest (:func:`iscd.campaign.manifest.load_manifest`).
    out : str or Path
        Output folder: ``tasks/``, ``summary.parquet``, ``summary.csv``, ``report.md``.
    workers : int, optional
        LocalCluster worker processes (default: the cores).
    scheduler : str, optional
        An existing Dask scheduler's address instead of a LocalCluster.
    command : str
        The command line, for the report.
    force : bool
        Run every task again, even those whose outputs are complete and unchanged.
    say : callable
        Where the progress lines go.
    verbose : bool
        Keep distributed's log lines.
    runner : Runner, optional
        A started :class:`~iscd.campaign.runner.Runner` to use (and leave open) instead of
        starting one from ``workers`` / ``scheduler`` (tests, benchmarks, notebooks).

    Returns
    -------
    CampaignResult

    Raises
    ------
    UserError
        A bad manifest, an output folder that cannot be made, an unreachable scheduler.
    KeyboardInterrupt
        After writing the summary of what finished (the rest: status ``not run``).
    """
    from iscd.campaign.runner import Runner
    from iscd.campaign.summary import summary_rows, write_csv, write_parquet, write_report

    t0 = time.perf_counter()
    specs = load_manifest(manifest)
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise UserError(f"--out: {out} exists and is not a folder")
    try:
        (out / TASKS_DIR).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"--out: cannot create {out}: {e.strerror or e}") from None
    clean_parts(out)
    results: list[dict[str, Any] | None] = [None if force else reusable(s, out) for s in specs]
    todo = [i for i, r in enumerate(results) if r is None]
    n_reused = len(specs) - len(todo)
    plan_line = f"iscd campaign: {len(specs)} tasks, {n_reused} complete and unchanged (skipped), {len(todo)} to run"
    runner_text = "no workers (nothing to run)"
    tasks_s = [0.0]
    interrupted = False
    if todo:
        def store(k: int, res: dict[str, Any]) -> None:
            results[todo[k]] = res

        def run_on(r: Any) -> None:
            nonlocal runner_text
            say(plan_line)  # once the runner is there (an unreachable scheduler is the only line)
            runner_text = r.describe()
            r.warm_up()
            t_tasks = time.perf_counter()
            try:
                _map(r)
            finally:
                tasks_s[0] = time.perf_counter() - t_tasks

        def _map(r: Any) -> None:
            r.map(run_task, [specs[i] for i in todo], args=(str(out), __version__, force),
                  labels=[specs[i].name for i in todo], desc="campaign", on_result=store,
                  failed=lambda res: None if res["status"] == "ok" else res["error"],
                  error_result=lambda k, e: {"name": specs[todo[k]].name, "kind": specs[todo[k]].kind,
                                             "status": "failed", "error": f"the task was lost: {one_line(e)}"})

        try:
            if runner is not None:
                run_on(runner)
            else:
                with Runner(workers, scheduler, say=say, verbose=verbose) as r:
                    run_on(r)
        except KeyboardInterrupt:
            interrupted = True
    else:
        say(plan_line)
    if interrupted:  # a task that finished on its worker as Ctrl-C came, before the client heard of it
        results = [r if r is not None else _finished_on_disk(s, out) for s, r in zip(specs, results)]
    final = [r if r is not None else {"name": s.name, "kind": s.kind, "status": "not run", "error": NOT_RUN}
             for s, r in zip(specs, results)]
    seconds = time.perf_counter() - t0
    rows = summary_rows(final)
    try:
        has_parquet = write_parquet(rows, out / "summary.parquet")
        write_csv(rows, out / "summary.csv")
        notes = write_report(rows, out, command=command, runner=runner_text, seconds=seconds)
    except OSError as e:
        raise UserError(f"--out: cannot write to {out}: {e.strerror or e}") from None
    for n in notes:
        say(f"iscd campaign: note: {n}")
    if interrupted:
        raise KeyboardInterrupt
    res = CampaignResult(final, [specs[i].name for i in todo], seconds, rows, tasks_s[0])
    say(f"iscd campaign: {len(specs) - len(res.failed)} ok, {len(res.failed)} failed in {seconds:.1f} s; wrote "
        f"{out / 'summary.parquet' if has_parquet else ''} {out / 'summary.csv'} {out / 'report.md'}")
    return res
