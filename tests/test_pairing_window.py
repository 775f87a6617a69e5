"""The pairing window as config, and the log line when pairing fails (issue 16, the soak's
drops on a saturated host).

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

import pytest

from iscd.core.config import ConfigError, loads, section
from iscd.rig.acquisition import Acquisition, AcquisitionOptions, PairingReport
from iscd.rig.ringbuffer import StereoRing

pytestmark = pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="needs Linux /dev/shm")

FPS = 200
RIG = f"""
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
pace = false
"""


class _Run:
    """The mock rig's two cameras opened and started, an :class:`Acquisition` on a ring with
    the config's ``[acquisition]``, and a fake clock for its pairing report."""

    def __init__(self, text: str) -> None:
        import iscd.drivers.urls  # noqa: F401  ([rig] is checked by the camera registry)
        from iscd.drivers.mock import MockRig
        from iscd.drivers.registry import settings_from_config

        cfg = loads(RIG + text)
        self.left, self.right = MockRig.from_config(cfg)
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
        """``n`` frames of one camera into the acquisition; the clock runs with the left
        camera's frames (1 / fps each)."""
        cam = self.left if side == "left" else self.right
        for _ in range(n):
            self.acq._handle(side, cam.read(timeout_s=1.0), 0)
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
        assert run.acq.pairer.unpaired_why == {"window": 36, "max_pending": 36, "late": 0, "overtaken": 0, "end": 0}
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
