"""The demodulation worker over plain pipes (iscd.decode.pipe): results in submission
order, the worker's exceptions handed back, submissions that never block the caller
(more than a pipe holds, queued while the worker is busy), a killed worker seen as
BrokenProcessPool, and a clean shutdown. No wall-clock assertions."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
from concurrent.futures.process import BrokenProcessPool

from iscd.core.config import default_config
from iscd.decode.pipe import PipeDemodWorker
from iscd.decode.comms.settings import receiver_config


@pytest.fixture()
def worker():
    w = PipeDemodWorker()
    yield w
    w.shutdown(wait=False)


def test_operations_run_in_order_and_errors_come_back(worker) -> None:
    # 'push' before 'new': the worker's RuntimeError reaches the caller's future
    bad = worker.submit("push", np.arange(4), np.arange(4) / 1e3, np.zeros((4, 64)), np.zeros((4, 64)))
    with pytest.raises(RuntimeError, match="before the assembler"):
        bad.result(timeout=60)
    cfg = default_config()
    futs = [worker.submit("new", cfg.transmitter, cfg.camera.fps, cfg.camera.exposure_s, receiver_config(cfg))]
    ids = np.arange(64)
    for s in range(0, 64, 16):
        futs.append(worker.submit("push", ids[s:s + 16], ids[s:s + 16] / 1e3, np.zeros((16, 64)),
                                  np.zeros((16, 64))))
    futs.append(worker.submit("reset"))
    futs.append(worker.submit("nonsense"))
    for f in futs[:-1]:
        assert f.result(timeout=60) == []  # dark frames: no packet
    with pytest.raises(ValueError, match="unknown operation"):
        futs[-1].result(timeout=60)
    assert worker.pids and all(f.done() for f in futs)


def test_submissions_beyond_the_pipe_buffer_do_not_block(worker) -> None:
    """Several MB submitted at once (a pipe holds 64 kB): submit returns each time (the
    rest waits in the backlog), and every operation is still delivered, in order."""
    big = np.zeros((16, 8192))  # 1 MiB each
    futs = [worker.submit("nonsense", big) for _ in range(6)]
    futs.append(worker.submit("warm"))  # after all the others: it succeeds
    for f in futs[:-1]:
        with pytest.raises(RuntimeError, match="'nonsense' before the assembler"):  # (no 'new' yet)
            f.result(timeout=120)
    assert futs[-1].result(timeout=300) == []


def test_a_killed_worker_breaks_its_pending_futures() -> None:
    w = PipeDemodWorker()
    try:
        assert w.submit("reset").exception(timeout=60) is not None  # it runs (no assembler yet)
        pid = w.pids[0]
        os.kill(pid, signal.SIGKILL)
        f = w.submit("warm")
        with pytest.raises(BrokenProcessPool):
            f.result(timeout=60)
        with pytest.raises(BrokenProcessPool):  # and every later one at once
            w.submit("reset").result(timeout=1)
    finally:
        w.shutdown(wait=False)


def test_shutdown_waits_for_the_pending_work() -> None:
    w = PipeDemodWorker()
    f = w.submit("reset")
    w.shutdown(wait=True)
    assert f.done() and isinstance(f.exception(), RuntimeError)
    assert w.pids == []
    with pytest.raises(BrokenProcessPool):
        w.submit("reset").result(timeout=1)
