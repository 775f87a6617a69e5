"""The daemon's control socket: commands from other in-car software (docs/outputs.md).

A ZeroMQ REP socket beside the record feed (``iscd run --control ENDPOINT``, ``[daemon]
control``). A client sends one short command and gets one short reply:

=============  ===============================================================
``blackbox``   write the blackbox recording's last seconds (and the next ones):
               ``ok`` or ``error: ...`` (no recording, or not in blackbox mode)
``ping``       ``pong``
=============  ===============================================================

Anything else gets ``error: unknown command``. The socket is polled by the frame loop once a
block and never waits (one command a poll at most). What arrives is untrusted: a message is at
most :data:`MAX_COMMAND_BYTES` (longer ones are refused by ZeroMQ itself, ``MAXMSGSIZE``:
the connection is dropped), it is compared with the known commands and never interpreted
otherwise. As the record feed, it binds only to loopback / ``ipc://`` unless
``output.zmq_allow_remote`` says otherwise.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import zmq

from iscd.outputs.socket import bind_local

log = logging.getLogger(__name__)

MAX_COMMAND_BYTES = 64
"""Longest command accepted, bytes."""

Handler = Callable[[], str]
"""A command's action: returns the reply (``ok``, ``error: ...``)."""


class ControlSocket:
    """A REP socket bound to ``endpoint`` answering the commands of ``handlers``.

    Parameters
    ----------
    endpoint : str
        ZeroMQ endpoint to bind (``tcp://127.0.0.1:5557``, ``ipc:///run/iscd/control``; port
        ``*`` picks one: :attr:`endpoint` holds it).
    handlers : dict
        Command (bytes) -> action returning the reply text.
    allow_remote : bool
        Bind to an address that is not loopback.

    Raises
    ------
    OutputError
        One line, for an endpoint that is refused or cannot be bound.
    """

    def __init__(self, endpoint: str, handlers: dict[bytes, Handler], *, allow_remote: bool = False,
                 context: zmq.Context | None = None) -> None:
        self.handlers = {b"ping": lambda: "pong", **handlers}
        self._sock = bind_local(zmq.REP, endpoint, name="control socket", purpose="take commands from",
                                allow_remote=allow_remote, context=context,
                                options={zmq.MAXMSGSIZE: MAX_COMMAND_BYTES})
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self.commands = 0
        """Commands answered (known or not)."""
        self.refused = 0
        """Unknown commands."""
        self._closed = False

    def poll(self) -> bool:
        """Answer at most one waiting command without waiting; True if one was answered."""
        if self._closed:
            return False
        try:
            parts = self._sock.recv_multipart(zmq.NOBLOCK)
        except zmq.Again:
            return False
        except zmq.ZMQError as e:  # pragma: no cover - a broken socket: say it, go on decoding
            log.error("control socket: %s", e)
            return False
        cmd = parts[0].strip().lower() if len(parts) == 1 else b""
        action = self.handlers.get(cmd)
        if action is None:
            self.refused += 1
            reply = "error: unknown command (known: " + ", ".join(sorted(c.decode() for c in self.handlers)) + ")"
        else:
            try:
                reply = action()
            except Exception as e:  # a command must never stop the daemon
                log.exception("control command %r failed", cmd)
                reply = f"error: {e}"
            log.info("control: %s -> %s", cmd.decode("ascii", "replace"), reply)
        self.commands += 1
        try:
            self._sock.send_string(reply[:200], zmq.NOBLOCK)
        except zmq.ZMQError as e:  # pragma: no cover - the client went away
            log.warning("control socket: reply not sent: %s", e)
        return True

    def counters(self) -> dict[str, int]:
        """For the daemon's stats record."""
        return {"control_commands": self.commands, "control_refused": self.refused}

    def close(self) -> None:
        """Close the socket (idempotent)."""
        if not self._closed:
            self._closed = True
            self._sock.close(0)
