"""``iscd info RECORDING``: JSON on stdout; bad input is one line on stderr, exit 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from iscd.cli.main import main
from iscd.recording import IscrWriter

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
BALL = SHARED / "data" / "photron" / "ball_12bit.cihx"
REPO = Path(__file__).resolve().parents[1]


def _need_ball() -> Path:
    if not BALL.is_file():
        pytest.skip(f"real Photron recording {BALL} not available (../shared beside the repo)")
    return BALL


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    rc = main(["info", *argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.shared
def test_info_photron_json(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = _run(capsys, str(_need_ball()), "--check")
    assert rc == 0, err
    info = json.loads(out)
    assert (info["frames"], info["width"], info["height"]) == (15, 384, 384)
    assert info["fps"] == 30000.0 and info["bit_depth"] == 12 and info["format"] == "photron"
    assert info["first_frame_id"] == 52 and info["dtype"] == "uint16"
    assert 255 < info["pixel_max"] <= 4095 and info["pixel_min"] < info["pixel_max"]


@pytest.mark.shared
def test_info_as_subprocess() -> None:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    proc = subprocess.run([sys.executable, "-m", "iscd", "info", "--compact",
                           str(_need_ball().with_suffix(".mraw"))],
                          capture_output=True, text=True, timeout=120, cwd=REPO, env=env)
    assert proc.returncode == 0, proc.stderr
    assert len(proc.stdout.strip().splitlines()) == 1
    info = json.loads(proc.stdout)
    assert info["frames"] == 15 and info["width"] == 384 and info["fps"] == 30000.0


def test_info_iscr_with_partial_record(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "left.iscr"
    with IscrWriter(path, width=32, height=16, dtype="uint16", camera="left", fps=1000.0,
                    exposure_s=1e-3, bit_depth=12, meta={"run": 7}) as w:
        w.append_many(np.arange(3), np.arange(3) * 10**6, np.full((3, 16, 32), 4000, np.uint16))
    with open(path, "ab") as f:
        f.write(b"\x01" * 20)
    rc, out, err = _run(capsys, str(path), "--check")
    assert rc == 0
    info = json.loads(out)
    assert (info["frames"], info["width"], info["height"], info["bit_depth"]) == (3, 32, 16, 12)
    assert info["camera"] == "left" and info["extra"]["meta"] == {"run": 7}
    assert info["pixel_max"] == 4000
    assert err.count("\n") == 1 and "warning" in err and "partial trailing record" in err
    assert info["warnings"] and "partial" in info["warnings"][0]


def _bad_cih(d: Path) -> Path:
    (d / "x.cih").write_text("nonsense\n")
    (d / "x.mraw").write_bytes(b"1")
    return d / "x.cih"


def _bad_iscr(d: Path) -> Path:
    (d / "y.iscr").write_bytes(b"garbage")
    return d / "y.iscr"


@pytest.mark.parametrize("make, expect", [
    (lambda d: d / "missing.iscr", "no such file"),
    (lambda d: d, "empty folder"),
    (_bad_cih, "cannot parse Photron header"),
    (_bad_iscr, "too short"),
])
def test_info_bad_input_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], make, expect) -> None:
    path = make(tmp_path)
    rc, out, err = _run(capsys, str(path))
    assert rc == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("iscd info: error: ") and expect in err, err
    assert "Traceback" not in err


def test_info_bad_input_subprocess_has_no_traceback(tmp_path: Path) -> None:
    cih = tmp_path / "cam.cih"
    cih.write_text("#Camera Information Header\n")
    proc = subprocess.run([sys.executable, "-m", "iscd", "info", str(cih)], capture_output=True,
                          text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 2 and proc.stdout == ""
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "missing pixel file cam.mraw" in proc.stderr
