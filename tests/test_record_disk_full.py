"""Disk full under a live recording (issue 18): one clear log line, the recording stops,
decoding goes on, and the stats say what was not written (record_dropped, with
record_written + record_dropped = pairs decoded); the file reads back to its last whole pair.

On a real 1 MiB tmpfs where ``mount -t tmpfs`` is permitted (else skipped, as in
tests/test_disk_full.py), and with ENOSPC injected into the writer's system call everywhere.
"""

from __future__ import annotations

import errno
import logging
import os
from pathlib import Path
from typing import Any

import pytest

from fakes import tmpfs, LIGHT, run_daemon_until, stats_records
from iscd.recording import pairfile
from iscd.recording.pairs import PairSession


@pytest.fixture
def tmpfs_1m(tmp_path: Path):
    """A 1 MiB tmpfs at tmp_path/mnt (skipped where mounting is not permitted)."""
    with tmpfs(tmp_path / "mnt", "1m") as mnt:
        yield mnt


def _run_until_packets(text: str, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> tuple[dict, list[str]]:
    def done(recs: list[dict]) -> bool:
        return sum(1 for r in recs if r["type"] == "packet" and r["crc_ok"]) >= 4

    with caplog.at_level(logging.WARNING, logger="iscd.recording.recorder"):
        _, recs, stop = run_daemon_until(text, tmp_path, done)
    assert stop.met_at_s is not None, "decoding did not go on"
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    return stats_records(recs, final=True)[0], errors


def _check(final: dict, errors: list[str], folder_root: Path) -> None:
    assert len(errors) == 1 and "recording stopped" in errors[0] and "No space left on device" in errors[0]
    assert "decoding goes on" in errors[0]
    assert final["record_stopped"] and final["record_dropped"] > 1000 and final["packets_ok"] >= 4
    assert final["record_written"] + final["record_dropped"] == final["pairs_decoded"]
    runs = sorted(folder_root.glob("run-*"))
    with PairSession(runs[0]) as s:  # what was written reads back, up to its last whole pair
        assert s.n_pairs == final["record_written"]
    print(f"disk full: {final['record_written']} pairs written, {final['record_dropped']} not "
          f"(of {final['pairs_decoded']} decoded), {final['packets_ok']} packets decoded")


def test_a_full_tmpfs_stops_the_recording_not_the_decoding(tmpfs_1m: Path, tmp_path: Path,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    text = LIGHT + f'\n[record]\ndir = "{tmpfs_1m}"\nmode = "roi"\n'
    final, errors = _run_until_packets(text, tmp_path, caplog)
    _check(final, errors, tmpfs_1m)


def test_injected_enospc_stops_the_recording_not_the_decoding(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    room = {"left": 3 * 2**20}
    real = pairfile._write

    def disk(fd: int, data: Any) -> int:
        if room["left"] <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        k = real(fd, data[:room["left"]])
        room["left"] -= k
        return k

    monkeypatch.setattr(pairfile, "_write", disk)
    rec_dir = tmp_path / "rec"
    text = LIGHT + f'\n[record]\ndir = "{rec_dir}"\nmode = "roi"\n'
    final, errors = _run_until_packets(text, tmp_path, caplog)
    _check(final, errors, rec_dir)
