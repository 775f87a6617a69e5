"""``iscd campaign --scheduler``: a campaign on an existing Dask cluster, a ``dask scheduler``
and a ``dask worker`` process started by this test on loopback (free ports), waited for by
polling (no sleeps against the clock), and stopped with their whole process groups (no
orphans, checked)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from fakes import cli
from benchmarks.bench_campaign import make_recordings, write_manifest
from test_campaign import free_port, replay_alone

READY_TIMEOUT_S = 120.0
"""Generous: a loaded 2-core machine starts a scheduler and a worker in seconds."""


def _spawn(args: list[str], log: Path) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "NUMBA_NUM_THREADS": "1"}
    with open(log, "wb") as f:
        return subprocess.Popen(args, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True, env=env)


def _stop(proc: subprocess.Popen) -> None:
    """SIGTERM to the process group, then SIGKILL if it lingers; waits until the group is empty."""
    for sig, grace in ((signal.SIGTERM, 30.0), (signal.SIGKILL, 30.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(timeout=grace)
        except subprocess.TimeoutExpired:
            continue
        if not group_alive(proc.pid, grace):
            break
    proc.wait(timeout=30)


def group_alive(pgid: int, timeout_s: float) -> bool:
    """Whether a process of group ``pgid`` is still there after polling up to ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return False
        time.sleep(0.1)
    return True


def _wait_ready(address: str, procs: list[subprocess.Popen], logs: list[Path]) -> None:
    """Poll until the scheduler answers and has a worker (or a process died: fail with its log)."""
    from distributed import Client

    deadline = time.monotonic() + READY_TIMEOUT_S
    while True:
        for p, log in zip(procs, logs):
            if p.poll() is not None:
                pytest.fail(f"{log.name} exited with {p.returncode}:\n{log.read_text()[-2000:]}")
        try:
            with Client(address, timeout="5s", set_as_default=False) as c:
                c.wait_for_workers(1, timeout=max(1.0, deadline - time.monotonic()))
                return
        except (OSError, TimeoutError):
            if time.monotonic() > deadline:
                pytest.fail(f"the dask cluster at {address} was not ready in {READY_TIMEOUT_S:g} s")
            time.sleep(0.2)


@pytest.fixture
def dask_cluster(tmp_path: Path) -> Iterator[str]:
    """tcp://127.0.0.1:PORT of a separately started dask scheduler with one worker process."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    logs = [tmp_path / "scheduler.log", tmp_path / "worker.log"]
    procs: list[subprocess.Popen] = []
    try:
        procs.append(_spawn([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                             "--port", str(port), "--no-dashboard"], logs[0]))
        procs.append(_spawn([sys.executable, "-m", "distributed.cli.dask_worker", address, "--host", "127.0.0.1",
                             "--nthreads", "1", "--nworkers", "1", "--no-dashboard", "--local-directory",
                             str(tmp_path / "worker-space")], logs[1]))
        _wait_ready(address, procs, logs)
        yield address
    finally:
        for p in reversed(procs):  # the worker first, then the scheduler
            _stop(p)
        for p in procs:
            assert not group_alive(p.pid, 5.0), f"processes of group {p.pid} outlived the test"


def test_a_campaign_on_a_separately_started_scheduler_and_worker(dask_cluster: str, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from iscd.campaign.rows import FIGURES
    from iscd.campaign.summary import read_summary

    recs = make_recordings(tmp_path / "recordings", n=3, frames=300)
    (tmp_path / "small.toml").write_text((recs[0] / "config.toml").read_text())
    manifest = write_manifest(tmp_path / "m.toml", recs,
                              extra='\n[[simulate]]\nname = "sim"\nconfig = "small.toml"\nframes = 300\nseed = 9\n')
    capsys.readouterr()
    rc, _, err = cli(capsys, "campaign", str(manifest), "--out", str(tmp_path / "out"), "--scheduler", dask_cluster)
    assert rc == 0, err
    assert f"scheduler {dask_cluster}, 1 worker(s); dashboard:" in err
    rows = read_summary(tmp_path / "out" / "summary.parquet")
    assert [r["status"] for r in rows] == ["ok"] * 4, [r["error"] for r in rows]
    for rec, row in zip(recs, rows):
        alone = replay_alone(capsys, rec, tmp_path / f"{rec.name}.jsonl")
        assert {k: row[k] for k in FIGURES} == alone, rec.name
    assert rows[3]["name"] == "sim" and rows[3]["pairs"] == 300 and rows[3]["packets_sent"] == 1
    # the tasks ran in the worker process, not here
    import json

    worker = json.loads((tmp_path / "out" / "tasks" / f"{recs[0].name}.json").read_text())["worker"]
    assert worker.rsplit(":", 1)[1] != str(os.getpid())
    # and a second run on the same cluster does no work
    rc, _, err = cli(capsys, "campaign", str(manifest), "--out", str(tmp_path / "out"), "--scheduler", dask_cluster)
    assert rc == 0 and "4 complete and unchanged (skipped), 0 to run" in err, err
