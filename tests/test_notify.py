"""iscd.service.notify against a fake systemd: an AF_UNIX datagram socket (a path, and the '@' abstract form)."""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from iscd.service.notify import Notifier, socket_address


def _recv_all(sock: socket.socket) -> list[str]:
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


@pytest.fixture(params=["path", "abstract"])
def fake_systemd(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    """A receiving datagram socket like systemd's, and the NOTIFY_SOCKET value naming it."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    if request.param == "path":
        p = tmp_path / "notify.sock"
        if len(str(p)) >= 100:  # sun_path is 108 bytes; pytest's tmp_path can be long
            p = Path(tempfile.mkdtemp(prefix="iscd-")) / "n.sock"
        sock.bind(str(p))
        name = str(p)
    else:
        tag = f"iscd-test-{uuid.uuid4().hex}"
        sock.bind(b"\0" + tag.encode())
        name = "@" + tag
    sock.setblocking(False)
    yield sock, name
    sock.close()


def test_address_forms() -> None:
    assert socket_address("/run/systemd/notify") == "/run/systemd/notify"
    assert socket_address("@sd-notify") == b"\0sd-notify"
    with pytest.raises(ValueError):
        socket_address("relative/path")


def test_ready_status_watchdog_stopping(fake_systemd: tuple[socket.socket, str]) -> None:
    sock, name = fake_systemd
    n = Notifier.from_env({"NOTIFY_SOCKET": name, "WATCHDOG_USEC": "5000000",
                           "WATCHDOG_PID": str(os.getpid())})
    assert n.enabled and n.ping_interval_s == pytest.approx(2.5)
    assert n.ready("cameras open\n2 x 1000 fps")
    assert n.status("decoding: 12 packets")
    assert n.watchdog(now=100.0)
    assert not n.watchdog(now=101.0)   # within WatchdogSec/2 = 2.5 s: rate-limited
    assert n.watchdog(now=102.6)
    assert n.extend_timeout(30)
    assert n.stopping()
    n.close()
    assert _recv_all(sock) == [
        "READY=1\nSTATUS=cameras open 2 x 1000 fps",   # status is kept to one line
        "STATUS=decoding: 12 packets",
        "WATCHDOG=1",
        "WATCHDOG=1",
        "EXTEND_TIMEOUT_USEC=30000000",
        "STOPPING=1",
    ]
    assert n.sent == 6 and n.errors == 0


def test_watchdog_pid_of_another_process_disables_the_watchdog_interval(
        fake_systemd: tuple[socket.socket, str]) -> None:
    sock, name = fake_systemd
    n = Notifier.from_env({"NOTIFY_SOCKET": name, "WATCHDOG_USEC": "200000",
                           "WATCHDOG_PID": str(os.getpid() + 1)})
    assert n.watchdog_usec is None          # the variables were meant for our parent
    n = Notifier.from_env({"NOTIFY_SOCKET": name, "WATCHDOG_USEC": "200000"})
    assert n.watchdog_usec == 200000 and n.ping_interval_s == pytest.approx(0.1)


def test_no_socket_is_a_silent_no_op() -> None:
    n = Notifier.from_env({})
    assert not n.enabled
    assert not n.ready() and not n.watchdog() and not n.status("x") and not n.stopping()
    assert n.sent == 0 and n.errors == 0
    bad = Notifier.from_env({"NOTIFY_SOCKET": "not-a-socket", "WATCHDOG_USEC": "abc"})
    assert not bad.enabled and bad.watchdog_usec is None


def test_vanished_systemd_never_raises(tmp_path: Path) -> None:
    p = tmp_path / "gone.sock"
    if len(str(p)) >= 100:
        p = Path(tempfile.mkdtemp(prefix="iscd-")) / "g.sock"
    n = Notifier(str(p), watchdog_usec=1_000_000)
    assert not n.ready()          # nobody listens: counted, not raised
    assert not n.watchdog(now=0.0)
    assert n.errors == 2 and n.sent == 0


def test_child_process_notifies_with_its_own_credentials(fake_systemd: tuple[socket.socket, str]) -> None:
    """A daemon started with NOTIFY_SOCKET in its environment reaches systemd, and the kernel
    credentials on the datagram name the daemon's pid (what NotifyAccess=main checks)."""
    sock, name = fake_systemd
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
    code = ("from iscd.service.notify import Notifier\n"
            "n = Notifier.from_env()\n"
            "assert n.ready('up'), 'ready not sent'\n"
            "assert n.watchdog(), 'watchdog not sent'\n"
            "assert not n.watchdog(), 'watchdog not rate-limited'\n")
    env = {**os.environ, "NOTIFY_SOCKET": name, "WATCHDOG_USEC": "5000000"}
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, stderr=subprocess.PIPE, text=True)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    msgs = []
    creds_len = socket.CMSG_LEN(struct.calcsize("3i"))
    while True:
        try:
            data, anc, _, _ = sock.recvmsg(4096, creds_len)
        except BlockingIOError:
            break
        pids = [struct.unpack("3i", d)[0] for lvl, typ, d in anc
                if lvl == socket.SOL_SOCKET and typ == socket.SCM_CREDENTIALS]
        msgs.append((data.decode(), pids))
    assert msgs == [("READY=1\nSTATUS=up", [proc.pid]), ("WATCHDOG=1", [proc.pid])]
