"""The packet assembler (timing, channel, decision, CRC) in a worker process of its own.

Demodulating a packet of an 8x8 array takes ~0.1-0.2 s of Python and numpy calls. In a
thread of the decoding process it holds the GIL in thousands of short slices, so that
the per-frame loop (luminance, ranging) waits behind it and its latency triples while a
packet is being decided. In its own process it costs the frame loop nothing but the
pickling of each block's luminance (a few kB).

The worker keeps one :class:`~iscd.decode.comms.packets.PacketAssembler` in a module global;
:class:`DemodWorker` sends it operations in order (one worker, first in first out) and
hands back a :class:`~concurrent.futures.Future` per operation whose result is the list
of packets that operation completed.

Memory debugging: with ``ISCD_DEMOD_TRACEMALLOC=FILE`` in its environment the worker traces
its Python allocations (:mod:`tracemalloc`) and, every ``ISCD_DEMOD_TRACEMALLOC_EVERY``
packets (default 1000), appends to FILE one line of figures (packets, traced KiB now, the
peak since the last line, RssAnon KiB) and the 10 biggest differences against its first
such line (:class:`MemoryReport`; docs/hardening.md, "The demodulation worker's memory").
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from iscd.decode.comms.packets import Packet, PacketAssembler

_assembler: PacketAssembler | None = None


def rss_anon_kib(pid: int | str = "self") -> int:
    """A process's private resident memory (``RssAnon`` of ``/proc/PID/status``), KiB."""
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("RssAnon:"):
                return int(line.split()[1])
    raise OSError(f"no RssAnon in /proc/{pid}/status")


class MemoryReport:
    """The ``ISCD_DEMOD_TRACEMALLOC`` lines (module docstring): :meth:`tick` after every push
    with the packets it completed. A line ``packets=N traced_kib=T peak_kib=P
    rss_anon_kib=R``, then ``  <difference>`` lines. The peak is reset after each line: it
    is the most traced at once between two lines (the report's own snapshot not counted)."""

    def __init__(self, path: str, every: int) -> None:
        self.path, self.every = path, max(1, every)
        self.packets = 0
        self._next = self.every
        self._first: Any = None

    def tick(self, packets: int) -> None:
        import gc
        import tracemalloc

        if not tracemalloc.is_tracing():  # from the first push on (the kernels are loaded)
            tracemalloc.start(8)
        self.packets += packets
        if self.packets < self._next:
            return
        self._next = self.packets + self.every
        gc.collect()
        now, peak = tracemalloc.get_traced_memory()
        lines = [f"packets={self.packets} traced_kib={now / 1024:.1f} peak_kib={peak / 1024:.1f} "
                 f"rss_anon_kib={rss_anon_kib()}"]
        snap = tracemalloc.take_snapshot()
        if self._first is None:
            self._first = snap
        else:
            lines += [f"  {d}" for d in snap.compare_to(self._first, "lineno")[:10]]
        with open(self.path, "a") as fh:
            fh.write("\n".join(lines) + "\n")
        del snap
        tracemalloc.reset_peak()


_report: MemoryReport | None = None


_slots: dict[int, PacketAssembler | None] = {}
"""Assemblers of further transmitters (``slot`` operations: one worker for several)."""


def _call(op: str, *args: Any) -> list[Packet]:
    """Runs in the worker: ``warm`` (load the compiled kernels), ``new`` (make the
    assembler from its arguments), ``push``, ``reset`` or ``flush`` on it; returns the
    packets completed. ``slot`` (key, op, *args): the same on the assembler of ``key``
    (:class:`SlotWorker`: several transmitters' assemblers in one worker), ``drop`` (key)
    forgets one."""
    global _assembler
    if op == "slot":
        key, inner, rest = args[0], args[1], args[2:]
        if inner == "drop":
            _slots.pop(key, None)
            return []
        saved, _assembler = _assembler, _slots.get(key)
        try:
            return _call(inner, *rest)
        finally:
            _slots[key], _assembler = _assembler, saved
    if op == "warm":  # load (or compile) the receiver's kernels before the first packet
        from iscd.core.jit import warm_up

        warm_up()
        return []
    if op == "new":
        tx, fps, exposure_s, cfg = args
        held = _assembler.reset() if _assembler is not None else []  # (nothing decoded is dropped)
        _assembler = PacketAssembler(tx, fps=fps, exposure_s=exposure_s, cfg=cfg)
        return held
    if _assembler is None:
        raise RuntimeError(f"demodulation worker: {op!r} before the assembler was made")
    if op == "push":
        out = _assembler.push(*args)
        if _report is not None:
            _report.tick(len(out))
        return out
    if op == "reset":
        return _assembler.reset()
    if op == "flush":
        return _assembler.flush()
    raise ValueError(f"demodulation worker: unknown operation {op!r}")


WORKER_NICE = 5
"""The worker runs at a lower priority than the acquisition and the frame loop: it has a
whole packet's time (1.3 s) for each packet, they have a millisecond per frame."""


def _init() -> None:
    import os
    import signal

    global _report
    if os.environ.get("ISCD_DEMOD_TRACEMALLOC"):  # memory debugging (module docstring)
        _report = MemoryReport(os.environ["ISCD_DEMOD_TRACEMALLOC"],
                               int(os.environ.get("ISCD_DEMOD_TRACEMALLOC_EVERY", "1000")))

    # Ctrl-C reaches the whole process group: the daemon stops this worker itself (it
    # closes the pipe), so the worker ignores SIGINT instead of dying with a traceback
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        os.nice(WORKER_NICE)
    except OSError:  # not permitted (some containers): run at normal priority
        pass


class DemodWorker:
    """One worker process holding a packet assembler; operations run in submission order."""

    def __init__(self) -> None:
        # spawn: the decoding process runs threads; the worker inherits its environment
        # (one BLAS thread, set by the CLI before numpy loads)
        self._pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init)

    @property
    def pids(self) -> list[int]:
        """The worker's process id(s) (for CPU accounting); empty before it has started."""
        return list(getattr(self._pool, "_processes", None) or {})

    def submit(self, op: str, *args: Any) -> Future:
        """Queue ``op``; a dead worker gives a future holding BrokenProcessPool (the caller
        replaces the worker when it collects it)."""
        try:
            return self._pool.submit(_call, op, *args)
        except BrokenProcessPool as e:
            f: Future = Future()
            f.set_exception(e)
            return f

    def shutdown(self, wait: bool = True) -> None:
        self._pool.shutdown(wait=wait, cancel_futures=not wait)


class SlotWorker:
    """One transmitter's view of a shared worker (:class:`iscd.decode.pipe.PipeDemodWorker`
    or :class:`DemodWorker`): the same interface, each operation run on this slot's own
    assembler in the worker. :meth:`shutdown` only forgets the slot; the owner of the
    shared worker stops it."""

    def __init__(self, worker: Any, key: int) -> None:
        self.worker, self.key = worker, int(key)

    @property
    def pids(self) -> list[int]:
        return list(self.worker.pids)

    def submit(self, op: str, *args: Any) -> Future:
        return self.worker.submit("slot", self.key, op, *args)

    def shutdown(self, wait: bool = True) -> None:
        self.worker.submit("slot", self.key, "drop")
