"""Acquisition worker: two cameras -> :class:`StereoPairer` -> :class:`StereoRing`.

Runs apart from decoding so that a slow decode step never stalls the cameras: the ring
drops its oldest pair instead of blocking the producer. On a 2-core machine decoding and
acquisition should not share a GIL, so :class:`AcquisitionProcess` runs the worker in a
spawned process that attaches to the ring by name; :class:`Acquisition` alone runs it in
threads of the calling process (tests, replay, single-core use)::

    ring = StereoRing.create(height=512, width=512, capacity=capacity_for(100, 1000))
    acq = AcquisitionProcess(functools.partial(iscd.drivers.registry.make_stereo, cfg), ring,
                             settings=(settings_from_config(cfg, "left"),
                                       settings_from_config(cfg, "right")))
    acq.start()
    ... ring.read() ... acq.stats() ...
    acq.stop(); ring.close()

Inside the worker each camera has its own reader thread (a stalled or reopening camera
never blocks the other); frames go through one lock into the pairer and complete pairs
are copied into the ring. A rig that delivers both frames of a trigger at once
(:class:`iscd.drivers.base.StereoPairSource`, the mock rig without injected faults) instead
fills each ring slot itself from one thread: no pairing and no copies; on any camera
error it falls back to the per-camera readers. A pair source without a clock of its own (the
unpaced mock rig: ``waits_for_consumer``) is waited for: the worker waits for room in the ring
instead of letting it drop its oldest pair. Cameras without a clock of their own
(``Camera.waits_for_consumer``; the unpaced mock rig with injected faults) are read in step:
a reader more than ``STEP_LEAD_FRAMES`` frame periods ahead of its running partner (by
timestamp) waits for it, and both wait for room in the ring. A frame that must wait for its partner is copied first (drivers
may reuse the buffer on the next read). Camera faults never end the worker:

* :class:`CameraTimeout`: counted (``timeouts_<side>``), reading goes on;
* :class:`CameraLost` (or ``max_errors`` other errors in a row, or an unexpected
  exception, logged with its traceback): counted (``lost_<side>``), logged, the camera is
  closed and reopened with exponential backoff (``reopen_backoff_s`` doubling up to
  ``reopen_backoff_max_s``; ``open_failures_<side>``, ``reopens_<side>``). A reopened
  camera's frame ids may restart: the pairer re-learns the alignment from timestamps.

A reader that falls behind its partner by more than pairing absorbs (``max_pending``) would
never pair again while the lag lasts; the pairer then asks it to catch up
(:meth:`StereoPairer.take_catch_up`): before its next read it discards its camera's backlog up
to the other camera's newest frame (``Camera.skip_to``), the frames counted unpaired
(``skipped``) and the catch-up said in one log line (at most one a second, the rest counted
into the next).

Counters are published into the ring's ``aux`` words (shared memory), so the consumer
reads them with :meth:`AcquisitionStats.from_ring` whether the worker is a thread or a
process; ``heartbeat_ns`` (``time.monotonic_ns``) shows that the worker is alive.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import signal
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from iscd.core.config import config_section
from iscd.drivers.base import Camera, CameraError, CameraLost, CameraSettings, CameraTimeout, Frame, StereoPairSource
from iscd.rig.pairing import UNPAIRED_WHY, CatchUp, StereoPairer
from iscd.rig.ringbuffer import RingError, StereoRing

log = logging.getLogger(__name__)

__all__ = ["Acquisition", "AcquisitionOptions", "AcquisitionProcess", "AcquisitionStats",
           "CameraFactory"]

CameraFactory = Callable[[], tuple[Camera, Camera]]
"""Builds the (left, right) cameras, not opened. Must be picklable for a process worker
(a module-level function or ``functools.partial`` of one)."""

_SIDES = ("left", "right")
STEP_LEAD_FRAMES = 4
"""How far (frame periods, by timestamp) a camera that waits for its consumer may read
ahead of its partner before it waits for it (well inside the pairing window)."""

FIRST_FRAME_WAIT_S = 2.0
"""A camera that waits for its consumer reads at most ``STEP_LEAD_FRAMES`` past its own first
frame while its running partner has delivered none yet, for at most this long after the
partner came up (a partner that never delivers does not stop it for good). Before, only a
partner's delivered frames held it back: on a loaded host whose scheduler started one
reader thread late, the other ran 30-200 frames ahead, and the first frames of both
cameras then fell out of the pairing window unpaired."""


def _opt(default: Any, doc: str, lo: float | None = None, lo_open: bool = False,
         hi: float | None = None) -> Any:
    return field(default=default, metadata={"lo": lo, "lo_open": lo_open, "hi": hi, "doc": doc})


@config_section("acquisition")
@dataclass(frozen=True)
class AcquisitionOptions:
    """Camera reads, pairing and reopening in the acquisition process.

    The daemon hands it to :class:`AcquisitionProcess`."""

    read_timeout_s: float = _opt(0.1, "longest wait in one camera read, s (also the stop latency)",
                                 lo=0, lo_open=True)
    ts_tolerance_s: float = _opt(0.0, "allowed left/right exposure-time difference, s "
                                 "(0 = a quarter of the frame period)", lo=0)
    ts_offset_s: float = _opt(0.0, "right-minus-left camera clock offset, s (for cameras on "
                              "one clock: 0)")
    learn_ts_offset: bool = _opt(False, "learn the clock offset from the first pair "
                                 "(free-running device clocks)")
    pair_window: int = _opt(16, "frames (1..4096) a camera may run ahead of a waiting frame "
                            "before that frame's partner counts as lost", lo=1, hi=4096)
    max_pending: int = _opt(64, "frames (1..4096) that may wait for their partner, per camera: "
                            "the longest skew between the two cameras' readers that pairing "
                            "absorbs (each waiting frame holds a copy of its image, 256 KiB at "
                            "512x512 8-bit)", lo=1, hi=4096)
    resync_after: int = _opt(8, "failed frames in a row before re-learning the id "
                             "alignment (0 = never)", lo=0)
    catch_up_after: int = _opt(250, "frames of a camera in a row that came after all the other's "
                               "waiting frames before its reader skips its backlog (0 = never; "
                               "a reader that was held up drains its backlog itself before that)",
                               lo=0)
    reopen_backoff_s: float = _opt(0.05, "first wait before reopening a lost camera, s",
                                   lo=0)
    reopen_backoff_max_s: float = _opt(2.0, "longest wait between reopen attempts, s", lo=0)
    max_errors: int = _opt(10, "camera errors in a row that count as a lost camera", lo=1)
    copy_frames: bool = _opt(True, "copy frames that wait for their partner (false only "
                             "for drivers that never reuse buffers; drivers that say so "
                             "themselves, the mock rig, are never copied)")
    one_cpu_readers: bool = _opt(True, "run the two reader threads on one CPU when both cameras "
                                 "make their images on the CPU as they are read (the mock rig "
                                 "with injected faults): CPU-bound threads that share the GIL "
                                 "cost less on one core than handing it across two")
    stats_interval_s: float = _opt(0.005, "how often the counters are published, s", lo=0)
    finish_ring: bool = _opt(True, "mark the ring finished when the worker stops")
    pairs_at_once: bool = _opt(True, "let a rig that delivers both frames of a trigger at once "
                               "(iscd.drivers.base.StereoPairSource: the mock rig) fill the ring "
                               "slots itself (no pairing, no copies)")

    def tolerance_ns(self, fps: float | None) -> int:
        """Timestamp tolerance in ns: the option, or a quarter frame period (250 µs at
        1000 fps; 250 µs when the frame rate is unknown)."""
        if self.ts_tolerance_s > 0:
            return round(self.ts_tolerance_s * 1e9)
        return round(0.25e9 / fps) if fps else 250_000


@dataclass
class AcquisitionStats:
    """Counters of the acquisition worker (frames unless noted)."""

    frames_left: int = 0
    frames_right: int = 0
    pairs_written: int = 0
    unpaired_left: int = 0
    unpaired_right: int = 0
    id_mismatch: int = 0
    duplicates_left: int = 0
    duplicates_right: int = 0
    out_of_order: int = 0
    resyncs: int = 0
    catch_ups: int = 0
    """times a late camera's reader skipped its backlog (the frames are in ``unpaired_*``)"""
    timeouts_left: int = 0
    timeouts_right: int = 0
    errors_left: int = 0
    errors_right: int = 0
    lost_left: int = 0
    lost_right: int = 0
    open_failures_left: int = 0
    open_failures_right: int = 0
    reopens_left: int = 0
    reopens_right: int = 0
    bad_frames_left: int = 0
    """wrong size or pixel type for the ring"""
    bad_frames_right: int = 0
    ring_errors: int = 0
    fps_mhz_left: int = 0
    """the frame rate the left camera reported after its last configure, mHz (0: not yet,
    or no settings applied); a device may clamp what the config asks"""
    fps_mhz_right: int = 0
    state: int = 0
    """0 starting, 1 running, 2 stopped, 3 failed"""
    heartbeat_ns: int = 0
    pid: int = 0

    STARTING, RUNNING, STOPPED, FAILED = 0, 1, 2, 3

    @property
    def frames_dropped(self) -> int:
        """Frames that did not reach the ring in a pair (before ring overflow)."""
        return (self.unpaired_left + self.unpaired_right + 2 * self.id_mismatch
                + self.duplicates_left + self.duplicates_right + self.bad_frames_left
                + self.bad_frames_right)

    @classmethod
    def n_words(cls) -> int:
        return len(fields(cls))

    def to_array(self, out: np.ndarray) -> None:
        out[: self.n_words()] = [getattr(self, f.name) for f in fields(self)]

    @classmethod
    def from_array(cls, arr: np.ndarray) -> "AcquisitionStats":
        vals = arr[: cls.n_words()].tolist()
        return cls(**{f.name: int(v) for f, v in zip(fields(cls), vals)})

    @classmethod
    def from_ring(cls, ring: StereoRing) -> "AcquisitionStats":
        """The counters the worker feeding ``ring`` published last."""
        return cls.from_array(ring.aux)

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


class PairingReport:
    """Says in the log, at most once every :attr:`every_s` (and only when it happened), that
    frames found no partner since the last line, how many per camera and why (the pairer's
    :data:`~iscd.rig.pairing.UNPAIRED_WHY`, and ``timestamps disagree``: equal ids, both
    dropped), naming the ``[acquisition]`` keys that decide it, e.g. ``pairing: 36 left and 36
    right frames of 200 + 200 found no partner in the last 1.0 s (window 36, max_pending 36;
    [acquisition] pair_window = 16, max_pending = 64 frames: ...)``. ``clock``: seconds,
    monotonic (tests hand it a fake one)."""

    every_s = 1.0

    def __init__(self, pairer: StereoPairer, clock: Callable[[], float] = time.monotonic) -> None:
        self.pairer = pairer
        self.clock = clock
        self._t = clock()
        self._seen = self._now()
        self.said = 0
        """lines written so far"""
        self._t_catch_up: float | None = None
        self._quiet_catch_ups = [0, 0]  # catch-ups and frames skipped since the last such line

    def caught_up(self, side: str, skipped: int, cu: CatchUp) -> bool:
        """Camera ``side``'s reader skipped ``skipped`` frames (``cu``: what was asked): one
        line, at most one every :attr:`every_s` (those in between are counted into the
        next). True when it wrote a line."""
        t = self.clock()
        self._quiet_catch_ups[0] += 1
        self._quiet_catch_ups[1] += skipped
        if self._t_catch_up is not None and t - self._t_catch_up < self.every_s:
            return False
        n, frames = self._quiet_catch_ups
        self._t_catch_up, self._quiet_catch_ups = t, [0, 0]
        more = (f" ({n - 1} more catch-ups, {frames - skipped} frames, since the last such line)"
                if n > 1 else "")
        log.warning("pairing: the %s camera's frames came %.3f s after the other camera's (more than "
                    "pairing absorbs: [acquisition] max_pending = %d frames); skipped %d of them "
                    "to re-anchor on the other camera's newest frame%s",
                    side, cu.lag_ns / 1e9, self.pairer.max_pending, skipped, more)
        self.said += 1
        return True

    def _now(self) -> tuple[int, ...]:
        c, why = self.pairer.counters, self.pairer.unpaired_why
        return (c.frames_left, c.frames_right, c.unpaired_left, c.unpaired_right, c.id_mismatch,
                *(why[k] for k in UNPAIRED_WHY))

    def check(self) -> bool:
        """Called after each frame; True when it wrote a line."""
        t = self.clock()
        if t - self._t < self.every_s:
            return False
        now = self._now()
        d = [a - b for a, b in zip(now, self._seen)]
        dt, self._t, self._seen = t - self._t, t, now
        if d[2] + d[3] + d[4] <= 0:
            return False
        p = self.pairer
        why = ", ".join([f"{k} {n}" for k, n in zip(UNPAIRED_WHY, d[5:]) if n]
                        + ([f"timestamps disagree {d[4]} + {d[4]}"] if d[4] else []))
        log.warning("pairing: %d left and %d right frames of %d + %d found no partner in the last %.1f s "
                    "(%s; [acquisition] pair_window = %d, max_pending = %d frames: raise them if one "
                    "camera's frames come that many frames after the other's)",
                    d[2] + d[4], d[3] + d[4], d[0], d[1], dt, why, p.window, p.max_pending)
        self.said += 1
        return True


def _this_cpu() -> int | None:
    """The CPU the calling thread runs on now, if it may run on more than one (else None:
    nothing to choose)."""
    try:
        allowed = os.sched_getaffinity(0)
        if len(allowed) < 2:
            return None
        with open("/proc/thread-self/stat", "rb") as f:
            stat = f.read()
        cpu = int(stat[stat.rindex(b")") + 2:].split()[36])  # field 39, "processor"
        return cpu if cpu in allowed else min(allowed)
    except (AttributeError, OSError, ValueError, IndexError):  # not Linux: leave it free
        return None


def _pin_thread(cpu: int) -> None:
    """Let the calling thread (only it: Linux affinity is per thread) run on ``cpu`` only."""
    try:
        os.sched_setaffinity(0, {cpu})
    except (AttributeError, OSError, ValueError) as e:  # a cpuset changed meanwhile
        log.debug("cannot pin reader thread to CPU %d: %s", cpu, e)


def _retain(frame: Frame) -> Frame:
    return dataclasses.replace(frame, image=np.array(frame.image, copy=True))


class Acquisition:
    """The worker: reads ``left`` and ``right`` (one thread each), pairs, writes ``ring``.

    settings: (left, right) :class:`CameraSettings` applied after every open (None: leave
      the camera as it is).
    The cameras are opened, started, stopped and closed by the worker.
    """

    def __init__(self, left: Camera, right: Camera, ring: StereoRing, *,
                 settings: tuple[CameraSettings | None, CameraSettings | None] = (None, None),
                 options: AcquisitionOptions | None = None) -> None:
        if ring.aux.size < AcquisitionStats.n_words():
            raise RingError(f"ring has {ring.aux.size} aux words, the acquisition needs "
                            f"{AcquisitionStats.n_words()}")
        self.cams = {"left": left, "right": right}
        self.ring = ring
        self.settings = dict(zip(_SIDES, settings))
        self.options = opt = options or AcquisitionOptions()
        fps = next((s.fps for s in settings if s is not None), None)
        tol = opt.tolerance_ns(fps)
        if fps and tol >= 0.5e9 / fps:
            raise ValueError(f"ts_tolerance_s = {tol / 1e9:g} s must be below half the frame "
                             f"period ({0.5 / fps:g} s), or frames could pair with a neighbour")
        self.pairer = StereoPairer(
            ts_tolerance_ns=tol,
            ts_offset_ns=None if opt.learn_ts_offset else round(opt.ts_offset_s * 1e9),
            window=opt.pair_window, max_pending=opt.max_pending, resync_after=opt.resync_after,
            catch_up_after=opt.catch_up_after,
            retain=_retain if opt.copy_frames and any(
                getattr(cam, "reuses_buffers", True) for cam in (left, right)) else None)
        self.pairing_report = PairingReport(self.pairer)
        self._stats = AcquisitionStats(pid=os.getpid())
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._readers: list[threading.Thread] = []
        self._last_publish = 0.0
        self._shape = (ring.height, ring.width)
        self._warned_bad = {side: False for side in _SIDES}
        self._step_lead_ns = round(STEP_LEAD_FRAMES * 1e9 / fps) if fps else STEP_LEAD_FRAMES * 1_000_000
        self._last_ts: dict[str, int | None] = {side: None for side in _SIDES}
        """timestamp of each camera's last frame read (ns), for reading in step"""
        self._first_ts: dict[str, int | None] = {side: None for side in _SIDES}
        """each camera's first frame's timestamp, ns (FIRST_FRAME_WAIT_S)"""
        self._up_since: dict[str, float] = {side: 0.0 for side in _SIDES}
        """time.monotonic() when each camera was last brought up"""
        self._reader_cpu: int | None = None
        """the CPU both reader threads run on (``one_cpu_readers``), None: any"""
        self._up = {side: False for side in _SIDES}
        """whether each camera's reader has its camera running"""
        self._publish(force=True)

    # ------------------------------------------------------------------ control
    def start(self) -> None:
        """Run :meth:`run` in a background thread of this process."""
        if self._thread is not None:
            raise RuntimeError("acquisition already started")
        self._thread = threading.Thread(target=self.run, name="iscd-acquisition", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> AcquisitionStats:
        """Ask the worker to stop; wait for the background thread (if any)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        return self.stats()

    def stats(self) -> AcquisitionStats:
        """The counters now (also published to the ring)."""
        with self._lock:
            self._publish(force=True)
            return dataclasses.replace(self._stats)

    def run(self, stop: threading.Event | Any | None = None, duration_s: float | None = None,
            ) -> AcquisitionStats:
        """Acquire until ``stop`` is set (or :meth:`stop` is called, or ``duration_s`` s
        have passed). Never raises for camera trouble; returns the final counters."""
        ext = stop
        st = self._stats
        try:
            up = {}
            for side in ("right", "left"):  # the trigger slave first, then the master
                up[side] = self._bring_up(side, first=True)
            with self._lock:
                st.state = AcquisitionStats.RUNNING
                self._publish(force=True)
            src = self._pair_source() if up["left"] and up["right"] else None
            if src is not None:  # both frames of a trigger at once, straight into the ring
                self._readers = [threading.Thread(target=self._pair_reader, args=(src,),
                                                  name="iscd-read-pairs", daemon=True)]
                self._readers[0].start()
            else:
                self._start_readers(up)
            readers = self._readers
            deadline = None if duration_s is None else time.monotonic() + duration_s
            while not self._stop.is_set():
                if ext is not None and ext.is_set():
                    break
                if deadline is not None and time.monotonic() >= deadline:
                    break
                self._stop.wait(0.05)
                with self._lock:
                    self._publish()
            self._stop.set()
            for t in list(self._readers):
                t.join(self.options.read_timeout_s + 5.0)
                if t.is_alive():
                    log.error("%s: a camera read did not return; abandoning its thread", t.name)
            final = AcquisitionStats.STOPPED
        except BaseException:
            log.exception("acquisition worker failed")
            final = AcquisitionStats.FAILED
            self._stop.set()
            raise
        finally:
            for side in _SIDES:
                self._shut(side)
            with self._lock:
                self.pairer.flush()
                st.state = final
                self._publish(force=True)
            if self.options.finish_ring:
                try:
                    self.ring.finish()
                except RingError as e:
                    log.warning("cannot mark the ring finished: %s", e)
        return self.stats()

    # ------------------------------------------------------------------ camera handling
    def _bump(self, name: str, n: int = 1) -> None:
        with self._lock:
            setattr(self._stats, name, getattr(self._stats, name) + n)

    def _bring_up(self, side: str, first: bool = False) -> bool:
        """Open, configure and start one camera; False (counted, logged) on failure."""
        cam = self.cams[side]
        try:
            cam.open()
            s = self.settings[side]
            if s is not None:
                accepted = cam.configure(s)
                fps = getattr(accepted, "fps", None)
                if isinstance(fps, (int, float)) and fps > 0 and fps == fps and fps < 1e9:
                    # published: the daemon checks what the device runs at, not what was asked
                    with self._lock:
                        setattr(self._stats, f"fps_mhz_{side}", round(fps * 1000))
                        self._publish(force=True)
            cam.start()
        except Exception as e:  # noqa: BLE001 - any driver failure means "not up yet"
            self._bump(f"open_failures_{side}")
            log.warning("%s camera: cannot %s: %s", side, "open" if first else "reopen", e)
            self._shut(side)
            return False
        self._up[side] = True
        self._up_since[side] = time.monotonic()
        if not first:
            self._bump(f"reopens_{side}")
            log.info("%s camera reopened", side)
        return True

    def _shut(self, side: str) -> None:
        self._up[side] = False
        cam = self.cams[side]
        for what in (cam.stop, cam.close):
            try:
                what()
            except Exception as e:  # noqa: BLE001
                log.debug("%s camera: %s failed: %s", side, what.__name__, e)

    def _start_readers(self, up: dict[str, bool]) -> None:
        """One reader thread per camera (frames one by one, paired by the pairer); both on
        one CPU where both cameras make their images as they are read (``one_cpu_readers``)."""
        if (self.options.one_cpu_readers and self._reader_cpu is None
                and all(getattr(cam, "makes_images_on_read", False) for cam in self.cams.values())):
            self._reader_cpu = _this_cpu()
            if self._reader_cpu is not None:
                log.info("both cameras make their images on the CPU: their readers share CPU %d",
                         self._reader_cpu)
        ts = [threading.Thread(target=self._reader, args=(side, up[side]),
                               name=f"iscd-read-{side}", daemon=True) for side in _SIDES]
        self._readers += ts
        for t in ts:
            t.start()

    def _pair_source(self) -> StereoPairSource | None:
        """The cameras' :class:`StereoPairSource`, if both offer the same one and the ring
        holds their frames' shape and dtype (else frames go one by one)."""
        if not self.options.pairs_at_once:
            return None
        try:
            src = self.cams["left"].pair_source()
            other = self.cams["right"].pair_source()
        except Exception as e:  # noqa: BLE001 - a driver bug: use the frame-by-frame path
            log.debug("pair source unavailable: %s", e)
            return None
        return src if src is not None and src is other else None

    def _pair_reader(self, src: StereoPairSource) -> None:
        """Pairs at once: each ring slot is filled by the source itself (no pairing, no
        copies). Timeouts are counted; any camera error falls back to the per-camera
        readers, which handle losses and reopening."""
        opt = self.options
        ring, c = self.ring, self.pairer.counters
        wait = bool(getattr(src, "waits_for_consumer", False))
        while not self._stop.is_set():
            if wait and not self._wait_for_room():
                break
            slot = ring.reserve()
            try:
                meta = src.read_pair_into(slot.left, slot.right, timeout_s=opt.read_timeout_s)
            except CameraTimeout:
                self._bump("timeouts_left")
                self._bump("timeouts_right")
                continue
            except Exception as e:  # noqa: BLE001 - CameraError/Lost or a driver bug
                ring.abort(slot)
                log.info("pairs at once stopped (%s); reading the cameras one by one", e)
                self._start_readers({"left": True, "right": True})
                return
            arrival = time.monotonic_ns()
            with self._lock:
                try:
                    ring.commit(slot, frame_id=meta.left_id, ts_left_ns=meta.ts_left_ns,
                                ts_right_ns=meta.ts_right_ns, left_id=meta.left_id,
                                right_id=meta.right_id, arrival_ns=arrival)
                    self._stats.pairs_written += 1
                except RingError as e:
                    self._stats.ring_errors += 1
                    log.warning("cannot write pair %d to the ring: %s", meta.left_id, e)
                c.frames_left += 1
                c.frames_right += 1
                self._publish()

    def _wait_for_room(self) -> bool:
        """Sleep until the ring has room for one more pair (for a source that waits for the
        consumer, :attr:`~iscd.drivers.base.StereoPairSource.waits_for_consumer`: nothing is
        dropped); False if the acquisition was stopped meanwhile."""
        ring = self.ring
        return self._wait_while(lambda: ring.queued >= ring.capacity)

    def _in_step(self, side: str) -> bool:
        """For a camera that waits for its consumer: sleep while the ring is full or this
        camera is more than ``STEP_LEAD_FRAMES`` ahead of its running partner (nothing is
        dropped, and the pairer sees the two cameras' frames close together); False if the
        acquisition was stopped meanwhile."""
        other = "right" if side == "left" else "left"
        ring, last = self.ring, self._last_ts

        def blocked() -> bool:
            mine, theirs = last[side], last[other]
            if theirs is not None:
                ahead = self._up[other] and mine is not None and mine - theirs > self._step_lead_ns
            else:  # the partner has delivered nothing yet: stay near this camera's first frame
                first = self._first_ts[side]
                ahead = (self._up[other] and mine is not None and first is not None
                         and mine - first > self._step_lead_ns
                         and time.monotonic() - self._up_since[other] < FIRST_FRAME_WAIT_S)
            return ahead or ring.queued >= ring.capacity

        return self._wait_while(blocked)

    def _wait_while(self, blocked: Callable[[], bool]) -> bool:
        """Sleep (50 us doubling to 1 ms) while ``blocked()``; False if the acquisition was
        stopped meanwhile. The counters (and the heartbeat) are published while it waits."""
        delay = 50e-6
        while blocked():
            if self._stop.wait(delay):
                return False
            delay = min(2 * delay, 1e-3)
            with self._lock:
                self._publish()
        return True

    def _reader(self, side: str, running: bool) -> None:
        opt = self.options
        cam = self.cams[side]
        in_step = bool(getattr(cam, "waits_for_consumer", False))
        backoff = opt.reopen_backoff_s
        errors_in_row = 0
        first = not running
        if self._reader_cpu is not None:
            _pin_thread(self._reader_cpu)
        while not self._stop.is_set():
            if in_step and running and not self._in_step(side):
                break
            if not running:
                if self._stop.wait(backoff):
                    break
                backoff = min(max(backoff * 2, 1e-3), opt.reopen_backoff_max_s)
                running = self._bring_up(side, first=first)
                if running:
                    first = False
                    backoff = opt.reopen_backoff_s
                continue
            try:
                frame = self._next_frame(side, cam)
                if frame is None:
                    continue
            except CameraTimeout:
                self._bump(f"timeouts_{side}")
                continue
            except CameraLost as e:
                self._lost(side, f"lost: {e}")
                running = False
                continue
            except CameraError as e:
                self._bump(f"errors_{side}")
                errors_in_row += 1
                log.debug("%s camera: read error: %s", side, e)
                if errors_in_row >= opt.max_errors:
                    self._lost(side, f"{errors_in_row} read errors in a row, last: {e}")
                    running = False
                continue
            except Exception as e:  # noqa: BLE001 - a driver bug must not end acquisition
                self._bump(f"errors_{side}")
                log.exception("%s camera: unexpected error in read", side)
                self._lost(side, f"unexpected {type(e).__name__}: {e}")
                running = False
                continue
            errors_in_row = 0
            self._last_ts[side] = frame.timestamp_ns
            if self._first_ts[side] is None:
                self._first_ts[side] = frame.timestamp_ns
            self._handle(side, frame, time.monotonic_ns())

    def _next_frame(self, side: str, cam: Camera) -> Frame | None:
        """The camera's next frame for the pairer; first, if the pairer asked this camera to
        catch up, its backlog skipped (counted and said; None if no frame followed it within
        the read timeout). Raises what ``cam.read`` raises."""
        timeout_s = self.options.read_timeout_s
        with self._lock:
            cu = self.pairer.take_catch_up(side)  # type: ignore[arg-type]
        if cu is None:
            return cam.read(timeout_s=timeout_s)
        n, frame = cam.skip_to(cu.until_ns, timeout_s=timeout_s, max_frames=cu.max_frames)
        with self._lock:
            self.pairer.skipped(side, n)  # type: ignore[arg-type]
            self.pairing_report.caught_up(side, n, cu)
            self._publish()
        return frame

    def _lost(self, side: str, why: str) -> None:
        self._bump(f"lost_{side}")
        log.warning("%s camera %s; reopening", side, why)
        self._shut(side)

    def _handle(self, side: str, frame: Frame, arrival_ns: int) -> None:
        img = frame.image
        with self._lock:
            if (not isinstance(img, np.ndarray) or img.shape != self._shape
                    or img.dtype != self.ring.dtype):
                setattr(self._stats, f"bad_frames_{side}",
                        getattr(self._stats, f"bad_frames_{side}") + 1)
                if not self._warned_bad[side]:
                    self._warned_bad[side] = True
                    got = (f"{img.shape} {img.dtype}" if isinstance(img, np.ndarray)
                           else type(img).__name__)
                    log.warning("%s camera delivers %s images, the ring holds %s %s: dropped",
                                side, got, self._shape, self.ring.dtype)
                return
            pairs = self.pairer.push(side, frame)  # type: ignore[arg-type]
            self.pairing_report.check()
            for pair in pairs:
                try:
                    self.ring.write(pair.left.image, pair.right.image, frame_id=pair.frame_id,
                                    ts_left_ns=pair.left.timestamp_ns,
                                    ts_right_ns=pair.right.timestamp_ns,
                                    left_id=pair.left.frame_id, right_id=pair.right.frame_id,
                                    arrival_ns=arrival_ns)
                    self._stats.pairs_written += 1
                except (RingError, ValueError) as e:
                    self._stats.ring_errors += 1
                    log.warning("cannot write pair %d to the ring: %s", pair.frame_id, e)
            self._publish()

    def _publish(self, force: bool = False) -> None:
        """Copy the counters into the ring (call with ``_lock`` held)."""
        now = time.monotonic()
        if not force and now - self._last_publish < self.options.stats_interval_s:
            return
        self._last_publish = now
        st, c = self._stats, self.pairer.counters
        st.frames_left, st.frames_right = c.frames_left, c.frames_right
        st.unpaired_left, st.unpaired_right = c.unpaired_left, c.unpaired_right
        st.id_mismatch, st.out_of_order, st.resyncs = c.id_mismatch, c.out_of_order, c.resyncs
        st.catch_ups = c.catch_ups
        st.duplicates_left, st.duplicates_right = c.duplicates_left, c.duplicates_right
        st.frames_left += st.bad_frames_left
        st.frames_right += st.bad_frames_right
        st.heartbeat_ns = time.monotonic_ns()
        try:
            st.to_array(self.ring.aux)
        except (RingError, TypeError, ValueError) as e:  # ring closed under us
            log.debug("cannot publish acquisition stats: %s", e)


# ---------------------------------------------------------------------- process worker
def _watch_parent(stop: Any) -> None:
    parent = multiprocessing.parent_process()
    if parent is not None:
        parent.join()  # returns when the parent process is gone
        log.warning("parent process ended: stopping acquisition")
        stop.set()


def _process_main(factory: CameraFactory, ring: StereoRing,
                  settings: tuple[CameraSettings | None, CameraSettings | None],
                  options: AcquisitionOptions, stop: Any, log_level: int) -> None:
    """Entry point of the spawned worker (``ring`` arrives attached by name). SIGINT is
    ignored: Ctrl-C reaches the whole process group, and the daemon stops this worker
    itself (``stop``), after its final records."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=log_level,
                        format="%(asctime)s %(levelname)s %(processName)s %(name)s: %(message)s")
    threading.Thread(target=_watch_parent, args=(stop,), daemon=True,
                     name="iscd-parent-watch").start()
    try:
        left, right = factory()
    except Exception as e:  # noqa: BLE001 - reported in the shared counters, exit status 3
        if isinstance(e, (CameraError, ValueError)):  # bad rig config: one line, no traceback
            log.error("cannot build the cameras: %s", e)
        else:
            log.exception("cannot build the cameras")
        st = AcquisitionStats(state=AcquisitionStats.FAILED, pid=os.getpid(),
                              heartbeat_ns=time.monotonic_ns())
        st.to_array(ring.aux)
        if options.finish_ring:
            ring.finish()
        raise SystemExit(3) from None
    Acquisition(left, right, ring, settings=settings, options=options).run(stop)
    ring.close()


class AcquisitionProcess:
    """The worker in a spawned process (its own GIL), feeding ``ring`` by name.

    factory: picklable callable returning (left, right) cameras, called in the child.
    """

    def __init__(self, factory: CameraFactory, ring: StereoRing, *,
                 settings: tuple[CameraSettings | None, CameraSettings | None] = (None, None),
                 options: AcquisitionOptions | None = None) -> None:
        if ring.aux.size < AcquisitionStats.n_words():
            raise RingError(f"ring has {ring.aux.size} aux words, the acquisition needs "
                            f"{AcquisitionStats.n_words()}")
        self.ring = ring
        self.options = options or AcquisitionOptions()
        ctx = multiprocessing.get_context("spawn")
        self._stop = ctx.Event()
        AcquisitionStats(pid=0).to_array(ring.aux)
        self._proc = ctx.Process(
            target=_process_main, name="iscd-acquisition", daemon=True,
            args=(factory, ring, settings, self.options, self._stop,
                  logging.getLogger().getEffectiveLevel()))

    def start(self) -> None:
        self._proc.start()

    def stats(self) -> AcquisitionStats:
        """The counters the worker published last (see :class:`AcquisitionStats`)."""
        return AcquisitionStats.from_ring(self.ring)

    def is_alive(self) -> bool:
        return self._proc.is_alive()

    @property
    def exitcode(self) -> int | None:
        return self._proc.exitcode

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def request_stop(self) -> None:
        """Ask the worker to stop without waiting (it marks the ring finished when done)."""
        self._stop.set()

    def stop(self, timeout_s: float = 10.0) -> AcquisitionStats:
        """Ask the worker to stop and wait; a worker that does not stop within
        ``timeout_s`` s is terminated (then killed). Returns the final counters."""
        self._stop.set()
        if self._proc.pid is not None:
            self._proc.join(timeout_s)
            if self._proc.is_alive():
                log.error("acquisition process did not stop within %g s: terminating", timeout_s)
                self._proc.terminate()
                self._proc.join(2.0)
                if self._proc.is_alive():
                    self._proc.kill()
                    self._proc.join(2.0)
        return self.stats()

    def __enter__(self) -> "AcquisitionProcess":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
