"""The pairing window as config, the log line when pairing fails, and a camera whose reader
stays behind catching up (issue 16, the soak's drops on a saturated host and a CI run whose
pairing never recovered).

The frames are the mock rig's (``iscd.drivers.mock``, its scene rendered, its injected
faults); they go through the acquisition's own path (:meth:`Acquisition._handle`: the
pairer from ``[acquisition]``, the ring, the pairing report) in an order the test chooses:
one camera's frames read far ahead of the other's is what a starved reader thread of a busy
host does. The report's clock is a fake one advanced by the frames' own time, so what is
said once a second does not depend on this machine's speed.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys

import numpy as np
import pytest

from iscd.core.config import ConfigError, loads, section
from iscd.rig.acquisition import Acquisition, AcquisitionOptions, PairingReport
from iscd.rig.ringbuffer import StereoRing

pytestmark = pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="needs Linux /dev/shm")

FPS = 200
RIG = """
[transmitter]
rows = 2
cols = 2
symbol_rate_hz = 100
[camera]
fps = {FPS}
exposure_s = 0.002
width = 64
height = 48
[rig]
pace = {pace}
buffer_frames = 2000
"""


CATCH_UP_8 = "[acquisition]\ncatch_up_after = 8\n"
"""The catch-up asked after 8 late frames (the default is 250: these tests hold a reader back
for good, so the threshold only moves where pairing resumes)."""


class _Run:
    """The mock rig's two cameras opened and started, an :class:`Acquisition` on a ring with
    the config's ``[acquisition]``, and a fake clock for its pairing report. ``pace``: the
    rig's frames come in (the mock module's) real time, into queues of 2000 frames as in the
    soak; the tests that pace it install a fake clock in ``iscd.drivers.mock``."""

    def __init__(self, text: str, pace: bool = False) -> None:
        import iscd.drivers.urls  # noqa: F401  ([rig] is checked by the camera registry)
        from iscd.drivers.mock import MockRig
        from iscd.drivers.registry import settings_from_config

        cfg = loads(RIG.format(FPS=FPS, pace=str(pace).lower()) + text)
        self.left, self.right = MockRig.from_config(cfg, buffer_frames=cfg.rig.buffer_frames)
        settings = (settings_from_config(cfg, "left"), settings_from_config(cfg, "right"))
        for cam, s in zip((self.left, self.right), settings):
            cam.open()
            cam.configure(s)
            cam.start()
        self.ring = StereoRing.create(height=48, width=64, capacity=4096)
        self.acq = Acquisition(self.left, self.right, self.ring, settings=settings,
                               options=section(cfg, AcquisitionOptions))
        self.now = 0.0
        self.acq.pairing_report = PairingReport(self.acq.pairer, clock=lambda: self.now)

    def read(self, side: str, n: int) -> None:
        """``n`` reads of one camera as its reader thread does them (a catch-up the pairer
        asked for first, then the frame into the acquisition); the clock runs with the left
        camera's reads (1 / fps each)."""
        cam = self.left if side == "left" else self.right
        for _ in range(n):
            frame = self.acq._next_frame(side, cam)
            if frame is not None:
                self.acq._handle(side, frame, 0)
            if side == "left":
                self.now += 1.0 / FPS

    def alternate(self, n: int) -> None:
        for _ in range(n):
            self.read("left", 1)
            self.read("right", 1)

    def pairs(self) -> list[tuple[int, int, int, int, int]]:
        out = []
        while (p := self.ring.read()) is not None:
            with p:
                out.append((p.frame_id, p.left_id, p.right_id, p.ts_left_ns, p.ts_right_ns))
        return out

    def close(self) -> None:
        for cam in (self.left, self.right):
            cam.stop()
            cam.close()
        self.ring.close()


def _said(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.getMessage().startswith("pairing: ")]


@pytest.mark.parametrize("max_pending", [64, 128])
def test_a_camera_read_far_ahead_is_absorbed_by_max_pending(max_pending: int, caplog) -> None:
    """The left camera's 100 frames are read before the right's (its reader thread starved
    for 100 frames, as in the soak on a saturated host), then both alternate. With the
    default ``max_pending = 64`` the 36 oldest left frames go (``max_pending``) and so do
    their right partners when they come (``window``), and the log says so once, naming the
    keys; with ``[acquisition] max_pending = 128`` every trigger is paired and nothing is
    said. Every pair in the ring is one trigger's two frames."""
    run = _Run("" if max_pending == 64 else f"[acquisition]\nmax_pending = {max_pending}\n")
    try:
        assert run.acq.pairer.max_pending == max_pending
        with caplog.at_level(logging.WARNING, logger="iscd.rig.acquisition"):
            run.read("left", 100)
            run.read("right", 100)
            run.alternate(300)  # 1.5 s more: the report looks at the second that held the skew
        pairs = run.pairs()
        c = run.acq.pairer.counters
    finally:
        run.close()
    assert all(p[1] == p[2] and p[3] == p[4] for p in pairs)
    ids = [p[0] for p in pairs]
    if max_pending == 64:
        assert ids == list(range(36, 400))
        assert (c.unpaired_left, c.unpaired_right) == (36, 36)
        assert run.acq.pairer.unpaired_why == {"window": 36, "max_pending": 36, "late": 0, "overtaken": 0, "end": 0,
                                               "skipped": 0}
        assert c.catch_ups == 0  # the right reader drained its backlog: closing the gap, not behind
        said = _said(caplog)
        assert len(said) == 1, said
        assert "36 left and 36 right frames" in said[0] and "max_pending 36" in said[0] \
            and "window 36" in said[0] and "max_pending = 64" in said[0] and "pair_window = 16" in said[0]
    else:
        assert ids == list(range(400))
        assert c.unpaired_left == c.unpaired_right == 0
        assert _said(caplog) == []


def test_a_stalled_camera_is_said_once_and_a_steady_fault_once_a_second(caplog) -> None:
    """The mock rig's faults: the right camera stalls 100 ms (20 frames) at trigger 300;
    from trigger 1000 its ids run 3 ahead and ``resync_after = 0`` never re-learns them, so
    no pair forms from then on. 2000 triggers = 10 s of the report's clock: one line for
    the stall, then one line a second while pairing fails (never one a frame), and none in
    the seconds where every frame was paired."""
    run = _Run("""
[[rig.faults]]
kind = "stall"
camera = "right"
frame = 300
duration_ms = 100
[[rig.faults]]
kind = "id_offset"
camera = "right"
frame = 1000
offset = 3
[acquisition]
resync_after = 0
catch_up_after = 0
""")
    times: list[float] = []

    class Times(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.getMessage().startswith("pairing: "):
                times.append(run.now)

    h = Times()
    logging.getLogger("iscd.rig.acquisition").addHandler(h)
    try:
        with caplog.at_level(logging.WARNING, logger="iscd.rig.acquisition"):
            run.alternate(1980)
        c = run.acq.pairer.counters
    finally:
        logging.getLogger("iscd.rig.acquisition").removeHandler(h)
        run.close()
    said = _said(caplog)
    assert len(said) == len(times)
    # the stall (triggers 300-319, 1.5-1.6 s): its 20 left frames, said in the line at 2 s
    assert times[0] == pytest.approx(2.0, abs=0.01) and "20 left and 0 right" in said[0], said
    # nothing said for seconds 2-4 (all paired), then once a second from trigger 1000 (5 s) on
    assert [round(t) for t in times[1:]] == [5, 6, 7, 8, 9], times
    assert all("201 left and 201 right" in m and "timestamps disagree 201 + 201" in m for m in said[2:5]), said
    assert all(b - a >= 1.0 - 1e-9 for a, b in zip(times, times[1:]))
    assert c.unpaired_left + c.unpaired_right + 2 * c.id_mismatch >= 2 * 900
    assert c.catch_ups == 0  # a stall and an id offset are not a late reader


def _caught_up(caplog) -> list[str]:
    return [m for m in _said(caplog) if "camera's frames came" in m]


@pytest.mark.parametrize("late,lag", [("right", 200), ("left", 65), ("right", 1500)])
def test_a_reader_that_stays_behind_catches_up(late: str, lag: int, caplog) -> None:
    """One camera's reader is held back for ``lag`` triggers (more than ``max_pending = 64``
    absorbs) and then reads at the other's pace, so its frames keep coming ``lag`` frames
    late: the CI run whose pairing failed from 2 s on and never recovered (the mock rig's
    two reader threads skewed on a starved start). Before the fix no pair ever formed again.
    Now, after ``resync_after = 8`` late frames in a row, that camera's reader skips its
    backlog to the other camera's newest frame (the mock rig discards them unrendered) and
    every trigger from there on is paired: at most 8 + 1 late reads from the skew to the
    first pair. The skipped frames count as unpaired (``skipped``), one catch-up, one line
    saying it."""
    early = "left" if late == "right" else "right"
    run = _Run(CATCH_UP_8)
    try:
        with caplog.at_level(logging.WARNING, logger="iscd.rig.acquisition"):
            run.read(early, lag)
            for _ in range(1000):
                run.read(early, 1)
                run.read(late, 1)
        pairs = run.pairs()
        p = run.acq.pairer
        c, why, pending = p.counters, dict(p.unpaired_why), p.pending
        late_cam = run.left if late == "left" else run.right
        skipped_unrendered = late_cam.stats.skipped
        st = run.acq.stats()
    finally:
        run.close()
    ids = [q[0] for q in pairs]
    assert ids, "no pair formed: the late camera never caught up"
    assert all(q[1] == q[2] and q[3] == q[4] for q in pairs)  # each pair one trigger's two frames
    # the 8th late read (trigger 7) asks for the catch-up; the 9th skips triggers 8 .. lag + 6
    # unrendered and pairs trigger lag + 7, the early camera's newest; then every trigger
    assert ids == list(range(lag + 7, lag + 999)), (ids[:3], ids[-3:])  # the last early frame waits
    assert c.catch_ups == st.catch_ups == 1 and c.resyncs == 0
    assert why["skipped"] == skipped_unrendered == lag - 1
    # every frame accounted for: frames = pairs + unpaired + still waiting
    for side, frames, unpaired in (("left", c.frames_left, c.unpaired_left),
                                   ("right", c.frames_right, c.unpaired_right)):
        assert frames == c.pairs + unpaired + pending[side], side
    assert st.frames_dropped == c.unpaired_left + c.unpaired_right
    said = _caught_up(caplog)
    assert len(said) == 1 and f"the {late} camera's frames came" in said[0] \
        and f"skipped {lag - 1} of them" in said[0], said


def test_a_paced_camera_whose_reader_stays_behind_catches_up(fake_clock, caplog) -> None:
    """The soak's case: paced cameras (on a fake clock: each read waits for its trigger),
    the right camera's queue 2000 frames deep. Its reader is held back while the left reads
    300 frames, then both read in turn: the right reader keeps serving 300-frame-old frames
    out of its queue and, before the fix, never paired again. Now its 8th late read asks for
    a catch-up, the 9th skips its queue to the left camera's newest frame (299 frames
    discarded unrendered), and from there every trigger is paired."""
    from iscd.drivers import mock

    fake_clock.install(mock)
    run = _Run(CATCH_UP_8, pace=True)
    try:
        with caplog.at_level(logging.WARNING, logger="iscd.rig.acquisition"):
            run.read("left", 300)
            run.alternate(500)
        ids = [q[0] for q in run.pairs()]
        c = run.acq.pairer.counters
        skipped = run.right.stats.skipped
        buffer_drops = run.right.stats.dropped_buffer
    finally:
        run.close()
    assert ids == list(range(307, 799))
    assert c.catch_ups == 1 and skipped == c.unpaired_right - 8 == 299 and buffer_drops == 0
    said = _caught_up(caplog)
    assert len(said) == 1 and "the right camera's frames came 1.500 s after" in said[0], said


def test_a_lag_pairing_absorbs_needs_no_catch_up() -> None:
    """A reader that stays 40 frames behind (less than ``max_pending = 64``) loses nothing:
    its partners wait, every trigger is paired, no catch-up."""
    run = _Run(CATCH_UP_8)
    try:
        run.read("left", 40)
        run.alternate(500)
        ids = [q[0] for q in run.pairs()]
        c = run.acq.pairer.counters
    finally:
        run.close()
    assert ids == list(range(500))
    assert c.catch_ups == 0 and c.unpaired_left == c.unpaired_right == 0


def test_pairing_recovers_after_every_skew(caplog) -> None:
    """The right reader held back again and again (300, 100, 70 frames, 1 s of alternating
    reads between): pairing comes back each time within 8 + 1 late reads, one catch-up each,
    at most one catch-up line a second (the clock is the left camera's frames)."""
    run = _Run(CATCH_UP_8)
    starts = []
    try:
        with caplog.at_level(logging.WARNING, logger="iscd.rig.acquisition"):
            for lag in (300, 100, 70):
                run.read("left", lag)
                before = len(run.pairs())
                run.alternate(9)
                got = run.pairs()
                assert before == 0 and len(got) == 1, (lag, got)  # paired by the 9th late read
                starts.append(got[0][0])
                run.alternate(200)
                assert len(run.pairs()) == 200
        c = run.acq.pairer.counters
    finally:
        run.close()
    assert c.catch_ups == 3
    assert len(_caught_up(caplog)) == 3  # 1 s of frames (and more) between them


def test_pairing_keys_bounds_errors_and_describe() -> None:
    """``[acquisition] pair_window`` and ``max_pending``: 1..4096 frames; a value outside is a
    ConfigError naming the key; ``iscd config --describe`` lists both with their unit."""
    assert section(loads("[acquisition]\npair_window = 64\nmax_pending = 512\n"),
                   AcquisitionOptions).max_pending == 512
    for key, bad in (("pair_window", 0), ("max_pending", 0), ("max_pending", 5000), ("pair_window", 1.5)):
        with pytest.raises(ConfigError, match=f"acquisition.{key}"):
            section(loads(f"[acquisition]\n{key} = {bad}\n"), AcquisitionOptions)
    out = subprocess.run([sys.executable, "-m", "iscd", "config", "--describe"], capture_output=True,
                         text=True, check=True).stdout
    lines = {ln.split("=")[0].strip(): ln for ln in out.splitlines() if "=" in ln}
    assert "frames (1..4096)" in lines["pair_window"] and "frames (1..4096)" in lines["max_pending"]
    bad = subprocess.run([sys.executable, "-m", "iscd", "config", "--check", "/dev/stdin"],
                         input="[acquisition]\nmax_pending = 0\n", capture_output=True, text=True)
    assert bad.returncode == 2 and "acquisition.max_pending" in bad.stderr \
        and len(bad.stderr.strip().splitlines()) == 1, bad.stderr


def test_camera_skip_to_by_default_reads_and_drops() -> None:
    """``Camera.skip_to`` of a backend without its own (the test fake: triggers every 1 ms,
    unpaced): frames below the time are read and dropped, the first one not older is
    returned; at the end of the frames (CameraTimeout) it returns None."""
    from fakes import FakeCamera

    cam = FakeCamera("left", n=50, t0_ns=0, period_ns=1_000_000, paced=False)
    cam.open()
    cam.start()
    n, frame = cam.skip_to(20_000_000, timeout_s=0.1)
    assert n == 20 and frame is not None and (frame.frame_id, frame.timestamp_ns) == (20, 20_000_000)
    assert cam.skip_to(10**12, timeout_s=0.1, max_frames=5) == (5, None)
    assert cam.skip_to(10**12, timeout_s=0.1) == (24, None)  # frames 26..49, then the end
    cam.stop()
    cam.close()


@pytest.mark.parametrize("guard", [True, False])
def test_no_catch_up_when_the_clocks_disagree(guard: bool, monkeypatch) -> None:
    """The right camera's timestamps jump 10 min ahead (a device clock reset, not a late
    reader: more than ``MAX_CATCH_UP_FRAMES`` frames at 1000 fps) and it reads 100 frames
    ahead, then in turn with the left: the left camera's next frames find no partner and are older than all the right
    one's waiting frames, yet the left is not asked to skip 10 minutes of frames (the
    ``guard=False`` case, the bound raised past the jump, shows that the bound is what stops
    it)."""
    from iscd.drivers.base import Frame
    from iscd.rig import pairing

    if not guard:
        monkeypatch.setattr(pairing, "MAX_CATCH_UP_FRAMES", 10**9)
    img = np.zeros((2, 2), np.uint8)
    p = pairing.StereoPairer(ts_tolerance_ns=250_000, catch_up_after=8)
    jump = 600 * 10**9
    assert jump // 1_000_000 > 1 << 16

    def push(side: str, n: int) -> None:
        ts = n * 1_000_000 + (jump if side == "right" and n >= 100 else 0)
        p.push(side, Frame(side, n, ts, img))  # type: ignore[arg-type]

    for n in range(100):
        push("left", n)
        push("right", n)
    for n in range(100, 200):
        push("right", n)
    asked = None
    for n in range(100, 140):  # both at the same pace from here: the left stays 100 behind
        push("left", n)
        push("right", n + 100)
        asked = asked or p.take_catch_up("left")
    assert p.counters.pairs == 100
    assert (asked is None) == guard, asked
