"""JsonlWriter: compact lines, rotation, and what survives a SIGKILL."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from iscd.outputs import OutputConfig, OutputError, output_config
from iscd.outputs import jsonl
from iscd.outputs.jsonl import JsonlWriter, encode_record, read_records, rotated_paths


def test_compact_lines_numpy_and_nan(tmp_path: Path) -> None:
    p = tmp_path / "out.jsonl"
    with JsonlWriter(p, flush_interval_s=10) as w:
        w.write({"type": "range", "tx": 0, "frame": 7, "t_s": 0.007, "z_m": 30.25,
                 "disparity_px": np.float32(29.5), "sigma_m": float("nan")})
        w.write({"type": "packet", "tx": np.int64(1), "frame": 8, "t_s": 0.008, "crc_ok": np.bool_(True),
                 "levels": np.array([1, 8, 3], dtype=np.uint8), "payload_hex": b"\x01\xff"})
        assert w.buffered == 2 and p.read_bytes() == b""   # within the flush interval: in memory
    lines = p.read_bytes().split(b"\n")
    assert lines[-1] == b"" and len(lines) == 3
    assert b" " not in lines[0]                       # compact separators
    recs = [json.loads(x) for x in lines[:2]]
    assert recs[0] == {"type": "range", "tx": 0, "frame": 7, "t_s": 0.007, "z_m": 30.25,
                       "disparity_px": 29.5, "sigma_m": None}  # NaN is not JSON: null
    assert recs[1]["levels"] == [1, 8, 3] and recs[1]["crc_ok"] is True
    assert recs[1]["tx"] == 1 and recs[1]["payload_hex"] == "01ff"
    assert read_records(p) == recs


def test_unencodable_record_is_dropped_not_raised(tmp_path: Path) -> None:
    with JsonlWriter(tmp_path / "o.jsonl") as w:
        w.write({"type": "stats", "bad": object()})
        w.write({"type": "stats", "ok": 1})
        assert w.dropped == 1 and w.records == 1
    assert read_records(tmp_path / "o.jsonl") == [{"type": "stats", "ok": 1}]


def test_time_based_flush_reaches_the_os(tmp_path: Path, fake_clock) -> None:
    fake_clock.install(jsonl)  # virtual time: a loaded machine cannot pass an interval early
    p = tmp_path / "o.jsonl"
    w = JsonlWriter(p, flush_interval_s=0.05)
    w.write({"i": 0})
    size0 = p.stat().st_size
    fake_clock.sleep(0.06)
    w.write({"i": 1})                 # the interval has passed: both lines go to the OS
    assert p.stat().st_size > size0 and w.buffered == 0
    w.write({"i": 2})
    assert w.buffered == 1
    fake_clock.sleep(0.06)
    w.maybe_flush()                   # the idle-loop hook
    assert w.buffered == 0 and [r["i"] for r in read_records(p)] == [0, 1, 2]
    w.close()
    w.write({"i": 3})                 # after close: counted, not raised
    assert w.dropped == 1


def test_rotation_keeps_order_and_size_limit(tmp_path: Path) -> None:
    p = tmp_path / "iscd.jsonl"
    recs = [{"type": "range", "tx": 0, "frame": i, "t_s": i / 1000, "z_m": 30 + i / 7} for i in range(600)]
    with JsonlWriter(p, rotate_bytes=4096, flush_interval_s=0, keep=None) as w:
        for r in recs:
            w.write(r)
        assert w.rotations >= 5
    files = rotated_paths(p)
    assert files[-1] == p and files[0].name == f"iscd.jsonl.{len(files) - 1}"
    sizes = [f.stat().st_size for f in files]
    assert max(sizes) <= 4096 and all(s > 4096 - 200 for s in sizes[:-1])   # full files, no split lines
    for f in files:
        assert f.read_bytes().endswith(b"\n")
    assert read_records(p) == json.loads(json.dumps(recs))   # every record once, in order


def test_rotation_deletes_beyond_keep_and_appends_on_restart(tmp_path: Path) -> None:
    p = tmp_path / "iscd.jsonl"
    with JsonlWriter(p, rotate_bytes=4096, flush_interval_s=0, keep=2) as w:
        for i in range(600):
            w.write({"frame": i, "pad": "x" * 40})
        total_rotations = w.rotations
    assert total_rotations > 3
    assert [f.name for f in rotated_paths(p)] == ["iscd.jsonl.2", "iscd.jsonl.1", "iscd.jsonl"]
    frames = [r["frame"] for r in read_records(p)]
    assert frames == list(range(frames[0], 600)) and frames[0] > 0   # the newest, contiguous
    with JsonlWriter(p, rotate_bytes=1 << 20) as w:                  # a restarted daemon appends
        w.write({"frame": 600})
    assert [r["frame"] for r in read_records(p, rotated=False)][-2:] == [599, 600]


def test_file_deleted_under_the_writer_is_recreated(tmp_path: Path) -> None:
    p = tmp_path / "o.jsonl"
    with JsonlWriter(p, flush_interval_s=0) as w:
        w.write({"i": 0})
        p.unlink()                    # e.g. an external logrotate moved it away
        w.write({"i": 1})
    assert read_records(p) == [{"i": 1}]


def test_unwritable_path_is_a_one_line_error(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputError, match="cannot open output file") as e:
        JsonlWriter(tmp_path / "file" / "sub" / "o.jsonl")
    assert "\n" not in str(e.value)


def test_disk_full_is_counted_not_raised(tmp_path: Path) -> None:
    if not Path("/dev/full").exists():
        pytest.skip("needs /dev/full to simulate a full disk")
    w = JsonlWriter(tmp_path / "o.jsonl", flush_interval_s=0)
    full = os.open("/dev/full", os.O_WRONLY)
    os.dup2(full, w._fd)              # every write now fails with ENOSPC
    os.close(full)
    w._ino = (os.stat("/dev/full").st_dev, os.stat("/dev/full").st_ino)
    w._reopen_if_moved = lambda: None  # type: ignore[method-assign]
    for i in range(3):
        w.write({"i": i})
    assert w.errors == 3 and w.dropped == 3 and w.written == 0
    w.close()


def test_output_config_section() -> None:
    from iscd.core.config import ConfigError, loads

    oc = output_config(loads("[output]\nkeep = 3\nzmq_hwm = 50\n"))
    assert oc.keep == 3 and oc.zmq_hwm == 50 and oc.flush_interval_s == OutputConfig.flush_interval_s
    assert output_config(loads("")) == OutputConfig()
    with pytest.raises(ConfigError, match="output.flush_interval_s"):
        output_config(loads("[output]\nflush_interval_s = -1\n"))
    with pytest.raises(ConfigError, match="output.rotate: unknown key"):
        output_config(loads("[output]\nrotate = 5\n"))


_CHILD = r"""
import sys, time
from iscd.outputs.jsonl import JsonlWriter
w = JsonlWriter(sys.argv[1], flush_interval_s=float(sys.argv[2]), fsync_interval_s=None)
i = 0
while True:
    w.write({"type": "stats", "tx": 0, "frame": i, "t_s": i / 1000, "t_mono": time.monotonic()})
    if i == 0:
        print("go", flush=True)
    i += 1
    time.sleep(0.001)
"""


def _run_and_kill(path: Path, flush_interval_s: float, run_s: float) -> tuple[float, int]:
    """Start a writer process, let it run ``run_s`` s after its first record, SIGKILL it.

    Returns the monotonic time of the kill and the pid."""
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(path), str(flush_interval_s)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "go"
        time.sleep(run_s)
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    return t_kill, proc.pid


def test_sigkill_loses_at_most_the_flush_interval(tmp_path: Path) -> None:
    interval = 0.2
    p = tmp_path / "killed.jsonl"
    t_kill, _ = _run_and_kill(p, interval, run_s=1.0)
    recs = read_records(p)                              # every line is whole JSON
    frames = [r["frame"] for r in recs]
    assert frames == list(range(len(frames))) and len(frames) > 50   # nothing missing before the end
    lost_s = t_kill - recs[-1]["t_mono"]
    # what was decoded more than one flush interval before the kill is on disk
    # (0.3 s of slack for a busy 2-core machine: sleeps overshoot, the kill is not instant)
    assert 0 <= lost_s <= interval + 0.3, lost_s
    print(f"records: {len(recs)}, lost before the kill: {lost_s * 1000:.0f} ms")


def test_sigkill_control_without_timed_flush_loses_everything(tmp_path: Path) -> None:
    """The same run with a 1000 s interval leaves the file empty: the test above measures the
    writer's timed flush, not some buffering of the OS or of Python."""
    p = tmp_path / "control.jsonl"
    _run_and_kill(p, 1000.0, run_s=0.3)
    assert p.exists() and p.stat().st_size == 0


def test_encode_record_rejects_nothing_json_can_hold() -> None:
    rec = {"type": "stats", "frames_in": 10, "latency_ms_p50": 1.5, "ok": False, "list": [1, 2.5],
           "inf": math.inf}
    assert json.loads(encode_record(rec)) == {**rec, "inf": None}
