"""The daemon on the mock rig: packets decoded live, faults survived and counted, stats,
graceful stop on SIGTERM, sd_notify READY/WATCHDOG.

These runs use a light transmitter (``fakes.LIGHT``: one LED, short packets of 153
symbols = 306 ms) so that they keep up on a loaded 2-core CI machine; the full-rate soak
is ``test_soak_full_rate`` (slow, ISCD_SLOW=1) and the speed claim lives in
benchmarks/bench_decode_loop.py. The mock rig is paced in real time, so a loaded machine
decodes the same frames later or drops some (counted); the load-tolerant tests therefore
run the daemon until what they check has been written (``fakes.run_daemon_until``, with
a generous wall-time safety net), not for a fixed number of seconds.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fakes import LIGHT, LIGHT_PACED, run_daemon_until, stats_records
from fakes import read_records as _records
from iscd.core import config as C
from iscd.service.daemon import Daemon


def _run(text: str, tmp_path: Path, duration: float) -> tuple[Daemon, list[dict]]:
    cfg = C.loads(text)
    out = tmp_path / "out.jsonl"
    d = Daemon(cfg, out=str(out), duration_s=duration, install_signals=False)
    d.run()
    return d, _records(out)


def _truth_payloads(cfg: C.Config, n: int) -> list[bytes]:
    from iscd.sim.scene import Scene

    scene = Scene(cfg)
    frames = np.arange(0, int(n))
    return list(scene.truth(frames).payloads)


def _check_live(recs: list[dict], strict: bool) -> None:
    pk = [r for r in recs if r["type"] == "packet"]
    stats = [r for r in recs if r["type"] == "stats"]
    rng = [r for r in recs if r["type"] == "range"]
    final = stats[-1]
    assert final["final"] is True and sum(s.get("final", False) for s in stats) == 1
    assert len(stats) >= 5  # one a second, and the last
    for key in ("frames_in", "frames_dropped", "pairs_decoded", "packets_ok", "packets_bad",
                "latency_ms_p50", "latency_ms_p99", "latency_run_ms_p50", "latency_run_ms_p99", "latency_run_ms_max"):
        assert key in final
    # the run's latencies cover every interval's: its maximum at least every interval's p99
    assert final["latency_run_ms_max"] >= max(s["latency_ms_p99"] or 0 for s in stats) - 1e-9
    assert final["latency_run_ms_p50"] <= final["latency_run_ms_p99"] <= final["latency_run_ms_max"]
    assert final["packets_ok"] == sum(r["crc_ok"] for r in pk)
    # every CRC-valid payload is one the transmitter sent (never a corrupted one)
    truth = _truth_payloads(C.loads(LIGHT), int(final["frame"]) + 400)
    ok = [r for r in pk if r["crc_ok"]]
    assert all(bytes.fromhex(r["payload_hex"]) in truth for r in ok)
    assert all(r["payload_hex"] == "" for r in pk if not r["crc_ok"])
    z = np.array([r["z_m"] for r in rng])
    assert z.size and abs(np.median(z) - 30.0) < 0.5
    # frames_dropped counts exactly the frame ids that never reached the decoder
    assert final["pairs_decoded"] + final["frames_dropped"] >= final["frame"] - 64
    if not strict:
        assert len(ok) >= 3
        return
    # real time: after a 2 s warm-up (process start, first detection) every packet is
    # decoded, no frame is dropped and the p99 latency is small
    warm = [s for s in stats if s["uptime_s"] >= 2.0]
    late = [r for r in pk if r["frame"] > warm[0]["frame"]]
    assert len(late) >= 10 and all(r["crc_ok"] for r in late), [(r["frame"], r["crc_ok"]) for r in pk]
    assert final["frames_dropped"] == warm[0]["frames_dropped"], [s["frames_dropped"] for s in stats]
    assert final["latency_ms_p99"] < 50


def _ok_packets(recs: list[dict]) -> list[dict]:
    return [r for r in recs if r["type"] == "packet" and r["crc_ok"]]


def test_live_decoding_on_the_mock_rig(tmp_path: Path) -> None:
    """Packets decoded live, stats every second. Load-tolerant: the daemon runs until it
    has written 5 stats records, 3 CRC-valid packets and a range (5 s on a quiet machine;
    at most 120 s); the real-time claims (no drops, latency) are in the slow test below
    and in benchmarks/bench_decode_loop.py."""
    def done(recs: list[dict]) -> bool:
        return (len(stats_records(recs, final=False)) >= 5 and len(_ok_packets(recs)) >= 3
                and any(r["type"] == "range" for r in recs))

    _, recs, stop = run_daemon_until(LIGHT, tmp_path, done, timeout_s=120.0)
    assert stop.met_at_s is not None, "not decoding: no 3 packets within 120 s"
    _check_live(recs, strict=False)


@pytest.mark.slow
def test_live_decoding_real_time(tmp_path: Path) -> None:
    _, recs = _run(LIGHT_PACED, tmp_path, 10.0)
    _check_live(recs, strict=True)


FAULTS = LIGHT_PACED + """
[[rig.faults]]
kind = "stall"
camera = "left"
frame = 1500
duration_ms = 200
[[rig.faults]]
kind = "drop"
camera = "right"
frame = 2500
[[rig.faults]]
kind = "duplicate"
camera = "left"
frame = 3000
[[rig.faults]]
kind = "id_offset"
camera = "right"
frame = 3500
offset = 3
"""


@pytest.mark.parametrize("pace", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_faults_are_counted_and_decoding_resumes(tmp_path: Path, pace: bool) -> None:
    """The faults are at frames 1500-3500; the daemon runs until a CRC-valid packet after
    frame 4000 is out (at most 120 s) and then its counters are checked. The unpaced rig
    (``pace = false``) makes each camera's frames when read, in step with the other, and the
    daemon waits for its decoder: what is lost is exactly what the faults lose, however busy
    the machine. The paced form (slow) is the cameras' real time: a machine that does not
    keep up loses more, and a loaded one may not decode in time."""
    def done(recs: list[dict]) -> bool:
        return any(r["frame"] > 4000 for r in _ok_packets(recs[-1:]))

    text = FAULTS if pace else FAULTS.replace("\npace = true\n", "\npace = false\n")
    assert ("pace = true" in text) == pace
    d, recs, stop = run_daemon_until(text, tmp_path, done, timeout_s=120.0)
    final = [r for r in recs if r["type"] == "stats"][-1]
    acq = final["acquisition"]
    # the stall (200 ms = 200 frames), the drop and the duplicate are each counted
    assert acq["unpaired_right"] >= 200
    # the duplicate is counted -- unless (paced) the mock camera's own 8-frame queue
    # overflowed around it (a loaded machine), which then shows as more dropped frames
    assert acq["duplicates_left"] >= 1 or (pace and final["frames_dropped"] > 260), (acq, final["frames_dropped"])
    assert acq["resyncs"] >= 1  # the right camera's ids jumped by 3
    assert final["frames_dropped"] >= 201
    if not pace:  # nothing but the faults: the 200 stalled frames, the one dropped, and
        # while the pairer resyncs on the jumped ids, at most its window (16) on each side
        # (10-11 measured; which ones depends on how the two readers interleave). The pairs
        # the ring still held when the test stopped the daemon and its 0.3 s drain ran out
        # are no fault's (``stop_dropped``, part of frames_dropped): a loaded machine failed
        # the bound once with 312 dropped; beside three busy loops, stop_dropped was 0-108
        # while pair_gaps stayed 211-212
        lost = final["frames_dropped"] - final["stop_dropped"]
        assert lost <= 201 + 2 * 16, (acq, final["frames_dropped"], final["stop_dropped"])
        assert acq["duplicates_left"] == 1
    pk = _ok_packets(recs)
    assert stop.met_at_s is not None and any(r["frame"] > 4000 for r in pk), \
        "decoding did not resume after the faults (no packet after frame 4000 within 120 s)"
    # a range never comes from a mismatched pair: ids after the offset are still paired
    # with the right frame, so ranges stay on the truth (a 3-frame mismatch would not show
    # in range on a static scene, but the pair's frame ids are checked by the pairer; here
    # we check no range is wildly off and none is reported for the stalled frames)
    rng = {r["frame"]: r for r in recs if r["type"] == "range"}
    assert not any(1510 < f < 1690 for f in rng)
    z = np.array([r["z_m"] for r in rng.values()])
    assert np.all(np.abs(z - 30.0) < 2.0)


def _fake_notify_socket(tmp_path: Path) -> tuple[socket.socket, str]:
    path = str(tmp_path / "notify.sock")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(path)
    s.settimeout(0.2)
    return s, path


def test_sd_notify_ready_and_watchdog_and_sigterm(tmp_path: Path) -> None:
    cfgf = tmp_path / "light.toml"
    cfgf.write_text(LIGHT)
    out = tmp_path / "svc.jsonl"
    sock, path = _fake_notify_socket(tmp_path)
    env = {k: v for k, v in os.environ.items()}
    env.update(NOTIFY_SOCKET=path, WATCHDOG_USEC="1000000")
    env.pop("WATCHDOG_PID", None)
    proc = subprocess.Popen([sys.executable, "-m", "iscd", "run", "--config", str(cfgf), "--out", str(out)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    msgs: list[str] = []
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < 20:
            try:
                msgs += sock.recv(4096).decode().splitlines()
            except socket.timeout:
                pass
            if "READY=1" in msgs and msgs.count("WATCHDOG=1") >= 2:
                break
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        sock.close()
    assert "READY=1" in msgs and "WATCHDOG=1" in msgs, msgs
    assert proc.returncode == 0, err.decode()[-2000:]
    recs = _records(out)
    assert recs and recs[-1]["type"] == "stats" and recs[-1]["final"] is True
    assert b"Traceback" not in err


def test_bad_config_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[rig]\nbackend = 'usb3'\n")
    p = subprocess.run([sys.executable, "-m", "iscd", "run", "--config", str(bad), "--duration", "1"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    assert "rig.backend" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.slow
def test_soak_full_rate(tmp_path: Path) -> None:
    """`iscd run --duration 60` on the embedded default at 1000 fps: every packet decoded,
    no dropped frames, p99 latency <= 40 ms (measured 24-31 ms: blocks of 16 pairs are
    waited for, since the LED following takes its background over a block's frames; 9-13 ms
    before the LEDs were followed), CPU and RSS flat after warm-up."""
    cfg = C.default_config()
    out = tmp_path / "soak.jsonl"
    d = Daemon(cfg, out=str(out), duration_s=60.0, install_signals=False)
    d.run()
    recs = _records(out)
    stats = [r for r in recs if r["type"] == "stats"]
    final = stats[-1]
    print({k: v for k, v in final.items() if k != "acquisition"}, final["acquisition"])
    assert final["frames_dropped"] == 0
    assert final["packets_bad"] == 0 and final["packets_ok"] >= 40
    assert final["latency_ms_p99"] <= 40
    rss = [s["rss_mb"] for s in stats[10:-1]]
    assert max(rss) - min(rss) < 50
    cpu = [s["cpu_cores"] for s in stats[10:-1]]
    assert max(cpu) - min(cpu) < 0.5 and max(cpu) < 1.9  # flat, and not both cores


def test_failing_pairing_is_said_once_a_stats_interval(caplog) -> None:
    """Free-running cameras (no common trigger): frames come in, few find a partner. The
    daemon says so at every stats record while it lasts, and not when pairing works."""
    import logging

    from iscd.service.daemon import _UnpairedWatch

    w = _UnpairedWatch()

    def rec(frames_in: int, ul: int, ur: int) -> dict:
        return {"frames_in": frames_in, "acquisition": {"unpaired_left": ul, "unpaired_right": ur}}

    with caplog.at_level(logging.WARNING, logger="iscd.service.daemon"):
        assert not w.check(rec(2000, 1, 0))  # pairing works: 1 of 2000
        assert w.check(rec(3759, 851, 845))  # 1695 of 1759 without a partner
        assert w.check(rec(5500, 1700, 1690))
        assert not w.check(rec(7500, 1701, 1690))  # paired again
    said = [r for r in caplog.records if "pairing fails" in r.getMessage()]
    assert len(said) == 2 and "1695 of 1759" in said[0].getMessage()
