"""The records on a local ZeroMQ socket, for other in-car software (docs/outputs.md).

Each record is one two-frame message ``[type, json]``: the record's ``type`` (``packet``,
``range``, ``stats``; ZeroMQ subscribers filter on it with ``SUBSCRIBE b"range"``) and the
same compact JSON line the ``.jsonl`` file gets (without the newline).

The socket is an XPUB (a PUB that also sees subscriptions) with ``XPUB_NODROP``: when a
subscriber's queue holds ``hwm`` messages, sending fails at once (EAGAIN) instead of
blocking or silently discarding, so the record is dropped *and counted*
(:attr:`ZmqPublisher.dropped`, reported in the stats record). The daemon never waits for a
subscriber. Note that with ``XPUB_NODROP`` one stalled subscriber makes the publisher drop
for every subscriber until it drains; ``nodrop=False`` gives plain PUB behaviour
(per-subscriber silent drops, uncounted).

Binding is refused for addresses other than loopback (``127.0.0.0/8``, ``::1``,
``localhost``, interface ``lo``) or ``ipc://``/``inproc://`` unless ``allow_remote=True``:
decoded data is not exposed to the car's other networks by accident.
"""

from __future__ import annotations

import ipaddress
import logging
import threading
from typing import Any

import zmq

from iscd.outputs.base import Output, OutputError
from iscd.outputs.jsonl import encode_record

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5556"


def is_local_endpoint(endpoint: str) -> bool:
    """True when binding ``endpoint`` exposes nothing beyond this machine.

    ``ipc://`` and ``inproc://`` are local; ``tcp://HOST:PORT`` is local when HOST is a
    loopback address, ``localhost`` or the interface ``lo``. Anything else (``*``,
    ``0.0.0.0``, another interface or address, ``udp://``, ``pgm://``) is not.
    Raises OutputError for an endpoint that is not ``transport://address``.
    """
    transport, sep, addr = endpoint.partition("://")
    if not sep or not addr:
        raise OutputError(f"ZeroMQ endpoint {endpoint!r}: expected transport://address, "
                          f"e.g. {DEFAULT_ENDPOINT}")
    if transport in ("ipc", "inproc"):
        return True
    if transport not in ("tcp", "ws"):
        return False
    host = addr.rsplit(":", 1)[0] if ":" in addr else addr
    host = host.split(";")[-1]  # "source;dest" form: the bind address is what matters
    host = host.strip("[]")
    if host in ("localhost", "lo"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def bind_local(kind: int, endpoint: str, *, name: str, purpose: str, allow_remote: bool = False,
               options: dict[int, int] | None = None, context: zmq.Context | None = None) -> zmq.Socket:
    """A ZeroMQ socket of ``kind`` bound to ``endpoint``, refused beyond this machine.

    Parameters
    ----------
    kind : int
        The socket type (``zmq.XPUB``, ``zmq.REP``).
    endpoint : str
        Where to bind (port ``*`` picks one: read it back with ``LAST_ENDPOINT``).
    name, purpose : str
        For the messages: ``"{name} {endpoint!r} is not loopback: refusing to {purpose} beyond
        this machine"``.
    allow_remote : bool
        Bind to an address that is not loopback (``output.zmq_allow_remote``).
    options : dict, optional
        Socket options set before binding (``LINGER`` is always 0).

    Raises
    ------
    OutputError
        One line: the endpoint malformed, not loopback, or not bindable.
    """
    if not is_local_endpoint(endpoint) and not allow_remote:
        raise OutputError(f"{name} {endpoint!r} is not loopback: refusing to {purpose} beyond this "
                          f"machine (set output.zmq_allow_remote = true to allow it)")
    sock = (context or zmq.Context.instance()).socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    for opt, value in (options or {}).items():
        sock.setsockopt(opt, value)
    try:
        sock.bind(endpoint)
    except zmq.ZMQError as e:
        sock.close(0)
        raise OutputError(f"cannot bind {name} {endpoint!r}: {e}") from None
    return sock


class ZmqPublisher(Output):
    """Publishes records as ``[type, json]`` on ``endpoint`` (bound; subscribers connect).

    ``endpoint`` may use port ``*`` (``tcp://127.0.0.1:*``): :attr:`endpoint` then holds the
    port chosen. ``hwm``: messages queued per subscriber. Raises
    :class:`~iscd.outputs.OutputError` (one line) for a refused or unusable endpoint.
    :meth:`write` never blocks and never raises.
    """

    def __init__(self, endpoint: str = DEFAULT_ENDPOINT, *, allow_remote: bool = False,
                 hwm: int = 10_000, nodrop: bool = True, context: zmq.Context | None = None) -> None:
        self._sock = bind_local(zmq.XPUB, endpoint, name="ZeroMQ endpoint", purpose="publish decoded data",
                                allow_remote=allow_remote, context=context,
                                options={zmq.SNDHWM: int(hwm), **({zmq.XPUB_NODROP: 1} if nodrop else {})})
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self.sent = 0
        """Messages handed to ZeroMQ."""
        self.dropped = 0
        """Records dropped because a subscriber's queue was full (or after close)."""
        self.errors = 0
        self.subscribers = 0
        """Distinct topic subscriptions currently live (ZeroMQ passes on the first SUBSCRIBE
        of a topic and the last UNSUBSCRIBE), a lower bound on the subscriber count."""
        self._lock = threading.Lock()
        self._closed = False

    def _drain_subscriptions(self) -> None:
        while self._sock.getsockopt(zmq.EVENTS) & zmq.POLLIN:
            try:
                msg = self._sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                return
            if msg[:1] == b"\x01":
                self.subscribers += 1
            elif msg[:1] == b"\x00":
                self.subscribers -= 1

    def write(self, record: dict[str, Any]) -> bool:  # type: ignore[override]
        """Publish one record; False when it was dropped (full queue, bad record, closed).

        With no subscriber at all nothing is encoded or sent (True is returned: nothing was
        lost that anyone asked for)."""
        with self._lock:
            if self._closed:
                self.dropped += 1
                return False
            try:
                self._drain_subscriptions()
                if self.subscribers <= 0:
                    return True
                body = encode_record(record)[:-1]
                topic = str(record.get("type", "")).encode()
                self._sock.send_multipart([topic, body], flags=zmq.NOBLOCK, copy=True)
            except zmq.Again:
                self.dropped += 1
                return False
            except (TypeError, ValueError, zmq.ZMQError) as e:
                self.dropped += 1
                self._error(f"record dropped: {e}")
                return False
            self.sent += 1
            return True

    def wait_for_subscribers(self, n: int = 1, timeout_s: float = 5.0) -> bool:
        """Block until ``n`` subscriptions have arrived (tests, tools); True on success."""
        import time

        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self.subscribers < n:
                left = deadline - time.monotonic()
                if left <= 0 or not self._sock.poll(int(left * 1000), zmq.POLLIN):
                    return self.subscribers >= n
                self._drain_subscriptions()
        return True

    def counters(self) -> dict[str, int]:
        """For the daemon's stats record."""
        return {"zmq_sent": self.sent, "zmq_dropped": self.dropped, "zmq_errors": self.errors}

    def close(self) -> None:
        """Close the socket (pending messages are discarded: LINGER 0). Idempotent."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._sock.close(0)

    def __enter__(self) -> "ZmqPublisher":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _error(self, msg: str) -> None:
        self.errors += 1
        if self.errors <= 5 or self.errors % 100 == 0:
            log.error("zmq output: %s (error %d)", msg, self.errors)
