"""From image files to board observations: globbing, pairing, reading, detection.

Everything here raises :class:`iscd.calibration.io.CalibrationError` with a one-line message for
bad input (no images, unequal counts, unreadable or differently sized images).
"""

from __future__ import annotations

import glob
import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from iscd.calibration.boards import BoardSpec
from iscd.calibration.detect import Detection, PairObservation, detect, pair_detections, read_image
from iscd.calibration.io import CalibrationError
from iscd.calibration.solve import PairStatus

log = logging.getLogger(__name__)


def expand(pattern: str, what: str) -> list[Path]:
    """Files matching a glob (``~`` expanded), in name order; a folder means all its files."""
    p = os.path.expanduser(pattern)
    if os.path.isdir(p):
        files = sorted(Path(p).iterdir())
        files = [f for f in files if f.is_file() and not f.name.startswith(".")]
    else:
        files = sorted(Path(f) for f in glob.glob(p) if os.path.isfile(f))
    if not files:
        raise CalibrationError(f"{what} {pattern!r} matches no image files")
    return files


def pair_files(left: str, right: str) -> list[tuple[Path, Path]]:
    """Left and right image files paired in name order."""
    lf, rf = expand(left, "--left"), expand(right, "--right")
    if len(lf) != len(rf):
        raise CalibrationError(
            f"--left matches {len(lf)} images but --right matches {len(rf)}; pairs are "
            "formed in name order, so both must match the same number")
    return list(zip(lf, rf))


@dataclass
class Detected:
    """The detection outcome over all pairs."""

    observations: list[PairObservation]
    rejected: list[PairStatus]
    image_size: tuple[int, int]
    names: list[str]


def pair_name(left: Path, right: Path) -> str:
    return f"{left.name} & {right.name}"


def _read(path: Path, size: tuple[int, int] | None) -> np.ndarray:
    img = read_image(path)
    if img is None:
        raise CalibrationError(f"cannot read image {path} (missing, empty or not an image)")
    if size is not None and (img.shape[1], img.shape[0]) != size:
        raise CalibrationError(f"image {path} is {img.shape[1]}x{img.shape[0]} px but the "
                               f"first image is {size[0]}x{size[1]} px")
    return img


def detect_image_pairs(pairs: Iterable[tuple[str, np.ndarray, np.ndarray]], board: BoardSpec,
                       total: int | None = None, progress: bool = False) -> Detected:
    """Detect the board in (name, left image, right image) pairs. A pair is rejected with a
    reason when the board is missing in either image or too few corners are common."""
    obs: list[PairObservation] = []
    rejected: list[PairStatus] = []
    names: list[str] = []
    size: tuple[int, int] | None = None
    it: Iterable[tuple[str, np.ndarray, np.ndarray]] = pairs
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, desc="detecting board", unit="pair", leave=False)
    try:
        for name, left, right in it:
            names.append(name)
            if size is None:
                size = (left.shape[1], left.shape[0])
            dl, dr = detect(left, board), detect(right, board)
            if bar is not None:
                bar.update(1)
            if not isinstance(dl, Detection) or not isinstance(dr, Detection):
                if not isinstance(dl, Detection) and not isinstance(dr, Detection):
                    reason = (f"{dl.reason} in either image" if dl.reason == dr.reason
                              else f"left image: {dl.reason}; right image: {dr.reason}")
                elif not isinstance(dl, Detection):
                    reason = f"{dl.reason} in left image"
                else:
                    reason = f"{dr.reason} in right image"  # type: ignore[union-attr]
                rejected.append(PairStatus(name, False, reason))
                continue
            po = pair_detections(name, dl, dr, board)
            if po is None:
                rejected.append(PairStatus(name, False, "too few corners seen in both images"))
                continue
            obs.append(po)
    finally:
        if bar is not None:
            bar.close()
    if size is None:
        raise CalibrationError("no image pairs given")
    return Detected(obs, rejected, size, names)


def detect_files(pairs: list[tuple[Path, Path]], board: BoardSpec,
                 progress: bool = False) -> Detected:
    """Read and detect file pairs. Every image must be readable and of the same size."""
    size: list[tuple[int, int] | None] = [None]

    def gen() -> Iterable[tuple[str, np.ndarray, np.ndarray]]:
        for lp, rp in pairs:
            left = _read(lp, size[0])
            if size[0] is None:
                size[0] = (left.shape[1], left.shape[0])
            right = _read(rp, size[0])
            yield pair_name(lp, rp), left, right

    # Fail fast on unreadable files before spending time on detection.
    for lp, rp in pairs:
        for p in (lp, rp):
            if not p.is_file() or p.stat().st_size == 0:
                raise CalibrationError(f"cannot read image {p} (missing or empty)")
    return detect_image_pairs(gen(), board, total=len(pairs), progress=progress)


def no_board_message(det: Detected, board: BoardSpec) -> str | None:
    """A specific message when the board was found in no pair at all (wrong --board?)."""
    if det.observations:
        return None
    reasons = {s.reason for s in det.rejected}
    c, r = board.corner_grid
    hint = ("--board gives inner corners COLSxROWS for a chessboard (a 10x7-square board is 9x6)"
            if board.kind == "chessboard" else
            "--board gives squares COLSxROWS for a ChArUco board; check --dict and --marker too")
    extra = ""
    if any("more corners than" in x for x in reasons):
        extra = "; the board in the images is larger than that"
    return (f"the {board.kind} with {c}x{r} corners was not found in any of the "
            f"{len(det.names)} pairs{extra}; {hint}")
