"""The blackbox triggered by a command on the daemon's control socket (issue 18: "a command on
the ZeroMQ feed's companion socket"), live on the mock rig; and the command refused when the
run has no blackbox recording."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from iscd.core import config as C
from iscd.recording.pairs import PairSession
from fakes import LIGHT
from test_record_live import _run_folder


class _CommandOnce:
    """An output that, once the acquisition has run ``at_s``, sends ``command`` on the control
    socket from another thread (the frame loop answers it) and stops the daemon ``then_s`` later."""

    def __init__(self, daemon: Any, endpoint: str, command: bytes, at_s: float, then_s: float) -> None:
        self.daemon, self.endpoint, self.command = daemon, endpoint, command
        self.at_s, self.then_s = at_s, then_s
        self.sent_at: float | None = None
        self.reply: str | None = None

    def _ask(self) -> None:
        req = zmq.Context.instance().socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        req.connect(self.endpoint)
        try:
            req.send(self.command)
            if req.poll(60_000):
                self.reply = req.recv_string()
        finally:
            req.close(0)

    def write(self, rec: dict) -> None:
        if rec.get("type") != "stats":
            return
        t = rec["acquiring_s"]
        if self.sent_at is None and t >= self.at_s:
            self.sent_at = t
            threading.Thread(target=self._ask, daemon=True).start()
        elif self.sent_at is not None and t >= self.sent_at + self.then_s and self.reply is not None:
            self.daemon.request_stop()

    def close(self) -> None:
        pass


def test_blackbox_on_a_control_command(tmp_path: Path) -> None:
    from iscd.service.daemon import Daemon

    rec_dir = tmp_path / "rec"
    endpoint = f"ipc://{tmp_path}/control"
    text = (LIGHT + f'\n[record]\ndir = "{rec_dir}"\nmode = "blackbox"\npre_s = 1.0\npost_s = 0.5\n'
            'trigger_bad_packet = false\ntrigger_lost = false\n')
    d = Daemon(C.loads(text), out=str(tmp_path / "out.jsonl"), duration_s=120, install_signals=False,
               control=endpoint)
    cmd = _CommandOnce(d, endpoint, b"blackbox", at_s=2.0, then_s=2.0)
    d.extra_outputs.append(cmd)
    final = d.run()
    assert cmd.reply == "ok"
    assert final["control_commands"] == 1 and final["record_triggers"] == 1
    with PairSession(_run_folder(rec_dir)) as s:
        meta = s.files[0].metadata
        t = meta["trigger_frame"]
        ids = s.frame_ids
    assert meta["reason"] == "control command"
    assert ids[0] >= t - 1000 and ids[-1] == t + 500 and np.all(np.diff(ids) > 0)


def test_the_command_is_refused_without_a_blackbox(tmp_path: Path) -> None:
    from iscd.service.daemon import Daemon

    endpoint = f"ipc://{tmp_path}/control"
    d = Daemon(C.loads(LIGHT), out=str(tmp_path / "out.jsonl"), duration_s=120, install_signals=False,
               control=endpoint)
    cmd = _CommandOnce(d, endpoint, b"blackbox", at_s=1.0, then_s=0.5)
    d.extra_outputs.append(cmd)
    final = d.run()
    assert cmd.reply is not None and cmd.reply.startswith("error: ") and "--record" in cmd.reply
    assert final["control_commands"] == 1


def test_a_bad_control_endpoint_is_one_line_and_exit_2() -> None:
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-m", "iscd", "run", "--duration", "1", "--control", "tcp://0.0.0.0:5599"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert lines[-1].startswith("iscd run: error: control socket") and "not loopback" in lines[-1]
    assert "Traceback" not in p.stderr
