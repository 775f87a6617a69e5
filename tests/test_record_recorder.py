"""The recorder (issue 18) off the daemon: pairs offered by a frame loop, written by its
thread. A slow disk drops pairs (counted, never a wait); files rotate by size and by
time; a full disk stops the recording with one log line and counts the rest; the blackbox
writes the pre_s seconds before a trigger and the post_s after, with no gap, a trigger in
the meantime extending it; failed packets and a lost transmitter trigger it.
"""

from __future__ import annotations

import errno
import logging
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fakes import wait_until
from iscd.recording import pairfile
from iscd.recording.pairs import PairSession
from iscd.recording.recorder import Recorder, RecordSettings
from iscd.service.recording import LiveRecording

H, W = 32, 48
FPS = 1000.0


def _frame(i: int, side: int) -> np.ndarray:
    return ((np.arange(H * W).reshape(H, W) + 7 * i + 100 * side) % 251).astype(np.uint8)


def _recorder(tmp_path: Path, **kw) -> Recorder:
    st = replace(RecordSettings(dir=str(tmp_path), fsync_s=0), **kw)
    return Recorder(tmp_path / "run", st, width=W, height=H, dtype=np.uint8, fps=FPS,
                    meta={"intake_buffers": 4}, beside={"config.toml": "# test\n"})


def _offer(rec: Recorder, ids, windows=((2, 3, 12, 9), (5, 1, 20, 30))) -> list[bool]:
    return [rec.offer(i, 1000 * i, 1000 * i + 1, i // 4, _frame(i, 0), _frame(i, 1), windows) for i in ids]


def _check_content(folder: Path) -> np.ndarray:
    """Every pair in the folder's files holds the windows of the frames offered; their ids."""
    with PairSession(folder) as s:
        for r in s.files:
            for k in range(r.n_pairs):
                i = int(r.frame_ids[k])
                for cam in (0, 1):
                    x0, y0, x1, y1 = r.windows[k, cam]
                    assert np.array_equal(r.window_pixels(k, cam), _frame(i, cam)[y0:y1, x0:x1])
        return s.frame_ids


def test_a_slow_disk_drops_pairs_counted_never_waits(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real = pairfile._write

    def slow(fd: int, data) -> int:
        time.sleep(0.02)  # a disk that stalls on every write
        return real(fd, data)

    monkeypatch.setattr(pairfile, "_write", slow)
    rec = _recorder(tmp_path, queue_mb=1.0, mode="full")  # 1 MiB = ~340 whole pairs of 3 kB
    t0 = time.perf_counter()
    ok = _offer(rec, range(3000))
    offer_s = time.perf_counter() - t0
    rec.close()
    c = rec.counters()
    assert c["record_dropped"] == c["record_dropped_queue_full"] == ok.count(False) > 0
    assert c["record_written"] + c["record_dropped"] == 3000
    ids = _check_content(tmp_path / "run")
    assert ids.tolist() == [i for i, k in enumerate(ok) if k]
    assert offer_s < 20  # never waited for the disk (3000 stalls would be 60 s)


def test_files_rotate_by_size_and_time_each_self_contained(tmp_path: Path) -> None:
    rec = _recorder(tmp_path, rotate_mb=0.01, mode="roi")  # ~10 kB: ~15 pairs of 656 bytes a file
    _offer(rec, range(200))
    rec.close()
    files = sorted((tmp_path / "run").glob("*.iscr"))
    assert len(files) >= 10 and (tmp_path / "run" / "config.toml").read_text() == "# test\n"
    assert all(f.stat().st_size <= 0.01 * 2**20 + 1024 for f in files)
    assert _check_content(tmp_path / "run").tolist() == list(range(200))
    rec2 = _recorder(tmp_path / "t", rotate_s=0.05)
    for i in range(6):
        _offer(rec2, [i])
        wait_until(lambda: rec2.counters()["record_queued"] == 0, 10)
        time.sleep(0.06)
    rec2.close()
    assert rec2.files >= 3


def test_disk_full_stops_recording_with_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    room = {"left": 20_000}
    real = pairfile._write

    def disk(fd: int, data) -> int:
        if room["left"] <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        k = real(fd, bytes(data[:room["left"]]))
        room["left"] -= k
        return k

    rec = _recorder(tmp_path)
    monkeypatch.setattr(pairfile, "_write", disk)
    with caplog.at_level(logging.ERROR, logger="iscd.recording.recorder"):
        for i in range(300):
            _offer(rec, [i])
            if i % 50 == 0:
                wait_until(lambda: rec.counters()["record_queued"] == 0 or rec.failure, 10)
        rec.close()
    c = rec.counters()
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "recording stopped" in errors[0] and "No space left" in errors[0]
    assert c["record_stopped"] and c["record_written"] > 0 and c["record_dropped"] > 0
    assert c["record_written"] + c["record_dropped"] == 300
    ids = _check_content(tmp_path / "run")  # cut back to its last whole pair, unsealed
    assert ids.tolist() == list(range(c["record_written"]))
    with PairSession(tmp_path / "run") as s:
        assert not s.files[0].sealed


def test_blackbox_writes_before_and_after_a_trigger_without_a_gap(tmp_path: Path) -> None:
    rec = _recorder(tmp_path, mode="blackbox", pre_s=0.05, post_s=0.03)  # 50 frames before, 30 after
    _offer(rec, range(0, 200))
    rec.trigger("SIGUSR1")
    _offer(rec, range(200, 260))  # the trigger is taken at frame 200
    wait_until(lambda: rec._state == "armed", 10)
    _offer(rec, range(260, 500))
    rec.trigger("bad packet")
    _offer(rec, range(500, 520))
    rec.trigger("bad packet")  # during the 30 frames after: extends them
    _offer(rec, range(520, 700))
    wait_until(lambda: rec._state == "armed", 10)
    rec.close()
    with PairSession(tmp_path / "run") as s:
        files = [(r.metadata["reason"], r.metadata["trigger_frame"], r.frame_ids.tolist()) for r in s.files]
    assert files == [("SIGUSR1", 200, list(range(150, 231))), ("bad packet", 500, list(range(450, 551)))]
    c = rec.counters()
    assert c["record_triggers"] == 3 and c["record_dropped"] == 0 and c["record_written"] == 81 + 101
    assert (tmp_path / "run" / "000000-trigger-sigusr1.iscr").exists()


def test_failed_packets_and_a_lost_transmitter_trigger(tmp_path: Path) -> None:
    losses = {"n": 0}
    rec = _recorder(tmp_path, mode="blackbox", pre_s=0.01, post_s=0.01)
    live = LiveRecording(rec, lambda: losses["n"])

    class Slot:
        def __init__(self, i: int) -> None:
            self.frame_id, self.ts_left_ns, self.ts_right_ns = i, 0, 0
            self.left, self.right = _frame(i, 0), _frame(i, 1)

    for i in range(100):
        live.pair(Slot(i), None, i // 4)
    live.observe([{"type": "packet", "crc_ok": True}, {"type": "range"}])
    assert rec.triggers == 0
    live.observe([{"type": "packet", "crc_ok": False}])
    for i in range(100, 200):
        live.pair(Slot(i), None, i // 4)
    losses["n"] = 1  # the decoder lost the transmitter: seen at the next block
    for i in range(200, 300):
        live.pair(Slot(i), None, i // 4)
    wait_until(lambda: rec._state == "armed", 10)
    rec.close()
    with PairSession(tmp_path / "run") as s:
        assert [(r.metadata["reason"], r.metadata["trigger_frame"]) for r in s.files] == [
            ("bad packet", 100), ("transmitter lost", 200)]
        assert s.info()["whole_frame_pairs"] == s.n_pairs == 42


def test_the_config_and_calibration_in_force_are_stored_beside(tmp_path: Path) -> None:
    from iscd.calibration.io import StereoCalibration, save_calibration
    from iscd.core import config as C
    from iscd.service.recording import live_recording

    cal = tmp_path / "rig.yml"
    save_calibration(StereoCalibration.from_parameters(512, 512, 3500.0, baseline_m=0.25), cal)
    cfg = C.loads(f'[record]\ndir = "{tmp_path / "rec"}"\n[scene]\nseed = 11\n')
    live = live_recording(cfg, str(cal), lambda: 0, 16)
    live.close()
    folder = live.folder
    assert folder.parent == tmp_path / "rec" and folder.name.startswith("run-")
    assert (folder / "calibration.yml").read_bytes() == cal.read_bytes()
    assert C.loads((folder / "config.toml").read_text()) == cfg  # the config, exactly
    assert live_recording(C.loads(""), None, lambda: 0, 16) is None  # no [record] dir: off
    live2 = live_recording(cfg, None, lambda: 0, 16)  # a second run: a folder of its own
    live2.close()
    assert live2.folder != folder and not (live2.folder / "calibration.yml").exists()
