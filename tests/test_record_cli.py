"""The recording's command line (issue 18): bad input is one line on stderr and exit 2
before the daemon starts (docs/hardening.md); ``iscd info`` of a stereo recording shows
its mode, windows and frame ranges, and with --check how much of a cut file was recovered;
``iscd replay`` of something that is not a recording is one line.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fakes import cli, one_error_line
from iscd.recording.pairfile import PairFileWriter


@pytest.mark.parametrize("case", ["a_file", "mode_alone", "bad_mode", "config_mode"])
def test_bad_record_options_are_one_line_exit_2(case: str, tmp_path: Path, no_daemon: None,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "f"
    f.write_text("x")
    cfg = tmp_path / "c.toml"
    cfg.write_text('[record]\nmode = "sometimes"\n')
    argv = {"a_file": ["--record", str(f)], "mode_alone": ["--record-mode", "full"],
            "bad_mode": ["--record", str(tmp_path), "--record-mode", "often"],
            "config_mode": ["--config", str(cfg), "--record", str(tmp_path)]}[case]
    rc, _, err = cli(capsys, "run", "--duration", "1", *argv)
    assert rc == 2
    if case == "bad_mode":
        assert "invalid choice" in err
        return
    line = one_error_line(err, "run")
    assert {"a_file": "is a file", "mode_alone": "needs --record", "config_mode": "record.mode"}[case] in line


def test_info_shows_mode_windows_ranges_and_recovery(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run-1"
    run.mkdir()
    img = np.arange(64 * 48, dtype=np.uint8).reshape(48, 64)
    with PairFileWriter(run / "000000-roi.iscr", width=64, height=48, mode="roi", fps=1000.0) as w:
        for i in list(range(10)) + list(range(20, 25)):
            w.append(i, i, i, img, img, *(((3, 4, 13, 12), (5, 6, 17, 14)) if i >= 3 else (None, None)), block=i // 4)
    rc, out, _ = cli(capsys, "info", "--compact", str(run))
    info = json.loads(out)
    assert rc == 0 and info["mode"] == "roi" and info["pairs"] == 15 and info["files"] == 1
    assert info["frame_ranges"] == [[0, 9], [20, 24]] and info["missing_frame_ids"] == 10
    assert info["whole_frame_pairs"] == 3 and info["windows"]["right"]["first"] == [5, 6, 17, 14]
    data = (run / "000000-roi.iscr").read_bytes()
    cut = tmp_path / "cut.iscr"
    cut.write_bytes(data[:len(data) // 2])
    rc, out, err = cli(capsys, "info", "--check", "--compact", str(cut))
    info = json.loads(out)
    c = info["check"][0]
    assert rc == 0 and not c["sealed"] and c["pairs"] == info["recovered_pairs"] > 0
    assert 0 < c["recovered_share"] < 1 and c["trailing_bytes_ignored"] > 0 and "not sealed" in err


def test_replay_of_a_stereo_file_without_pairs_isone_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "x.iscr"
    PairFileWriter(p, width=64, height=48, mode="full", fps=1000.0).close()
    rc, _, err = cli(capsys, "replay", str(p), "--out", str(tmp_path / "o.jsonl"))
    assert rc == 2 and "no whole pair" in one_error_line(err, "replay")
