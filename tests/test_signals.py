"""Signals on a live `iscd run` (issue 16, items 5 and 6), as a user sends them.

* Ctrl-C in a terminal reaches the whole process group (daemon, acquisition process,
  demodulation worker): one line saying so, the final records, exit 0 -- no
  KeyboardInterrupt tracebacks from the children.
* ``kill -9`` of the daemon: its children and the shared-memory ring are gone within 2 s.

Each waits for the daemon's own "transmitter acquired" line (no wall-clock race); the
timeouts are only safety nets for a machine that is very busy.
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

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="process groups and /dev/shm: Linux")


def _start(tmp_path: Path) -> tuple[subprocess.Popen, Path, Path]:
    out = tmp_path / "run.jsonl"
    err = tmp_path / "stderr.txt"
    proc = subprocess.Popen([sys.executable, "-m", "iscd", "run", "--duration", "60", "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=err.open("wb"), start_new_session=True)
    # the daemon's own lines say when it is decoding: no guess of how long that takes
    deadline = time.monotonic() + 240  # a cold start compiles the kernels first
    while time.monotonic() < deadline:
        if "transmitter acquired" in err.read_text(errors="replace"):
            break
        if proc.poll() is not None:
            pytest.fail(f"iscd run ended early: {err.read_text(errors='replace')[-2000:]}")
        time.sleep(0.2)  # polling the log; the deadline is only a safety net
    else:
        proc.kill()
        pytest.fail("iscd run did not acquire the transmitter")
    return proc, out, err


def _children(pid: int) -> list[int]:
    """Live processes whose parent is ``pid`` or that are in its session (orphans too)."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            st = (d / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        ppid, sid, state = int(st[1]), int(st[3]), st[0]
        if (ppid == pid or sid == pid) and int(d.name) != pid and state != "Z":
            found.append(int(d.name))
    return found


def _rings() -> set[str]:
    return {p.name for p in Path("/dev/shm").glob("iscd_ring_*")} if Path("/dev/shm").is_dir() else set()


def test_ctrl_c_on_the_process_group_is_one_line_and_the_final_record(tmp_path: Path) -> None:
    proc, out, err = _start(tmp_path)
    os.killpg(proc.pid, signal.SIGINT)
    assert proc.wait(timeout=60) == 0
    text = err.read_text(errors="replace")
    assert "Traceback" not in text and "KeyboardInterrupt" not in text
    assert "died" not in text  # no "demodulation worker died; starting a new one"
    assert "SIGINT: stopping" in text
    recs = [json.loads(line) for line in out.read_text().splitlines() if line.strip()]
    assert recs and recs[-1]["type"] == "stats" and recs[-1]["final"] is True
    assert any(r["type"] == "range" for r in recs)
    time.sleep(0.5)
    assert _children(proc.pid) == []


def test_kill_9_leaves_no_process_and_no_ring(tmp_path: Path) -> None:
    before = _rings()
    proc, _, _ = _start(tmp_path)
    kids = _children(proc.pid)
    assert kids, "the daemon runs its acquisition and demodulation in child processes"
    # its own ring (named after its pid): other daemons may start beside it (pytest -n 2)
    mine = {r for r in _rings() - before if r.split("_")[2] == str(proc.pid)}
    assert mine, "the daemon's shared-memory ring is not in /dev/shm"
    proc.send_signal(signal.SIGKILL)  # the daemon alone, as `kill -9 PID` does
    proc.wait(timeout=10)
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline and (_children(proc.pid) or (_rings() & mine)):
        time.sleep(0.05)
    left = _children(proc.pid)
    if left:  # clean up before failing
        for k in left:
            try:
                os.kill(k, signal.SIGKILL)
            except OSError:
                pass
    assert left == [], f"processes left after kill -9 of the daemon: {left}"
    assert not (_rings() & mine), "the daemon's shared-memory ring outlived it"


def test_stale_ring_of_a_dead_daemon_is_reclaimed(tmp_path: Path) -> None:
    """A ring left in /dev/shm by a daemon that died with its resource tracker (a whole
    process group sent SIGKILL) is removed at the next start; a live process's ring stays."""
    from iscd.rig.ringbuffer import reclaim_stale_rings

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # its pid is free now (reaped)
    stale = tmp_path / f"iscd_ring_{dead.pid}_0badf00d"
    live = tmp_path / f"iscd_ring_{os.getpid()}_00c0ffee"
    other = tmp_path / "iscd_ring_notapid_1"
    for p in (stale, live, other):
        p.write_bytes(b"\0" * 64)
    assert reclaim_stale_rings(str(tmp_path)) == [stale.name]
    assert not stale.exists() and live.exists() and other.exists()
