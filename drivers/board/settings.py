"""The ``[board]`` config section: how the host finds and talks to the LED board.

::

    [board]
    port = "/dev/serial/by-id/usb-iscd_LED_board_0001-if00"   # "" = find by VID:PID
    vid = 0x1209
    pid = 0x0001
    timeout_s = 0.2
    retries = 3

For demos without hardware, ``emulate = true`` makes the daemon's mock rig run an emulated
board (:class:`iscd.drivers.board.emulator.PtyEmulator`) whose LEDs are the simulated
transmitter; its pseudo-terminal appears at ``port`` (a symlink), where ``iscd tx
--config`` (same file) finds it::

    [board]
    emulate = true
    port = "/tmp/iscd-board"
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

from iscd.core.config import config_section, section
from iscd.drivers.board.client import DEFAULT_BAUDRATE, DEFAULT_RETRIES, DEFAULT_TIMEOUT_S
from iscd.drivers.board.discovery import DEFAULT_PID, DEFAULT_VID


def _meta(lo: float | None = None, hi: float | None = None, lo_open: bool = False, doc: str = "") -> dict[str, Any]:
    return {"lo": lo, "hi": hi, "lo_open": lo_open, "choices": None, "doc": doc}


@config_section("board")
@dataclass(frozen=True)
class BoardSettings:
    """The LED transmitter board's serial link (see docs/board-protocol.md)."""

    port: str = field(default="", metadata=_meta(
        doc="serial port or pyserial URL of the board; empty: find it by vid:pid. With "
            "emulate: where the emulated board's pty appears (a symlink path)"))
    vid: int = field(default=DEFAULT_VID, metadata=_meta(0, 0xFFFF, doc="USB vendor ID (pid.codes 0x1209)"))
    pid: int = field(default=DEFAULT_PID, metadata=_meta(0, 0xFFFF, doc="USB product ID (0x0001: test PID)"))
    baudrate: int = field(default=DEFAULT_BAUDRATE, metadata=_meta(1, doc="UART baud rate (ignored by USB CDC)"))
    timeout_s: float = field(default=DEFAULT_TIMEOUT_S, metadata=_meta(0, 10, lo_open=True,
                                                                       doc="wait for each reply, s"))
    retries: int = field(default=DEFAULT_RETRIES, metadata=_meta(0, 20, doc="resends of an unanswered command"))
    emulate: bool = field(default=False, metadata=_meta(
        doc="mock rig only: the daemon runs an emulated board at port whose LEDs are the "
            "simulated transmitter (load it with 'iscd tx')"))


def board_settings(cfg: Any) -> BoardSettings:
    """The validated ``[board]`` section of a :class:`iscd.core.config.Config` (defaults if absent)."""
    return section(cfg, BoardSettings)


def emulated_board_link(cfg: Any) -> str | None:
    """Where the emulated board of ``cfg`` appears (``[board] port``), or None when
    ``[board] emulate`` is off.

    Raises :class:`iscd.core.config.ConfigError` (one line, naming the key) when the board
    cannot be emulated with this config: the rig is not the paced mock rig (the board's
    symbol clock is wall-clock time, so the scene must render in real time), ``port`` is
    empty or a pyserial URL, its directory does not exist, or something other than a
    symlink is already there (it would be replaced).
    """
    from iscd.core.config import ConfigError

    s = board_settings(cfg)
    if not s.emulate:
        return None
    if cfg.rig.scheme != "mock":
        raise ConfigError(f"board.emulate: the emulated board drives the simulated scene; it needs "
                          f"rig.backend = \"mock\", not {cfg.rig.scheme!r}")
    if not cfg.rig.pace:
        raise ConfigError("board.emulate: the board runs on wall-clock time; it needs rig.pace = true")
    link = s.port
    if not link:
        raise ConfigError("board.port: set where the emulated board's pty appears, e.g. \"/tmp/iscd-board\"")
    if "://" in link:
        raise ConfigError(f"board.port: the emulated board needs a file path, not the URL {link!r}")
    link = os.path.expanduser(link)
    parent = os.path.dirname(os.path.abspath(link))
    if not os.path.isdir(parent):
        raise ConfigError(f"board.port: directory {parent} does not exist")
    if os.path.lexists(link) and not os.path.islink(link):
        raise ConfigError(f"board.port: {link} exists and is not a symlink; the emulated board "
                          f"will not replace it")
    return link
