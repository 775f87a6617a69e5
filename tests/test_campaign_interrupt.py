"""Ctrl-C during ``iscd campaign``: the finished tasks' outputs stay whole, nothing unfinished
is left under a final name, the summary says which tasks did not run, and running the same
command again does only those.

No race against the clock: the last task's left recording is a named pipe that nobody writes,
so that task blocks (hashing its input) until the campaign is interrupted; the test waits,
by polling, for the other tasks' results and then sends SIGINT to the command's process
group, as a terminal's Ctrl-C does.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.bench_campaign import make_recordings
from test_campaign_scheduler import group_alive

TIMEOUT_S = 120.0


def _wait_for(cond, what: str, proc: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not cond():
        if proc.poll() is not None:
            pytest.fail(f"iscd campaign exited ({proc.returncode}) before {what}:\n{log.read_text()[-2000:]}")
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} within {TIMEOUT_S:g} s:\n{log.read_text()[-2000:]}")
        time.sleep(0.05)


def test_ctrl_c_keeps_the_finished_outputs_and_a_rerun_does_the_rest(tmp_path: Path) -> None:
    from iscd.campaign.summary import read_summary
    from iscd.campaign.tasks import is_complete, read_result

    recs = make_recordings(tmp_path / "recordings", n=3, frames=300)
    fifo = tmp_path / "blocked-left.iscr"
    os.mkfifo(fifo)
    manifest = tmp_path / "m.toml"
    manifest.write_text("".join(f'[[recording]]\nleft = "{r}"\n\n' for r in recs) +
                        f'[[recording]]\nname = "blocked"\nleft = "{fifo}"\nright = "{recs[0] / "right.iscr"}"\n'
                        f'config = "{recs[0] / "config.toml"}"\n')
    out = tmp_path / "out"
    log = tmp_path / "campaign.log"
    cmd = [sys.executable, "-m", "iscd", "campaign", str(manifest), "--out", str(out), "--workers", "1"]
    with open(log, "wb") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True)
    try:
        _wait_for(lambda: all(read_result(out, r.name) for r in recs), "results of the three recordings", proc, log)
        os.killpg(proc.pid, signal.SIGINT)
        rc = proc.wait(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)
    assert not group_alive(proc.pid, 30.0), "processes of the interrupted campaign outlived it"
    assert rc == 130, log.read_text()[-2000:]
    assert "interrupted" in log.read_text().splitlines()[-1]
    for r in recs:
        assert is_complete(out, read_result(out, r.name)), r.name
    tasks = sorted(p.name for p in (out / "tasks").iterdir())
    assert tasks == sorted([f"{r.name}.json" for r in recs] + [f"{r.name}.jsonl" for r in recs]), tasks
    rows = read_summary(out / "summary.parquet")
    assert [r["status"] for r in rows] == ["ok", "ok", "ok", "not run"]
    # the pipe becomes a real recording: the same command does the one task left
    fifo.unlink()
    os.link(recs[0] / "left.iscr", fifo)
    done = subprocess.run(cmd, capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "3 complete and unchanged (skipped), 1 to run" in done.stderr
    rows = read_summary(out / "summary.parquet")
    assert [(r["status"], r["reused"]) for r in rows] == [("ok", True)] * 3 + [("ok", False)]
    assert json.loads((out / "tasks" / "blocked.json").read_text())["figures"]["pairs"] == 300
