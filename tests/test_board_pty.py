"""The board protocol end to end over a real pseudo-terminal: BoardClient (pyserial on the
pty's slave device) against the emulated board (on the master side)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from iscd.drivers.board import protocol as P
from iscd.drivers.board.client import BoardClient, BoardNak, BoardPortError, BoardTimeout
from iscd.drivers.board.emulator import DEFAULT_INFO, Board, PtyEmulator
from iscd.core.airinterface import AirInterface

TIMEOUT = 0.1
RETRIES = 2

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs POSIX pseudo-terminals")


@pytest.fixture
def emu(tmp_path: Path):
    with PtyEmulator(link=tmp_path / "board") as e:
        yield e


@pytest.fixture
def client(emu: PtyEmulator):
    with BoardClient(emu.port, timeout=TIMEOUT, retries=RETRIES, first_seq=0) as c:  # deterministic
        yield c


def exchange(client: BoardClient, wire: bytes, wait: float = 0.15) -> list[P.Frame]:
    """Write raw bytes on the client's port; the frames that come back within ``wait``."""
    ser = client._ser
    assert ser is not None
    ser.write(wire)
    d = P.Deframer()
    frames: list[P.Frame] = []
    end = time.monotonic() + wait
    while time.monotonic() < end:
        frames += [P.parse_body(b) for b in d.feed(ser.read(max(1, ser.in_waiting)))]
    return frames


def small_config(**kw) -> P.BoardConfig:
    base = dict(levels=4, rows=2, cols=3, symbol_rate_mhz=500_000, pwm_hz=50_000,
                training_symbols=8, data_symbols=40, idle_symbols=2)
    base.update(kw)
    return P.BoardConfig(**base)


# --- every command ----------------------------------------------------------------------


def test_every_command_round_trip(emu: PtyEmulator, client: BoardClient) -> None:
    board = emu.board
    assert client.info == DEFAULT_INFO  # HELLO in the constructor
    assert client.hello() == DEFAULT_INFO
    st = client.status()
    assert (st.state, st.content, st.faults) == (P.State.UNCONFIGURED, P.Content.NONE, P.Fault.POWER_ON_RESET)

    cfg = small_config()
    client.set_config(cfg)
    assert board.config == cfg and client.status().state is P.State.CONFIGURED

    air = AirInterface(levels=4, n_leds=6, training_symbols=8, data_symbols=40, idle_symbols=2)
    payload = b"iscd!"
    assert client.load_payload(payload) == len(payload)
    st = client.status()
    assert (st.state, st.content, st.bytes_loaded, st.bytes_total) == (P.State.READY, P.Content.PAYLOAD, 5, 5)

    client.start()
    time.sleep(0.06)  # 30 symbols at 500 Hz
    st = client.status()
    assert st.state is P.State.RUNNING and 10 <= st.symbol_counter <= 2000
    assert st.packets_sent == st.symbol_counter // air.period_symbols

    client.stop()
    a, b = client.status(), client.status()
    assert a.state is P.State.READY and a.symbol_counter == b.symbol_counter >= st.symbol_counter

    assert client.clear_faults(P.Fault.POWER_ON_RESET) == P.Fault(0)
    assert client.status().faults == P.Fault(0)

    seq = np.random.default_rng(5).integers(1, 5, size=(7, 6)).astype(np.uint8)
    assert client.load_levels(seq) == seq.size
    client.start()
    np.testing.assert_array_equal(board.sequence(), seq)
    np.testing.assert_array_equal(board.levels(5, 4), seq[[5, 6, 0, 1]])
    assert client.status().content is P.Content.LEVELS

    assert set(board.executed) == {c.name for c in P.Command}
    assert client.stats.retries == 0 and client.stats.bad_frames == 0
    assert board.rx_errors == 0 and board.rx_frames == client.stats.commands


def test_level_source_is_the_air_interface_packet_of_a_full_pwm16_payload(
        emu: PtyEmulator, client: BoardClient) -> None:
    air = AirInterface(levels=16, n_leds=64)
    assert air.payload_bytes == 19196
    payload = np.random.default_rng(11).integers(0, 256, air.payload_bytes, dtype=np.uint8).tobytes()
    st = client.transmit(P.BoardConfig(levels=16), payload)
    assert st.state is P.State.RUNNING and st.bytes_loaded == 19196 and st.faults == P.Fault(0)
    assert client.stats.commands >= 19196 // P.MAX_CHUNK

    board = emu.board
    packet = air.packet(payload)
    np.testing.assert_array_equal(board.sequence(), packet)
    period = air.period_symbols
    got = board.levels(3 * period - 10, 30, n_leds=64)  # across a packet boundary
    np.testing.assert_array_equal(got, np.concatenate([packet[-10:], packet[:20]]))
    assert got.dtype == np.uint8 and got.shape == (30, 64)
    start = air.data_offset
    data, ok = air.decode_data(board.levels(period + start, air.data_symbols))
    assert ok and data == payload

    np.testing.assert_array_equal(board.levels(-3, 5), np.concatenate([np.ones((3, 64)), packet[:2]]))
    with pytest.raises(ValueError, match="configured for 64 LEDs"):
        board.levels(0, 3, n_leds=1)
    src = board.level_source(64)  # the simulator's level-source protocol: levels(k0, k1)
    np.testing.assert_array_equal(src.levels(period, 2 * period), packet)
    try:
        from iscd.sim.transmitter import LevelSource
    except ImportError:
        pass  # the simulator is not there: the shape check above is the contract
    else:
        assert isinstance(src, LevelSource)
    client.stop()
    np.testing.assert_array_equal(board.levels(0, 5), np.ones((5, 64), np.uint8))


def test_oversized_payload_is_refused_and_the_loaded_one_kept(emu: PtyEmulator, client: BoardClient) -> None:
    client.transmit(P.BoardConfig(levels=16), b"keep me", start=False)
    with pytest.raises(BoardNak) as e:
        client.load_payload(bytes(19197))
    assert e.value.code is P.NakCode.TOO_LARGE and e.value.arg == 19196
    assert "refused LOAD_PAYLOAD: too large (the limit is 19196 bytes)" in str(e.value)
    st = client.status()
    assert (st.state, st.bytes_loaded) == (P.State.READY, 7)
    # a smaller board buffer is the limit when it is below the packet capacity
    emu.board.info = P.BoardInfo(**{**DEFAULT_INFO.__dict__, "buffer_bytes": 1000})
    with pytest.raises(BoardNak, match="the limit is 1000 bytes"):
        client.load_payload(bytes(1001))


# --- NAK paths --------------------------------------------------------------------------


def test_wrong_state_and_busy(emu: PtyEmulator, client: BoardClient) -> None:
    with pytest.raises(BoardNak, match=r"refused LOAD_PAYLOAD: wrong state \(board is UNCONFIGURED\)"):
        client.load_payload(b"x")
    client.set_config(small_config())
    with pytest.raises(BoardNak, match=r"refused START: wrong state \(board is CONFIGURED\)") as e:
        client.start()
    assert e.value.code is P.NakCode.WRONG_STATE
    client.load_payload(b"x")
    client.start()
    with pytest.raises(BoardNak, match="refused START: wrong state .board is RUNNING"):
        client.start()
    for call in (lambda: client.set_config(small_config()), lambda: client.load_payload(b"y")):
        with pytest.raises(BoardNak, match="busy") as e:
            call()
        assert e.value.code is P.NakCode.BUSY
    assert client.status().state is P.State.RUNNING  # nothing changed
    client.stop()
    client.stop()  # STOP is accepted in any state


@pytest.mark.parametrize("field,value,index", [
    ("levels", 3, 0), ("levels", 64, 0), ("rows", 0, 1), ("cols", 0, 2), ("cols", 255, 2),
    ("flags", 8, 3), ("symbol_rate_mhz", 999, 4), ("symbol_rate_mhz", 200_000_000, 4),
    ("pwm_hz", 499, 5), ("pwm_hz", 3_000_000, 5), ("data_symbols", 0, 7),
    ("training_symbols", 65535, 6), ("data_symbols", 65535, 7),
])
def test_set_config_bad_parameter_names_the_field(client: BoardClient, field: str, value: int, index: int) -> None:
    if field == "cols" and value == 255:
        cfg = small_config(rows=255, cols=255)  # more LEDs than max_leds
    elif value == 65535:
        cfg = small_config(rows=64, cols=64, **{field: value})  # a period beyond the emulator's limit
    else:
        cfg = small_config(**{field: value})
    with pytest.raises(BoardNak) as e:
        client.set_config(cfg)
    assert e.value.code is P.NakCode.BAD_PARAMETER and e.value.arg == index
    assert P.CONFIG_FIELDS[index] in str(e.value)
    assert client.status().state is P.State.UNCONFIGURED


def test_load_levels_refuses_bad_levels_and_counts(client: BoardClient) -> None:
    client.set_config(small_config())  # M = 4, N = 6
    bad = np.ones((3, 6), np.uint8)
    bad[2, 4] = 5
    with pytest.raises(BoardNak) as e:
        client.load_levels(bad)
    assert e.value.code is P.NakCode.BAD_PARAMETER and e.value.arg == 2 * 6 + 4
    with pytest.raises(BoardNak) as e:
        client.load_levels(np.ones((1, 5), np.uint8))  # not a multiple of N = 6
    assert e.value.code is P.NakCode.BAD_PARAMETER and e.value.arg == 6
    with pytest.raises(BoardNak) as e:
        client.load_levels(np.ones((65536 // 6 + 1, 6), np.uint8))
    assert e.value.code is P.NakCode.TOO_LARGE
    assert client.status().state is P.State.CONFIGURED


def test_chunk_offsets_lengths_and_raw_errors(client: BoardClient) -> None:
    client.set_config(small_config())
    air = AirInterface(levels=4, n_leds=6, training_symbols=8, data_symbols=40, idle_symbols=2)
    cap = air.payload_bytes

    def nak(cmd: int, payload: bytes) -> P.Nak:
        with pytest.raises(BoardNak) as e:
            client.request(cmd, payload)
        return P.Nak(e.value.command, int(e.value.code), e.value.arg)

    assert nak(P.Command.LOAD_PAYLOAD, P.LoadChunk(4, cap, b"ab").pack()).code == P.NakCode.BAD_OFFSET
    client.request(P.Command.LOAD_PAYLOAD, P.LoadChunk(0, cap, b"ab").pack())
    n = nak(P.Command.LOAD_PAYLOAD, P.LoadChunk(3, cap, b"cd").pack())
    assert (n.code, n.arg) == (P.NakCode.BAD_OFFSET, 2)
    n = nak(P.Command.LOAD_PAYLOAD, P.LoadChunk(2, cap, bytes(cap)).pack()[:P.MAX_PAYLOAD])
    assert n.code == P.NakCode.BAD_LENGTH  # runs past the announced total
    assert nak(P.Command.LOAD_PAYLOAD, b"\x00\x00").code == P.NakCode.BAD_LENGTH
    assert nak(P.Command.START, b"\x01").code == P.NakCode.BAD_LENGTH
    assert nak(P.Command.SET_CONFIG, small_config().pack()[:-1]).code == P.NakCode.BAD_LENGTH
    assert nak(P.Command.CLEAR_FAULTS, b"").code == P.NakCode.BAD_LENGTH
    st = client.status()
    assert (st.state, st.bytes_loaded) == (P.State.CONFIGURED, 2)  # the good chunk only

    # frames the client would never send: unknown type, another version
    (f,) = exchange(client, P.encode_frame(0x3F, 77))
    assert (f.type, f.seq, P.Nak.unpack(f.payload).code) == (P.ReplyType.NAK, 77, P.NakCode.UNKNOWN_COMMAND)
    (f,) = exchange(client, P.encode_frame(P.Command.GET_STATUS, 78, version=2))
    n = P.Nak.unpack(f.payload)
    assert (f.version, f.seq, n.code, n.arg) == (1, 78, P.NakCode.VERSION_MISMATCH, 1)


def test_critical_fault_stops_the_leds_until_cleared(emu: PtyEmulator, client: BoardClient) -> None:
    client.transmit(small_config(), b"go")
    emu.board.inject_fault(P.Fault.OVERTEMP | P.Fault.LED_OPEN)
    st = client.status()
    assert st.state is P.State.FAULT and P.Fault.OVERTEMP in st.faults
    assert (emu.board.levels(0, 50) == 1).all()
    with pytest.raises(BoardNak, match="board is FAULT"):
        client.start()
    assert client.clear_faults(P.Fault.OVERTEMP) == P.Fault.LED_OPEN
    assert client.status().state is P.State.READY
    client.start()
    assert (emu.board.levels(0, 13)[:5] == 4).all()  # the header's first '+' symbols, M = 4


# --- a noisy line -----------------------------------------------------------------------


def test_garbage_and_partial_frames_towards_the_host(emu: PtyEmulator, client: BoardClient) -> None:
    rng = np.random.default_rng(2)
    status_reply = P.encode_frame(P.ReplyType.ACK, 99, P.ack_payload(P.Command.GET_STATUS, bytes(28)))
    for _ in range(5):
        noise = rng.integers(1, 256, int(rng.integers(1, 600)), dtype=np.uint8).tobytes()
        emu.inject_to_host(noise + status_reply[: int(rng.integers(2, len(status_reply) - 1))])
        assert client.status().state is P.State.UNCONFIGURED
    emu.inject_to_host(status_reply)  # a complete but unexpected (stale seq) reply
    client.hello()
    assert client.stats.retries == 0  # every reply was found behind the noise on first try
    assert client.stats.garbage_bytes > 0 and client.stats.stray_frames >= 1


def test_garbage_and_partial_frames_towards_the_board(emu: PtyEmulator, client: BoardClient) -> None:
    rng = np.random.default_rng(4)
    ser = client._ser
    assert ser is not None
    start_frame = P.encode_frame(P.Command.SET_CONFIG, 5, small_config().pack())
    for _ in range(5):
        ser.write(rng.integers(1, 256, 100, dtype=np.uint8).tobytes() + start_frame[1:20])
        client.set_config(small_config())
    ser.write(rng.integers(1, 256, 3000, dtype=np.uint8).tobytes())  # longer than any frame
    st = client.status()
    assert st.state is P.State.CONFIGURED and P.Fault.RX_OVERFLOW in st.faults
    assert st.rx_errors >= 6 and client.stats.retries == 0
    assert emu.board.executed["SET_CONFIG"] == 5


def test_a_corrupted_request_is_nakked_and_resent(emu: PtyEmulator, client: BoardClient) -> None:
    client.transmit(small_config(), b"abc", start=False)
    ser = client._ser
    assert ser is not None
    real_write = ser.write
    hits = []

    def flip_once(data: bytes) -> int:
        if not hits:
            hits.append(data)
            data = data[:-3] + bytes([data[-3] ^ 0x40]) + data[-2:]  # a CRC byte, never 0x00
        return real_write(data)

    ser.write = flip_once  # type: ignore[method-assign]
    t0 = time.monotonic()
    client.start()
    assert time.monotonic() - t0 < TIMEOUT  # resent on the NAK, not after the timeout
    assert client.stats.retries == 1 and emu.board.executed["START"] == 1
    assert client.status().state is P.State.RUNNING


# --- duplicates -------------------------------------------------------------------------


def test_duplicate_seq_is_answered_from_the_cache_not_executed(emu: PtyEmulator, client: BoardClient) -> None:
    board = emu.board
    client.set_config(small_config())
    chunk = P.encode_frame(P.Command.LOAD_PAYLOAD, 40, P.LoadChunk(0, 10, b"01234").pack())
    (a,) = exchange(client, chunk)
    (b,) = exchange(client, chunk)
    assert a == b and a.type == P.ReplyType.ACK and P.LOAD_PROGRESS.unpack(a.payload[1:]) == (5,)
    assert board.executed["LOAD_PAYLOAD"] == 1 and board.duplicates == 1
    assert client.status().bytes_loaded == 5  # not appended twice
    # the same seq with another body is a new command
    (c,) = exchange(client, P.encode_frame(P.Command.LOAD_PAYLOAD, 40, P.LoadChunk(5, 10, b"56789").pack()))
    assert P.LOAD_PROGRESS.unpack(c.payload[1:]) == (10,) and board.executed["LOAD_PAYLOAD"] == 2
    start = P.encode_frame(P.Command.START, 41)
    replies = exchange(client, start + start)
    assert [r.type for r in replies] == [P.ReplyType.ACK, P.ReplyType.ACK]
    assert board.executed["START"] == 1
    # a new START (new seq) is executed, and refused: the board is running
    (d,) = exchange(client, P.encode_frame(P.Command.START, 42))
    assert P.Nak.unpack(d.payload).code == P.NakCode.WRONG_STATE
    # read-only commands are always executed afresh
    st = P.encode_frame(P.Command.GET_STATUS, 43)
    exchange(client, st + st)
    assert board.executed["GET_STATUS"] >= 2


def test_lost_reply_is_retried_with_the_same_seq(emu: PtyEmulator, client: BoardClient) -> None:
    client.transmit(small_config(), b"abc", start=False)
    emu.board.drop_replies = 2  # the START executes; its first two replies are lost
    client.start()
    assert client.stats.retries == 2 and client.stats.timeouts == 2
    assert emu.board.executed["START"] == 1 and emu.board.duplicates == 2
    assert client.status().state is P.State.RUNNING


# --- a board that goes away -------------------------------------------------------------


def test_hung_board_times_out_with_a_clear_message_and_recovers(emu: PtyEmulator, client: BoardClient) -> None:
    emu.paused = True
    t0 = time.monotonic()
    with pytest.raises(BoardTimeout) as e:
        client.start()
    elapsed = time.monotonic() - t0
    assert str(e.value) == f"board on {emu.port} did not answer 2 retries of START within 0.1 s"
    assert (1 + RETRIES) * TIMEOUT * 0.9 <= elapsed < 2.0
    emu.paused = False
    assert client.status().state is P.State.UNCONFIGURED


def test_closed_pty_is_reported_and_the_client_recovers_when_the_board_returns(
        tmp_path: Path, emu: PtyEmulator, client: BoardClient) -> None:
    client.transmit(small_config(), b"abc")
    emu.close()  # unplugged: the pty and its link vanish
    with pytest.raises(BoardTimeout) as e:
        client.status()
    msg = str(e.value)
    assert msg.startswith(f"board on {emu.port} did not answer 2 retries of GET_STATUS within 0.1 s")
    assert "No such file or directory" in msg and "\n" not in msg
    with pytest.raises(BoardTimeout):  # still gone
        client.stop()

    with PtyEmulator(link=tmp_path / "board") as back:  # plugged in again (a new pty)
        st = client.status()
        assert st.state is P.State.UNCONFIGURED and P.Fault.POWER_ON_RESET in st.faults
        assert client.stats.reconnects == 1 and client.stats.port_errors >= 2
        client.transmit(small_config(), b"again")
        assert back.board.state is P.State.RUNNING


def test_killed_emulator_process_then_restarted(tmp_path: Path) -> None:
    link = tmp_path / "board"

    def spawn() -> subprocess.Popen[str]:
        proc = subprocess.Popen([sys.executable, "-m", "iscd.drivers.board.emulator", "--pty", "--link", str(link)],
                                stdout=subprocess.PIPE, text=True)
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == str(link)
        return proc

    proc = spawn()
    try:
        with BoardClient(str(link), timeout=TIMEOUT, retries=1) as client:
            client.transmit(small_config(), b"x")
            proc.kill()
            proc.wait(5)
            with pytest.raises(BoardTimeout, match=f"board on {link} did not answer 1 retries of GET_STATUS"):
                client.status()
            proc = spawn()
            assert client.status().state is P.State.UNCONFIGURED
            assert client.stats.reconnects == 1
    finally:
        proc.kill()
        proc.wait(5)


def test_unopenable_port_and_silent_port(tmp_path: Path) -> None:
    with pytest.raises(BoardPortError, match=f"cannot open board port {tmp_path}/nope: No such file or directory"):
        BoardClient(str(tmp_path / "nope"))
    master, slave = os.openpty()  # a tty where nothing answers
    try:
        with pytest.raises(BoardTimeout, match="did not answer 0 retries of GET_INFO within 0.05 s"):
            BoardClient(os.ttyname(slave), timeout=0.05, retries=0)
    finally:
        os.close(master)
        os.close(slave)


def test_board_logic_without_a_pty_uses_its_clock() -> None:
    now = [100.0]
    board = Board(clock=lambda: now[0])

    def cmd(c: P.Command, payload: bytes = b"", seq: int = 0) -> P.Frame:
        out = P.Deframer().feed(board.receive(P.encode_frame(c, seq, payload)))
        return P.parse_body(out[0])

    assert cmd(P.Command.SET_CONFIG, small_config(symbol_rate_mhz=1_000_000).pack(), 1).type == P.ReplyType.ACK
    assert cmd(P.Command.LOAD_PAYLOAD, P.LoadChunk(0, 0, b"").pack(), 2).type == P.ReplyType.ACK  # empty payload
    assert cmd(P.Command.START, seq=3).type == P.ReplyType.ACK
    assert board.running and board.start_time == 100.0
    now[0] += 2.5  # 2500 symbols at 1 kHz; a period is 13 + 8 + 40 + 2 = 63
    st = board.status()
    assert (st.symbol_counter, st.packets_sent) == (2500, 2500 // 63)
    cmd(P.Command.STOP, seq=4)
    now[0] += 1.0
    assert board.status().symbol_counter == 2500 and board.start_time is None


def test_board_survives_random_frames_and_bytes() -> None:
    """Untrusted input: valid-CRC frames with random payloads for every command, mutated
    frames and raw noise never crash the board, and it answers normally afterwards."""
    rng = np.random.default_rng(12)
    board = Board()
    d = P.Deframer()
    board.receive(P.encode_frame(P.Command.SET_CONFIG, 1, small_config().pack()))
    for i in range(3000):
        kind = i % 3
        if kind == 0:  # well-formed frame, random type and payload
            ftype = int(rng.choice([*map(int, P.Command), int(rng.integers(0, 256))]))
            payload = rng.integers(0, 256, int(rng.integers(0, P.MAX_PAYLOAD + 1)), dtype=np.uint8).tobytes()
            if ftype in (P.Command.LOAD_PAYLOAD, P.Command.LOAD_LEVELS) and rng.random() < 0.5:
                payload = P.LoadChunk(int(rng.integers(0, 50)), int(rng.integers(0, 400)),
                                      payload[: P.MAX_CHUNK]).pack()
            wire = P.encode_frame(ftype, int(rng.integers(0, 256)), payload, version=int(rng.choice([1, 1, 1, 2])))
        elif kind == 1:  # a frame with bytes flipped
            wire = bytearray(P.encode_frame(P.Command.SET_CONFIG, 3, small_config().pack()))
            for j in rng.integers(0, len(wire), int(rng.integers(1, 4))):
                wire[j] = int(rng.integers(0, 256))
            wire = bytes(wire)
        else:  # noise
            wire = rng.integers(0, 256, int(rng.integers(1, 700)), dtype=np.uint8).tobytes()
        for body in d.feed(board.receive(wire)):
            f = P.parse_body(body)  # every reply is well-formed
            assert f.type in (P.ReplyType.ACK, P.ReplyType.NAK) and f.version == 1
        assert len(board._buffer) <= board.info.buffer_bytes
    board.inject_fault(P.Fault(0))
    board.receive(b"\0")  # end any partial frame
    out = d.feed(board.receive(P.encode_frame(P.Command.GET_STATUS, 9)))
    f = P.parse_body(out[-1])
    assert f.type == P.ReplyType.ACK and f.seq == 9
    st = P.BoardStatus.unpack(f.payload[1:])
    assert st.rx_errors > 100 and st.rx_frames > 1000
