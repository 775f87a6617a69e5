"""Host driver of the LED board (protocol v1) on a pyserial port.

::

    with BoardClient("/dev/ttyACM0") as board:        # or any pyserial URL: socket://, loop://
        board.transmit(BoardConfig.from_transmitter(cfg.transmitter), b"hello")
        print(board.status().as_dict())

Every command is one request/reply transaction: the request goes out with a fresh
sequence number; if no valid reply with that number arrives within ``timeout`` seconds
the same bytes (same seq) are sent again, up to ``retries`` more times. The board
answers a repeated seq from its reply cache, so a command whose reply was lost is not
executed twice. Then :class:`BoardTimeout` says so in one line.

Garbage and partial frames on the line are dropped at the next 0x00 delimiter and
counted (:attr:`BoardClient.stats`). If the port fails (the USB device was unplugged,
the pty closed), it is closed and reopened by name on the next attempt, so the client
recovers by itself once the board is back.

Commands from several threads are serialised by an internal lock.
"""

from __future__ import annotations

import logging
import os
import random
import threading
import time
from dataclasses import dataclass

import numpy as np
import serial

from iscd.drivers.board.protocol import (
    ALL_FAULTS,
    CONFIG_FIELDS,
    FAULT_MASK,
    LOAD_PROGRESS,
    MAX_CHUNK,
    PROTOCOL_VERSION,
    BoardConfig,
    BoardInfo,
    BoardStatus,
    Command,
    Deframer,
    Fault,
    FrameError,
    LoadChunk,
    MessageError,
    Nak,
    NakCode,
    ReplyType,
    State,
    command_name,
    encode_frame,
    nak_name,
    parse_body,
)

log = logging.getLogger(__name__)

DEFAULT_TIMEOUT_S = 0.2
DEFAULT_RETRIES = 3
DEFAULT_BAUDRATE = 115200


class BoardError(RuntimeError):
    """Base of the board driver's errors; ``str`` is one line naming the port."""


class BoardPortError(BoardError):
    """The port could not be opened at all (wrong path, permissions, in use)."""


class BoardTimeout(BoardError):
    """The board did not answer a command, retries included."""


class BoardProtocolError(BoardError):
    """The board answered with something this host cannot use (version, bad layout)."""


class BoardNak(BoardError):
    """The board refused a command. ``command`` and ``code`` (:class:`NakCode` when known)
    and ``arg`` are the NAK's fields."""

    def __init__(self, port: str, nak: Nak) -> None:
        self.command = nak.command
        self.code: NakCode | int = NakCode(nak.code) if nak.code in NakCode._value2member_map_ else nak.code
        self.arg = nak.arg
        super().__init__(f"board on {port} refused {command_name(nak.command)}: {describe_nak(nak)}")


def describe_nak(nak: Nak) -> str:
    """A NAK in words, with its ``arg`` decoded as docs/board-protocol.md defines it."""
    code, arg = nak.code, nak.arg
    name = nak_name(code).lower().replace("_", " ")
    if code == NakCode.BAD_PARAMETER:
        if nak.command == Command.SET_CONFIG and arg < len(CONFIG_FIELDS):
            return f"{name} ({CONFIG_FIELDS[arg]} out of the board's range)"
        if nak.command == Command.LOAD_LEVELS:
            return f"{name} (level #{arg} out of 1..M, or the count is not a multiple of the LEDs)"
        return f"{name} (#{arg})"
    if code in (NakCode.WRONG_STATE, NakCode.BUSY):
        state = State(arg).name if arg in State._value2member_map_ else str(arg)
        return f"{name} (board is {state})"
    if code == NakCode.TOO_LARGE:
        return f"{name} (the limit is {arg} bytes)"
    if code == NakCode.BAD_OFFSET:
        return f"{name} (the board expected offset {arg})"
    if code == NakCode.VERSION_MISMATCH:
        return f"{name} (the board speaks protocol up to v{arg}, this host v{PROTOCOL_VERSION})"
    return name


@dataclass
class ClientStats:
    """What the driver saw on the line."""

    commands: int = 0
    retries: int = 0
    timeouts: int = 0
    """Attempts that got no reply in time."""
    port_errors: int = 0
    reconnects: int = 0
    bad_frames: int = 0
    """Frames with a bad CRC or length."""
    stray_frames: int = 0
    """Valid frames that did not answer the pending command (late replies, other seq)."""
    garbage_bytes: int = 0
    """Bytes dropped by the deframer (invalid COBS, overlong runs)."""


class BoardClient:
    """The host side of protocol v1 on a pyserial port (path or URL).

    ``timeout`` (s) is the wait per attempt; a command is tried ``1 + retries`` times.
    With ``hello=True`` the constructor sends GET_INFO (HELLO), which checks that a v1
    board answers; :attr:`info` keeps its reply. ``first_seq`` is the first sequence
    number (default random). Raises :class:`BoardPortError` if the
    port cannot be opened and :class:`BoardTimeout` if nothing answers.
    """

    def __init__(self, port: str, timeout: float = DEFAULT_TIMEOUT_S, retries: int = DEFAULT_RETRIES,
                 baudrate: int = DEFAULT_BAUDRATE, hello: bool = True, first_seq: int | None = None) -> None:
        if timeout <= 0:
            raise ValueError(f"timeout must be > 0 s, got {timeout}")
        if retries < 0:
            raise ValueError(f"retries must be >= 0, got {retries}")
        self.port = str(port)
        self.timeout = float(timeout)
        self.retries = int(retries)
        self.baudrate = int(baudrate)
        self.stats = ClientStats()
        self.info: BoardInfo | None = None
        self._deframer = Deframer()
        self._ser: serial.SerialBase | None = None
        self._ever_opened = False
        # a new host session does not reuse the last one's seq (None: random; tests fix it)
        self._seq = random.randrange(256) if first_seq is None else first_seq & 0xFF
        self._lock = threading.Lock()
        try:
            self._open()
        except (serial.SerialException, OSError, ValueError) as e:
            raise BoardPortError(f"cannot open board port {self.port}: {_os_reason(e)}") from None
        if hello:
            try:
                self.hello()
            except BaseException:
                self.close()
                raise

    # --- port handling --------------------------------------------------------------

    def _open(self) -> serial.SerialBase:
        ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=min(self.timeout, 0.02),
                                    write_timeout=self.timeout, do_not_open=True)
        if hasattr(ser, "exclusive") and not self.port.startswith(("loop://", "socket://", "rfc2217://")):
            ser.exclusive = True  # a second host on the same board is an error, not a race
        ser.open()
        ser.reset_input_buffer()
        self._deframer.reset()
        if self._ever_opened:
            self.stats.reconnects += 1
            log.info("board port %s reopened", self.port)
        self._ever_opened = True
        self._ser = ser
        return ser

    def _drop_port(self, err: BaseException) -> None:
        self.stats.port_errors += 1
        log.warning("board port %s failed: %s", self.port, _one_line(err))
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:  # noqa: BLE001 - closing a dead port may fail any way
                pass
        self._ser = None

    def close(self) -> None:
        """Close the port (the board keeps running)."""
        if self._ser is not None:
            try:
                self._ser.close()
            finally:
                self._ser = None

    def __enter__(self) -> "BoardClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- transactions ---------------------------------------------------------------

    def _next_seq(self) -> int:
        seq = self._seq
        self._seq = (seq + 1) & 0xFF
        return seq

    def request(self, cmd: Command, payload: bytes = b"") -> bytes:
        """Send one command, with retries; the ACK's data (after the echoed command byte).

        Raises :class:`BoardNak`, :class:`BoardTimeout`.
        """
        with self._lock:
            return self._transact(Command(cmd), payload)

    def _transact(self, cmd: Command, payload: bytes) -> bytes:
        seq = self._next_seq()
        wire = encode_frame(cmd, seq, payload)
        self.stats.commands += 1
        cause = ""
        for attempt in range(1 + self.retries):
            if attempt:
                self.stats.retries += 1
            deadline = time.monotonic() + self.timeout
            try:
                ser = self._ser if self._ser is not None else self._open()
            except (serial.SerialException, OSError, ValueError) as e:
                self.stats.port_errors += 1
                log.debug("board port %s: cannot open: %s", self.port, _one_line(e))
                cause = f"cannot open the port: {_os_reason(e)}"
                _sleep_until(deadline)
                continue
            try:
                ser.write(wire)
                reply = self._await_reply(ser, cmd, seq, deadline)
            except (serial.SerialException, OSError, ValueError) as e:
                self._drop_port(e)
                cause = f"port error: {_one_line(e)}"
                _sleep_until(deadline)
                continue
            if reply is None:
                self.stats.timeouts += 1
                continue
            if reply.type == ReplyType.NAK:
                nak = Nak.unpack(reply.payload)
                if nak.code == NakCode.BAD_CRC:
                    cause = "the board received corrupted frames"
                    continue  # the request was damaged on the way: send it again now
                raise BoardNak(self.port, nak)
            return reply.payload[1:]
        raise BoardTimeout(
            f"board on {self.port} did not answer {self.retries} retries of {cmd.name} within "
            f"{self.timeout:g} s" + (f" ({cause})" if cause else ""))

    def _await_reply(self, ser: serial.SerialBase, cmd: Command, seq: int, deadline: float):
        """The first valid ACK/NAK for (cmd, seq) before ``deadline``, else None."""
        while time.monotonic() < deadline:
            data = ser.read(max(1, ser.in_waiting))
            if not data:
                continue
            garbage = self._deframer.stats.garbage_bytes
            bodies = self._deframer.feed(data)
            self.stats.garbage_bytes += self._deframer.stats.garbage_bytes - garbage
            for body in bodies:
                try:
                    frame = parse_body(body)
                except FrameError:
                    self.stats.bad_frames += 1
                    continue
                if (frame.version != PROTOCOL_VERSION or frame.seq != seq
                        or frame.type not in (ReplyType.ACK, ReplyType.NAK) or not frame.payload):
                    self.stats.stray_frames += 1
                    continue
                if frame.type == ReplyType.NAK:
                    try:
                        nak = Nak.unpack(frame.payload)
                    except MessageError:
                        self.stats.bad_frames += 1
                        continue
                    if nak.command != cmd and nak.code != NakCode.BAD_CRC:
                        self.stats.stray_frames += 1
                        continue
                elif frame.payload[0] != cmd:
                    self.stats.stray_frames += 1
                    continue
                return frame
        return None

    def _parse(self, what: str, fn, data: bytes):
        try:
            return fn(data)
        except MessageError as e:
            raise BoardProtocolError(f"board on {self.port} sent a malformed {what} reply: {e}") from None

    # --- commands -------------------------------------------------------------------

    def hello(self) -> BoardInfo:
        """GET_INFO (HELLO): what the board is; starts a session (clears its reply cache)."""
        info = self._parse("INFO", BoardInfo.unpack, self.request(Command.GET_INFO))
        if not info.protocol_min <= PROTOCOL_VERSION <= info.protocol_max:
            raise BoardProtocolError(
                f"board on {self.port} speaks protocol v{info.protocol_min}..v{info.protocol_max}, "
                f"this host v{PROTOCOL_VERSION}")
        self.info = info
        return info

    get_info = hello

    def set_config(self, config: BoardConfig) -> None:
        """SET_CONFIG: geometry and timing; discards loaded content (board must be stopped)."""
        self.request(Command.SET_CONFIG, config.pack())

    def _chunk_size(self) -> int:
        return min(MAX_CHUNK, self.info.max_chunk) if self.info is not None else MAX_CHUNK

    def _load(self, cmd: Command, data: bytes) -> int:
        size = self._chunk_size()
        total = len(data)
        offset = 0
        loaded = 0
        while True:
            chunk = data[offset: offset + size]
            reply = self.request(cmd, LoadChunk(offset, total, chunk).pack())
            (loaded,) = self._parse("LOAD", lambda b: _progress(b), reply)
            offset += len(chunk)
            if offset >= total:
                break
        if loaded != total:
            raise BoardProtocolError(f"board on {self.port} loaded {loaded} of {total} bytes")
        return loaded

    def load_payload(self, payload: bytes) -> int:
        """LOAD_PAYLOAD in chunks: the board builds air-interface packets from it."""
        return self._load(Command.LOAD_PAYLOAD, bytes(payload))

    def load_levels(self, levels: np.ndarray) -> int:
        """LOAD_LEVELS: a raw (T, N) sequence of levels 1..M, played back to back."""
        lv = np.asarray(levels)
        if lv.ndim != 2 or lv.size == 0:
            raise ValueError(f"levels must be a non-empty (T, N) array, got shape {lv.shape}")
        if lv.min() < 1 or lv.max() > 255:
            raise ValueError("levels must be in 1..M")
        return self._load(Command.LOAD_LEVELS, lv.astype(np.uint8).tobytes())

    def start(self) -> None:
        self.request(Command.START)

    def stop(self) -> None:
        self.request(Command.STOP)

    def status(self) -> BoardStatus:
        return self._parse("STATUS", BoardStatus.unpack, self.request(Command.GET_STATUS))

    def clear_faults(self, mask: Fault | int = ALL_FAULTS) -> Fault:
        """CLEAR_FAULTS; returns the faults still set."""
        reply = self.request(Command.CLEAR_FAULTS, FAULT_MASK.pack(int(mask) & 0xFFFF))
        (left,) = self._parse("CLEAR_FAULTS", lambda b: FAULT_MASK.unpack_from(b) if len(b) >= 2
                              else _short("CLEAR_FAULTS", b), reply)
        return Fault(left & int(ALL_FAULTS))

    def transmit(self, config: BoardConfig, payload: bytes | None = None, levels: np.ndarray | None = None,
                 start: bool = True) -> BoardStatus:
        """Stop, configure, load ``payload`` (packets) or ``levels`` (raw sequence), clear
        POWER_ON_RESET (the host has restored the settings) and by default start.
        Returns the status after."""
        if (payload is None) == (levels is None):
            raise ValueError("give exactly one of payload and levels")
        self.stop()
        self.set_config(config)
        if payload is not None:
            self.load_payload(payload)
        else:
            self.load_levels(levels)  # type: ignore[arg-type]
        self.clear_faults(Fault.POWER_ON_RESET)
        if start:
            self.start()
        return self.status()


def _progress(b: bytes) -> tuple[int]:
    if len(b) < LOAD_PROGRESS.size:
        _short("LOAD", b)
    return LOAD_PROGRESS.unpack_from(b)


def _short(what: str, b: bytes):
    raise MessageError(NakCode.BAD_LENGTH, f"{what}: {len(b)} bytes is too short")


def _sleep_until(deadline: float) -> None:
    delay = deadline - time.monotonic()
    if delay > 0:
        time.sleep(delay)


def _os_reason(e: BaseException) -> str:
    err = getattr(e, "errno", None)
    return os.strerror(err) if isinstance(err, int) and err > 0 else _one_line(e)


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__
