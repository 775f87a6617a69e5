"""The demodulation worker process over a plain pipe: no helper threads in the frame loop's
process.

:class:`iscd.decode.worker.DemodWorker` sends each operation through a
:class:`~concurrent.futures.ProcessPoolExecutor`, whose manager thread and queue feeder
thread live in the decoding process: every block's submission wakes both, and they take
the GIL from the frame loop. Measured on the 2-core machine: 0.65 ms of CPU per
submission (62 a second at blocks of 16 pairs) and single submissions that held the frame
loop up to 5-10 ms (the manager thread keeps the GIL for a switch interval) -- the worst
pairs' latency. :class:`PipeDemodWorker` is the same interface (:meth:`submit` returning a
:class:`~concurrent.futures.Future`, :attr:`pids`, :meth:`shutdown`) on two pipes:

* the frame loop pickles an operation and writes it to a **non-blocking** pipe from its own
  thread (one system call, ~20-50 us); what the pipe cannot take yet (the worker is busy
  deciding a packet and its reader has not run) waits in a local backlog that every later
  call flushes, so the frame loop never blocks on the worker;
* the worker polls that pipe every :data:`POLL_S` (it is never blocked in ``read``, so a
  write does not wake it and let it preempt the frame loop), runs the operations in order
  (:func:`iscd.decode.worker._call`, the same code as before) and writes each result back;
  the pipe is enlarged to :data:`PIPE_BYTES` for what queues while a packet is decided;
* the futures complete when the frame loop polls them (:meth:`Future.done` reads what
  the worker has sent, without blocking; :meth:`Future.result` waits).

A worker that dies (killed, out of memory) shows as end of file on the result pipe: every
pending future gets :class:`~concurrent.futures.process.BrokenProcessPool`, as with the
pool, and the caller replaces the worker.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import select
import struct
import time
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool
from typing import Any

_HDR = struct.Struct("!Q")
"""frame header: the payload's length, bytes"""


def _read_exact(fd: int, n: int) -> bytes | None:
    """n bytes from a blocking fd, or None at end of file."""
    buf = bytearray()
    while len(buf) < n:
        chunk = os.read(fd, n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


POLL_S = 0.004
"""How often the worker looks for new operations when it has none, s. It polls instead of
blocking in ``read``: a pipe write that wakes a blocked reader lets the reader preempt the
writer (Linux wakes pipe readers "synchronously"), which cost the frame loop 1.3 ms median,
5 ms p99 per block on the 2-core machine; a write with no reader waiting is a copy."""

PIPE_BYTES = 1 << 20
"""Requested size of the operations pipe (Linux ``F_SETPIPE_SZ``; the default 64 kB holds
four blocks of an 8x8 array): what queues while the worker decides a packet."""


READ_BYTES = 1 << 16
"""The worker reads the operations pipe into one buffer of this size, allocated once (a
full pipe takes a few reads).
(``os.read(fd, 1 MiB)`` allocated a fresh 1 MiB ``bytes`` at every poll, 250 a second, and
shrank it to the few hundred bytes read; glibc serves these from the heap once its mmap
threshold has risen past 1 MiB, and the heap grew: the worker's private memory rose 13 MiB
in the first 5 minutes of a live run, the soak's "climb", and stays flat without these
reads; docs/hardening.md, "The demodulation worker's memory".)"""


def _serve(conn_in: Any, conn_out: Any) -> None:  # pragma: no cover - runs in the worker
    """The worker process: read operations, run them in order, send the results back."""
    from iscd.decode.worker import _call, _init

    _init()
    rfd, wfd = conn_in.fileno(), conn_out.fileno()
    os.set_blocking(rfd, False)
    os.set_blocking(wfd, True)
    buf = bytearray()
    chunk = bytearray(READ_BYTES)  # read into this one buffer: see READ_BYTES
    view = memoryview(chunk)
    eof = False
    while True:
        got = False
        while not eof:
            try:
                n_read = os.readv(rfd, [chunk])
            except BlockingIOError:
                break
            if not n_read:  # the decoder closed its end: stop after what it sent
                eof = True
                break
            buf += view[:n_read]
            got = True
        ran = False
        while len(buf) >= _HDR.size and len(buf) >= _HDR.size + _HDR.unpack_from(buf)[0]:
            n = _HDR.unpack_from(buf)[0]
            op, args = pickle.loads(bytes(buf[_HDR.size:_HDR.size + n]))
            del buf[:_HDR.size + n]
            ran = True
            try:
                out: tuple[bool, Any] = (True, _call(op, *args))
            except BaseException as e:  # noqa: BLE001 - handed to the caller's future
                out = (False, e)
            try:
                data = pickle.dumps(out, pickle.HIGHEST_PROTOCOL)
            except Exception as e:  # noqa: BLE001 - an unpicklable result or exception
                data = pickle.dumps((False, RuntimeError(f"demodulation worker: {type(e).__name__}: {e}")))
            try:
                _write_all(wfd, _HDR.pack(len(data)) + data)
            except OSError:  # the decoder has gone
                return
        if eof:
            return
        if not got and not ran:
            time.sleep(POLL_S)


class _PipeFuture(Future):
    """A future completed by polling its worker's result pipe (no thread completes it)."""

    def __init__(self, owner: "PipeDemodWorker") -> None:
        super().__init__()
        self._owner = owner

    def done(self) -> bool:
        if not super().done():
            self._owner.poll()
        return super().done()

    def result(self, timeout: float | None = None) -> Any:
        if not super().done():
            self._owner.wait_for(self, timeout)
        return super().result(timeout=0)

    def exception(self, timeout: float | None = None) -> BaseException | None:
        if not super().done():
            self._owner.wait_for(self, timeout)
        return super().exception(timeout=0)


class PipeDemodWorker:
    """One worker process holding a packet assembler; operations run in submission order
    (the interface of :class:`iscd.decode.worker.DemodWorker`; see the module docstring)."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        w_in, self._send_conn = ctx.Pipe(duplex=False)   # decoder -> worker
        self._recv_conn, w_out = ctx.Pipe(duplex=False)  # worker -> decoder
        # spawn: the decoding process runs threads; the worker inherits its environment
        self._proc = ctx.Process(target=_serve, args=(w_in, w_out), name="iscd-demod", daemon=True)
        self._proc.start()
        w_in.close()  # the worker holds its ends: its death is end of file here
        w_out.close()
        self._wfd = self._send_conn.fileno()
        self._rfd = self._recv_conn.fileno()
        try:  # room for what queues while the worker decides a packet (Linux)
            import fcntl

            fcntl.fcntl(self._wfd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
        except (ImportError, AttributeError, OSError):
            pass
        os.set_blocking(self._wfd, False)
        os.set_blocking(self._rfd, False)
        self._backlog = bytearray()
        self._inbuf = bytearray()
        self._futures: list[_PipeFuture] = []
        """pending futures, oldest first (results come back in submission order)"""
        self._broken: BrokenProcessPool | None = None
        self._closed = False

    @property
    def pids(self) -> list[int]:
        """The worker's process id (for CPU accounting); empty once it is gone."""
        return [self._proc.pid] if self._proc.pid is not None and self._proc.is_alive() else []

    # ------------------------------------------------------------------ sending
    def submit(self, op: str, *args: Any) -> Future:
        """Queue ``op`` (never blocks); a dead worker gives a future holding
        BrokenProcessPool (the caller replaces the worker when it collects it)."""
        fut = _PipeFuture(self)
        if self._broken is not None or self._closed:
            fut.set_exception(self._broken or BrokenProcessPool("demodulation worker shut down"))
            return fut
        data = pickle.dumps((op, args), pickle.HIGHEST_PROTOCOL)
        self._futures.append(fut)
        self._backlog += _HDR.pack(len(data))
        self._backlog += data
        self._flush()
        return fut

    def _flush(self) -> None:
        """Write what the pipe takes now of the backlog (non-blocking)."""
        while self._backlog and self._broken is None:
            try:
                n = os.write(self._wfd, self._backlog)
            except BlockingIOError:
                return
            except OSError:  # the worker is gone (broken pipe)
                self._break("demodulation worker died")
                return
            del self._backlog[:n]

    # ------------------------------------------------------------------ receiving
    def poll(self) -> None:
        """Complete the futures whose results have arrived (non-blocking)."""
        self._flush()
        while self._broken is None:
            try:
                chunk = os.read(self._rfd, 1 << 16)
            except BlockingIOError:
                break
            except OSError:
                chunk = b""
            if not chunk:  # end of file: the worker has gone
                self._deliver()
                self._break("demodulation worker died")
                return
            self._inbuf += chunk
        self._deliver()

    def _deliver(self) -> None:
        buf = self._inbuf
        while len(buf) >= _HDR.size:
            n = _HDR.unpack_from(buf)[0]
            if len(buf) < _HDR.size + n:
                return
            ok, value = pickle.loads(bytes(buf[_HDR.size:_HDR.size + n]))
            del buf[:_HDR.size + n]
            if not self._futures:
                continue
            fut = self._futures.pop(0)
            if ok:
                fut.set_result(value)
            else:
                fut.set_exception(value)

    def wait_for(self, fut: Future, timeout: float | None) -> None:
        """Wait until ``fut`` completes, at most ``timeout`` s (then it is left pending)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not Future.done(fut):
            self.poll()
            if Future.done(fut) or self._broken is not None:
                return
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return
            wl = [self._wfd] if self._backlog else []
            select.select([self._rfd], wl, [], 0.5 if left is None else min(left, 0.5))
            if not self._proc.is_alive():  # read what it sent before it went, then break
                self.poll()
                if not Future.done(fut):
                    self._break("demodulation worker died")
                return

    def _break(self, why: str) -> None:
        if self._broken is None:
            self._broken = BrokenProcessPool(why)
        self._backlog.clear()
        for fut in self._futures:
            if not Future.done(fut):
                fut.set_exception(self._broken)
        self._futures.clear()

    # ------------------------------------------------------------------ the end
    def shutdown(self, wait: bool = True) -> None:
        """Stop the worker: ``wait`` lets it finish what was submitted (and waits for its
        results); otherwise pending futures are cancelled and it is stopped."""
        if self._closed:
            return
        if wait and self._broken is None:
            for fut in list(self._futures):
                self.wait_for(fut, None)
        self._closed = True
        for fut in self._futures:
            fut.cancel() or (not Future.done(fut) and fut.set_exception(BrokenProcessPool("shut down")))
        self._futures.clear()
        self._send_conn.close()  # end of file: the worker leaves after its current step
        if wait:
            self._proc.join(5.0)
        if self._proc.is_alive() and not wait:
            self._proc.terminate()
        if self._proc.is_alive():
            self._proc.join(1.0)
        self._recv_conn.close()
