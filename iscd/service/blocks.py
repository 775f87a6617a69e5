"""The frame loop's intake: blocks of stereo pairs taken out of the ring.

:class:`BlockReader` takes up to ``block_max`` pairs at a time out of a
:class:`iscd.rig.ringbuffer.StereoRing` into block buffers it reuses, waiting at most
``block_wait_s`` for a block to fill, and copies only the pixel windows the decoder reads
(whole frames while it has no transmitter to read around). Every pair queued is taken
under one ring lock and given back under one more (not four lock operations a pair).
Between blocks it sleeps until the block is about due instead of waking for every pair
(a thousand wake-ups a second cost a tenth of a core).

Per pair it keeps the left camera's frame id, the exposure start ``t_s`` (s, the left
camera's timestamp; the id over the frame rate where the camera gives none) and the
arrival time on the host ``arrival_ns`` (``time.monotonic_ns``, what the latency counts from).

Whole frames (no windows: the decoder is looking for a transmitter) go into block arrays
that no later read writes while anything else holds them, :attr:`BlockReader.fresh` True:
the decoder may keep them (its look-back) without a copy of its own (``push(owned=True)``).
They come from a pool: a pair of arrays is reused once nothing but the pool refers to it
(no view of it is left), so that a searcher keeping hundreds of frames does not fault in
fresh memory for every block (~4-20 us a 4 KiB page on this kind of VM: a 160 MB look-back
cost ~0.5 s of stalls at start-up); ``pool_blocks`` pairs are made and touched when the
reader is made. The windows of a tracked transmitter go into buffers of their own, reused.

An optional :attr:`BlockReader.tap` (the run's recording, :mod:`iscd.service.recording`)
sees every pair taken, before its slot goes back to the ring: ``tap.pair(slot, windows,
block)``, ``block`` numbering the blocks read (it must copy what it keeps, and never wait).
"""

from __future__ import annotations

import sys
import time
from typing import Any, Callable

import numpy as np

Window = tuple[int, int, int, int]
"""(x0, y0, x1, y1) px, x1 and y1 exclusive."""


class BlockReader:
    """Blocks of up to ``block_max`` pairs out of ``ring`` (see module docstring).

    Parameters
    ----------
    ring : StereoRing
        The ring the acquisition process writes.
    height, width : int
        Frame size, px.
    dtype : numpy dtype
        Pixel type (uint8 or uint16).
    block_max : int
        Most pairs in a block.
    fps : float
        Camera frame rate, frames/s (the pacing of the sleep between blocks).
    block_wait_s : float
        Longest wait for a block to fill once its first pair is in, s.
    pool_blocks : int
        Pairs of whole-frame block arrays made and touched now (the decoder's look-back in
        blocks, a few more); the pool grows past it when a decoder holds more, up to
        ``pool_max``.
    pool_max : int
        Most pairs the pool keeps (beyond it a block's arrays are fresh and let go).
    """

    def __init__(self, ring: Any, height: int, width: int, dtype: Any, block_max: int, fps: float,
                 block_wait_s: float, *, pool_blocks: int = 0, pool_max: int = 64) -> None:
        self.ring = ring
        self.block_max = B = int(block_max)
        self.fps = float(fps)
        self.block_wait_s = float(block_wait_s)
        self.left = np.zeros((B, height, width), dtype)
        self.right = np.zeros((B, height, width), dtype)
        self.ids = np.zeros(B, np.int64)
        self.t_s = np.zeros(B, np.float64)
        self.arrival_ns = np.zeros(B, np.int64)
        self.tap: Any = None
        """sees each pair before its slot is released (see the module docstring)"""
        self.blocks_read = 0
        """blocks read so far (the number of the next one)"""
        self.fresh = False
        """the last block is in arrays of its own that no later read reuses (whole frames)"""
        self._shape = (B, height, width)
        self._dtype = dtype
        self._pool: list[tuple[np.ndarray, np.ndarray]] = []
        self.pool_max = max(int(pool_max), int(pool_blocks))
        for _ in range(int(pool_blocks)):
            pair = (np.empty(self._shape, dtype), np.empty(self._shape, dtype))
            for a in pair:
                a.fill(0)  # touched now, not while frames wait
            self._pool.append(pair)

    def read(self, windows: tuple[Window, Window] | None, *, pace: bool = True,
             on_part: Callable[[int], None] | None = None) -> int:
        """Take the next block; returns how many pairs it holds (0: none came within the
        wait). ``windows``: the (left, right) pixel windows to copy (None: whole frames).
        ``pace``: sleep until the block is about due first (False while draining).
        ``on_part(k)``: called once the block's first ``k`` pairs (about half of it, or what
        was already queued when the read began) are in and copied, while the rest is still
        coming (paced reads only; not when the whole block was already queued): the daemon
        ranges them then (``range_ahead``)."""
        ring, B = self.ring, self.block_max
        n = 0
        if windows is None:  # whole frames: arrays the decoder may keep (see the module docstring)
            self.left, self.right = self._free_pair()
        elif self.fresh:  # back to buffers of its own, reused from now on
            self.left = np.zeros(self._shape, self._dtype)
            self.right = np.zeros(self._shape, self._dtype)
        self.fresh = windows is None
        t_fill = time.monotonic() + self.block_wait_s
        if pace:
            missing = B - ring.queued
            if (windows is None or on_part is not None) and missing > 1:
                # the first half taken as soon as it is in (at once if the last block's
                # decoding took longer than its filling): whole frames (0.5 MB a pair)
                # copied while the second half arrives, so that half as much is left to
                # copy after the block's last pair (the latency), and handed to on_part
                if missing > B // 2 + 1:
                    time.sleep(min(self.block_wait_s, (missing - B // 2) / self.fps))
                n = self._take(ring.read_batch(B, timeout_s=0.0), windows, n)
                if on_part is not None and 0 < n < B:
                    on_part(n)
                missing = B - n - ring.queued
            if missing > 1:
                time.sleep(max(0.0, min(t_fill - time.monotonic(), (missing - 1) / self.fps)))
        while n < B:
            timeout = max(0.0, t_fill - time.monotonic()) if n else 0.05
            slots = ring.read_batch(B - n, timeout_s=timeout)
            if not slots:
                break
            n = self._take(slots, windows, n)
            if time.monotonic() >= t_fill:
                break
        if n:
            self.blocks_read += 1
        return n

    def _take(self, slots: list, windows: tuple[Window, Window] | None, n: int) -> int:
        """Copy ``slots`` (read from the ring) into the block from pair ``n`` on, then give
        them back; returns the pairs in the block now."""
        try:
            for slot in slots:
                if windows is None:
                    self.left[n] = slot.left
                    self.right[n] = slot.right
                else:
                    (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = windows
                    self.left[n, ay0:ay1, ax0:ax1] = slot.left[ay0:ay1, ax0:ax1]
                    self.right[n, by0:by1, bx0:bx1] = slot.right[by0:by1, bx0:bx1]
                self.ids[n] = slot.frame_id
                self.t_s[n] = slot.ts_left_ns * 1e-9 if slot.ts_left_ns else slot.frame_id / self.fps
                self.arrival_ns[n] = slot.arrival_ns
                if self.tap is not None:
                    self.tap.pair(slot, windows, self.blocks_read)
                n += 1
        finally:
            self.ring.release_batch(slots)
        return n

    def _free_pair(self) -> tuple[np.ndarray, np.ndarray]:
        """Whole-frame block arrays that nothing outside the pool refers to (no view of them
        kept by a decoder), else a new pair (kept in the pool up to ``pool_max``)."""
        cur = (self.left, self.right) if self.fresh else None
        for pair in self._pool:
            # references: the pool's tuple and getrefcount's argument (2), and this
            # reader's own ``left``/``right`` while it is the last block read; any view of
            # it (a decoder's kept frame) holds one more
            own = 2 + (cur is not None and pair[0] is cur[0])
            if sys.getrefcount(pair[0]) <= own and sys.getrefcount(pair[1]) <= own:
                return pair
        pair = (np.empty(self._shape, self._dtype), np.empty(self._shape, self._dtype))
        if len(self._pool) < self.pool_max:
            self._pool.append(pair)
        return pair

    def discard(self) -> int:
        """Take and drop every pair the ring still holds; returns how many."""
        n_drop = 0
        while True:
            slots = self.ring.read_batch(max(self.block_max, 64), timeout_s=0.0)
            if not slots:
                return n_drop
            n_drop += len(slots)
            self.ring.release_batch(slots)
