"""StereoRing: shared-memory SPSC ring of stereo pairs, drop-oldest, across processes.

Cross-process tests use the ``spawn`` start method (a fresh interpreter that attaches by
name, as the daemon's acquisition process does). Every ring a test makes is removed in the
fixture's teardown even when the test fails, and the teardown asserts that the code under
test already removed it.
"""

from __future__ import annotations

import hashlib
import multiprocessing as mp
import os
import pickle
import signal
import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator
from multiprocessing import shared_memory

import numpy as np
import pytest

from fakes import wait_until
from iscd.rig.ringbuffer import RingError, StereoRing, capacity_for

SHM = "/dev/shm"
pytestmark = pytest.mark.skipif(not os.path.isdir(SHM), reason="needs Linux /dev/shm")
CTX = mp.get_context("spawn")


@pytest.fixture
def make_ring() -> Iterator[Callable[..., StereoRing]]:
    made: list[StereoRing] = []

    def make(**kw: object) -> StereoRing:
        kw.setdefault("height", 8)
        kw.setdefault("width", 6)
        kw.setdefault("capacity", 4)
        ring = StereoRing.create(**kw)  # type: ignore[arg-type]
        made.append(ring)
        return ring

    yield make
    leaked = []
    for ring in made:
        ring.close()
        path = os.path.join(SHM, ring.name)
        if os.path.exists(path):
            leaked.append(ring.name)
            os.unlink(path)
    assert not leaked, f"segments left after close(): {leaked}"


def pattern(fid: int, shape: tuple[int, int], side: int, dtype: type = np.uint8) -> np.ndarray:
    """A seeded random image that depends on frame id and side (0 left, 1 right)."""
    rng = np.random.default_rng([fid, side])
    return rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)


def digest(a: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(a).tobytes()).hexdigest()


# ----------------------------------------------------------------------------- single process
def test_capacity_from_milliseconds() -> None:
    assert capacity_for(100, 1000) == 100
    assert capacity_for(2.5, 1000) == 3
    assert capacity_for(0.1, 1000) == 1
    assert capacity_for(33.3, 30) == 1
    with pytest.raises(RingError, match="buffer_ms"):
        capacity_for(0, 1000)
    with pytest.raises(RingError, match="fps"):
        capacity_for(10, float("nan"))


def test_memory_is_allocated_up_front(make_ring: Callable[..., StereoRing]) -> None:
    ring = make_ring(height=512, width=512, capacity=10)
    st = os.stat(os.path.join(SHM, ring.name))
    slots = 10 + ring.max_held + 1
    assert st.st_size >= slots * 2 * 512 * 512
    assert st.st_blocks * 512 >= st.st_size  # fallocated, not sparse


@pytest.mark.parametrize("seed", [0, 1])
def test_wrap_around_and_drop_oldest_match_a_model(make_ring: Callable[..., StereoRing],
                                                   seed: int) -> None:
    """Random writes and reads against a bounded deque: same pairs, same drop count."""
    rng = np.random.default_rng(seed)
    cap = 5
    ring = make_ring(capacity=cap)
    model: deque[int] = deque()
    dropped = 0
    fid = 0
    for _ in range(400):
        if rng.random() < 0.6:
            ring.write(pattern(fid, (8, 6), 0), pattern(fid, (8, 6), 1), frame_id=fid,
                       ts_left_ns=fid * 1000, ts_right_ns=fid * 1000 + 7)
            if len(model) == cap:
                model.popleft()
                dropped += 1
            model.append(fid)
            fid += 1
        else:
            got = ring.read()
            if not model:
                assert got is None
                continue
            want = model.popleft()
            assert got is not None and got.frame_id == want
            assert (got.ts_left_ns, got.ts_right_ns) == (want * 1000, want * 1000 + 7)
            assert np.array_equal(got.left, pattern(want, (8, 6), 0))
            assert np.array_equal(got.right, pattern(want, (8, 6), 1))
            got.release()
    st = ring.stats()
    assert fid > 3 * ring.n_slots  # the slots were reused many times over
    assert st.dropped_overflow == dropped > 0
    assert st.queued == len(model) and st.committed == fid
    assert st.consumed + st.dropped_overflow + st.queued == st.committed


def test_overflow_keeps_the_newest_pairs(make_ring: Callable[..., StereoRing]) -> None:
    ring = make_ring(capacity=4)
    for i in range(10):
        ring.write(pattern(i, (8, 6), 0), pattern(i, (8, 6), 1), frame_id=100 + i)
    assert ring.dropped_overflow == 6 and ring.queued == 4
    ids = []
    while (p := ring.read()) is not None:
        ids.append(p.frame_id)
        p.release()
    assert ids == [106, 107, 108, 109]


def test_held_pair_is_never_overwritten(make_ring: Callable[..., StereoRing]) -> None:
    ring = make_ring(capacity=3)
    for i in range(3):
        ring.write(pattern(i, (8, 6), 0), pattern(i, (8, 6), 1), frame_id=i)
    held = ring.read()
    assert held is not None and held.frame_id == 0
    for i in range(3, 40):  # the producer laps the ring many times while we hold pair 0
        ring.write(pattern(i, (8, 6), 0), pattern(i, (8, 6), 1), frame_id=i)
    assert np.array_equal(held.left, pattern(0, (8, 6), 0))
    assert np.array_equal(held.right, pattern(0, (8, 6), 1))
    assert not held.left.flags.writeable
    with pytest.raises(RingError, match="release"):
        ring.read()  # max_held = 1
    held.release()
    held.release()  # idempotent
    assert held.left is None
    with ring.read() as p:
        assert p is not None and p.frame_id == 37
    assert ring.stats().dropped_overflow == 40 - 3 - 1


def test_several_held_pairs(make_ring: Callable[..., StereoRing]) -> None:
    ring = make_ring(capacity=2, max_held=3)
    for i in range(3):
        ring.write(pattern(i, (8, 6), 0), pattern(i, (8, 6), 1), frame_id=i)
    a, b = ring.read(), ring.read()
    assert a is not None and b is not None
    for i in range(3, 20):
        ring.write(pattern(i, (8, 6), 0), pattern(i, (8, 6), 1), frame_id=i)
    assert [a.frame_id, b.frame_id] == [1, 2]
    assert np.array_equal(a.left, pattern(1, (8, 6), 0))
    assert np.array_equal(b.right, pattern(2, (8, 6), 1))
    assert ring.stats().held == 2
    assert ring.release_all() == 2 and ring.stats().held == 0


def test_uint16_and_zero_copy_reserve_commit(make_ring: Callable[..., StereoRing]) -> None:
    ring = make_ring(height=5, width=7, dtype=np.uint16)
    slot = ring.reserve()
    assert ring.reserve().index == slot.index  # re-reserving before commit: same slot
    slot.left[...] = pattern(3, (5, 7), 0, np.uint16)
    slot.right[...] = pattern(3, (5, 7), 1, np.uint16)
    seq = ring.commit(slot, frame_id=3, left_id=13, right_id=23, arrival_ns=5)
    with ring.read() as p:
        assert p is not None and p.seq == seq == 0
        assert p.left.dtype == np.uint16 and p.left.max() > 255
        assert np.array_equal(p.right, pattern(3, (5, 7), 1, np.uint16))
        assert (p.frame_id, p.left_id, p.right_id, p.arrival_ns) == (3, 13, 23, 5)
        assert p.commit_ns >= p.arrival_ns
    ring.abort(ring.reserve())
    assert ring.read() is None


def test_read_timeout_and_finish(make_ring: Callable[..., StereoRing]) -> None:
    ring = make_ring()
    t = time.monotonic()
    assert ring.read(timeout_s=0.05) is None
    assert time.monotonic() - t >= 0.05
    ring.write(pattern(0, (8, 6), 0), pattern(0, (8, 6), 1), frame_id=0)
    ring.finish()
    with ring.read(timeout_s=5) as p:
        assert p is not None and p.frame_id == 0
    t = time.monotonic()
    assert ring.read(timeout_s=5) is None  # finished and empty: no waiting
    assert time.monotonic() - t < 1.0
    assert ring.stats().finished


def test_bad_input_is_a_one_line_error(make_ring: Callable[..., StereoRing]) -> None:
    ring = make_ring(height=8, width=6)
    with pytest.raises(ValueError, match=r"left image must be \(8, 6\) uint8.*\(6, 8\)"):
        ring.write(np.zeros((6, 8), np.uint8), np.zeros((8, 6), np.uint8), frame_id=0)
    with pytest.raises(ValueError, match="right image.*uint16"):
        ring.write(np.zeros((8, 6), np.uint8), np.zeros((8, 6), np.uint16), frame_id=0)
    with pytest.raises(RingError, match="capacity") as e:
        StereoRing.create(height=8, width=8, capacity=0)
    assert "\n" not in str(e.value)
    with pytest.raises(RingError, match="dtype"):
        StereoRing.create(height=8, width=8, capacity=2, dtype=np.float32)
    with pytest.raises(RingError, match="/dev/shm has"):
        StereoRing.create(height=100_000, width=100_000, capacity=10_000)
    with pytest.raises(RingError, match="no ring named"):
        StereoRing.attach("iscd_ring_does_not_exist")
    with pytest.raises(RingError, match="already exists"):
        StereoRing.create(height=8, width=8, capacity=2, name=ring.name)
    other = shared_memory.SharedMemory(create=True, size=4096)
    try:
        with pytest.raises(RingError, match="not an iscd ring"):
            StereoRing.attach(other.name)
    finally:
        other.close()
        other.unlink()


def test_close_unlinks_also_when_the_block_fails() -> None:
    with pytest.raises(ZeroDivisionError):
        with StereoRing.create(height=4, width=4, capacity=2) as ring:
            name = ring.name
            ring.write(np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.uint8), frame_id=0)
            1 / 0
    assert not os.path.exists(os.path.join(SHM, name))


def test_close_with_views_still_alive_still_unlinks(make_ring: Callable[..., StereoRing]) -> None:
    ring = make_ring()
    ring.write(pattern(0, (8, 6), 0), pattern(0, (8, 6), 1), frame_id=0)
    p = ring.read()
    assert p is not None
    view = p.left
    ring.close()
    assert not os.path.exists(os.path.join(SHM, ring.name))
    assert np.array_equal(view, pattern(0, (8, 6), 0))  # mapping lives as long as the view
    p.release()  # after close: no-op, no error
    with pytest.raises(RingError, match="closed"):
        ring.read()


def test_a_handle_does_not_cross_fork(make_ring: Callable[..., StereoRing]) -> None:
    ring = make_ring()
    q = mp.get_context("fork").Queue()
    proc = mp.get_context("fork").Process(target=_use_inherited_handle, args=(ring, q))
    proc.start()
    msg = q.get(timeout=20)
    proc.join(20)
    assert "attach by name" in msg
    # pickling a handle attaches by name instead
    again = pickle.loads(pickle.dumps(ring))
    try:
        assert again.name == ring.name and not again.owner
    finally:
        again.close()
    assert os.path.exists(os.path.join(SHM, ring.name))  # an attached handle never unlinks


def _use_inherited_handle(ring: StereoRing, q: mp.Queue) -> None:
    try:
        ring.read()
        q.put("no error")
    except RingError as e:
        q.put(str(e))


# ----------------------------------------------------------------------------- across processes
def _consume_digests(ring: StereoRing, n: int, q: mp.Queue) -> None:
    """Child: read n pairs (the ring arrives pickled, i.e. attached by name)."""
    out = []
    while len(out) < n:
        p = ring.read(timeout_s=10)
        if p is None:
            break
        with p:
            out.append((p.frame_id, p.left_id, p.right_id, p.ts_left_ns, p.ts_right_ns,
                        digest(p.left), digest(p.right)))
    q.put(out)
    # no close(): exiting must not unlink the creator's segment


def test_consumer_in_another_process_reads_exactly_what_was_written(
        make_ring: Callable[..., StereoRing]) -> None:
    n = 24
    ring = make_ring(height=512, width=512, capacity=n)
    want = []
    for i in range(n):
        left, right = pattern(i, (512, 512), 0), pattern(i, (512, 512), 1)
        ring.write(left, right, frame_id=1000 + i, left_id=i, right_id=i + 7,
                   ts_left_ns=i * 10**6, ts_right_ns=i * 10**6 + 3)
        want.append((1000 + i, i, i + 7, i * 10**6, i * 10**6 + 3, digest(left), digest(right)))
    q = CTX.Queue()
    proc = CTX.Process(target=_consume_digests, args=(ring, n, q))
    proc.start()
    got = q.get(timeout=60)
    proc.join(30)
    assert proc.exitcode == 0
    assert got == want
    st = ring.stats()
    assert (st.consumed, st.queued, st.dropped_overflow, st.held) == (n, 0, 0, 0)
    assert os.path.exists(os.path.join(SHM, ring.name))  # still there after the child exited


def _produce(ring: StereoRing, n: int, shape: tuple[int, int], paced_s: float) -> None:
    """Child: write n pairs with id-dependent content, then finish."""
    base_l, base_r = pattern(999_999, shape, 0), pattern(999_999, shape, 1)
    for i in range(n):
        ring.write(base_l ^ np.uint8(i & 255), base_r ^ np.uint8((3 * i) & 255), frame_id=i,
                   ts_left_ns=i, ts_right_ns=-i)
        if paced_s:
            time.sleep(paced_s)
    ring.finish()


def test_no_torn_reads_with_producer_and_consumer_in_separate_processes(
        make_ring: Callable[..., StereoRing]) -> None:
    """A producer process laps the ring as fast as it can while this process reads, checks
    every byte against the pair's id, and sometimes holds a pair for a while before
    checking it again: every pair read is whole, ids increase, and the counters add up."""
    shape, n = (128, 128), 3000
    ring = make_ring(height=shape[0], width=shape[1], capacity=8)
    base_l, base_r = pattern(999_999, shape, 0), pattern(999_999, shape, 1)
    proc = CTX.Process(target=_produce, args=(ring, n, shape, 0.0))
    proc.start()
    rng = np.random.default_rng(0)
    ids, bad, held_long = [], 0, 0
    try:
        while True:
            p = ring.read(timeout_s=30)
            if p is None:
                break
            with p:
                i = p.frame_id
                ok = (np.array_equal(p.left, base_l ^ np.uint8(i & 255))
                      and np.array_equal(p.right, base_r ^ np.uint8((3 * i) & 255))
                      and (p.ts_left_ns, p.ts_right_ns) == (i, -i))
                if rng.random() < 0.1:  # hold it while the producer runs on
                    time.sleep(0.002)
                    held_long += 1
                    ok = ok and np.array_equal(p.left, base_l ^ np.uint8(i & 255))
                bad += not ok
                ids.append(i)
    finally:
        proc.join(60)
    assert proc.exitcode == 0
    st = ring.stats()
    assert bad == 0
    assert all(b > a for a, b in zip(ids, ids[1:]))
    assert st.committed == n and st.consumed == len(ids)
    assert st.consumed + st.dropped_overflow + st.queued == n and st.queued == 0
    assert held_long > 0 and len(ids) > 100
    assert ids[-1] == n - 1  # the newest pair always survives


def test_an_unrelated_process_attaching_does_not_unlink(
        make_ring: Callable[..., StereoRing]) -> None:
    """Python < 3.13's resource tracker would unlink an attached segment at exit."""
    ring = make_ring()
    ring.write(pattern(5, (8, 6), 0), pattern(5, (8, 6), 1), frame_id=5)
    code = ("import sys; from iscd.rig.ringbuffer import StereoRing;"
            "r = StereoRing.attach(sys.argv[1]);"
            "p = r.read(); print(p.frame_id); p.release()")
    out = subprocess.run([sys.executable, "-c", code, ring.name], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "5" and "leaked" not in out.stderr
    assert os.path.exists(os.path.join(SHM, ring.name))
    assert ring.stats().consumed == 1


def test_segment_is_removed_when_its_creator_is_killed() -> None:
    code = ("import sys, time; from iscd.rig.ringbuffer import StereoRing;"
            "r = StereoRing.create(height=64, width=64, capacity=4); print(r.name, flush=True);"
            "time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        name = proc.stdout.readline().strip()  # type: ignore[union-attr]
        assert name.startswith("iscd_ring_")
        assert os.path.exists(os.path.join(SHM, name))
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        # the creator's resource tracker cleans up after it
        wait_until(lambda: not os.path.exists(os.path.join(SHM, name)), 30, interval_s=0.05,
                   what=f"/dev/shm/{name} removed")
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=10)


def test_read_batch_takes_what_is_queued_and_releases_it_at_once(make_ring: Callable[..., StereoRing]) -> None:
    """read_batch: the queued pairs oldest first under one lock (at most max_n, at most
    max_held held), the same pixels and metadata as one read at a time; release_batch
    frees them all (idempotent); an empty ring gives [] after the timeout."""
    ring = make_ring(capacity=8, max_held=4)
    for i in range(6):
        ring.write(pattern(i, (8, 6), 0), pattern(i, (8, 6), 1), frame_id=100 + i, arrival_ns=10 + i)
    got = ring.read_batch(16)
    assert [s.frame_id for s in got] == [100, 101, 102, 103]  # max_held = 4
    assert [s.arrival_ns for s in got] == [10, 11, 12, 13]
    for k, s in enumerate(got):
        assert np.array_equal(s.left, pattern(k, (8, 6), 0)) and np.array_equal(s.right, pattern(k, (8, 6), 1))
        assert not s.left.flags.writeable
    assert ring.stats().held == 4
    for i in range(6, 30):  # the producer laps the ring while they are held
        ring.write(pattern(i, (8, 6), 0), pattern(i, (8, 6), 1), frame_id=100 + i)
    assert np.array_equal(got[3].left, pattern(3, (8, 6), 0))
    ring.release_batch(got)
    ring.release_batch(got)  # idempotent
    assert ring.stats().held == 0 and all(s.released and s.left is None for s in got)
    two = ring.read_batch(2)
    assert [s.frame_id for s in two] == [122, 123]  # the 8 newest were kept
    ring.release_batch(two)
    rest = ring.read_batch(16)
    assert [s.frame_id for s in rest] == [124, 125, 126, 127]
    ring.release_batch(rest)
    assert len(ring.read_batch(16)) == 2
    ring.release_all()
    assert ring.read_batch(4, timeout_s=0.0) == []
