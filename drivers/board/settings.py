"""The ``[board]`` config section: how the host finds and talks to the LED board.

::

    [board]
    port = "/dev/serial/by-id/usb-iscd_LED_board_0001-if00"   # "" = find by VID:PID
    vid = 0x1209
    pid = 0x0001
    timeout_s = 0.2
    retries = 3
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from drivers.board.client import DEFAULT_BAUDRATE, DEFAULT_RETRIES, DEFAULT_TIMEOUT_S
from drivers.board.discovery import DEFAULT_PID, DEFAULT_VID


def _meta(lo: float | None = None, hi: float | None = None, lo_open: bool = False, doc: str = "") -> dict[str, Any]:
    return {"lo": lo, "hi": hi, "lo_open": lo_open, "choices": None, "doc": doc}


@dataclass(frozen=True)
class BoardSettings:
    """The LED transmitter board's serial link (see docs/board-protocol.md)."""

    port: str = field(default="", metadata=_meta(
        doc="serial port or pyserial URL of the board; empty: find it by vid:pid"))
    vid: int = field(default=DEFAULT_VID, metadata=_meta(0, 0xFFFF, doc="USB vendor ID (pid.codes 0x1209)"))
    pid: int = field(default=DEFAULT_PID, metadata=_meta(0, 0xFFFF, doc="USB product ID (0x0001: test PID)"))
    baudrate: int = field(default=DEFAULT_BAUDRATE, metadata=_meta(1, doc="UART baud rate (ignored by USB CDC)"))
    timeout_s: float = field(default=DEFAULT_TIMEOUT_S, metadata=_meta(0, 10, lo_open=True,
                                                                       doc="wait for each reply, s"))
    retries: int = field(default=DEFAULT_RETRIES, metadata=_meta(0, 20, doc="resends of an unanswered command"))


def board_settings(cfg: Any) -> BoardSettings:
    """The validated ``[board]`` section of a :class:`iscd.config.Config` (defaults if absent)."""
    from iscd.config import build_section

    return build_section(BoardSettings, dict(cfg.extra.get("board", {})), "board")
