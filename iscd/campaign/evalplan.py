"""``iscd eval``'s sweeps on the campaign runner: every simulated point of an
:class:`~iscd.eval.suites.EvalPlan` is one task, and the rows come back in the plan's order,
so the results are those of the serial :func:`iscd.eval.suites.run_plan` (each point has
its own seed and renders its own frames on its worker; only the config goes out and the
scores come back)."""

from __future__ import annotations

import time
from typing import Any

from iscd.campaign.runner import Runner
from iscd.core.config import Config
from iscd.eval.suites import EvalPlan, EvalResults, Job, jobs


def run_job(job: Job) -> list[Any]:
    """One point on a worker.

    Parameters
    ----------
    job : Job
        The point (its closure appends its rows to a copy of the tables there, dropped).

    Returns
    -------
    list
        Its rows (``CommsRow``, ``RangingRow`` or ``MotionRow``).
    """
    return job.run(None)


def run_plan_on(runner: Runner, base: Config, plan: EvalPlan) -> EvalResults:
    """:func:`iscd.eval.suites.run_plan` with every point a task on ``runner``.

    Parameters
    ----------
    runner : Runner
        A started runner (LocalCluster or scheduler).
    base : Config
        As :func:`~iscd.eval.suites.run_plan`.
    plan : EvalPlan
        The points.

    Returns
    -------
    EvalResults
        The rows in the order the serial run appends them; ``seconds`` the wall time, s.
    """
    t0 = time.perf_counter()
    results = EvalResults(settings=plan.settings())
    todo = jobs(base, plan, EvalResults(settings={}))
    rows = runner.map(run_job, todo, labels=[j.label for j in todo], desc="eval")
    for job, r in zip(todo, rows):
        getattr(results, job.suite).extend(r)  # the table the job's closure appends to: comms, hdr, ...
    results.seconds = time.perf_counter() - t0
    return results
