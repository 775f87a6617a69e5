"""``iscd tx``: the command against an emulated board on a pty."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from iscd.drivers.board import discovery
from iscd.drivers.board import protocol as P
from iscd.drivers.board.emulator import DEFAULT_INFO, Board, PtyEmulator
from iscd.core.airinterface import AirInterface
from iscd.cli.main import main

SMALL = """
[transmitter]
rows = 2
cols = 2
levels = 4
training_symbols = 8
data_symbols = 64
idle_symbols = 3
"""
SMALL_AIR = AirInterface(levels=4, n_leds=4, training_symbols=8, data_symbols=64, idle_symbols=3)


@pytest.fixture
def emu():
    with PtyEmulator() as e:
        yield e


@pytest.fixture
def small_cfg(tmp_path: Path) -> Path:
    p = tmp_path / "small.toml"
    p.write_text(SMALL)
    return p


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, dict | None, str]:
    rc = main(["tx", *argv])
    out, err = capsys.readouterr()
    lines = [ln for ln in out.splitlines() if ln.strip()]
    return rc, (json.loads(lines[-1]) if lines else None), err


def decoded_payload(board: Board, air: AirInterface) -> tuple[bytes, bool]:
    """What a receiver decodes from the board's LEDs: the data symbols of the 2nd packet."""
    return air.decode_data(board.levels(air.period_symbols + air.data_offset, air.data_symbols, air.n_leds))


def test_tx_loads_the_payload_the_leds_then_carry(capsys, emu: PtyEmulator, small_cfg: Path) -> None:
    payload = bytes.fromhex("c0ffee00") + b"tx test"
    rc, out, err = run(capsys, "--port", emu.port, "--config", str(small_cfg), "--payload-hex",
                       "c0 ff ee 00" + b"tx test".hex())
    assert rc == 0, err
    assert out is not None and out["port"] == emu.port and out["payload_hex"] == payload.hex()
    assert out["config"]["levels"] == 4 and out["config"]["rows"] == 2 and out["config"]["idle_symbols"] == 3
    assert out["status"]["state"] == "RUNNING" and out["status"]["faults"] == []  # POWER_ON_RESET cleared
    assert out["board"]["max_leds"] == DEFAULT_INFO.max_leds
    data, ok = decoded_payload(emu.board, SMALL_AIR)
    assert ok and data == payload.ljust(SMALL_AIR.payload_bytes, b"\0")
    np.testing.assert_array_equal(emu.board.sequence(), SMALL_AIR.packet(payload))

    rc, out, _ = run(capsys, "--port", emu.port, "--stop")
    assert rc == 0 and out["status"]["state"] == "READY"
    assert (emu.board.levels(0, 100, 4) == 1).all()
    rc, out, _ = run(capsys, "--port", emu.port, "--start")
    assert rc == 0 and out["status"]["state"] == "RUNNING"
    rc, out, _ = run(capsys, "--port", emu.port, "--status")
    assert rc == 0 and out["status"]["bytes_loaded"] == len(payload) and out["board"]["firmware"] == "1.0.0"
    emu.board.inject_fault(P.Fault.LED_OPEN)
    rc, out, _ = run(capsys, "--port", emu.port, "--status", "--clear-faults")
    assert rc == 0 and out["status"]["faults"] == []


def test_tx_payload_sources(capsys, tmp_path: Path, emu: PtyEmulator, small_cfg: Path) -> None:
    f = tmp_path / "p.bin"
    f.write_bytes(b"\x00\x01file")
    rc, out, _ = run(capsys, "--port", emu.port, "--config", str(small_cfg), "--payload-file", str(f),
                     "--no-start")
    assert rc == 0 and out["status"]["state"] == "READY" and out["payload_bytes"] == 6
    # a fixed [payload] in the config is used when no payload option is given
    cfg = tmp_path / "fixed.toml"
    cfg.write_text(SMALL + '[payload]\nsource = "text"\nvalue = "from config"\n')
    rc, out, _ = run(capsys, "--port", emu.port, "--config", str(cfg))
    assert rc == 0 and out["status"]["state"] == "RUNNING"
    data, ok = decoded_payload(emu.board, SMALL_AIR)
    assert ok and data.rstrip(b"\0") == b"from config"
    # a raw level sequence
    lv = np.random.default_rng(8).integers(1, 5, size=(10, 4))
    np.save(tmp_path / "lv.npy", lv)
    rc, out, _ = run(capsys, "--port", emu.port, "--config", str(small_cfg), "--levels-file", str(tmp_path / "lv.npy"))
    assert rc == 0 and out["levels_symbols"] == 10 and out["status"]["content"] == "LEVELS"
    np.testing.assert_array_equal(emu.board.levels(20, 10, 4), lv)


def test_tx_emulate_demo(capsys) -> None:
    rc, out, err = run(capsys, "--emulate", "--duration", "0", "--payload-text", "héllo")
    assert rc == 0 and "emulated board on /dev/" in err
    assert out["status"]["state"] == "RUNNING" and out["payload_hex"] == "héllo".encode().hex()


@pytest.mark.parametrize("argv,msg", [
    (["--payload-hex", "zz"], "--payload-hex: not a hex byte string"),
    (["--payload-text", "x" * 14397], "payload of 14397 bytes exceeds the capacity of 14396 bytes"),
    (["--payload-file", "/nonexistent/p.bin"], "--payload-file: cannot read /nonexistent/p.bin"),
    (["--emulate", "--port", "/dev/null"], "--emulate and --port exclude each other"),
    (["--duration", "1", "--status", "--port", "/dev/null"], "--duration only applies with --emulate"),
    (["--port", "/nonexistent/tty", "--status"], "cannot open board port /nonexistent/tty: No such file"),
    (["--config", "/nonexistent.toml"], "config file not found"),
])
def test_tx_bad_input_is_one_line_exit_2(capsys, argv: list[str], msg: str) -> None:
    rc, _, err = run(capsys, *argv)
    assert rc == 2 and msg in err and err.count("\n") == 1


def test_tx_bad_levels_file(capsys, tmp_path: Path, small_cfg: Path) -> None:
    np.save(tmp_path / "bad.npy", np.full((3, 5), 2))
    rc, _, err = run(capsys, "--port", "/dev/null", "--config", str(small_cfg), "--levels-file", str(tmp_path / "bad.npy"))
    assert rc == 2 and "expected a (T, 4) integer array for 2x2 LEDs" in err
    np.save(tmp_path / "bad.npy", np.full((3, 4), 5))
    rc, _, err = run(capsys, "--port", "/dev/null", "--config", str(small_cfg), "--levels-file", str(tmp_path / "bad.npy"))
    assert rc == 2 and "levels must be in 1..4" in err


def test_tx_board_errors_are_one_line_exit_1(capsys, tmp_path: Path) -> None:
    master, slave = os.openpty()  # nothing answers there
    try:
        rc, _, err = run(capsys, "--port", os.ttyname(slave), "--status", "--timeout", "0.05", "--retries", "1")
    finally:
        os.close(master)
        os.close(slave)
    assert rc == 1 and "did not answer 1 retries of GET_INFO within 0.05 s" in err and err.count("\n") == 1
    # a board that cannot do PWM-32 refuses the config, and says which field
    cfg = tmp_path / "m32.toml"
    cfg.write_text("[transmitter]\nlevels = 32\n")
    small_board = Board(info=P.BoardInfo(**{**DEFAULT_INFO.__dict__, "max_levels": 16}))
    with PtyEmulator(board=small_board) as e:
        rc, _, err = run(capsys, "--port", e.port, "--config", str(cfg), "--payload-text", "x")
    assert rc == 1 and "refused SET_CONFIG: bad parameter (levels out of the board's range)" in err


def test_tx_finds_the_board_on_usb(capsys, monkeypatch: pytest.MonkeyPatch, emu: PtyEmulator) -> None:
    boards = [discovery.FoundBoard(emu.port, "E1", 0x1209, 0x0001, "1-2", "emulated", ("usb", "serial")),
              discovery.FoundBoard(None, "E2", 0x1209, 0x0001, "1-3", "no tty", ("usb",))]
    monkeypatch.setattr(discovery, "find_boards", lambda vid, pid, **kw: boards)
    rc, out, _ = run(capsys, "--status")
    assert rc == 0 and out["port"] == emu.port
    rc = main(["tx", "--list"])
    lines = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    assert rc == 0 and [ln["serial_number"] for ln in lines] == ["E1", "E2"]
    boards.append(discovery.FoundBoard("/dev/ttyACM9", "E3", 0x1209, 0x0001, "1-4", "", ("serial",)))
    rc, _, err = run(capsys, "--status")
    assert rc == 2 and "2 LED boards found" in err and "choose one with --port" in err
    boards.clear()
    rc, _, err = run(capsys, "--status")
    assert rc == 2 and "no LED board found on USB (1209:0001)" in err


def test_tx_help_lists_the_options(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["tx", "--help"])
    text = capsys.readouterr().out
    for opt in ("--port", "--payload-text", "--payload-hex", "--payload-file", "--levels-file", "--start",
                "--stop", "--status", "--emulate", "--list", "--config"):
        assert opt in text
