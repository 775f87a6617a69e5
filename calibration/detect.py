"""Board corner detection with sub-pixel refinement, and stereo pairing of detections.

Chessboard: the classic ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix`` (window scaled to
the square size) first, ``cv2.findChessboardCornersSB`` as a fallback. On synthetic boards
the classic path was 3x more accurate (0.06 px vs 0.17 px RMS corner error) and on the OpenCV
stereo sample it gave a lower reprojection RMS (0.195 vs 0.266 px). ChArUco:
``cv2.aruco.CharucoDetector`` (markers identify each corner, so partial views are fine).
All positions are in px with OpenCV's convention (pixel centres at integer coordinates).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from iscd.calibration.boards import BoardSpec

SUBPIX_PRESMOOTH_PX = 1.0
"""Gaussian sigma (px) of the smoothing applied before cv2.cornerSubPix."""

MIN_CHARUCO_CORNERS = 8
"""A ChArUco view (or a stereo pair's common corners) needs at least this many corners."""


@dataclass(frozen=True)
class Detection:
    """The board corners found in one image.

    image_points: (n, 2) float32 px. object_points: (n, 3) float32 m on the board.
    ids: (n,) corner ids (index into :attr:`BoardSpec.object_points`). method: which detector.
    """

    image_points: np.ndarray
    object_points: np.ndarray
    ids: np.ndarray
    method: str

    @property
    def n(self) -> int:
        return int(self.ids.size)


@dataclass(frozen=True)
class Miss:
    """Why a board was not detected in an image (``reason`` is a short phrase)."""

    reason: str


@dataclass(frozen=True)
class PairObservation:
    """Corners seen in both images of a stereo pair (same ids, same order)."""

    name: str
    object_points: np.ndarray  # (n, 3) float32, m
    left_points: np.ndarray  # (n, 2) float32, px
    right_points: np.ndarray  # (n, 2) float32, px
    ids: np.ndarray | None = None  # (n,) corner ids on the board


def to_gray8(image: np.ndarray) -> np.ndarray:
    """Any grey/BGR(A) image of any integer or float depth -> uint8 grey (contrast kept)."""
    img = np.asarray(image)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        else:
            code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            img = cv2.cvtColor(img, code)
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    f = img.astype(np.float32)
    lo, hi = float(f.min()), float(f.max())
    if hi <= lo:
        return np.zeros(f.shape, np.uint8)
    return np.clip((f - lo) * (255.0 / (hi - lo)) + 0.5, 0, 255).astype(np.uint8)


def read_image(path: str | Path) -> np.ndarray | None:
    """An image file as uint8 grey, or None when it cannot be read/decoded."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError:
        return None
    if data.size == 0:
        return None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        return None
    return to_gray8(img)


def _subpix_window(corners: np.ndarray, grid: tuple[int, int]) -> int:
    """Half-size of the cornerSubPix window, px: 0.35 x the smallest corner spacing, clamped
    to 2..11 (a window reaching the neighbouring corners biases the result; measured on the
    OpenCV stereo sample and on synthetic boards, 0.35 gave the lowest errors)."""
    c, r = grid
    pts = corners.reshape(r, c, 2)
    d = []
    if c > 1:
        d.append(np.linalg.norm(np.diff(pts, axis=1), axis=2).min())
    if r > 1:
        d.append(np.linalg.norm(np.diff(pts, axis=0), axis=2).min())
    spacing = float(min(d)) if d else 10.0
    return int(np.clip(np.floor(spacing * 0.35), 2, 11))


def _canonical_chessboard(pts: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """Remove the 180-degree ambiguity of a chessboard's corner order: the first row runs
    from left to right in the image (or top to bottom when it is vertical)."""
    c, r = grid
    g = pts.reshape(r, c, 2)
    v = g[:, -1].mean(axis=0) - g[:, 0].mean(axis=0)  # along rows
    flip = v[0] < 0 if abs(v[0]) >= abs(v[1]) else v[1] < 0
    return pts[::-1].copy() if flip else pts


def _saddle_scores(gray: np.ndarray, centres: np.ndarray, ex: np.ndarray,
                   ey: np.ndarray) -> np.ndarray:
    """Chessboard-corner score at image points ``centres`` (k, 2) px whose local board axes
    (one square along a row / a column) are ``ex``, ``ey`` (k, 2) px: the grey-level contrast
    of a saddle (diagonal quadrants equal, neighbouring quadrants different). About
    (white - black) at a real corner, <= 0 on a plain area or a straight edge, NaN outside
    the image."""
    quad = np.array([(-1, -1), (1, -1), (1, 1), (-1, 1)], np.float64) * 0.25  # TL TR BR BL
    sub = np.array([(a, b) for a in (-0.08, 0.0, 0.08) for b in (-0.08, 0.0, 0.08)])
    off = (quad[:, None, :] + sub[None, :, :]).reshape(-1, 2)  # (36, 2) in squares
    pts = (centres[:, None, :] + off[None, :, 0:1] * ex[:, None, :]
           + off[None, :, 1:2] * ey[:, None, :])
    mx = pts[..., 0].astype(np.float32).reshape(1, -1)
    my = pts[..., 1].astype(np.float32).reshape(1, -1)
    vals = cv2.remap(gray.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
    q = vals.reshape(len(centres), 4, -1).mean(axis=2)
    tl, tr, br, bl = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    near = np.minimum.reduce([abs(tl - tr), abs(tl - bl), abs(br - tr), abs(br - bl)])
    diag = np.maximum(abs(tl - br), abs(tr - bl))
    return near - diag


def _grid_axes(g: np.ndarray, axis: int) -> np.ndarray:
    """Local step (px per square) along ``axis`` of a (rows, cols, 2) corner grid."""
    return np.gradient(g, axis=axis) if g.shape[axis] > 1 else np.zeros_like(g)


def check_grid(gray: np.ndarray, pts: np.ndarray, grid: tuple[int, int]) -> str | None:
    """Sanity check of a detected chessboard grid; None if fine, else the reason.

    Every detected corner must look like a chessboard corner (saddle score above a fifth of
    the median), and the board must not continue beyond the grid: a wrong ``--board`` size
    makes the detectors lock onto part of a larger board. Each side is tested at one more
    row/column, extrapolated quadratically from the nearest three."""
    c, r = grid
    g = pts.reshape(r, c, 2).astype(np.float64)
    ex, ey = _grid_axes(g, 1), _grid_axes(g, 0)
    inner = _saddle_scores(gray, g.reshape(-1, 2), ex.reshape(-1, 2), ey.reshape(-1, 2))
    ref = float(np.nanmedian(inner)) if np.isfinite(inner).any() else float("nan")
    if not ref > 0:
        return "corner grid is not a chessboard"
    bad = int(np.sum(inner[np.isfinite(inner)] < 0.2 * ref))
    if bad:
        return f"{bad} detected corners are not chessboard corners"

    def extrapolate(a: np.ndarray) -> np.ndarray:  # a: (3, k, 2), nearest first
        return 3 * a[0] - 3 * a[1] + a[2] if len(a) >= 3 else 2 * a[0] - a[1]

    sides: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
    if c >= 2:
        sides.append(("column", extrapolate(g[:, :3].transpose(1, 0, 2)), ex[:, 0], ey[:, 0]))
        sides.append(("column", extrapolate(g[:, ::-1][:, :3].transpose(1, 0, 2)), ex[:, -1], ey[:, -1]))
    if r >= 2:
        sides.append(("row", extrapolate(g[:3]), ex[0], ey[0]))
        sides.append(("row", extrapolate(g[::-1][:3]), ex[-1], ey[-1]))
    for kind, centres, sx, sy in sides:
        sc = _saddle_scores(gray, centres, sx, sy)
        sc = sc[np.isfinite(sc)]
        if sc.size >= max(2, len(centres) // 2) and float(np.median(sc)) > 0.5 * ref:
            return (f"board has more corners than {c}x{r} (a further {kind} of corners "
                    "found; check --board)")
    return None


def detect_chessboard(gray: np.ndarray, board: BoardSpec, fast: bool = False) -> Detection | Miss:
    """Find all inner corners of a chessboard; a :class:`Miss` if not all of them are found
    or if the board visibly continues beyond them (wrong board size).

    fast: classic detector with CALIB_CB_FAST_CHECK and no sub-pixel refinement (live preview).
    """
    grid = board.corner_grid
    corners = None
    method = ""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    if fast:
        flags |= cv2.CALIB_CB_FAST_CHECK
    ok, c = cv2.findChessboardCorners(gray, grid, flags=flags)
    if ok and fast:
        corners, method = c, "classic-fast"
    elif ok:
        w = _subpix_window(c.reshape(-1, 2), grid)
        # Refining on a slightly smoothed copy reduces cornerSubPix's pixel-locking bias on
        # sharp edges: synthetic corners 0.060 -> 0.040 px RMS, OpenCV sample RMS 0.195 -> 0.190.
        smooth = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), SUBPIX_PRESMOOTH_PX)
        corners = cv2.cornerSubPix(smooth, c, (w, w), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3))
        method = "classic+subpix"
    elif not fast:
        ok, c = cv2.findChessboardCornersSB(
            gray, grid, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY)
        if ok:
            corners, method = c, "sb"
    if corners is None:
        return Miss("board not found")
    pts = np.asarray(corners, np.float32).reshape(-1, 2)
    problem = check_grid(gray, pts, grid)
    if problem is not None:
        return Miss(problem)
    pts = _canonical_chessboard(pts, grid)
    ids = np.arange(board.n_corners)
    return Detection(pts, board.object_points, ids, method)


def detect_charuco(gray: np.ndarray, board: BoardSpec) -> Detection | Miss:
    """Find the ChArUco corners (sub-pixel, interpolated from the markers); a :class:`Miss`
    if fewer than :data:`MIN_CHARUCO_CORNERS` or all collinear."""
    detector = cv2.aruco.CharucoDetector(board.charuco_board)
    corners, ids, _, marker_ids = detector.detectBoard(gray)
    if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        n_markers = 0 if marker_ids is None else len(marker_ids)
        n = 0 if ids is None else len(ids)
        return Miss(f"board not found ({n_markers} markers, {n} corners)" if n_markers
                    else "board not found")
    ids = np.asarray(ids, np.int64).reshape(-1)
    if board.charuco_board.checkCharucoCornersCollinear(ids.astype(np.int32).reshape(-1, 1)):
        return Miss("board corners all on one line")
    pts = np.asarray(corners, np.float32).reshape(-1, 2)
    order = np.argsort(ids)
    ids, pts = ids[order], pts[order]
    # The detector's own cornerSubPix keeps its window clear of the markers; a wider
    # window (as used for plain chessboards) was measured to be less accurate here.
    return Detection(pts, board.object_points[ids], ids, "charuco")


def detect(image: np.ndarray, board: BoardSpec, fast: bool = False) -> Detection | Miss:
    """Detect ``board`` in ``image`` (any depth; converted to 8-bit grey)."""
    gray = to_gray8(image)
    if board.kind == "charuco":
        return detect_charuco(gray, board)
    return detect_chessboard(gray, board, fast=fast)


def _orientation(pts: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    c, r = grid
    g = pts.reshape(r, c, 2)
    return np.concatenate([g[:, -1].mean(0) - g[:, 0].mean(0), g[-1].mean(0) - g[0].mean(0)])


def pair_detections(name: str, left: Detection, right: Detection,
                    board: BoardSpec) -> PairObservation | None:
    """Combine the two views of one pair: common corner ids (ChArUco) or a consistent corner
    order (chessboard: the right order is reversed if it runs against the left's). None when
    fewer than :data:`MIN_CHARUCO_CORNERS` corners are common."""
    if board.kind == "chessboard":
        lp, rp = left.image_points, right.image_points
        grid = board.corner_grid
        ol, orr = _orientation(lp, grid), _orientation(rp, grid)
        if float(ol @ orr) < float(ol @ _orientation(rp[::-1], grid)):
            rp = rp[::-1].copy()
        return PairObservation(name, board.object_points, lp, rp, np.arange(board.n_corners))
    common, il, ir = np.intersect1d(left.ids, right.ids, return_indices=True)
    if common.size < MIN_CHARUCO_CORNERS:
        return None
    if board.charuco_board.checkCharucoCornersCollinear(common.astype(np.int32).reshape(-1, 1)):
        return None
    return PairObservation(name, board.object_points[common], left.image_points[il],
                           right.image_points[ir], common)
