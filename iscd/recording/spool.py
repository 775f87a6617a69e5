"""The bounded queue between the frame loop and the recording's writer thread: one block of
memory, records packed into it back to back (wrapping around), oldest first.

One producer (the frame loop) and one consumer (the writer). The producer reserves room
for a record (:meth:`Spool.reserve`, never blocking: None when it does not fit), packs the
record straight into :attr:`Spool.buf` and commits it; the consumer looks at the oldest
records (:meth:`Spool.peek`), writes their bytes straight out of the buffer (runs of
records that lie back to back are one write) and releases them. In blackbox mode the
producer may also drop the oldest records (:meth:`Spool.evict_before`, :meth:`Spool.evict_oldest`)
while nothing is being written.
"""

from __future__ import annotations

import mmap
import threading
from collections import deque
from typing import NamedTuple

import numpy as np


class Item(NamedTuple):
    """A record in the spool: byte offset and size in the buffer, its frame id, whether it
    is a pair (else a block note)."""

    off: int
    size: int
    frame_id: int
    pair: bool = True


class Spool:
    """A ring of ``capacity`` bytes (rounded down to 8) holding whole records.

    Parameters
    ----------
    capacity : bytes of memory, allocated and populated at once (where the system can:
        ``MAP_POPULATE``), so that the frame loop never takes the page faults of fresh
        memory while it packs (a 512 KiB pair into untouched pages cost ~1.8 ms instead of
        40 us on a loaded 2-core VM)
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity) // 8 * 8
        if self.capacity < 64:
            raise ValueError(f"spool capacity must be >= 64 bytes, got {capacity}")
        flags = mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | getattr(mmap, "MAP_POPULATE", 0)
        self._mem = mmap.mmap(-1, self.capacity, flags=flags)
        self.buf = np.frombuffer(self._mem, np.uint8)
        self.items: deque[Item] = deque()
        self.lock = threading.Lock()
        self._head = 0
        self.used = 0
        """bytes of the records held"""

    def __len__(self) -> int:
        return len(self.items)

    def reserve(self, size: int) -> int | None:
        """A byte offset where ``size`` contiguous bytes are free, or None (full). The
        caller packs its record there and then calls :meth:`commit` (one producer: no
        other reservation in between)."""
        with self.lock:
            return self._fit(size)

    def _fit(self, size: int) -> int | None:
        if size > self.capacity:
            return None
        if not self.items:
            self._head = 0
            return 0
        tail, head = self.items[0].off, self._head
        if head > tail:
            if self.capacity - head >= size:
                return head
            return 0 if tail >= size else None
        if head < tail:
            return head if tail - head >= size else None
        return None  # head == tail with records held: full

    def commit(self, off: int, size: int, frame_id: int, pair: bool = True) -> None:
        """The record packed at ``off`` is whole: the consumer may take it."""
        with self.lock:
            self.items.append(Item(off, size, frame_id, pair))
            self._head = off + size
            self.used += size

    def peek(self, max_items: int) -> list[Item]:
        """The oldest records (at most ``max_items``), not yet released."""
        with self.lock:
            n = min(max_items, len(self.items))
            return [self.items[i] for i in range(n)]

    def release(self, n: int) -> None:
        """The ``n`` oldest records are written: their room is free."""
        with self.lock:
            for _ in range(n):
                self.used -= self.items.popleft().size

    def evict_before(self, frame_id: int) -> int:
        """Drop the oldest records with an id below ``frame_id``; returns how many."""
        k = 0
        with self.lock:
            while self.items and self.items[0].frame_id < frame_id:
                self.used -= self.items.popleft().size
                k += 1
        return k

    def reserve_evicting(self, size: int) -> tuple[int | None, int]:
        """As :meth:`reserve`, dropping the oldest records until the record fits; returns
        (offset or None, records dropped)."""
        k = 0
        with self.lock:
            while True:
                off = self._fit(size)
                if off is not None or not self.items:
                    return off, k
                self.used -= self.items.popleft().size
                k += 1

    def pairs_held(self) -> int:
        """How many of the records held are pairs."""
        with self.lock:
            return sum(it.pair for it in self.items)

    def runs(self, items: list[Item]) -> list[tuple[int, int, list[Item]]]:
        """``items`` in runs of records that lie back to back: (start byte, end byte, items)."""
        out: list[tuple[int, int, list[Item]]] = []
        for it in items:
            if out and out[-1][1] == it.off:
                a, _, run = out[-1]
                run.append(it)
                out[-1] = (a, it.off + it.size, run)
            else:
                out.append((it.off, it.off + it.size, [it]))
        return out
