"""Pair left and right camera frames by trigger frame id, verified by timestamp.

Pure logic, no I/O or threads: :class:`StereoPairer` takes the frames of the two cameras
in arrival order (:meth:`StereoPairer.push`) and returns the pairs that are complete, in
increasing frame order. A frame is paired only with the other camera's frame that has the
same (aligned) frame id *and* whose exposure timestamp agrees within a tolerance; anything
else is counted and dropped, never paired with the wrong partner:

* ``unpaired_left`` / ``unpaired_right``: the partner never came within the window (or
  came after a later pair had been emitted, so it could only be emitted out of order);
* ``id_mismatch``: equal ids but timestamps that disagree (both frames dropped);
* ``duplicates_left`` / ``duplicates_right``: an id that camera already delivered;
* ``out_of_order``: a frame with a lower id than one its camera delivered before
  (informational: it is still paired if that can be done in order);
* ``resyncs``: the id alignment was re-learnt from timestamps.

Every frame that is pushed ends up in exactly one of: a pair, ``unpaired_*``,
``id_mismatch``, ``duplicates_*`` or still pending (:attr:`StereoPairer.pending`), so for
each side ``frames = pairs + unpaired + id_mismatch + duplicates + pending``.

Timestamps: ``right.timestamp_ns - left.timestamp_ns - offset`` must be within
``ts_tolerance_ns``. ``offset`` starts at ``ts_offset_ns`` (0 for cameras on one clock, e.g.
host timestamps) or, with ``ts_offset_ns=None``, is learnt from the first id-matched pair
(two free-running device clocks); either way it then follows slow clock drift (±200 ppm)
with an exponential average over accepted pairs. The tolerance must stay below half a
frame period so that a frame can only agree with its own partner.

Resync: when one camera's ids step out of line (a skipped or double-counted trigger, a
counter restarted by reopening the camera), pairs stop forming. After ``resync_after``
consecutive failures the pairer looks for the id shift under which the two cameras' recent
timestamps agree; if the last ``resync_after // 2`` (at least 2) timestamp matches all show
the same non-zero shift, it adopts it and pairing resumes. Pair ids (:attr:`StereoPair.frame_id`)
are the left camera's frame ids, shifted where needed so that they keep increasing across a
left camera restart.

Catching up: a camera whose frames are delivered later than the other's by more than pairing
absorbs (a starved reader thread, a deep driver queue) has its every frame arrive after the
other camera has already given up its partner (``window``, ``max_pending``); as long as that
lag lasts no pair forms, and ids and timestamps both agree, so the resync above has nothing to
re-learn. After ``catch_up_after`` (250) frames in a row of one camera that came after every
frame the other camera still holds (by timestamp), unless that camera is closing the gap (its lag to the
other camera's newest frame shrank by at least one frame for every two of its frames in the
run: a reader draining a backlog, which then pairs within twice the lag), the pairer asks that
camera's reader to skip its backlog up to the other camera's newest frame
(:meth:`StereoPairer.take_catch_up`, :class:`CatchUp`): both re-anchor on their newest frames
(re-anchoring on the other's oldest waiting one would leave the lag at ``max_pending``, still
too long while the other camera moves on). The reader discards those frames
(``Camera.skip_to``) and reports them (:meth:`StereoPairer.skipped`): they are counted unpaired
(``skipped``); the other camera's frames older than the new anchor go as ``overtaken``, and
pairing resumes with the next frame. So a lag that lasts is paired again after at most
``catch_up_after + 1`` of the late camera's reads (a shorter run asked too soon: with 8, a CI
run's short soak skipped 64-73 frames seven times in 75 s on lags of 65-74 ms that a
descheduled reader was draining itself). Lags of more than
:data:`MAX_CATCH_UP_FRAMES` are taken for clocks that disagree, not a late reader, and left
alone.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np

from iscd.drivers.base import Frame

Side = Literal["left", "right"]
_SIDES: tuple[Side, Side] = ("left", "right")
_OTHER: dict[str, Side] = {"left": "right", "right": "left"}


@dataclass(frozen=True)
class StereoPair:
    """A left and a right frame exposed by the same trigger.

    frame_id: the pair's frame index (left camera's id plus its resync shift; increasing).
    """

    frame_id: int
    left: Frame
    right: Frame

    @property
    def ts_delta_ns(self) -> int:
        """Right minus left exposure timestamp, ns."""
        return self.right.timestamp_ns - self.left.timestamp_ns


UNPAIRED_WHY = ("window", "max_pending", "late", "overtaken", "end", "skipped")
"""Why frames went unpaired (:attr:`StereoPairer.unpaired_why`): ``window``: the other camera
got ``window`` frames past it without its partner; ``max_pending``: more than
``max_pending`` frames of its camera waited (the oldest goes); ``late``: it came after a
later pair had gone out; ``overtaken``: it waited while a later pair went out; ``end``:
still waiting at :meth:`StereoPairer.flush`; ``skipped``: discarded unread by its camera's
reader catching up (:meth:`StereoPairer.skipped`)."""

MAX_CATCH_UP_FRAMES = 1 << 16
"""The longest lag, frames, that a catch-up skips (65 s at 1000 fps: longer than any driver
queue); beyond it the two cameras' timestamps are taken to disagree (a clock reset), not a
reader to be late."""


@dataclass(frozen=True)
class CatchUp:
    """What a late camera's reader should skip (:meth:`StereoPairer.take_catch_up`).

    until_ns: discard this camera's frames with a timestamp below it (ns, this camera's
      clock): the other camera's newest frame, less the timestamp tolerance.
    max_frames: at most this many (the lag in frames, plus the pairing window).
    lag_ns: how far behind the frame that triggered it was, ns.
    """

    until_ns: int
    max_frames: int
    lag_ns: int


@dataclass
class PairingCounters:
    """What happened to the pushed frames (see the module docstring)."""

    frames_left: int = 0
    frames_right: int = 0
    pairs: int = 0
    unpaired_left: int = 0
    unpaired_right: int = 0
    id_mismatch: int = 0
    duplicates_left: int = 0
    duplicates_right: int = 0
    out_of_order: int = 0
    resyncs: int = 0
    catch_ups: int = 0
    """times a late camera skipped its backlog (its frames are in ``unpaired_*``)"""

    @property
    def duplicates(self) -> int:
        return self.duplicates_left + self.duplicates_right

    @property
    def frames_dropped(self) -> int:
        """Frames that did not end up in a pair (both cameras)."""
        return (self.unpaired_left + self.unpaired_right + 2 * self.id_mismatch
                + self.duplicates)

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass
class _SideState:
    offset: int = 0  # added to the camera's frame id to get the pair id
    pending: dict[int, Frame] = field(default_factory=dict)  # pair id -> frame
    recent: deque[int] = field(default_factory=deque)  # pair ids seen (duplicate check)
    recent_set: set[int] = field(default_factory=set)
    max_seen: int | None = None
    history: deque[tuple[int, int]] = field(default_factory=deque)  # (camera id, ts_ns)
    behind: int = 0  # frames in a row that came after every frame the other camera holds
    behind_lag0_ns: int = 0  # the first of them: its lag to the other camera's newest frame
    catch_up: CatchUp | None = None  # asked of this camera's reader, not yet taken


class StereoPairer:
    """Pairs frames of a left and a right camera (see the module docstring).

    ts_tolerance_ns: allowed |right - left - offset| timestamp difference, ns (keep it
      below half a frame period: 250 µs suits 1000 fps).
    ts_offset_ns: initial right-minus-left clock offset, ns; ``None`` learns it.
    window: a pending frame is dropped once the other camera is ``window`` frames past it.
    max_pending: at most this many frames wait per camera (a stalled partner camera).
    resync_after: consecutive failures before re-learning the id alignment (0: never).
    catch_up_after: frames of one camera in a row, each later than all the other camera's
      waiting frames, before that camera is asked to catch up (0: never). 250 (a quarter of
      a second at 1000 fps): a reader that was descheduled for a while drains its backlog
      by itself within that (a CI run's short soak with 8 here skipped 64-73 frames seven
      times in 75 s, on lags of 65-74 ms that were passing).
    history: recent (id, timestamp) pairs kept per camera for that.
    retain: called on a frame that must wait for its partner; return a frame that stays
      valid (e.g. with a copied image: drivers may reuse a frame's buffer on the next read).
    clock_gain: weight of each accepted pair in the clock-offset average.
    """

    def __init__(self, *, ts_tolerance_ns: int = 250_000, ts_offset_ns: int | None = 0,
                 window: int = 16, max_pending: int = 64, resync_after: int = 8,
                 history: int = 64, retain: Callable[[Frame], Frame] | None = None,
                 clock_gain: float = 1.0 / 16, catch_up_after: int = 250) -> None:
        if ts_tolerance_ns < 0:
            raise ValueError(f"ts_tolerance_ns must be >= 0, got {ts_tolerance_ns}")
        if window < 1 or max_pending < 1:
            raise ValueError(f"window and max_pending must be >= 1, got {window}, {max_pending}")
        if catch_up_after < 0:
            raise ValueError(f"catch_up_after must be >= 0, got {catch_up_after}")
        if resync_after < 0 or history < 2:
            raise ValueError(f"resync_after must be >= 0 and history >= 2, got "
                             f"{resync_after}, {history}")
        if not 0.0 <= clock_gain <= 1.0:
            raise ValueError(f"clock_gain must be in [0, 1], got {clock_gain}")
        self.ts_tolerance_ns = int(ts_tolerance_ns)
        self._offset: float | None = None if ts_offset_ns is None else float(ts_offset_ns)
        self.window = int(window)
        self.max_pending = int(max_pending)
        self.resync_after = int(resync_after)
        self.catch_up_after = int(catch_up_after)
        self._recent_len = max(4 * self.window, self.max_pending + self.window)
        self._retain = retain
        self._gain = float(clock_gain)
        self._s = {side: _SideState(history=deque(maxlen=int(history))) for side in _SIDES}
        self._last_emitted: int | None = None
        self._fail_run = 0
        self.counters = PairingCounters()
        self.unpaired_why: dict[str, int] = dict.fromkeys(UNPAIRED_WHY, 0)
        """the unpaired frames (both cameras) by cause, :data:`UNPAIRED_WHY`"""

    # ------------------------------------------------------------------ public
    @property
    def ts_offset_ns(self) -> float | None:
        """Current right-minus-left clock offset estimate, ns (None: not learnt yet)."""
        return self._offset

    @property
    def id_offsets(self) -> dict[str, int]:
        """What is added to each camera's frame id to give the pair id."""
        return {side: self._s[side].offset for side in _SIDES}

    @property
    def pending(self) -> dict[str, int]:
        """Frames waiting for their partner, per camera."""
        return {side: len(self._s[side].pending) for side in _SIDES}

    def push_left(self, frame: Frame) -> list[StereoPair]:
        return self.push("left", frame)

    def push_right(self, frame: Frame) -> list[StereoPair]:
        return self.push("right", frame)

    def push(self, side: Side, frame: Frame) -> list[StereoPair]:
        """Add the next frame of camera ``side``; returns the pairs completed by it
        (usually none or one; more after a resync), in increasing ``frame_id``."""
        if side not in _OTHER:
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        c = self.counters
        me, other = self._s[side], self._s[_OTHER[side]]
        setattr(c, f"frames_{side}", getattr(c, f"frames_{side}") + 1)
        me.history.append((int(frame.frame_id), int(frame.timestamp_ns)))
        pid = int(frame.frame_id) + me.offset

        if pid in me.recent_set:
            self._count(f"duplicates_{side}")
            return self._failed()
        self._remember(me, pid)
        if me.max_seen is not None and pid <= me.max_seen:
            c.out_of_order += 1
        else:
            me.max_seen = pid
        if self._last_emitted is not None and pid <= self._last_emitted:
            self._count(f"unpaired_{side}", why="late")  # its pair can no longer go out in order
            self._check_behind(side, frame)
            return self._failed()

        partner = other.pending.pop(pid, None)
        if partner is None:
            me.pending[pid] = self._retain(frame) if self._retain else frame
            expired = self._expire(side)
            self._check_behind(side, frame)
            return self._failed() if expired else []
        left, right = (frame, partner) if side == "left" else (partner, frame)
        pair = self._try_pair(pid, left, right)
        return [pair] if pair is not None else self._failed()

    def take_catch_up(self, side: Side) -> CatchUp | None:
        """What camera ``side``'s reader should skip before its next read (see the module
        docstring, "Catching up"), or None; each request is returned once. The reader
        reports what it discarded with :meth:`skipped`."""
        st = self._s[side]
        cu, st.catch_up = st.catch_up, None
        return cu

    def skipped(self, side: Side, n: int) -> None:
        """Camera ``side``'s reader discarded ``n`` frames unread to catch up: they count as
        its frames and as unpaired (``skipped``)."""
        if side not in _OTHER or n < 0:
            raise ValueError(f"skipped({side!r}, {n}): side must be 'left' or 'right', n >= 0")
        c = self.counters
        setattr(c, f"frames_{side}", getattr(c, f"frames_{side}") + n)
        self._count(f"unpaired_{side}", n, why="skipped")
        c.catch_ups += 1

    def flush(self) -> None:
        """End of stream: count every pending frame as unpaired."""
        for side in _SIDES:
            st = self._s[side]
            self._count(f"unpaired_{side}", len(st.pending), why="end")
            st.pending.clear()

    # ------------------------------------------------------------------ internals
    def _count(self, name: str, n: int = 1, why: str = "") -> None:
        setattr(self.counters, name, getattr(self.counters, name) + n)
        if why:
            self.unpaired_why[why] += n

    def _remember(self, st: _SideState, pid: int) -> None:
        st.recent.append(pid)
        st.recent_set.add(pid)
        while len(st.recent) > self._recent_len:
            st.recent_set.discard(st.recent.popleft())

    def _try_pair(self, pid: int, left: Frame, right: Frame) -> StereoPair | None:
        """Emit (pid, left, right) if the timestamps agree; else count a mismatch."""
        d = float(right.timestamp_ns - left.timestamp_ns)
        if self._offset is None:
            self._offset = d
        resid = d - self._offset
        if abs(resid) > self.ts_tolerance_ns:
            self.counters.id_mismatch += 1
            return None
        self._offset += self._gain * resid
        for side in _SIDES:  # older pending frames can no longer be paired in order
            st = self._s[side]
            old = [k for k in st.pending if k < pid]
            for k in old:
                del st.pending[k]
            self._count(f"unpaired_{side}", len(old), why="overtaken")
        self._last_emitted = pid
        self._fail_run = 0
        for st in self._s.values():
            st.behind = 0
        self.counters.pairs += 1
        return StereoPair(pid, left, right)

    def _expire(self, side: Side) -> int:
        """Drop pending frames whose partner is overdue; returns how many were dropped."""
        n = 0
        for s in _SIDES:
            st, ot = self._s[s], self._s[_OTHER[s]]
            drop = []
            if ot.max_seen is not None:
                drop = [k for k in st.pending if k <= ot.max_seen - self.window]
            for k in drop:
                del st.pending[k]
            self._count(f"unpaired_{s}", len(drop), why="window")
            n_win = len(drop)
            while len(st.pending) > self.max_pending:
                k = min(st.pending)
                del st.pending[k]
                drop.append(k)
            self._count(f"unpaired_{s}", len(drop) - n_win, why="max_pending")
            n += len(drop)
        return n

    def _check_behind(self, side: Side, frame: Frame) -> None:
        """``frame`` of camera ``side`` found no partner: if it is older (timestamp, beyond
        the tolerance) than every frame the other camera still holds, its partner is gone;
        ``catch_up_after`` such frames in a row ask this camera to catch up."""
        me, ot = self._s[side], self._s[_OTHER[side]]
        if not self.catch_up_after or self._offset is None or not ot.pending or me.catch_up is not None:
            return
        off = self._offset if side == "left" else -self._offset  # other's clock -> this one's
        oldest = ot.pending[min(ot.pending)]
        if oldest.timestamp_ns - off - int(frame.timestamp_ns) <= self.ts_tolerance_ns:
            me.behind = 0  # the partner may still be waiting (or only this one was lost)
            return
        t_other = ot.history[-1][1] - off  # the other camera's newest frame
        lag = round(t_other - int(frame.timestamp_ns))
        me.behind += 1
        if me.behind == 1:
            me.behind_lag0_ns = lag
        if me.behind < self.catch_up_after:
            return
        period = self._frame_period_ns(me)
        frames = math.ceil(lag / period) if period else MAX_CATCH_UP_FRAMES + 1
        if frames > MAX_CATCH_UP_FRAMES:
            return  # not a late reader: clocks that disagree
        if (me.behind_lag0_ns - lag) / period >= me.behind / 2:
            return  # closing the gap fast enough: it will pair within twice the first lag
        me.catch_up = CatchUp(until_ns=round(t_other - self.ts_tolerance_ns),
                              max_frames=frames + self.window, lag_ns=round(lag))
        me.behind = 0

    @staticmethod
    def _frame_period_ns(st: _SideState) -> float | None:
        """The shortest timestamp step per frame id in the camera's recent frames, ns."""
        best = None
        h = list(st.history)
        for (i0, t0), (i1, t1) in zip(h, h[1:]):
            if i1 > i0 and t1 > t0:
                p = (t1 - t0) / (i1 - i0)
                best = p if best is None else min(best, p)
        return best

    def _failed(self) -> list[StereoPair]:
        """Note a failure; every ``resync_after`` failures in a row, try to re-align ids."""
        self._fail_run += 1
        if self.resync_after and self._fail_run % self.resync_after == 0:
            return self._resync()
        return []

    def _match_history(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Timestamp matches between the cameras' recent frames: (left id, right id, ts)."""
        if self._offset is None:
            return None
        hl, hr = self._s["left"].history, self._s["right"].history
        if not hl or not hr:
            return None
        lid, lts = np.array(hl, dtype=np.int64).T
        rid, rts = np.array(hr, dtype=np.int64).T
        order = np.argsort(lts, kind="stable")
        lid, lts = lid[order], lts[order]
        want = rts.astype(np.float64) - self._offset  # the left timestamp each right frame needs
        hi = np.clip(np.searchsorted(lts, want), 0, len(lts) - 1)
        lo = np.clip(hi - 1, 0, None)
        j = np.where(np.abs(lts[lo] - want) <= np.abs(lts[hi] - want), lo, hi)
        ok = np.abs(lts[j] - want) <= self.ts_tolerance_ns
        if not ok.any():
            return None
        return lid[j[ok]], rid[ok], rts[ok]

    def _resync(self) -> list[StereoPair]:
        m = self._match_history()
        if m is None:
            return []
        lid, rid, rts = m
        order = np.argsort(rts, kind="stable")
        lid, rid = lid[order], rid[order]
        sl, sr = self._s["left"], self._s["right"]
        delta = (rid + sr.offset) - (lid + sl.offset)  # pair-id disagreement of each match
        need = max(2, self.resync_after // 2)
        if len(delta) < need or np.any(delta[-need:] != delta[-1]) or delta[-1] == 0:
            return []
        d = int(delta[-1])
        # shift the right camera's ids if the left's are current; else (left restarted) the left's
        if self._last_emitted is None or int(lid[-1]) + sl.offset > self._last_emitted:
            side, shift = "right", -d
        else:
            side, shift = "left", d
        st = self._s[side]
        st.offset += shift
        st.pending = {k + shift: f for k, f in st.pending.items()}
        st.recent.clear()
        st.recent_set.clear()
        for k in st.pending:
            self._remember(st, k)
        st.max_seen = max(st.pending, default=None)
        if st.max_seen is None and st.history:
            st.max_seen = st.history[-1][0] + st.offset
        self.counters.resyncs += 1
        self._fail_run = 0
        return self._rematch()

    def _rematch(self) -> list[StereoPair]:
        """After a resync, pair pending frames whose ids now agree, in order."""
        sl, sr = self._s["left"], self._s["right"]
        out = []
        for pid in sorted(set(sl.pending) & set(sr.pending)):
            if pid not in sl.pending or pid not in sr.pending:
                continue  # flushed by an earlier pair of this loop
            left, right = sl.pending.pop(pid), sr.pending.pop(pid)
            if self._last_emitted is not None and pid <= self._last_emitted:
                self._count("unpaired_left", why="late")
                self._count("unpaired_right", why="late")
                continue
            pair = self._try_pair(pid, left, right)
            if pair is not None:
                out.append(pair)
        return out
