"""One campaign task, run on a Dask worker (or in the client's process).

A task gets its :class:`~iscd.campaign.manifest.TaskSpec` (paths and numbers only: the
worker opens the recordings where they lie, no frame crosses the scheduler) and the
campaign's output folder, and writes

- ``tasks/NAME.jsonl``: every record of the replay (as ``iscd replay`` writes them);
- ``tasks/NAME.json``: the result: status, error (one line), identity, inputs (path,
  stamp, digest by role), the summary figures (:mod:`iscd.campaign.rows`), timings.

Both are written under a temporary name and renamed when complete (the ``.json`` last), so
an interrupted campaign leaves every finished task's output whole and no half-written one
under a final name. A task whose finished result records the same identity is not run
again (``reused``). Any exception becomes a ``failed`` result with one line of error; the
task never raises.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import traceback
import uuid
from pathlib import Path
from typing import Any

from iscd.campaign.identity import describe_inputs, task_identity
from iscd.campaign.manifest import TaskSpec
from iscd.core.errors import UserError

TASKS_DIR = "tasks"
NO_ROTATION = 2**62
"""A task's JSONL is one file (bytes before a rotation: never)."""


def task_file(out_dir: str | Path, name: str, suffix: str) -> Path:
    """A task's output file.

    Parameters
    ----------
    out_dir : str or Path
        The campaign's output folder.
    name : str
        The task's name.
    suffix : str
        ``.json`` (its result) or ``.jsonl`` (its records).

    Returns
    -------
    Path
        ``out_dir/tasks/NAME.SUFFIX``.
    """
    return Path(out_dir) / TASKS_DIR / f"{name}{suffix}"


def read_result(out_dir: str | Path, name: str) -> dict[str, Any] | None:
    """The finished result of task ``name`` in ``out_dir`` (:func:`task_file` ``.json``),
    or None when there is none or it is unreadable."""
    try:
        return json.loads(task_file(out_dir, name, ".json").read_text())
    except (OSError, ValueError):
        return None


def is_complete(out_dir: str | Path, result: dict[str, Any] | None) -> bool:
    """Whether a result is a successful task's whose JSONL is there, of the size recorded.

    Parameters
    ----------
    out_dir : str or Path
        The campaign's output folder.
    result : dict or None
        A task result.

    Returns
    -------
    bool
    """
    if not result or result.get("status") != "ok":
        return False
    try:
        return task_file(out_dir, result["name"], ".jsonl").stat().st_size == result.get("jsonl_bytes")
    except (OSError, KeyError):
        return False


def _atomic_json(path: Path, doc: dict[str, Any]) -> None:
    tmp = path.with_name(f"{path.name}.part-{uuid.uuid4().hex[:8]}")
    tmp.write_text(json.dumps(doc, indent=1, default=str) + "\n")
    os.replace(tmp, path)


def one_line(e: BaseException) -> str:
    """An exception as one line of error.

    Parameters
    ----------
    e : BaseException
        The exception.

    Returns
    -------
    str
        A UserError's message, else ``Type: message (at file:line)``, white space folded.
    """
    if isinstance(e, UserError):
        msg = str(e)
    else:
        where = traceback.extract_tb(e.__traceback__)[-1:] if e.__traceback__ else []
        at = f" (at {Path(where[0].filename).name}:{where[0].lineno})" if where else ""
        msg = f"{type(e).__name__}: {e}{at}"
    return " ".join(msg.split()) or type(e).__name__


def run_task(spec: TaskSpec, out_dir: str, version: str, force: bool = False) -> dict[str, Any]:
    """Run one task (see the module docstring); returns its result (also in ``tasks/NAME.json``).

    Parameters
    ----------
    spec : TaskSpec
        The task.
    out_dir : str
        The campaign's output folder (shared with the client: the same path on every worker).
    version : str
        The iscd version the identity is made with (the client's: a worker of another
        version makes a different identity, so nothing of another version is reused).
    force : bool
        Decode even when a finished output has the same identity.

    Returns
    -------
    dict
        name, kind, status (ok/failed), error, reused, identity, inputs, figures, wall_s,
        jsonl_bytes, warnings, worker.
    """
    t0 = time.perf_counter()
    tasks = Path(out_dir) / TASKS_DIR
    old = read_result(out_dir, spec.name)
    result: dict[str, Any] = {"name": spec.name, "kind": spec.kind, "status": "failed", "error": "",
                              "reused": False, "identity": "", "inputs": {}, "figures": {}, "warnings": [],
                              "worker": f"{os.uname().nodename}:{os.getpid()}", "spec": spec.as_dict()}
    tmp_jsonl = tasks / f"{spec.name}.jsonl.part-{uuid.uuid4().hex[:8]}"
    try:
        tasks.mkdir(parents=True, exist_ok=True)
        inputs = describe_inputs(spec.inputs(), (old or {}).get("inputs"))
        ident = task_identity(spec.params(), inputs, version)
        result.update(inputs=inputs, identity=ident)
        if not force and old and old.get("identity") == ident and is_complete(out_dir, old):
            old.update(reused=True, inputs=inputs)
            _atomic_json(task_file(out_dir, spec.name, ".json"), {k: v for k, v in old.items() if k != "reused"})
            return old
        figures, warnings = _decode(spec, tmp_jsonl, tasks)
        os.replace(tmp_jsonl, task_file(out_dir, spec.name, ".jsonl"))
        result.update(status="ok", figures=figures, warnings=warnings,
                      jsonl_bytes=task_file(out_dir, spec.name, ".jsonl").stat().st_size)
    except Exception as e:  # noqa: BLE001 - a task records its failure and never raises
        result["error"] = one_line(e)
        task_file(out_dir, spec.name, ".jsonl").unlink(missing_ok=True)  # a former output is stale now
    finally:
        tmp_jsonl.unlink(missing_ok=True)
    result["wall_s"] = round(time.perf_counter() - t0, 3)
    try:
        _atomic_json(task_file(out_dir, spec.name, ".json"), result)
    except OSError as e:
        result.update(status="failed", error=one_line(e))
    return result


def _decode(spec: TaskSpec, out: Path, tasks: Path) -> tuple[dict[str, Any], list[str]]:
    """Replay the task's recording (rendered first for a simulated point) into ``out``;
    (figures, warnings)."""
    from iscd.campaign.rows import figures, iter_records
    from iscd.eval.replay import ReplayInputs, replay

    warnings: list[str] = []
    rec_dir = None
    try:
        if spec.kind == "simulate":
            rec_dir = tasks / (f"{spec.name}.rec" if spec.keep else f"{spec.name}.rec.part-{uuid.uuid4().hex[:8]}")
            simulate(spec, rec_dir)
            inp = ReplayInputs(left=rec_dir, block=spec.block)
            truth: str | Path | None = rec_dir
        else:
            inp = ReplayInputs(left=Path(spec.left or ""), right=Path(spec.right) if spec.right else None,
                               config=spec.config, calibration=spec.calibration,
                               allow_mismatch=spec.allow_mismatch, block=spec.block)
            truth = spec.truth
        res = replay(inp, out, warn=warnings.append, rotate_bytes=NO_ROTATION)
        return figures(iter_records(out), res.config, truth), warnings
    finally:
        if rec_dir is not None and not spec.keep:
            shutil.rmtree(rec_dir, ignore_errors=True)


def simulate(spec: TaskSpec, out: Path) -> None:
    """Render a simulated point with ``iscd simulate`` in a child process (the same code and
    options as the command).

    Parameters
    ----------
    spec : TaskSpec
        The point (config, frames, seed, randomize, noise).
    out : Path
        The recording's folder.

    Raises
    ------
    UserError
        With the command's last line of error.
    """
    cmd = [sys.executable, "-m", "iscd", "-q", "simulate", "--out", str(out), "--overwrite"]
    if spec.config:
        cmd += ["--config", spec.config]
    if spec.frames is not None:
        cmd += ["--frames", str(spec.frames)]
    if spec.seed is not None:
        cmd += ["--seed", str(spec.seed)]
    if spec.randomize is not None:
        cmd += ["--randomize", str(spec.randomize)]
    if not spec.noise:
        cmd.append("--no-noise")
    r = subprocess.run(cmd, capture_output=True, text=True, stdin=subprocess.DEVNULL)
    if r.returncode != 0:
        lines = [x for x in r.stderr.strip().splitlines() if x.strip()]
        raise UserError(f"iscd simulate failed (exit {r.returncode}): {lines[-1] if lines else 'no message'}")
