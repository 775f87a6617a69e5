"""The sd_notify protocol: tell systemd that the daemon is ready, alive and stopping.

A ``Type=notify`` service gets ``NOTIFY_SOCKET`` (an ``AF_UNIX`` datagram socket: a path, or
an abstract name written with a leading ``@``) and, with ``WatchdogSec=``, ``WATCHDOG_USEC``
(the watchdog interval, microseconds) and ``WATCHDOG_PID`` (the process that must ping).
Each notification is one datagram of newline-separated ``KEY=VALUE`` lines
(sd_notify(3)): ``READY=1``, ``STATUS=...``, ``WATCHDOG=1``, ``STOPPING=1``,
``EXTEND_TIMEOUT_USEC=...``.

This is plain socket code (no libsystemd). Outside systemd (no ``NOTIFY_SOCKET``) every
call is a cheap no-op; a send that fails (systemd gone, socket full) is logged at debug
level and never raises, so the decode loop can call :meth:`Notifier.watchdog` every
iteration: it sends at most once per half watchdog interval.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Mapping

log = logging.getLogger(__name__)

DEFAULT_PING_INTERVAL_S = 1.0
"""Watchdog ping spacing when NOTIFY_SOCKET is set but WATCHDOG_USEC is not, s."""


def socket_address(notify_socket: str) -> str | bytes:
    """The ``sendto`` address of a NOTIFY_SOCKET value: a path, or ``@name`` -> abstract ``\\0name``.

    Raises ValueError for a value that is not an AF_UNIX address (systemd also supports
    ``vsock:`` addresses for VMs; this daemon does not run in one).
    """
    if not notify_socket:
        raise ValueError("NOTIFY_SOCKET is empty")
    if notify_socket.startswith("@"):
        return b"\0" + notify_socket[1:].encode()
    if notify_socket.startswith("/"):
        return notify_socket
    raise ValueError(f"NOTIFY_SOCKET={notify_socket!r}: expected an absolute path or @abstract name")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


class Notifier:
    """Sends sd_notify messages; a no-op when ``address`` is None.

    ``watchdog_usec`` is systemd's watchdog interval (µs) or None; :meth:`watchdog` then
    pings at most every ``watchdog_usec / 2`` (systemd's recommendation), or every
    :data:`DEFAULT_PING_INTERVAL_S` when the interval is unknown but a socket is set.
    Thread-safe.
    """

    def __init__(self, address: str | bytes | None, watchdog_usec: int | None = None) -> None:
        self.address = address
        self.watchdog_usec = watchdog_usec
        self.ping_interval_s = (watchdog_usec / 2e6 if watchdog_usec
                                else DEFAULT_PING_INTERVAL_S)
        self.sent = 0
        self.errors = 0
        self._last_ping = -float("inf")
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "Notifier":
        """Build from NOTIFY_SOCKET, WATCHDOG_USEC and WATCHDOG_PID (``os.environ`` by default).

        No socket -> a disabled notifier. A WATCHDOG_PID naming another process (the
        variables leaked into a child) disables the watchdog, as sd_watchdog_enabled(3)
        does. A malformed value is logged and ignored (never an exception).
        """
        env = os.environ if environ is None else environ
        address: str | bytes | None = None
        raw = env.get("NOTIFY_SOCKET", "")
        if raw:
            try:
                address = socket_address(raw)
            except ValueError as e:
                log.warning("ignoring NOTIFY_SOCKET: %s", e)
        usec: int | None = None
        raw_usec = env.get("WATCHDOG_USEC", "")
        if raw_usec:
            try:
                usec = int(raw_usec)
                if usec <= 0:
                    raise ValueError
            except ValueError:
                log.warning("ignoring WATCHDOG_USEC=%r: not a positive integer", raw_usec)
                usec = None
        raw_pid = env.get("WATCHDOG_PID", "")
        if usec and raw_pid:
            try:
                if int(raw_pid) != os.getpid():
                    usec = None
            except ValueError:
                log.warning("ignoring WATCHDOG_PID=%r: not an integer", raw_pid)
        return cls(address, usec)

    @property
    def enabled(self) -> bool:
        """True when there is a socket to notify."""
        return self.address is not None

    def notify(self, *lines: str) -> bool:
        """Send one datagram of ``KEY=VALUE`` lines; True when it was sent."""
        if self.address is None:
            return False
        data = "\n".join(lines).encode("utf-8", "replace")
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                    self._sock.setblocking(False)
                self._sock.sendto(data, self.address)
            except OSError as e:
                self.errors += 1
                log.debug("sd_notify %r failed: %s", lines, e)
                return False
            self.sent += 1
            return True

    def ready(self, status: str | None = None) -> bool:
        """``READY=1`` (startup finished: cameras open, first frames in), with a status line."""
        lines = ["READY=1"]
        if status:
            lines.append(f"STATUS={_one_line(status)}")
        return self.notify(*lines)

    def status(self, text: str) -> bool:
        """``STATUS=text``: the one line ``systemctl status iscd`` shows."""
        return self.notify(f"STATUS={_one_line(text)}")

    def watchdog(self, now: float | None = None) -> bool:
        """``WATCHDOG=1``, at most once per :attr:`ping_interval_s`; True when sent.

        Call it from the loop whose progress proves the daemon alive (the decode loop), not
        from a timer thread, or a hung loop would go unnoticed. ``now`` is
        ``time.monotonic()`` seconds (for tests).
        """
        if self.address is None:
            return False
        t = time.monotonic() if now is None else now
        if t - self._last_ping < self.ping_interval_s:
            return False
        self._last_ping = t
        return self.notify("WATCHDOG=1")

    def extend_timeout(self, seconds: float) -> bool:
        """``EXTEND_TIMEOUT_USEC``: ask for ``seconds`` more to start or stop (slow cameras)."""
        return self.notify(f"EXTEND_TIMEOUT_USEC={max(0, int(seconds * 1e6))}")

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1`` (shutdown begun)."""
        lines = ["STOPPING=1"]
        if status:
            lines.append(f"STATUS={_one_line(status)}")
        return self.notify(*lines)

    def close(self) -> None:
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def __enter__(self) -> "Notifier":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
