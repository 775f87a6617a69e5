"""``iscd tx``: drive the LED transmitter board (load a payload, start, stop, status)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

DESCRIPTION = """\
Drive the LED transmitter board over its serial protocol (docs/board-protocol.md).
With a payload (--payload-text/-hex/-file, --levels-file, or a fixed [payload] in the
config) it stops the board, sends the config's [transmitter] settings (M, symbol rate,
PWM carrier, rows x cols, K, F, G), loads the payload and starts sending; then it prints
one JSON line with the board's info and status. --start, --stop and --status do only
that. The board is --port, else [board].port, else the one board found on USB by
[board].vid:pid (default 1209:0001). --emulate runs an emulated board on a pty instead,
for demos: it prints the pty's path and keeps serving until Ctrl-C (or --duration), so
that another 'iscd tx --port PATH' can talk to it."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("tx", help="drive the LED transmitter board (load payload, start/stop, status)",
                       description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--port", metavar="PORT",
                   help="serial device or pyserial URL of the board, e.g. /dev/ttyACM0 or socket://host:7000")
    p.add_argument("--config", metavar="FILE",
                   help="TOML config: [transmitter], [payload] and [board] (default: the embedded one)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--payload-text", metavar="S", help="send the UTF-8 bytes of S")
    src.add_argument("--payload-hex", metavar="H", help="send these bytes, in hex (spaces allowed)")
    src.add_argument("--payload-file", metavar="F", help="send the bytes of file F")
    src.add_argument("--levels-file", metavar="F.npy",
                     help="send a raw (T, N) level sequence (.npy, values 1..M) instead of packets")
    act = p.add_mutually_exclusive_group()
    act.add_argument("--start", action="store_true", help="only start sending what the board holds")
    act.add_argument("--stop", action="store_true", help="only stop sending (LEDs dark)")
    act.add_argument("--status", action="store_true", help="only print the board's info and status")
    p.add_argument("--air-interface", choices=("v1", "v2"),
                   help="send the payload as air interface v1 or v2 (PHY header + Reed-Solomon; "
                        "docs/air-interface.md); default [transmitter].air_interface")
    p.add_argument("--fec", choices=("none", "rs255_239", "rs255_223", "rs255_191"),
                   help="v2's code (default [transmitter].fec)")
    p.add_argument("--no-start", action="store_true", help="load the payload but do not start")
    p.add_argument("--clear-faults", action="store_true", help="clear the board's fault flags first")
    p.add_argument("--list", action="store_true", help="list the boards found on USB (JSON lines) and exit")
    p.add_argument("--emulate", action="store_true",
                   help="run an emulated board on a pseudo-terminal and drive that one")
    p.add_argument("--duration", type=float, metavar="S",
                   help="with --emulate: keep the emulated board for S seconds (default: until Ctrl-C)")
    p.add_argument("--timeout", type=float, metavar="S", help="reply timeout per try, s (default [board].timeout_s)")
    p.add_argument("--retries", type=int, metavar="N", help="resends of an unanswered command (default [board].retries)")
    p.set_defaults(func=run)


def _payload(args: argparse.Namespace, cfg: Any) -> bytes | None:
    from iscd.core.errors import UserError

    if args.payload_text is not None:
        return args.payload_text.encode("utf-8")
    if args.payload_hex is not None:
        return _hex(args.payload_hex, "--payload-hex")
    if args.payload_file is not None:
        return _read_file(args.payload_file, "--payload-file")
    source, value = cfg.payload.source, cfg.payload.value
    if source == "text":
        return value.encode("utf-8")
    if source == "hex":
        return _hex(value, "payload.value")
    if source == "file":
        if not value:
            raise UserError("payload.value: the file path is empty")
        return _read_file(value, "payload.value")
    return None


def _hex(text: str, what: str) -> bytes:
    from iscd.core.errors import UserError

    try:
        return bytes.fromhex(text.removeprefix("0x"))
    except ValueError:
        raise UserError(f"{what}: not a hex byte string: {text[:40]!r}") from None


def _read_file(path: str, what: str) -> bytes:
    from iscd.core.errors import UserError

    try:
        return Path(path).read_bytes()
    except OSError as e:
        raise UserError(f"{what}: cannot read {path}: {e.strerror or e}") from None


def _levels(path: str, tx: Any) -> np.ndarray:
    from iscd.core.errors import UserError

    try:
        lv = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise UserError(f"--levels-file: cannot read {path} as .npy: {e}") from None
    n = tx.rows * tx.cols
    if lv.ndim != 2 or lv.shape[1] != n or lv.shape[0] == 0 or not np.issubdtype(lv.dtype, np.integer):
        raise UserError(f"--levels-file: expected a (T, {n}) integer array for {tx.rows}x{tx.cols} LEDs, "
                        f"got {lv.dtype} {lv.shape}")
    if lv.min() < 1 or lv.max() > tx.levels:
        raise UserError(f"--levels-file: levels must be in 1..{tx.levels} (M), got {lv.min()}..{lv.max()}")
    return lv.astype(np.uint8)


def _check_link_options(args: argparse.Namespace, settings: Any) -> None:
    """--timeout and --retries within the bounds of the ``[board]`` keys they override
    (timeout_s, retries): one line naming the option (a NaN timeout would never time out,
    an infinite one or a billion retries would hang on a silent board)."""
    from iscd.core.errors import UserError

    bounds = {f.name: f.metadata for f in dataclasses.fields(settings)}
    hi_t = bounds["timeout_s"].get("hi") or math.inf
    hi_r = bounds["retries"].get("hi") or math.inf
    t, r = args.timeout, args.retries
    if t is not None and not (0 < t <= hi_t and math.isfinite(t)):
        raise UserError(f"--timeout must be > 0 and <= {hi_t:g} s (as [board] timeout_s), got {t}")
    if r is not None and not 0 <= r <= hi_r:
        raise UserError(f"--retries must be in 0..{hi_r:g} (as [board] retries), got {r}")


def _find_port(settings: Any) -> str:
    from iscd.drivers.board.discovery import find_boards
    from iscd.core.errors import UserError

    found = [b for b in find_boards(settings.vid, settings.pid) if b.device]
    usb_id = f"{settings.vid:04x}:{settings.pid:04x}"
    if not found:
        raise UserError(f"no LED board found on USB ({usb_id}); give --port or [board].port")
    if len(found) > 1:
        names = ", ".join(f"{b.device} ({b.serial_number})" for b in found)
        raise UserError(f"{len(found)} LED boards found ({names}); choose one with --port")
    return str(found[0].device)


def run(args: argparse.Namespace) -> int:
    from iscd.drivers.board.client import BoardClient, BoardError, BoardPortError
    from iscd.drivers.board.discovery import find_boards
    from iscd.drivers.board.protocol import BoardConfig, ProtocolError
    from iscd.drivers.board.settings import board_settings
    from iscd.core.airinterface_v2 import from_config as air_from_config
    from iscd.core.errors import UserError
    from iscd.core.config import load

    cfg = load(args.config)
    settings = board_settings(cfg)
    _check_link_options(args, settings)
    timeout = settings.timeout_s if args.timeout is None else args.timeout
    retries = settings.retries if args.retries is None else args.retries
    if args.list:
        boards = find_boards(settings.vid, settings.pid)
        for b in boards:
            print(json.dumps(b.as_dict()))
        if not boards:
            print(f"iscd tx: no boards with USB ID {settings.vid:04x}:{settings.pid:04x}", file=sys.stderr)
        return 0
    if args.emulate and args.port:
        raise UserError("--emulate and --port exclude each other")
    if args.duration is not None and not args.emulate:
        raise UserError("--duration only applies with --emulate")
    if args.duration is not None and not (args.duration >= 0 and math.isfinite(args.duration)):
        raise UserError(f"--duration must be a finite number of seconds >= 0, got {args.duration}")

    tx = cfg.transmitter
    if args.air_interface or args.fec:
        from iscd.core.config import ConfigError

        try:
            tx = dataclasses.replace(tx, air_interface=args.air_interface or tx.air_interface,
                                     fec=args.fec or tx.fec, payload_len=0)
        except ConfigError as e:
            raise UserError(str(e)) from None
    levels = _levels(args.levels_file, tx) if args.levels_file else None
    payload = None if (args.start or args.stop or args.status or levels is not None) else _payload(args, cfg)
    if payload is not None:
        air = air_from_config(tx)
        capacity = air.payload_bytes
        if len(payload) > capacity:
            raise UserError(f"payload of {len(payload)} bytes exceeds the capacity of {capacity} bytes of a "
                            f"{tx.rows}x{tx.cols} PWM-{tx.levels} {tx.air_interface} packet with "
                            f"F={air.data_symbols}")
    try:
        board_config = BoardConfig.from_transmitter(tx)
        board_config.pack()
    except ProtocolError as e:
        raise UserError(f"transmitter: {e}") from None

    emu = None
    if args.emulate:
        from iscd.drivers.board.emulator import PtyEmulator

        emu = PtyEmulator().start()
        port = emu.port
        print(f"iscd tx: emulated board on {port}", file=sys.stderr, flush=True)
    else:
        port = args.port or settings.port or _find_port(settings)
    try:
        try:
            with BoardClient(port, timeout=timeout, retries=retries, baudrate=settings.baudrate) as board:
                if args.clear_faults:
                    board.clear_faults()
                loaded: dict[str, Any] = {}
                if args.stop:
                    board.stop()
                elif args.start:
                    board.start()
                elif levels is not None or payload is not None:
                    board.transmit(board_config, payload=payload, levels=levels, start=not args.no_start)
                    loaded = ({"levels_symbols": int(levels.shape[0])} if levels is not None else
                              {"payload_bytes": len(payload), "payload_hex": payload.hex()})  # type: ignore[arg-type]
                    loaded["config"] = board_config.as_dict()
                status = board.status()
                info = board.info
                print(json.dumps({"port": port, **loaded, "board": info.as_dict() if info else None,
                                  "status": status.as_dict()}), flush=True)
        except BoardPortError as e:
            raise UserError(str(e)) from None
        except BoardError as e:
            print(f"iscd tx: error: {e}", file=sys.stderr)
            return 1
        if emu is not None:
            _serve(args.duration)
        return 0
    finally:
        if emu is not None:
            emu.close()


def _serve(duration: float | None) -> None:
    done = threading.Event()
    try:
        done.wait(duration)
    except KeyboardInterrupt:
        pass
