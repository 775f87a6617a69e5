"""The LED board's side of protocol v1, in Python: the reference for firmware authors.

:class:`Board` is the board's logic with no I/O: bytes from the serial line go in
(:meth:`Board.receive`), reply bytes come out. It does what the firmware must do, in the
same order (docs/board-protocol.md, "Board behaviour"): resynchronise at delimiters,
check CRC and lengths, answer a repeated sequence number from its reply cache without
executing the command again, validate every parameter against its limits, and build the
packets with the air interface (:class:`iscd.core.airinterface.AirInterface`).

For the simulator it is also a level source: :meth:`Board.levels` gives what the LEDs
show at any symbol index counted from START.

:class:`PtyEmulator` runs a board on a pseudo-terminal in a thread, so that the host
driver talks to it exactly as to a USB serial device::

    with PtyEmulator(link="/tmp/iscd-board") as emu:      # emu.port -> /tmp/iscd-board
        client = BoardClient(emu.port)

``python -m iscd.drivers.board.emulator --pty`` serves one until Ctrl-C and prints its path,
for demos with ``iscd tx --port /dev/pts/N``.
"""

from __future__ import annotations

import argparse
import collections
import logging
import os
import select
import signal
import sys
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from iscd.drivers.board.protocol import (
    CRITICAL_FAULTS,
    FAULT_MASK,
    FLAG_AIR_V2,
    FLAG_FEC_MASK,
    LOAD_PROGRESS,
    MAX_CHUNK,
    PROTOCOL_VERSION,
    READ_ONLY_COMMANDS,
    BoardConfig,
    BoardInfo,
    BoardStatus,
    Command,
    Content,
    Deframer,
    Fault,
    FrameError,
    LoadChunk,
    MessageError,
    Nak,
    NakCode,
    ReplyType,
    State,
    ack_payload,
    encode_frame,
    parse_body,
)
from iscd.core.airinterface import AirInterface, AirInterfaceError
from iscd.core.airinterface_v2 import AirInterfaceV2, header_symbols

log = logging.getLogger(__name__)

DEFAULT_INFO = BoardInfo(
    protocol_min=1, protocol_max=PROTOCOL_VERSION, firmware=(1, 0, 0), board_id=b"EMUL0001",
    max_leds=4096, max_levels=32, max_chunk=MAX_CHUNK, buffer_bytes=65536,
    max_symbol_rate_mhz=100_000_000, max_pwm_hz=2_000_000)
"""What the emulated board reports: up to 64x64 LEDs, M <= 32, a 64 KiB buffer (enough for
the 8x8 PWM-16 payload of 19 196 bytes and for a whole 653-symbol 8x8 level sequence),
f_sym <= 100 kHz, f_pwm <= 2 MHz."""


MAX_PERIOD_LEVELS = 1 << 24
"""The emulator precomputes one packet period: it refuses (BAD_PARAMETER, K or F) a config
whose period has more than 16 Mi LED-symbols ((13 + K + F + G) * N; 8x8 default: 41 792).
Firmware that generates symbols on the fly need not have this limit."""


class _Refuse(Exception):
    """Internal: answer the current command with NAK ``code``/``arg``."""

    def __init__(self, code: NakCode, arg: int = 0, why: str = "") -> None:
        super().__init__(why)
        self.code = code
        self.arg = arg


class Board:
    """The board's protocol logic and LED state (thread-safe).

    ``clock`` (s, monotonic) drives the symbol counter reported by GET_STATUS.
    Test hooks: :meth:`inject_fault`, :attr:`drop_replies` (swallow the next n replies, as
    if lost on the wire), :attr:`executed` (how many times each command was handled, not
    answered from the duplicate cache).
    """

    def __init__(self, info: BoardInfo = DEFAULT_INFO,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.info = info
        self._clock = clock
        self._lock = threading.RLock()
        self._deframer = Deframer()
        self.config: BoardConfig | None = None
        self._air: AirInterface | AirInterfaceV2 | None = None
        self._content = Content.NONE
        self._total = 0
        self._buffer = bytearray()
        self._sequence: np.ndarray | None = None  # (P, N) levels of one period
        self._running = False
        self._t_start = 0.0
        self._frozen_symbols = 0
        self.faults = Fault.POWER_ON_RESET
        self.rx_frames = 0
        self._frame_errors = 0
        self._cache: tuple[int, bytes, bytes] | None = None  # seq, request body, reply wire bytes
        self.executed: collections.Counter[str] = collections.Counter()
        self.duplicates = 0
        self.drop_replies = 0

    # --- the serial side ------------------------------------------------------------

    def receive(self, data: bytes) -> bytes:
        """Bytes from the serial line in; the reply bytes to send back out."""
        with self._lock:
            before = self._deframer.stats.overflows
            bodies = self._deframer.feed(data)
            if self._deframer.stats.overflows != before:
                self.faults |= Fault.RX_OVERFLOW
            out = bytearray()
            for body in bodies:
                reply = self.handle_body(body)
                if reply is not None:
                    out += reply
            return bytes(out)

    def handle_body(self, body: bytes) -> bytes | None:
        """One COBS-decoded frame body in; the reply's wire bytes (or None: no reply)."""
        with self._lock:
            try:
                frame = parse_body(body)
            except FrameError as e:
                self._frame_errors += 1
                log.debug("board: dropped frame: %s", e)
                if e.seq is None:
                    return None
                cmd = body[1] if len(body) > 1 else 0
                return encode_frame(ReplyType.NAK, e.seq, Nak(cmd, e.code).pack())
            self.rx_frames += 1
            if frame.version != PROTOCOL_VERSION:
                return encode_frame(ReplyType.NAK, frame.seq,
                                    Nak(frame.type, NakCode.VERSION_MISMATCH, self.info.protocol_max).pack())
            try:
                cmd = Command(frame.type)
            except ValueError:
                return encode_frame(ReplyType.NAK, frame.seq, Nak(frame.type, NakCode.UNKNOWN_COMMAND).pack())
            if (cmd not in READ_ONLY_COMMANDS and self._cache is not None
                    and self._cache[0] == frame.seq and self._cache[1] == body):
                self.duplicates += 1
                log.debug("board: duplicate seq %d (%s): cached reply", frame.seq, cmd.name)
                return self._send(self._cache[2])
            try:
                data = self._execute(cmd, frame.payload)
                reply = encode_frame(ReplyType.ACK, frame.seq, ack_payload(cmd, data))
            except _Refuse as r:
                log.debug("board: NAK %s %s(%d): %s", cmd.name, r.code.name, r.arg, r)
                reply = encode_frame(ReplyType.NAK, frame.seq, Nak(cmd, r.code, r.arg).pack())
            except MessageError as e:
                reply = encode_frame(ReplyType.NAK, frame.seq, Nak(cmd, e.code, e.arg).pack())
            if cmd is Command.GET_INFO:
                self._cache = None  # HELLO: a (new) host starts a session
            elif cmd not in READ_ONLY_COMMANDS:
                self._cache = (frame.seq, bytes(body), reply)
            return self._send(reply)

    def _send(self, reply: bytes) -> bytes | None:
        if self.drop_replies > 0:
            self.drop_replies -= 1
            return None
        return reply

    # --- commands -------------------------------------------------------------------

    def _execute(self, cmd: Command, payload: bytes) -> bytes:
        self.executed[cmd.name] += 1
        if cmd in (Command.GET_INFO, Command.START, Command.STOP, Command.GET_STATUS) and payload:
            raise _Refuse(NakCode.BAD_LENGTH, 0, f"{cmd.name} takes no payload")
        if cmd is Command.GET_INFO:
            return self.info.pack()
        if cmd is Command.GET_STATUS:
            return self.status().pack()
        if cmd is Command.SET_CONFIG:
            return self._set_config(BoardConfig.unpack(payload))
        if cmd is Command.LOAD_PAYLOAD:
            return self._load(Content.PAYLOAD, LoadChunk.unpack(payload))
        if cmd is Command.LOAD_LEVELS:
            return self._load(Content.LEVELS, LoadChunk.unpack(payload))
        if cmd is Command.START:
            return self._start()
        if cmd is Command.STOP:
            self._stop()
            return b""
        if cmd is Command.CLEAR_FAULTS:
            if len(payload) != FAULT_MASK.size:
                raise _Refuse(NakCode.BAD_LENGTH, 0, "CLEAR_FAULTS takes a u16 mask")
            (mask,) = FAULT_MASK.unpack(payload)
            self.faults = Fault(int(self.faults) & ~mask & 0x7F)
            return FAULT_MASK.pack(int(self.faults))
        raise _Refuse(NakCode.UNKNOWN_COMMAND)  # pragma: no cover - every Command is handled

    def _set_config(self, c: BoardConfig) -> bytes:
        if self._running:
            raise _Refuse(NakCode.BUSY, int(State.RUNNING), "SET_CONFIG while running: STOP first")
        i = self.info
        m = c.levels
        v2 = bool(c.flags & FLAG_AIR_V2)
        hdr = header_symbols(max(c.n_leds, 1)) if v2 else 0  # v2's PHY header after the Barker
        checks = (
            (2 <= m <= i.max_levels and m & (m - 1) == 0, 0),
            (c.rows >= 1, 1),
            (c.cols >= 1 and c.rows * c.cols <= i.max_leds, 2),
            (c.flags & ~(FLAG_AIR_V2 | FLAG_FEC_MASK) == 0 and (v2 or c.flags == 0), 3),
            (1000 <= c.symbol_rate_mhz <= i.max_symbol_rate_mhz, 4),
            (c.symbol_rate_mhz <= 1000 * c.pwm_hz and c.pwm_hz <= i.max_pwm_hz, 5),
            ((13 + c.training_symbols) * c.n_leds <= MAX_PERIOD_LEVELS, 6),
            (c.data_symbols >= 1 and c.data_symbols * c.n_leds * (m.bit_length() - 1) >= 32
             and (13 + hdr + c.training_symbols + c.data_symbols + c.idle_symbols) * c.n_leds
             <= MAX_PERIOD_LEVELS, 7),
        )
        for ok, index in checks:
            if not ok:
                raise _Refuse(NakCode.BAD_PARAMETER, index, "SET_CONFIG parameter out of range")
        air: AirInterface | AirInterfaceV2
        if v2:
            try:  # the largest payload F data symbol times carry with this code
                air = AirInterfaceV2.for_capacity(c.data_symbols, levels=m, rows=c.rows, cols=c.cols,
                                                  training_symbols=c.training_symbols, fec=c.fec,
                                                  idle_symbols=c.idle_symbols)
            except AirInterfaceError:
                raise _Refuse(NakCode.BAD_PARAMETER, 7, "F too small for a v2 packet") from None
        else:
            air = AirInterface(levels=m, n_leds=c.n_leds, training_symbols=c.training_symbols,
                               data_symbols=c.data_symbols, idle_symbols=c.idle_symbols)
        self.config = c
        self._air = air
        self._clear_content()
        return b""

    def _clear_content(self) -> None:
        self._content, self._total, self._buffer, self._sequence = Content.NONE, 0, bytearray(), None

    def _load(self, kind: Content, ch: LoadChunk) -> bytes:
        if self.config is None or self._air is None:
            raise _Refuse(NakCode.WRONG_STATE, int(self.state), "LOAD before SET_CONFIG")
        if self._running:
            raise _Refuse(NakCode.BUSY, int(State.RUNNING), "LOAD while running: STOP first")
        if len(ch.data) > self.info.max_chunk:
            raise _Refuse(NakCode.BAD_LENGTH, self.info.max_chunk, "chunk too long")
        n = self.config.n_leds
        if kind is Content.PAYLOAD:
            limit = min(self._air.payload_bytes, self.info.buffer_bytes)
            if ch.total > limit:
                raise _Refuse(NakCode.TOO_LARGE, limit, "payload exceeds the packet capacity")
        else:
            if ch.total > self.info.buffer_bytes:
                raise _Refuse(NakCode.TOO_LARGE, self.info.buffer_bytes, "levels exceed the buffer")
            if ch.total == 0 or ch.total % n:
                raise _Refuse(NakCode.BAD_PARAMETER, n, "level count is not a positive multiple of N")
        loaded = 0 if ch.offset == 0 else len(self._buffer)
        if ch.offset != 0 and (self._content is not kind or ch.total != self._total):
            raise _Refuse(NakCode.BAD_OFFSET, 0, "no such load in progress")
        if ch.offset != loaded:
            raise _Refuse(NakCode.BAD_OFFSET, loaded, "chunks must be contiguous")
        if ch.offset + len(ch.data) > ch.total or (not ch.data and ch.total > ch.offset):
            raise _Refuse(NakCode.BAD_LENGTH, ch.total - ch.offset, "chunk does not fit the announced total")
        if kind is Content.LEVELS and ch.data:
            lv = np.frombuffer(ch.data, dtype=np.uint8)
            bad = np.flatnonzero((lv < 1) | (lv > self.config.levels))
            if bad.size:
                raise _Refuse(NakCode.BAD_PARAMETER, ch.offset + int(bad[0]), "level out of 1..M")
        if ch.offset == 0:
            self._clear_content()
            self._content, self._total = kind, ch.total
        self._buffer += ch.data
        if len(self._buffer) == self._total:
            if kind is Content.PAYLOAD and isinstance(self._air, AirInterfaceV2):
                # v2: the header says the payload's own length (F stays the configured one)
                self._sequence = replace(self._air, payload_len=self._total).packet(bytes(self._buffer))
            elif kind is Content.PAYLOAD:
                self._sequence = self._air.packet(bytes(self._buffer))
            else:
                self._sequence = np.frombuffer(bytes(self._buffer), dtype=np.uint8).reshape(-1, n).copy()
        return LOAD_PROGRESS.pack(len(self._buffer))

    def _start(self) -> bytes:
        state = self.state
        if state is not State.READY:
            raise _Refuse(NakCode.WRONG_STATE, int(state), f"START in state {state.name}")
        self._running = True
        self._t_start = self._clock()
        return b""

    def _stop(self) -> None:
        if self._running:
            self._frozen_symbols = self._symbols_now()
            self._running = False

    def _symbols_now(self) -> int:
        if not self._running or self.config is None:
            return self._frozen_symbols
        return int((self._clock() - self._t_start) * self.config.symbol_rate_mhz / 1000.0)

    # --- state ------------------------------------------------------------------------

    @property
    def state(self) -> State:
        with self._lock:
            if self.faults & CRITICAL_FAULTS:
                return State.FAULT
            if self._running:
                return State.RUNNING
            if self._sequence is not None:
                return State.READY
            return State.CONFIGURED if self.config is not None else State.UNCONFIGURED

    @property
    def running(self) -> bool:
        with self._lock:
            return self._running

    @property
    def start_time(self) -> float | None:
        """``clock()`` at the last START while running (symbol 0 of :meth:`levels` began
        then), else None: lets a simulator put the board's symbols on its own time line."""
        with self._lock:
            return self._t_start if self._running else None

    @property
    def rx_errors(self) -> int:
        return self._frame_errors + self._deframer.stats.dropped

    def status(self) -> BoardStatus:
        with self._lock:
            sym = self._symbols_now()
            period = len(self._sequence) if self._sequence is not None else 0
            return BoardStatus(
                state=self.state, content=self._content, faults=self.faults, symbol_counter=sym,
                packets_sent=sym // period if period else 0, bytes_loaded=len(self._buffer),
                bytes_total=self._total, rx_frames=self.rx_frames, rx_errors=self.rx_errors)

    def inject_fault(self, faults: Fault) -> None:
        """Raise fault flags as the hardware would; critical ones stop the output."""
        with self._lock:
            self.faults |= faults
            if faults & CRITICAL_FAULTS:
                self._stop()

    # --- the LEDs ---------------------------------------------------------------------

    def sequence(self) -> np.ndarray | None:
        """(P, N) levels of one period of the loaded content (a packet with its idle
        symbols, or the level sequence), or None while nothing complete is loaded."""
        with self._lock:
            return None if self._sequence is None else self._sequence.copy()

    def levels(self, symbol_start: int, n: int, n_leds: int | None = None) -> np.ndarray:
        """(n, N) uint8 levels the LEDs show at symbols ``symbol_start .. +n-1``.

        Symbol 0 is the first symbol after START; the content repeats back to back;
        symbols before START (k < 0) are level 1. While not running (stopped, not loaded,
        faulted) every LED shows level 1 (dark).
        ``n_leds`` is the caller's LED count: it sets N while the board is unconfigured and
        must equal rows*cols once it is configured.
        """
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        with self._lock:
            if self.config is not None:
                big_n = self.config.n_leds
                if n_leds is not None and n_leds != big_n:
                    raise ValueError(f"the board is configured for {big_n} LEDs "
                                     f"({self.config.rows}x{self.config.cols}), the caller has {n_leds}")
            else:
                big_n = n_leds or 1
            if not self._running or self._sequence is None:
                return np.ones((n, big_n), dtype=np.uint8)
            k = int(symbol_start) + np.arange(n, dtype=np.int64)
            out = self._sequence[k % len(self._sequence)]
            out[k < 0] = 1
            return out

    def level_source(self, n_leds: int) -> "BoardLevelSource":
        """This board as a simulator level source (``iscd.sim.transmitter.LevelSource``)."""
        return BoardLevelSource(self, n_leds)


class BoardLevelSource:
    """Adapter to the simulator's level-source protocol: ``n_leds`` and
    ``levels(k0, k1) -> (k1 - k0, N) uint8`` for symbols k0 .. k1-1 counted from START."""

    def __init__(self, board: Board, n_leds: int) -> None:
        self.board = board
        self.n_leds = int(n_leds)

    def levels(self, k0: int, k1: int) -> np.ndarray:
        return self.board.levels(k0, max(0, k1 - k0), self.n_leds)


class PtyEmulator:
    """A :class:`Board` answering on a pseudo-terminal, served by a thread.

    The host opens :attr:`port` (the pty's slave device, or ``link``: a symlink to it
    that survives restarts, like udev's /dev/serial/by-id names). :meth:`close` is the
    board vanishing (the pty goes away, the link is removed); a new PtyEmulator with the
    same ``link`` is the board coming back. ``paused = True`` is a hung board: it reads
    and ignores everything.
    """

    def __init__(self, board: Board | None = None, link: str | Path | None = None) -> None:
        self.board = board if board is not None else Board()
        self.link = Path(link) if link is not None else None
        self.paused = False
        self.path = ""
        self._master = -1
        self._slave = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> str:
        """What the host should open."""
        return str(self.link) if self.link is not None else self.path

    def start(self) -> "PtyEmulator":
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing: a byte pipe like a UART
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.path = os.ttyname(slave)
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + ".tmp")
            tmp.unlink(missing_ok=True)
            os.symlink(self.path, tmp)
            os.replace(tmp, self.link)
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name=f"board-emulator {self.path}", daemon=True)
        self._thread.start()
        return self

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(self._master, 4096)
            except (OSError, ValueError):
                time.sleep(0.01)  # no slave open (EIO) or closing
                continue
            if self.paused or not data:
                continue
            try:
                reply = self.board.receive(data)
            except Exception:  # noqa: BLE001 - a board must not die of what it receives
                log.exception("board: internal error handling %d received bytes", len(data))
                continue
            if reply:
                try:
                    os.write(self._master, reply)
                except BlockingIOError:
                    log.debug("board: host is not reading, reply dropped")
                except OSError:
                    pass

    def levels(self, symbol_start: int, n: int, n_leds: int | None = None) -> np.ndarray:
        """The board's level source (:meth:`Board.levels`)."""
        return self.board.levels(symbol_start, n, n_leds)

    def inject_to_host(self, data: bytes) -> None:
        """Put raw bytes on the line towards the host (noise, a partial frame) — for tests."""
        os.write(self._master, data)

    def close(self) -> None:
        """Stop answering and close the pty: the board is unplugged."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1
        if self.link is not None and os.path.islink(self.link) and os.readlink(self.link) == self.path:
            self.link.unlink(missing_ok=True)

    def __enter__(self) -> "PtyEmulator":
        return self.start() if self._thread is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: list[str] | None = None) -> int:
    """``python -m iscd.drivers.board.emulator --pty``: serve an emulated board until Ctrl-C."""
    ap = argparse.ArgumentParser(
        prog="python -m iscd.drivers.board.emulator",
        description="Emulate the LED transmitter board (protocol v1) on a pseudo-terminal and "
                    "print its path, for 'iscd tx --port PATH'. Runs until Ctrl-C / SIGTERM.")
    ap.add_argument("--pty", action="store_true", required=True,
                    help="serve on a new pseudo-terminal (the only transport so far)")
    ap.add_argument("--link", metavar="PATH",
                    help="also make PATH a symlink to the pty (a stable name across restarts)")
    ap.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: never)")
    ap.add_argument("-v", "--verbose", action="store_true", help="log every command")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s: %(message)s")
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    with PtyEmulator(link=args.link) as emu:
        print(emu.port, flush=True)
        try:
            done.wait(args.duration)
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
