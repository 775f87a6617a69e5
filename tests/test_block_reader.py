"""The frame loop's intake (iscd.service.blocks.BlockReader) on a real shared-memory ring:
whole frames while acquiring, only the decoder's windows once tracking, ids / timestamps /
arrival kept per pair, a short block when the ring runs dry, the rest discarded."""

from __future__ import annotations

import time

import numpy as np

from iscd.rig.ringbuffer import StereoRing
from iscd.service.blocks import BlockReader


def _frame(fid: int, side: int) -> np.ndarray:
    return ((np.arange(24 * 32).reshape(24, 32) + 7 * fid + 100 * side) % 251).astype(np.uint8)


def test_blocks_whole_frames_then_windows_then_discard() -> None:
    ring = StereoRing.create(height=24, width=32, capacity=64, max_held=4)
    try:
        for fid in range(11):
            ring.write(_frame(fid, 0), _frame(fid, 1), frame_id=fid,
                       ts_left_ns=0 if fid == 2 else 1_000_000 * fid + 5)
        rd = BlockReader(ring, 24, 32, np.uint8, block_max=4, fps=1000.0, block_wait_s=0.0)
        assert rd.read(None, pace=False) == 4
        for i in range(4):
            assert np.array_equal(rd.left[i], _frame(i, 0)) and np.array_equal(rd.right[i], _frame(i, 1))
        assert rd.ids.tolist() == [0, 1, 2, 3]
        # the camera's timestamp where it gives one, else the id over the frame rate
        assert np.allclose(rd.t_s, [5e-9, 1e-3 + 5e-9, 2e-3, 3e-3 + 5e-9])
        assert (rd.arrival_ns > 0).all()
        # windows: only those pixels are copied, the rest of the buffers stays as it was
        rd.left[:] = 0
        rd.right[:] = 0
        win = ((2, 3, 10, 9), (20, 0, 32, 5))
        assert rd.read(win, pace=False) == 4
        for i, fid in enumerate(range(4, 8)):
            assert np.array_equal(rd.left[i, 3:9, 2:10], _frame(fid, 0)[3:9, 2:10])
            assert np.array_equal(rd.right[i, 0:5, 20:32], _frame(fid, 1)[0:5, 20:32])
            assert rd.left[i].sum() == _frame(fid, 0)[3:9, 2:10].sum()
            assert rd.right[i].sum() == _frame(fid, 1)[0:5, 20:32].sum()
        assert rd.read(None, pace=False) == 3  # what is left: a short block, no waiting for more
        assert rd.ids[:3].tolist() == [8, 9, 10]
        for fid in range(11, 16):
            ring.write(_frame(fid, 0), _frame(fid, 1), frame_id=fid)
        assert rd.discard() == 5 and ring.queued == 0
    finally:
        ring.close()


def test_whole_frames_come_in_arrays_of_their_own() -> None:
    """Whole frames (the decoder looking for a transmitter keeps them) are in fresh arrays
    that no later read writes; windows go into buffers the reader reuses."""
    ring = StereoRing.create(height=24, width=32, capacity=64, max_held=4)
    try:
        for fid in range(16):
            ring.write(_frame(fid, 0), _frame(fid, 1), frame_id=fid)
        rd = BlockReader(ring, 24, 32, np.uint8, block_max=4, fps=1000.0, block_wait_s=0.0)
        assert rd.read(None, pace=False) == 4 and rd.fresh
        kept_l, kept_r = rd.left[:4], rd.right[:4]  # what a decoder keeps (views, no copy)
        assert rd.read(None, pace=False) == 4 and rd.fresh
        assert rd.left is not kept_l.base and rd.ids.tolist() == [4, 5, 6, 7]
        win = ((0, 0, 32, 24), (0, 0, 32, 24))
        assert rd.read(win, pace=False) == 4 and not rd.fresh
        buf = rd.left
        assert rd.read(win, pace=False) == 4 and rd.left is buf  # reused while windows
        for i in range(4):  # the kept frames were written by no later read
            assert np.array_equal(kept_l[i], _frame(i, 0)) and np.array_equal(kept_r[i], _frame(i, 1))
    finally:
        ring.close()


def test_whole_frame_arrays_are_reused_once_nothing_holds_them() -> None:
    """The pool: a pair of block arrays comes back once no view of it is kept (a decoder's
    look-back lets go of its frames), never while one is."""
    ring = StereoRing.create(height=24, width=32, capacity=64, max_held=4)
    try:
        for fid in range(40):
            ring.write(_frame(fid, 0), _frame(fid, 1), frame_id=fid)
        rd = BlockReader(ring, 24, 32, np.uint8, block_max=4, fps=1000.0, block_wait_s=0.0, pool_blocks=3)
        assert len(rd._pool) == 3
        rd.read(None, pace=False)
        kept = rd.left[2]  # a decoder keeps one frame of the first block
        first = id(rd.left)  # (no reference of our own: it would hold the arrays too)
        seen = {first}
        for _ in range(4):
            rd.read(None, pace=False)
            assert id(rd.left) != first  # never while the kept view lives
            seen.add(id(rd.left))
        assert np.array_equal(kept, _frame(2, 0))  # the kept frame was not written over
        assert len(seen) <= 3 and len(rd._pool) == 3  # the other two pairs took turns
        del kept
        handed = []
        for _ in range(3):
            rd.read(None, pace=False)
            handed.append(id(rd.left) == first)
        assert any(handed)  # free again: handed out within one turn of the pool
        assert len(rd._pool) == 3  # no new arrays were needed
    finally:
        ring.close()


def test_paced_whole_frame_block_taken_in_two_halves_is_whole_and_in_order() -> None:
    """With pacing, whole frames are taken as the first half is in and then the rest (the
    copy overlaps the arrival): the block is still every pair once, in order, each its own
    content, whatever the writer's timing (a generous fill wait: nothing here races a clock)."""
    import threading

    ring = StereoRing.create(height=24, width=32, capacity=64, max_held=16)
    try:
        rd = BlockReader(ring, 24, 32, np.uint8, block_max=16, fps=1000.0, block_wait_s=5.0)

        def writer() -> None:
            for fid in range(16):
                ring.write(_frame(fid, 0), _frame(fid, 1), frame_id=fid)
                time.sleep(0.001)

        t = threading.Thread(target=writer)
        t.start()
        try:
            assert rd.read(None, pace=True) == 16
        finally:
            t.join()
        assert rd.ids.tolist() == list(range(16))
        for i in range(16):
            assert np.array_equal(rd.left[i], _frame(i, 0)) and np.array_equal(rd.right[i], _frame(i, 1))
        assert ring.queued == 0
    finally:
        ring.close()


def test_on_part_gets_the_first_pairs_while_the_rest_is_still_coming() -> None:
    """``read(on_part=...)`` (the daemon's ranging ahead): called once, with the pairs taken
    so far, before the rest of the block is written (the writer waits for the call: no
    clock raced), windows copied; the block then whole and in order."""
    import threading

    ring = StereoRing.create(height=24, width=32, capacity=64, max_held=16)
    try:
        rd = BlockReader(ring, 24, 32, np.uint8, block_max=16, fps=1000.0, block_wait_s=5.0)
        win = ((2, 3, 10, 12), (4, 3, 12, 12))
        for fid in range(4):
            ring.write(_frame(fid, 0), _frame(fid, 1), frame_id=fid)
        called = threading.Event()
        seen: list[tuple[int, list[int], bool]] = []

        def on_part(k: int) -> None:
            (x0, y0, x1, y1) = win[0]
            seen.append((k, rd.ids[:k].tolist(),
                         all(np.array_equal(rd.left[i, y0:y1, x0:x1], _frame(i, 0)[y0:y1, x0:x1]) for i in range(k))))
            called.set()

        def writer() -> None:
            called.wait(10.0)
            for fid in range(4, 16):
                ring.write(_frame(fid, 0), _frame(fid, 1), frame_id=fid)

        t = threading.Thread(target=writer)
        t.start()
        try:
            assert rd.read(win, pace=True, on_part=on_part) == 16
        finally:
            called.set()
            t.join()
        assert seen == [(4, [0, 1, 2, 3], True)]
        assert rd.ids.tolist() == list(range(16))
        (x0, y0, x1, y1) = win[1]
        assert all(np.array_equal(rd.right[i, y0:y1, x0:x1], _frame(i, 1)[y0:y1, x0:x1]) for i in range(16))
    finally:
        ring.close()
