"""StereoPairer: frames of two cameras in arrival order -> pairs, never a wrong one.

Every synthetic frame carries its physical trigger index in its 1x1 image, independent of
the (possibly faulty) frame id and of the timestamp, so a test can check that each emitted
pair really was exposed by one trigger. Streams are seeded; arrival order interleaves the
two cameras randomly (each camera in order unless a test reorders it).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np
import pytest

from iscd.drivers.base import Frame
from iscd.rig.pairing import StereoPair, StereoPairer

PERIOD = 1_000_000  # ns: 1000 fps
T0 = 10**12  # ns


def make_frames(side: str, n: int, *, drop: Iterable[int] = (),
                ids: Callable[[int], int] = lambda t: t,
                ts: Callable[[int], int] = lambda t: T0 + t * PERIOD,
                jitter_ns: float = 0.0, seed: int = 0) -> list[Frame]:
    """Frames of one camera for triggers 0..n-1 (minus ``drop``)."""
    rng = np.random.default_rng(seed)
    dropped = set(drop)
    out = []
    for t in range(n):
        if t in dropped:
            continue
        stamp = int(ts(t) + rng.normal(0.0, jitter_ns)) if jitter_ns else int(ts(t))
        out.append(Frame(side, ids(t), stamp, np.array([[t]], dtype=np.int64)))
    return out


def phys(f: Frame) -> int:
    return int(f.image[0, 0])


def interleave(left: Sequence[Frame], right: Sequence[Frame], seed: int, *,
               max_lag: float = 2.5, delay: dict[tuple[str, int], float] | None = None,
               ) -> list[tuple[str, Frame]]:
    """Both cameras' frames in a random arrival order; each camera stays in its own order.

    A frame arrives ``U(0, max_lag)`` frame periods after its trigger, plus ``delay[(side,
    trigger)]`` periods; a camera never delivers a frame before its previous one.
    """
    rng = np.random.default_rng(seed)
    delay = delay or {}
    events = []
    for side, frames in (("left", left), ("right", right)):
        t = np.array([phys(f) for f in frames], dtype=float)
        extra = np.array([delay.get((side, phys(f)), 0.0) for f in frames])
        arrival = np.maximum.accumulate(t + rng.uniform(0, max_lag, len(t)) + extra)
        events += [(a, i, side, f) for i, (a, f) in enumerate(zip(arrival, frames))]
    events.sort(key=lambda e: (e[0], e[1], e[2]))
    return [(side, f) for _, _, side, f in events]


def run(pairer: StereoPairer, events: Iterable[tuple[str, Frame]],
        check_pending: int | None = None) -> list[StereoPair]:
    pairs: list[StereoPair] = []
    for side, f in events:
        pairs += pairer.push(side, f)  # type: ignore[arg-type]
        if check_pending is not None:
            assert max(pairer.pending.values()) <= check_pending
    return pairs


def assert_sound(pairs: list[StereoPair], pairer: StereoPairer, n_left: int, n_right: int,
                 flushed: bool = True) -> None:
    """No wrong pair, increasing ids, and every pushed frame accounted for exactly once."""
    for p in pairs:
        assert phys(p.left) == phys(p.right), \
            f"wrong pair {p.frame_id}: triggers {phys(p.left)} / {phys(p.right)}"
        assert p.left.camera == "left" and p.right.camera == "right"
    ids = [p.frame_id for p in pairs]
    assert all(b > a for a, b in zip(ids, ids[1:])), "pair ids must increase"
    c = pairer.counters
    pend = pairer.pending
    if flushed:
        assert pend == {"left": 0, "right": 0}
    assert c.frames_left == n_left and c.frames_right == n_right
    assert c.pairs == len(pairs)
    assert n_left == (c.pairs + c.unpaired_left + c.id_mismatch + c.duplicates_left
                      + pend["left"])
    assert n_right == (c.pairs + c.unpaired_right + c.id_mismatch + c.duplicates_right
                       + pend["right"])


def test_clean_streams_pair_every_frame_in_order() -> None:
    left, right = make_frames("left", 500), make_frames("right", 500, jitter_ns=20_000, seed=1)
    pairer = StereoPairer()
    pairs = run(pairer, interleave(left, right, seed=2, max_lag=6.0))
    assert [p.frame_id for p in pairs] == list(range(500))
    c = pairer.counters
    assert (c.unpaired_left, c.unpaired_right, c.id_mismatch, c.duplicates, c.out_of_order,
            c.resyncs) == (0, 0, 0, 0, 0, 0)
    assert_sound(pairs, pairer, 500, 500)


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_random_drops_give_exactly_the_common_frames(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 1000
    drop_l = set(np.flatnonzero(rng.random(n) < 0.1).tolist())
    drop_r = set(np.flatnonzero(rng.random(n) < 0.1).tolist())
    left, right = make_frames("left", n, drop=drop_l), make_frames("right", n, drop=drop_r)
    pairer = StereoPairer()
    pairs = run(pairer, interleave(left, right, seed=seed))
    pairer.flush()
    both = sorted(set(range(n)) - drop_l - drop_r)
    assert [p.frame_id for p in pairs] == both
    c = pairer.counters
    assert c.unpaired_left == len(drop_r - drop_l)  # left frames whose right partner was lost
    assert c.unpaired_right == len(drop_l - drop_r)
    assert c.id_mismatch == c.duplicates == c.resyncs == 0
    assert_sound(pairs, pairer, len(left), len(right))


def test_duplicates_are_counted_and_never_paired_twice() -> None:
    n = 300
    right = make_frames("right", n)
    dup_at = [10, 50, 51, 200]
    dups = [right[t] for t in dup_at]
    events = interleave(make_frames("left", n), right, seed=6)
    # each duplicate re-delivered a few events after its original
    for f in dups:
        i = next(k for k, (s, g) in enumerate(events) if g is f)
        events.insert(i + 5, ("right", f))
    pairer = StereoPairer()
    pairs = run(pairer, events)
    pairer.flush()
    assert [p.frame_id for p in pairs] == list(range(n))
    assert pairer.counters.duplicates_right == len(dup_at)
    assert pairer.counters.duplicates_left == 0
    assert_sound(pairs, pairer, n, n + len(dup_at))


@pytest.mark.parametrize("shift", [1, -1, 3, -2])
def test_ids_out_of_step_are_never_paired_wrong_and_resync(shift: int) -> None:
    """From trigger 100 on, the right camera's ids are off by ``shift``: the same ids now
    name frames exposed ``shift`` triggers apart, which only the timestamps reveal."""
    n, at = 600, 100
    left = make_frames("left", n)
    right = make_frames("right", n, ids=lambda t: t + (shift if t >= at else 0))
    pairer = StereoPairer(resync_after=8)
    pairs = run(pairer, interleave(left, right, seed=7))
    pairer.flush()
    assert_sound(pairs, pairer, n, n)
    c = pairer.counters
    assert c.resyncs == 1
    assert c.id_mismatch + c.duplicates_right + c.unpaired_left + c.unpaired_right > 0
    assert pairer.id_offsets == {"left": 0, "right": -shift}
    lost = n - len(pairs)
    assert lost <= 2 * 8 + abs(shift), f"{lost} triggers lost around the fault"
    # after the resync every trigger pairs again, under the left camera's ids
    tail = [p for p in pairs if phys(p.left) >= at + 40]
    assert [p.frame_id for p in tail] == list(range(at + 40, n))


def test_ids_out_of_step_without_resync_pair_nothing_wrong() -> None:
    n, at = 400, 100
    left = make_frames("left", n)
    right = make_frames("right", n, ids=lambda t: t + (1 if t >= at else 0))
    pairer = StereoPairer(resync_after=0)
    pairs = run(pairer, interleave(left, right, seed=8))
    pairer.flush()
    assert_sound(pairs, pairer, n, n)
    assert [p.frame_id for p in pairs] == list(range(at))
    assert pairer.counters.id_mismatch >= n - at - 2
    assert pairer.counters.resyncs == 0


def test_stalled_camera_counts_unpaired_and_resumes() -> None:
    """The right camera delivers nothing for triggers 100..149 (its frames are lost)."""
    n = 400
    left, right = make_frames("left", n), make_frames("right", n, drop=range(100, 150))
    pairer = StereoPairer(max_pending=16)
    pairs = run(pairer, interleave(left, right, seed=9), check_pending=16)
    pairer.flush()
    assert_sound(pairs, pairer, n, n - 50)
    assert pairer.counters.unpaired_left == 50 and pairer.counters.unpaired_right == 0
    assert [p.frame_id for p in pairs] == [*range(100), *range(150, n)]


def test_late_burst_after_a_stall_pairs_what_is_still_pending() -> None:
    """The right camera stalls for 60 ms and then delivers its backlog in a burst: with 16
    left frames allowed to wait, the older partners are gone, the rest pair."""
    n = 300
    left, right = make_frames("left", n), make_frames("right", n)
    delay = {("right", t): 60.0 - (t - 100) for t in range(100, 160)}
    pairer = StereoPairer(max_pending=16)
    pairs = run(pairer, interleave(left, right, seed=10, max_lag=0.5, delay=delay),
                check_pending=16)
    pairer.flush()
    assert_sound(pairs, pairer, n, n)
    c = pairer.counters
    assert c.unpaired_left == c.unpaired_right > 0  # each lost left partner strands a right frame
    assert len(pairs) == n - c.unpaired_left
    assert [p.frame_id for p in pairs][-100:] == list(range(200, n))


@pytest.mark.parametrize("side", ["left", "right"])
def test_camera_restart_resets_ids_and_pairing_resumes(side: str) -> None:
    """One camera is lost for triggers 250..299 and reopened: its ids restart at 0."""
    n = 600
    gone = range(250, 300)
    other = "right" if side == "left" else "left"
    restarted = make_frames(side, n, drop=gone, ids=lambda t: t if t < 250 else t - 300)
    steady = make_frames(other, n)
    left, right = (restarted, steady) if side == "left" else (steady, restarted)
    pairer = StereoPairer()
    pairs = run(pairer, interleave(left, right, seed=11))
    pairer.flush()
    assert_sound(pairs, pairer, len(left), len(right))
    assert pairer.counters.resyncs == 1
    after = [p for p in pairs if phys(p.left) >= 300]
    assert len(after) >= n - 300 - 16
    assert all(p.frame_id == phys(p.left) for p in pairs)  # ids continue across the restart


def test_out_of_order_frames_are_counted_and_paired_in_order() -> None:
    n = 200
    left = make_frames("left", n)
    for i in (20, 80, 150):  # the camera delivers i+1 before i
        left[i], left[i + 1] = left[i + 1], left[i]
    events: list[tuple[str, Frame]] = []
    right = make_frames("right", n)
    for lf, rf in zip(left, right):  # left first at every trigger
        events += [("left", lf), ("right", rf)]
    pairer = StereoPairer()
    pairs = run(pairer, events)
    pairer.flush()
    assert_sound(pairs, pairer, n, n)
    assert pairer.counters.out_of_order == 3
    assert len(pairs) == n  # the right frame came after both, so nothing was lost


def test_learnt_clock_offset_follows_drift() -> None:
    """Free-running device clocks: the right one is 5 s ahead and 200 ppm fast."""
    n = 2000
    left = make_frames("left", n)
    fast = lambda t: int(5e9 + (T0 + t * PERIOD) * (1 + 200e-6))  # noqa: E731
    right = make_frames("right", n, ts=fast)
    events = interleave(left, right, seed=12)
    learnt = StereoPairer(ts_offset_ns=None)
    pairs = run(learnt, events)
    assert len(pairs) == n and learnt.counters.id_mismatch == 0
    end = fast(n - 1) - (T0 + (n - 1) * PERIOD)
    assert learnt.ts_offset_ns == pytest.approx(end, abs=20_000)
    # the same streams against a fixed zero offset, or without tracking the drift
    fixed = StereoPairer(ts_offset_ns=0, resync_after=0)
    assert run(fixed, events) == [] and fixed.counters.id_mismatch == n
    frozen = StereoPairer(ts_offset_ns=None, clock_gain=0.0, resync_after=0)
    got = run(frozen, events)
    assert 0 < len(got) < n  # 250 µs of drift later, the timestamps disagree
    assert_sound(got, frozen, n, n, flushed=False)


def test_memory_stays_bounded_when_one_camera_never_delivers() -> None:
    pairer = StereoPairer(max_pending=8)
    events = [("left", f) for f in make_frames("left", 100)]
    assert run(pairer, events, check_pending=8) == []
    assert pairer.counters.unpaired_left == 92
    pairer.flush()
    assert pairer.counters.unpaired_left == 100


def test_retain_is_called_only_for_frames_that_wait() -> None:
    kept: list[int] = []

    def retain(f: Frame) -> Frame:
        kept.append(f.frame_id)
        return Frame(f.camera, f.frame_id, f.timestamp_ns, f.image.copy())

    pairer = StereoPairer(retain=retain)
    left, right = make_frames("left", 3), make_frames("right", 3)
    out = pairer.push_left(left[0]) + pairer.push_right(right[0])
    assert kept == [0] and out[0].right is right[0] and out[0].left is not left[0]


@pytest.mark.parametrize("seed", range(6))
def test_fuzz_no_wrong_pair_under_mixed_faults(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    n = 800
    at = int(rng.integers(100, 600))
    shift = int(rng.choice([-2, -1, 1, 2]))
    left = make_frames("left", n, drop=np.flatnonzero(rng.random(n) < 0.05).tolist(),
                       jitter_ns=30_000, seed=seed)
    right = make_frames("right", n, drop=np.flatnonzero(rng.random(n) < 0.05).tolist(),
                        ids=lambda t: t + (shift if t >= at else 0), jitter_ns=30_000,
                        seed=seed + 1)
    for i in rng.integers(0, len(left) - 1, 4):  # a few swaps
        left[i], left[i + 1] = left[i + 1], left[i]
    events = interleave(left, right, seed=seed, max_lag=4.0)
    for i in rng.integers(0, len(events), 6):  # a few duplicates
        events.insert(int(i) + 3, events[int(i)])
    pairer = StereoPairer()
    pairs = run(pairer, events, check_pending=pairer.max_pending)
    pairer.flush()
    n_l = sum(s == "left" for s, _ in events)
    assert_sound(pairs, pairer, n_l, len(events) - n_l)
    assert len(pairs) > 0.8 * n


def test_bad_arguments_are_one_line_errors() -> None:
    with pytest.raises(ValueError, match="side"):
        StereoPairer().push("middle", make_frames("left", 1)[0])  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="window"):
        StereoPairer(window=0)
    with pytest.raises(ValueError, match="ts_tolerance_ns"):
        StereoPairer(ts_tolerance_ns=-1)
