"""``iscd calibrate`` end to end on synthetic image files: rejection reasons, and bad input
(too few pairs, wrong board size, unequal counts, unreadable images): a one-line message,
exit status 2, and no file written."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from iscd.calibration.io import StereoCalibration, load_calibration, save_calibration
from iscd.calibration.synthetic import make_pairs
from iscd.cli.main import main
from iscd.core.config import CameraConfig


@pytest.fixture(scope="module")
def images(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """9 pairs: 8 good ones and one whose right image shows no board."""
    folder = tmp_path_factory.mktemp("pairs")
    sp = make_pairs(8, seed=5)
    sp.write(folder)
    blank = np.full((512, 512), 110, np.uint8)
    cv2.imwrite(str(folder / "left_08.png"), sp.left[0])
    cv2.imwrite(str(folder / "right_08.png"), blank)
    return folder, sp


def subset(src: Path, dst: Path, n: int, drop_right: int = 0) -> tuple[str, str]:
    dst.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        shutil.copy(src / f"left_{i:02d}.png", dst)
        if i < n - drop_right:
            shutil.copy(src / f"right_{i:02d}.png", dst)
    return str(dst / "left_*.png"), str(dst / "right_*.png")


def run(args: list[str]) -> int:
    return main(["-q", "calibrate", *args])


def one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("iscd calibrate: error: ")
    assert "Traceback" not in err
    return err


def test_calibrates_and_reports_rejected_pair(images, tmp_path: Path,  # type: ignore[no-untyped-def]
                                              capsys: pytest.CaptureFixture[str]) -> None:
    folder, sp = images
    out = tmp_path / "sub" / "rig.yml"
    rc = run(["--left", str(folder / "left_*.png"), "--right", str(folder / "right_*.png"),
              "--board", "9x6", "--square", "0.08", "--out", str(out)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "rejected pair left_08.png & right_08.png: board not found in right image" in cap.err
    assert "calibrated from 8 of 9 pairs" in cap.out
    cal = load_calibration(out)
    assert abs(cal.baseline_m - 0.25) / 0.25 < 0.01
    assert cal.n_pairs == 8 and cal.is_rectified
    report = tmp_path / "sub" / "rig_report"
    assert {p.name for p in report.iterdir()} == {"report.json", "report.md", "preview.png"}
    assert "board not found in right image" in (report / "report.md").read_text()


def test_folder_inputs_and_custom_report_dir(images, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    folder, _ = images
    left, right = tmp_path / "L", tmp_path / "R"
    left.mkdir()
    right.mkdir()
    for i in range(7):
        shutil.copy(folder / f"left_{i:02d}.png", left)
        shutil.copy(folder / f"right_{i:02d}.png", right)
    rc = run(["--left", str(left), "--right", str(right), "--board", "9x6", "--square", "0.08",
              "--out", str(tmp_path / "r.yml"), "--report", str(tmp_path / "rep"),
              "--no-joint", "--dist-model", "k1k2k3"])
    assert rc == 0
    assert (tmp_path / "rep" / "report.json").is_file()


def assert_nothing_written(tmp_path: Path, out: Path) -> None:
    assert not out.exists()
    assert not out.with_name(f"{out.stem}_report").exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temp files


def test_too_few_pairs(images, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    folder, _ = images
    left, right = subset(folder, tmp_path / "few", 4)
    out = tmp_path / "rig.yml"
    assert run(["--left", left, "--right", right, "--board", "9x6", "--square", "0.08",
                "--out", str(out)]) == 2
    assert "only 4 usable pairs (need at least 6)" in one_line_error(capsys)
    assert_nothing_written(tmp_path, out)


def test_too_few_pairs_names_the_rejections(images, tmp_path: Path,  # type: ignore[no-untyped-def]
                                            capsys: pytest.CaptureFixture[str]) -> None:
    folder, _ = images
    out = tmp_path / "rig.yml"
    assert run(["--left", str(folder / "left_*.png"), "--right", str(folder / "right_*.png"),
                "--board", "9x6", "--square", "0.08", "--out", str(out), "--min-pairs", "9"]) == 2
    err = one_line_error(capsys)
    assert "only 8 usable pairs (need at least 9): board not found in right image (1 pair)" in err
    assert_nothing_written(tmp_path, out)


@pytest.mark.parametrize("board", ["8x6", "10x6"])
def test_wrong_board_size(images, tmp_path: Path, board: str,  # type: ignore[no-untyped-def]
                          capsys: pytest.CaptureFixture[str]) -> None:
    folder, _ = images
    left, right = subset(folder, tmp_path / "p", 3)
    out = tmp_path / "rig.yml"
    assert run(["--left", left, "--right", right, "--board", board, "--square", "0.08",
                "--out", str(out)]) == 2
    err = one_line_error(capsys)
    assert f"with {board} corners was not found in any of the 3 pairs" in err
    assert "inner corners" in err
    if board == "8x6":
        assert "larger than that" in err
    assert_nothing_written(tmp_path, out)


def test_unequal_counts(images, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    folder, _ = images
    left, right = subset(folder, tmp_path / "p", 7, drop_right=1)
    out = tmp_path / "rig.yml"
    assert run(["--left", left, "--right", right, "--board", "9x6", "--square", "0.08",
                "--out", str(out)]) == 2
    assert "--left matches 7 images but --right matches 6" in one_line_error(capsys)
    assert_nothing_written(tmp_path, out)


@pytest.mark.parametrize("damage", ["garbage", "empty", "truncated"])
def test_unreadable_image(images, tmp_path: Path, damage: str,  # type: ignore[no-untyped-def]
                          capsys: pytest.CaptureFixture[str]) -> None:
    folder, _ = images
    left, right = subset(folder, tmp_path / "p", 7)
    bad = tmp_path / "p" / "right_04.png"
    data = bad.read_bytes()
    bad.write_bytes({"garbage": b"not an image at all" * 10, "empty": b"",
                     "truncated": data[:60]}[damage])
    out = tmp_path / "rig.yml"
    assert run(["--left", left, "--right", right, "--board", "9x6", "--square", "0.08",
                "--out", str(out)]) == 2
    err = one_line_error(capsys)
    assert "cannot read image" in err and "right_04.png" in err
    assert_nothing_written(tmp_path, out)


def test_images_of_different_sizes(images, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    folder, _ = images
    left, right = subset(folder, tmp_path / "p", 7)
    cv2.imwrite(str(tmp_path / "p" / "left_02.png"), np.zeros((100, 120), np.uint8))
    out = tmp_path / "rig.yml"
    assert run(["--left", left, "--right", right, "--board", "9x6", "--square", "0.08",
                "--out", str(out)]) == 2
    assert "is 120x100 px but the first image is 512x512 px" in one_line_error(capsys)
    assert_nothing_written(tmp_path, out)


@pytest.mark.parametrize("args, message", [
    (["--left", "/nonexistent/*.png", "--right", "/nonexistent/*.png", "--board", "9x6",
      "--square", "0.025", "--out", "OUT"], "--left '/nonexistent/*.png' matches no image files"),
    (["--left", "a", "--right", "b", "--board", "9by6", "--square", "0.025", "--out", "OUT"],
     "board size must look like COLSxROWS"),
    (["--left", "a", "--right", "b", "--board", "9x6", "--square", "-1", "--out", "OUT"],
     "square size must be > 0 m"),
    (["--left", "a", "--right", "b", "--board", "6x6", "--square", "0.02", "--out", "OUT"],
     "square, so its corner order is ambiguous"),
    (["--left", "a", "--right", "b", "--board", "7x5", "--square", "0.04", "--charuco",
      "--out", "OUT"], "--charuco needs --marker"),
    (["--left", "a", "--right", "b", "--board", "7x5", "--square", "0.04", "--charuco",
      "--marker", "0.05", "--out", "OUT"], "marker size must be > 0 and smaller than the square"),
    (["--left", "a", "--right", "b", "--board", "7x5", "--square", "0.04", "--charuco",
      "--marker", "0.03", "--dict", "9X9_1", "--out", "OUT"], "unknown ArUco dictionary"),
    (["--left", "a", "--board", "9x6", "--square", "0.025", "--out", "OUT"],
     "give --left GLOB and --right GLOB"),
    (["--left", "a", "--right", "b", "--board", "9x6", "--square", "0.025"], "give --out"),
    (["--left", "a", "--right", "b", "--board", "9x6", "--square", "0.025",
      "--verify", "/nonexistent/cal.yml"], "calibration file not found"),
])
def test_bad_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str],
                       message: str) -> None:
    out = tmp_path / "rig.yml"
    args = [str(out) if a == "OUT" else a for a in args]
    assert run(args) == 2
    assert message in one_line_error(capsys)
    assert not out.exists()


def test_verify_rejects_calibration_of_other_image_size(images, tmp_path: Path,  # type: ignore[no-untyped-def]
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    folder, _ = images
    cal_path = tmp_path / "other.yml"
    save_calibration(StereoCalibration.ideal(CameraConfig(width=640, height=480)), cal_path)
    left, right = subset(folder, tmp_path / "p", 3)
    assert run(["--left", left, "--right", right, "--board", "9x6", "--square", "0.08",
                "--verify", str(cal_path)]) == 2
    assert "images are 512x512 px but" in one_line_error(capsys)


def test_verify_synthetic_truth_ok_and_ideal_rig_not(images, tmp_path: Path,  # type: ignore[no-untyped-def]
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """The true rig passes --verify; an ideal (distortion-free, unrotated) model of the same
    rig does not."""
    folder, sp = images
    left, right = subset(folder, tmp_path / "p", 4)
    truth = tmp_path / "truth.yml"
    save_calibration(sp.truth, truth)
    assert run(["--left", left, "--right", right, "--board", "9x6", "--square", "0.08",
                "--verify", str(truth)]) == 0
    assert capsys.readouterr().out.startswith("OK:")
    ideal = tmp_path / "ideal.yml"
    save_calibration(StereoCalibration.from_parameters(512, 512, 600.0, baseline_m=0.25), ideal)
    assert run(["--left", left, "--right", right, "--board", "9x6", "--square", "0.08",
                "--verify", str(ideal)]) == 1
    assert capsys.readouterr().out.startswith("RECALIBRATE:")


def test_help_describes_the_command(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    text = capsys.readouterr().out
    for word in ("--left", "--right", "--board", "--square", "--out", "--verify", "--live",
                 "--charuco", "RECALIBRATE", "inner corners"):
        assert word in text
