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
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from iscd.decode.comms.packets import Packet, PacketAssembler

_assembler: PacketAssembler | None = None


def _call(op: str, *args: Any) -> list[Packet]:
    """Runs in the worker: ``warm`` (load the compiled kernels), ``new`` (make the
    assembler from its arguments), ``push``, ``reset`` or ``flush`` on it; returns the
    packets completed."""
    global _assembler
    if op == "warm":  # load (or compile) the receiver's kernels before the first packet
        from iscd.core.jit import warm_up

        warm_up()
        return []
    if op == "new":
        tx, fps, exposure_s, cfg = args
        _assembler = PacketAssembler(tx, fps=fps, exposure_s=exposure_s, cfg=cfg)
        return []
    if _assembler is None:
        raise RuntimeError(f"demodulation worker: {op!r} before the assembler was made")
    if op == "push":
        return _assembler.push(*args)
    if op == "reset":
        _assembler.reset()
        return []
    if op == "flush":
        return _assembler.flush()
    raise ValueError(f"demodulation worker: unknown operation {op!r}")


WORKER_NICE = 5
"""The worker runs at a lower priority than the acquisition and the frame loop: it has a
whole packet's time (1.3 s) for each packet, they have a millisecond per frame."""


def _init() -> None:
    import os
    import signal

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
