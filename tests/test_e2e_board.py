"""End to end on one machine: ``iscd tx`` loads a payload into the emulated LED board, the
board drives the simulator's transmitter, and ``iscd run`` on the mock rig decodes exactly
that payload (issue 6).

``[board] emulate = true`` makes :func:`iscd.drivers.registry.make_stereo` (inside the daemon's
acquisition process) serve an emulated board on a pty linked at ``[board] port`` and show
its LEDs in the mock rig's scene (:class:`iscd.drivers.registry.BoardOnSceneClock`). The unit
tests below check the clock alignment against the scene's ground truth; the last test
runs the real commands as subprocesses.
"""

from __future__ import annotations

import gc
import json
import logging
import os
import random
import signal
import string
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from iscd.drivers.board.client import BoardClient
from iscd.drivers.board.protocol import BoardConfig
from iscd.drivers.registry import BoardOnSceneClock, check_stereo_config, make_stereo
from iscd.core.airinterface import AirInterface
from iscd.core.config import ConfigError, loads

# A 2x2 array (6 cm pitch: several LEDs also check that the board's LED order is the
# scene's), PWM-8, b = 0.25 m at 30 m, equal f/4 apertures, F = 100 so that a packet lasts
# 153 symbols = 0.306 s (capacity 146 bytes) and a short run holds many. A 128x128 ROI and
# no ranging, so that the daemon keeps up with 1000 fps on a loaded, shared 2-core machine
# (this test is about the board -> scene -> decoder path; at 512x512 it drops most frames).
CONFIG = """
[transmitter]
rows = 2
cols = 2
levels = 8
data_symbols = {F}

[camera]
baseline_m = 0.25
f_number_right = 4
width = 128
height = 128

[scene]
distance_m = 30
seed = {seed}

[payload]
source = "text"
value = "DECOY: the scene must not send the config's payload"

[rig]
backend = "mock"
pace = true

[board]
emulate = true
port = "{port}"

[tracking]
ranging = false
"""


def config_text(port: Path, F: int = 100, seed: int = 1) -> str:
    return CONFIG.format(port=port, F=F, seed=seed)


def random_text(n: int, seed: int) -> str:
    r = random.Random(seed)
    return "".join(r.choice(string.ascii_letters + string.digits) for _ in range(n))


def started_rig(cfg_text: str) -> tuple[Any, Any, Any]:
    """(left, right, rig) of make_stereo, cameras started (the rig clock runs)."""
    left, right = make_stereo(loads(cfg_text))
    for cam in (right, left):
        cam.open()
        cam.start()
    return left, right, left.rig


def shut(left: Any, right: Any, rig: Any) -> None:
    for cam in (left, right):
        cam.close()
    rig.level_source.emulator.close()


# ------------------------------------------------------------------ config checks

@pytest.mark.parametrize("extra, match", [
    ('[rig]\nbackend = "genicam"\nleft = "0"\nright = "1"\n[board]\nemulate = true\nport = "{p}"',
     "needs rig.backend = \"mock\""),
    ('[rig]\npace = false\n[board]\nemulate = true\nport = "{p}"', "needs rig.pace = true"),
    ('[board]\nemulate = true', "board.port: set where the emulated board's pty appears"),
    ('[board]\nemulate = true\nport = "socket://localhost:7000"', "needs a file path"),
    ('[board]\nemulate = true\nport = "{p}/no/such/dir/board"', "does not exist"),
    ('[board]\nemulate = true\nport = "{f}"', "exists and is not a symlink"),
])
def test_board_emulation_config_errors_name_the_key(tmp_path: Path, extra: str, match: str) -> None:
    regular = tmp_path / "a-real-file"
    regular.write_text("keep me")
    cfg = loads(extra.format(p=tmp_path, f=regular))
    with pytest.raises(ConfigError, match=match) as e:
        make_stereo(cfg)
    assert "\n" not in str(e.value)
    assert regular.read_text() == "keep me"


def test_the_config_can_be_checked_before_anything_is_built(tmp_path: Path) -> None:
    link = tmp_path / "board"
    assert check_stereo_config(loads(config_text(link))) == str(link)
    assert not os.path.lexists(link)  # nothing served yet
    assert check_stereo_config(loads("")) is None
    with pytest.raises(ConfigError, match="rig.pace"):
        check_stereo_config(loads(config_text(link) + "\n").replace(
            rig=loads('[rig]\npace = false').rig))


def test_without_emulate_no_board_is_served(tmp_path: Path) -> None:
    left, _ = make_stereo(loads(f'[board]\nport = "{tmp_path / "board"}"'))
    assert not isinstance(left.rig.level_source, BoardOnSceneClock)
    assert not (tmp_path / "board").exists()


# ------------------------------------------------------------------ the board on the scene clock

def test_board_symbols_start_on_the_scene_clock_at_start(tmp_path: Path) -> None:
    """What the scene shows (its ground truth) is the air-interface packet of the payload
    loaded over the pty, from the first LED symbol that starts at or after START."""
    link = tmp_path / "board"
    cfg_text = config_text(link, seed=3)
    left, right, rig = started_rig(cfg_text)
    scene = rig.scene
    assert scene.clock.drift_ppm == 100  # a drifting LED clock with a random phase
    src = rig.level_source
    assert isinstance(src, BoardOnSceneClock) and link.is_symlink()
    fps, T = scene.fps, scene.clock.symbol_period_s
    t0_s = rig.trigger_time_ns(0) * 1e-9

    # not loaded yet: the LEDs are dark in the scene
    tr = scene.truth(np.arange(0, 400))
    assert np.all(tr.levels == 1) and np.all(tr.on_fraction == 0)

    cfg = loads(cfg_text)
    payload = random_text(50, seed=11).encode()
    time.sleep(0.3)  # START well after trigger 0, so that frames before it exist
    with BoardClient(str(link)) as client:
        status = client.transmit(BoardConfig.from_transmitter(cfg.transmitter), payload=payload)
    assert status.state.name == "RUNNING"
    start = src.board.start_time
    assert start is not None
    t_start = start - t0_s  # camera time of START, s
    assert t_start > 0.25

    frames = np.arange(max(0, int(t_start * fps) - 50), int(t_start * fps) + 1200)
    tr = scene.truth(frames)
    lit = np.flatnonzero(np.any(tr.levels != 1, axis=1))
    first = lit[0]
    # symbol 0 of the board (the header's first "+", level M) starts within one symbol
    # after START on the scene's own (drifting, phase-shifted) LED clock
    assert t_start <= tr.symbol_t_s[first] < t_start + T
    assert np.all(tr.levels[first] == cfg.transmitter.levels)
    air = AirInterface.from_config(cfg.transmitter)
    want = air.packet(payload)  # (P, N): every LED in the air interface's row-major order
    got = tr.levels[first:first + 2 * len(want)]
    assert np.array_equal(got, np.concatenate([want, want]))  # back to back, bit-exact
    assert np.all(tr.levels[:first] == 1)
    # and the frames integrate it: the LEDs are lit in frames after START only
    on = tr.on_fraction
    before = tr.t_s + scene.exposure_s <= t_start
    assert before.sum() >= 40 and on[before].max() == 0.0
    assert on[tr.t_s > t_start + T].max() > 0.5

    # a new START (iscd tx again) restarts the packets at the new START
    payload2 = random_text(50, seed=12).encode()
    time.sleep(0.05)
    with BoardClient(str(link)) as client:
        client.transmit(BoardConfig.from_transmitter(cfg.transmitter), payload=payload2)
    t_start2 = src.board.start_time - t0_s
    assert t_start2 > t_start + 0.04
    k2 = src.start_symbol(src.board.start_time)
    assert t_start2 <= scene.clock.symbol_start_cam(k2) < t_start2 + T
    assert np.array_equal(src.levels(k2, k2 + len(want)), air.packet(payload2))
    shut(left, right, rig)


def test_a_board_configured_for_another_transmitter_leaves_the_leds_dark(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    link = tmp_path / "board"
    left, right, rig = started_rig(config_text(link))
    src = rig.level_source
    wrong = BoardConfig(levels=8, rows=1, cols=4, data_symbols=100)  # N = 4 too, but 1x4
    with caplog.at_level(logging.WARNING), BoardClient(str(link)) as client:
        client.transmit(wrong, payload=b"x" * 10)
        k = src.start_symbol(src.board.start_time)
        assert np.all(src.levels(k, k + 300) == 1)
        assert np.all(rig.scene.truth(np.arange(0, 3000)).levels == 1)  # rendering goes on
    assert "configured for 1x4 LEDs" in caplog.text and "iscd tx --config" in caplog.text
    shut(left, right, rig)


def test_the_board_goes_away_with_the_cameras(tmp_path: Path) -> None:
    link = tmp_path / "board"
    left, right = make_stereo(loads(config_text(link)))
    pty = os.readlink(link)
    assert os.path.exists(pty)
    with BoardClient(str(link)) as client:
        assert client.status().state.name == "UNCONFIGURED"
    del left, right
    gc.collect()
    assert not os.path.lexists(link)


# ------------------------------------------------------------------ the real commands

def _records(path: Path) -> list[dict]:
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:  # pragma: no cover - the writer writes whole lines
            pass
    return out


def _wait_for(pred, proc: subprocess.Popen, timeout_s: float, what: str, err: Path) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = pred()
        if got:
            return got
        if proc.poll() is not None:
            pytest.fail(f"iscd run ended (rc {proc.returncode}) before {what}:\n"
                        + err.read_text()[-3000:])
        time.sleep(0.1)
    pytest.fail(f"no {what} within {timeout_s:g} s; daemon log:\n" + err.read_text()[-3000:])


def _tx(cfg: Path, payload: str) -> dict:
    r = subprocess.run([sys.executable, "-m", "iscd", "tx", "--config", str(cfg),
                        "--payload-text", payload], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_iscd_tx_into_the_emulated_board_and_iscd_run_decodes_exactly_that_payload(
        tmp_path: Path) -> None:
    """`iscd run` (mock rig, [board] emulate) as a subprocess; `iscd tx --config` (port from
    the config) loads payload A, later payload B. The JSONL must hold CRC-valid packets of A,
    then of B, zero-padded to the capacity, and no CRC-valid packet of anything else.

    The run is stopped (SIGTERM) once B was decoded; a loaded machine that drops frames
    only makes it take longer (up to 60 s), it cannot make a wrong packet pass.
    """
    link = tmp_path / "board"
    cfg_path = tmp_path / "e2e.toml"
    cfg_path.write_text(config_text(link))
    cfg = loads(cfg_path.read_text())
    capacity = AirInterface.from_config(cfg.transmitter).payload_bytes
    assert capacity == 146
    # nearly full packets: a short payload's zero padding is level 1 (dark) for most of
    # the packet, and the tracker then loses the LED (see the report to the lead)
    a, b = random_text(capacity - 8, seed=1), random_text(capacity - 3, seed=2)
    want = {name: text.encode().ljust(capacity, b"\0").hex() for name, text in (("A", a), ("B", b))}
    out, err = tmp_path / "run.jsonl", tmp_path / "run.log"
    with open(err, "w") as log_file:
        proc = subprocess.Popen([sys.executable, "-m", "iscd", "run", "--config", str(cfg_path),
                                 "--duration", "90", "--out", str(out)],
                                stdout=subprocess.PIPE, stderr=log_file, text=True)
    try:
        _wait_for(link.is_symlink, proc, 60, "the emulated board's link", err)

        def streaming() -> bool:
            return any(r["type"] == "stats" and r["pairs_decoded"] >= 300 for r in _records(out))

        _wait_for(streaming, proc, 60, "300 decoded pairs", err)
        # dark LEDs before START: nothing blinks, so no packet and no transmitter
        before = _records(out)
        assert not [r for r in before if r["type"] == "packet"]
        assert not any(r["type"] == "stats" and r["tracking"] for r in before)

        def ok_packets(payload_hex: str):
            return lambda: [r for r in _records(out) if r["type"] == "packet" and r["crc_ok"]
                            and r["payload_hex"] == payload_hex]

        sent = _tx(cfg_path, a)
        assert sent["port"] == str(link) and sent["status"]["state"] == "RUNNING"
        assert sent["payload_hex"] == a.encode().hex()
        _wait_for(ok_packets(want["A"]), proc, 60, "a CRC-valid packet of payload A", err)
        _tx(cfg_path, b)
        _wait_for(ok_packets(want["B"]), proc, 60, "a CRC-valid packet of payload B", err)
        proc.send_signal(signal.SIGTERM)
        stdout, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 0, err.read_text()[-3000:]
    summary = json.loads(stdout.strip().splitlines()[-1])
    recs = _records(out)
    packets = [r for r in recs if r["type"] == "packet"]
    ok = [r for r in packets if r["crc_ok"]]
    names = [next((n for n, h in want.items() if h == r["payload_hex"]), r["payload_hex"][:16])
             for r in ok]
    assert set(names) == {"A", "B"}, names  # nothing else ever passed the CRC
    assert names == sorted(names), names  # all A packets before all B packets
    for r in ok:
        assert len(r["levels"]) == cfg.transmitter.data_symbols * cfg.transmitter.n_leds
        assert set(r["levels"]) <= set(range(1, 9))
    final = recs[-1]
    assert final["type"] == "stats" and final["final"]
    assert final["packets_ok"] == len(ok) == summary["packets_ok"]
    # the acquisition process closed the board on its way out
    assert not os.path.lexists(link)
    print(f"\ne2e: {len(ok)} packets ok ({names.count('A')} A, {names.count('B')} B), "
          f"{len(packets) - len(ok)} bad, {final['frames_dropped']} frames dropped of "
          f"{final['frame'] + 1}, {final['t_s']} s")
