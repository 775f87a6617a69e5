"""Calibration targets: plain chessboards and ChArUco boards.

Sizes on the command line (``--board COLSxROWS``):

- chessboard: the *inner* corners per row and per column (OpenCV's ``patternSize``); the
  OpenCV sample board ``9x6`` has 10 x 7 squares.
- ChArUco: the *squares* per row and per column (OpenCV's ``CharucoBoard`` size); its corners
  are the (COLS-1) x (ROWS-1) inner chessboard corners, each identified by the markers around it.

Board coordinates are metres in the board plane (z = 0), x along a row, y down the columns,
with the first inner corner at the origin (chessboard) or OpenCV's ChArUco corner layout.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import cv2
import numpy as np

BoardKind = Literal["chessboard", "charuco"]

ARUCO_DICTS: tuple[str, ...] = tuple(
    n[len("DICT_"):] for n in dir(cv2.aruco) if n.startswith("DICT_") and n.upper() == n)
"""Names accepted by ``--dict`` (e.g. ``4X4_50``, ``5X5_100``, ``APRILTAG_36H11``)."""


class BoardError(ValueError):
    """An invalid board description; ``str(err)`` is one line."""


def parse_board_size(text: str) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6). Raises :class:`BoardError` for anything else."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX*]\s*(\d+)\s*", text or "")
    if not m:
        raise BoardError(f"board size must look like COLSxROWS, e.g. 9x6; got {text!r}")
    cols, rows = int(m.group(1)), int(m.group(2))
    return cols, rows


@dataclass(frozen=True)
class BoardSpec:
    """A calibration target.

    kind: ``"chessboard"`` or ``"charuco"``. cols, rows: inner corners (chessboard) or squares
    (ChArUco) per row / column. square_m: square side, m. marker_m: ChArUco marker side, m.
    dictionary: ArUco dictionary name without ``DICT_`` (ChArUco only).
    """

    kind: BoardKind
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "4X4_50"
    legacy: bool = False

    def __post_init__(self) -> None:
        if self.kind not in ("chessboard", "charuco"):
            raise BoardError(f"board kind must be chessboard or charuco, got {self.kind!r}")
        if not (self.square_m > 0 and np.isfinite(self.square_m)):
            raise BoardError(f"square size must be > 0 m, got {self.square_m}")
        if self.kind == "chessboard":
            if self.cols < 2 or self.rows < 2:
                raise BoardError(f"a chessboard needs at least 2x2 inner corners, got "
                                 f"{self.cols}x{self.rows}")
            if self.cols == self.rows:
                # A square pattern is 90-degree symmetric: corner order is ambiguous.
                raise BoardError(f"a {self.cols}x{self.rows} chessboard is square, so its corner "
                                 "order is ambiguous; use a board with unequal sides (e.g. 9x6)")
        else:
            if self.cols < 3 or self.rows < 3:
                raise BoardError(f"a ChArUco board needs at least 3x3 squares, got "
                                 f"{self.cols}x{self.rows}")
            if not 0 < self.marker_m < self.square_m:
                raise BoardError(f"marker size must be > 0 and smaller than the square "
                                 f"({self.square_m} m), got {self.marker_m}")
            if self.dictionary.upper() not in ARUCO_DICTS:
                raise BoardError(f"unknown ArUco dictionary {self.dictionary!r} "
                                 f"(e.g. {', '.join(ARUCO_DICTS[:6])}, ...)")
            need = (self.cols * self.rows) // 2
            size = self.aruco_dictionary.bytesList.shape[0]
            if need > size:
                raise BoardError(f"a {self.cols}x{self.rows} ChArUco board needs {need} markers "
                                 f"but DICT_{self.dictionary.upper()} has only {size}")

    # ------------------------------------------------------------------ geometry
    @property
    def corner_grid(self) -> tuple[int, int]:
        """(columns, rows) of the corners that are detected."""
        if self.kind == "chessboard":
            return self.cols, self.rows
        return self.cols - 1, self.rows - 1

    @property
    def n_corners(self) -> int:
        c, r = self.corner_grid
        return c * r

    @property
    def squares(self) -> tuple[int, int]:
        """(columns, rows) of squares of the printed board."""
        if self.kind == "chessboard":
            return self.cols + 1, self.rows + 1
        return self.cols, self.rows

    @cached_property
    def object_points(self) -> np.ndarray:
        """(n_corners, 3) float32 corner positions on the board, m, in detection/id order."""
        if self.kind == "charuco":
            return np.asarray(self.charuco_board.getChessboardCorners(), np.float32).reshape(-1, 3)
        c, r = self.corner_grid
        pts = np.zeros((r * c, 3), np.float32)
        pts[:, :2] = np.mgrid[0:c, 0:r].T.reshape(-1, 2) * self.square_m
        return pts

    @property
    def label(self) -> str:
        """Short description for reports, e.g. ``chessboard 9x6, 25 mm``."""
        s = f"{self.kind} {self.cols}x{self.rows}, square {self.square_m * 1000:g} mm"
        if self.kind == "charuco":
            s += f", marker {self.marker_m * 1000:g} mm, DICT_{self.dictionary.upper()}"
        return s

    # ------------------------------------------------------------------ ChArUco objects
    @cached_property
    def aruco_dictionary(self) -> "cv2.aruco.Dictionary":
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, f"DICT_{self.dictionary.upper()}"))

    @cached_property
    def charuco_board(self) -> "cv2.aruco.CharucoBoard":
        if self.kind != "charuco":
            raise BoardError("not a ChArUco board")
        board = cv2.aruco.CharucoBoard((self.cols, self.rows), float(self.square_m),
                                       float(self.marker_m), self.aruco_dictionary)
        if self.legacy:
            board.setLegacyPattern(True)
        return board

    # ------------------------------------------------------------------ rendering
    def texture(self, px_per_square: int = 64, margin_squares: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """A printable image of the board (uint8, white margin) and the 2x3 affine map from
        board coordinates (m) to its pixels, so that ``A @ (x, y, 1)`` is a texture pixel."""
        sq_c, sq_r = self.squares
        margin = int(round(margin_squares * px_per_square))
        w, h = sq_c * px_per_square, sq_r * px_per_square
        if self.kind == "chessboard":
            yy, xx = np.mgrid[0:h, 0:w] // px_per_square
            # Top-left square black, as OpenCV's printable pattern.
            inner = np.where((xx + yy) % 2 == 0, 0, 255).astype(np.uint8)
            # Board origin (first inner corner) sits one square in from the top-left.
            ox = oy = margin + px_per_square
        else:
            inner = self.charuco_board.generateImage((w, h), marginSize=0)
            # ChArUco board coordinates start at the board's outer top-left corner.
            ox = oy = margin
        img = np.full((h + 2 * margin, w + 2 * margin), 255, np.uint8)
        img[margin:margin + h, margin:margin + w] = inner
        s = px_per_square / self.square_m
        # Texture pixel centres are at integer coordinates; a square edge falls on a pixel
        # boundary, i.e. at (k * px_per_square - 0.5).
        A = np.array([[s, 0.0, ox - 0.5], [0.0, s, oy - 0.5]])
        return img, A
