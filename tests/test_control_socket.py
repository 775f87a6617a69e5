"""The daemon's control socket (iscd.service.control): one short command, one short reply,
over real ZeroMQ on loopback; unknown or oversized commands never reach an action."""

from __future__ import annotations

import zmq
import pytest

from fakes import wait_until
from iscd.outputs.base import OutputError
from iscd.service.control import MAX_COMMAND_BYTES, ControlSocket


def _ask(endpoint: str, msg: bytes, sock_poll: ControlSocket, timeout_s: float = 10.0) -> str:
    ctx = zmq.Context.instance()
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(endpoint)
    try:
        req.send(msg)
        assert wait_until(lambda: sock_poll.poll(), timeout_s), "the command never arrived"
        assert req.poll(int(timeout_s * 1000)), "no reply"
        return req.recv_string()
    finally:
        req.close(0)


def test_commands_and_replies() -> None:
    calls: list[str] = []
    ctl = ControlSocket("tcp://127.0.0.1:*", {b"blackbox": lambda: calls.append("bb") or "ok"})
    try:
        assert not ctl.poll()  # nothing waiting: no wait, nothing done
        assert _ask(ctl.endpoint, b"blackbox", ctl) == "ok" and calls == ["bb"]
        assert _ask(ctl.endpoint, b" BLACKBOX\n", ctl) == "ok" and calls == ["bb", "bb"]
        assert _ask(ctl.endpoint, b"ping", ctl) == "pong"
        reply = _ask(ctl.endpoint, b"rm -rf /", ctl)
        assert reply.startswith("error: unknown command") and "blackbox" in reply
        assert calls == ["bb", "bb"]
        assert ctl.counters() == {"control_commands": 4, "control_refused": 1}
    finally:
        ctl.close()
    assert not ctl.poll()  # closed: nothing


def test_a_failing_action_is_an_error_reply_not_an_exception() -> None:
    def boom() -> str:
        raise RuntimeError("no blackbox recording")

    ctl = ControlSocket("tcp://127.0.0.1:*", {b"blackbox": boom})
    try:
        assert _ask(ctl.endpoint, b"blackbox", ctl) == "error: no blackbox recording"
    finally:
        ctl.close()


def test_an_oversized_command_is_dropped_by_zeromq() -> None:
    calls: list[int] = []
    ctl = ControlSocket("tcp://127.0.0.1:*", {b"blackbox": lambda: calls.append(1) or "ok"})
    ctx = zmq.Context.instance()
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(ctl.endpoint)
    try:
        req.send(b"blackbox" + b" " * (MAX_COMMAND_BYTES + 1))
        for _ in range(50):  # the peer is disconnected by ZeroMQ; nothing reaches the handler
            ctl.poll()
        assert calls == [] and ctl.commands == 0
        assert _ask(ctl.endpoint, b"ping", ctl) == "pong"  # the socket still serves others
    finally:
        req.close(0)
        ctl.close()


@pytest.mark.parametrize("endpoint", ["tcp://0.0.0.0:5599", "tcp://*:5599"])
def test_only_loopback_unless_allowed(endpoint: str) -> None:
    with pytest.raises(OutputError, match="not loopback"):
        ControlSocket(endpoint, {})


def test_a_bad_endpoint_is_one_line() -> None:
    with pytest.raises(OutputError, match="expected transport://address"):
        ControlSocket("nonsense", {})
