"""Synthetic calibration images: a known board seen by a known stereo rig.

Rendering is inverse mapping: every (super-sampled) pixel's ray is undistorted once per camera
(cv2.undistortPoints), intersected with the board plane (a homography per pose), looked up
in a high-resolution board texture with cv2.remap, averaged down to the sensor grid
(anti-aliasing), blurred by the lens PSF, and given sensor noise. Ground-truth corners come
from cv2.projectPoints of the same model, so calibration results can be checked against the
rig that produced the images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from iscd.calibration.boards import BoardSpec
from iscd.calibration.io import StereoCalibration, Which

if TYPE_CHECKING:  # pragma: no cover
    from iscd.core.config import CameraConfig


def default_rig() -> StereoCalibration:
    """A 512x512 calibration-target rig: fx ~ 600 px (a wide lens), barrel distortion
    (k1 ~ -0.2, k2 ~ 0.05), principal points off centre, cameras 0.25 m apart and rotated
    by about 0.5 degrees against each other."""
    M1 = np.array([[600.0, 0.0, 259.3], [0.0, 601.2, 250.8], [0.0, 0.0, 1.0]])
    M2 = np.array([[604.5, 0.0, 252.1], [0.0, 605.0, 258.6], [0.0, 0.0, 1.0]])
    D1 = np.array([-0.21, 0.055, 4e-4, -3e-4, 0.0])
    D2 = np.array([-0.19, 0.045, -2e-4, 5e-4, 0.0])
    R = cv2.Rodrigues(np.radians([0.20, 0.42, -0.15]).reshape(3, 1))[0]
    T = -R @ np.array([[0.25], [0.0], [0.0]])  # right camera 0.25 m along the left's x axis
    return StereoCalibration(512, 512, M1, D1, M2, D2, R, T).with_rectification()


def nonideal_rig(camera_cfg: "CameraConfig", k1: float = -0.05, k2: float = 0.02,
                 rotation_deg: tuple[float, float, float] = (0.1, 0.3, 0.05),
                 principal_offset_px: tuple[float, float] = (3.0, -2.0),
                 focal_ratio_right: float = 1.003) -> StereoCalibration:
    """A realistic, imperfect version of the config's rig, for simulating ranging before and
    after calibration: the nominal focal length and baseline, but lens distortion (k1, k2),
    principal points off centre (left +offset, right -offset, px), the right focal length
    ``focal_ratio_right`` times the left's, and the right camera rotated by ``rotation_deg``
    (Rodrigues components about x, y, z, degrees). Render with
    :func:`iscd.calibration.io.project_points`; the returned calibration is the truth."""
    w, h, f = camera_cfg.width, camera_cfg.height, camera_cfg.focal_px
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    dx, dy = principal_offset_px
    M1 = np.array([[f, 0.0, cx + dx], [0.0, f, cy + dy], [0.0, 0.0, 1.0]])
    f2 = f * focal_ratio_right
    M2 = np.array([[f2, 0.0, cx - dx], [0.0, f2, cy - dy], [0.0, 0.0, 1.0]])
    D = np.array([k1, k2, 0.0, 0.0, 0.0])
    R = cv2.Rodrigues(np.radians(np.asarray(rotation_deg, np.float64)).reshape(3, 1))[0]
    T = -R @ np.array([[camera_cfg.baseline_m], [0.0], [0.0]])
    return StereoCalibration(w, h, M1, D, M2, D.copy(), R, T).with_rectification()


def default_board() -> BoardSpec:
    """A 9x6 inner-corner chessboard with 80 mm squares (0.8 m x 0.56 m: a poster, so that
    at 1.5-3.5 m it covers the field that both cameras of a 0.25 m rig share)."""
    return BoardSpec("chessboard", 9, 6, 0.08)


@dataclass
class SyntheticPairs:
    """Rendered stereo pairs and the truth behind them.

    left, right: uint8 images. rvecs, tvecs: board pose in the left camera (board -> camera,
    Rodrigues vector in rad and translation in m). truth: the rig. corners_left/right: true
    image positions (n, 2) px of the board's corners in each pair.
    """

    left: list[np.ndarray]
    right: list[np.ndarray]
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]
    truth: StereoCalibration
    board: BoardSpec
    corners_left: list[np.ndarray] = field(default_factory=list)
    corners_right: list[np.ndarray] = field(default_factory=list)

    def write(self, folder: str | Path, ext: str = "png") -> tuple[str, str]:
        """Save as ``left_NN.ext``/``right_NN.ext`` in ``folder``; returns the two globs."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        for i, (a, b) in enumerate(zip(self.left, self.right)):
            cv2.imwrite(str(folder / f"left_{i:02d}.{ext}"), a)
            cv2.imwrite(str(folder / f"right_{i:02d}.{ext}"), b)
        return str(folder / f"left_*.{ext}"), str(folder / f"right_*.{ext}")


class BoardRenderer:
    """Renders a board at a given pose as seen by one camera of a rig (see module docstring).

    supersample: sub-samples per pixel along each axis. px_per_square: texture resolution.
    """

    def __init__(self, cal: StereoCalibration, board: BoardSpec, supersample: int = 3,
                 px_per_square: int = 64) -> None:
        self.cal = cal
        self.board = board
        self.ss = int(supersample)
        self.texture, self.tex_affine = board.texture(px_per_square)
        self._rays: dict[str, np.ndarray] = {}

    def _camera_rays(self, which: Which) -> np.ndarray:
        """(H*ss, W*ss, 2) undistorted normalized coordinates (x/z, y/z) of sub-pixel centres."""
        if which not in self._rays:
            w, h, s = self.cal.image_width, self.cal.image_height, self.ss
            off = (np.arange(s) + 0.5) / s - 0.5
            xs = (np.arange(w)[:, None] + off[None, :]).reshape(-1)
            ys = (np.arange(h)[:, None] + off[None, :]).reshape(-1)
            gx, gy = np.meshgrid(xs, ys)
            pts = np.stack([gx, gy], axis=-1).reshape(-1, 1, 2)
            M, D = (self.cal.M1, self.cal.D1) if which == "left" else (self.cal.M2, self.cal.D2)
            und = cv2.undistortPoints(pts, M, D, criteria=(
                cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-9))
            self._rays[which] = und.reshape(h * s, w * s, 2).astype(np.float64)
        return self._rays[which]

    def pose_in(self, rvec: np.ndarray, tvec: np.ndarray, which: Which) -> tuple[np.ndarray, np.ndarray]:
        """Board pose (rotation matrix, translation m) in the ``which`` camera's frame, from
        the pose (rvec, tvec) in the left camera."""
        Rb = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
        t = np.asarray(tvec, np.float64).reshape(3, 1)
        if which == "right":
            return self.cal.R @ Rb, self.cal.R @ t + self.cal.T
        return Rb, t

    def true_corners(self, rvec: np.ndarray, tvec: np.ndarray, which: Which,
                     object_points: np.ndarray | None = None) -> np.ndarray:
        """Ideal image positions (n, 2) px of board points (default: all corners)."""
        Rb, t = self.pose_in(rvec, tvec, which)
        obj = self.board.object_points if object_points is None else object_points
        M, D = (self.cal.M1, self.cal.D1) if which == "left" else (self.cal.M2, self.cal.D2)
        img, _ = cv2.projectPoints(np.asarray(obj, np.float64).reshape(-1, 1, 3),
                                   cv2.Rodrigues(Rb)[0], t, M, D)
        return img.reshape(-1, 2)

    def render(self, rvec: np.ndarray, tvec: np.ndarray, which: Which,
               rng: np.random.Generator | None = None, noise_dn: float = 1.5,
               blur_px: float = 0.5, black_dn: float = 30.0, white_dn: float = 220.0,
               background_dn: float = 110.0) -> np.ndarray:
        """The uint8 image of the board at pose (rvec, tvec) (board -> left camera).

        noise_dn: RMS Gaussian noise in grey levels. blur_px: Gaussian PSF sigma, px.
        """
        Rb, t = self.pose_in(rvec, tvec, which)
        rays = self._camera_rays(which)
        # Homography normalized image coords -> board (x, y) in m: inverse of [r1 r2 t].
        H = np.linalg.inv(np.column_stack([Rb[:, 0], Rb[:, 1], t.ravel()]))
        x, y = rays[..., 0], rays[..., 1]
        den = H[2, 0] * x + H[2, 1] * y + H[2, 2]
        bx = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / den
        by = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / den
        A = self.tex_affine
        mx = (A[0, 0] * bx + A[0, 1] * by + A[0, 2]).astype(np.float32)
        my = (A[1, 0] * bx + A[1, 1] * by + A[1, 2]).astype(np.float32)
        behind = den <= 0  # the ray meets the plane behind the camera
        mx[behind] = -1e6
        tex = self.texture.astype(np.float32)
        scale = (white_dn - black_dn) / 255.0
        big = cv2.remap(tex * scale + black_dn, mx, my, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=float(background_dn))
        w, h = self.cal.image_width, self.cal.image_height
        img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
        if blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_px)
        if noise_dn > 0:
            rng = rng or np.random.default_rng(0)
            img = img + rng.normal(0.0, noise_dn, img.shape).astype(np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _outline(board: BoardSpec) -> np.ndarray:
    """Board points that must be in view: the printed squares' outer corners plus a margin."""
    sc, sr = board.squares
    sq = board.square_m
    if board.kind == "chessboard":
        x0, y0 = -sq, -sq
    else:
        x0, y0 = 0.0, 0.0
    m = 0.5 * sq
    xs = np.linspace(x0 - m, x0 + sc * sq + m, 9)
    ys = np.linspace(y0 - m, y0 + sr * sq + m, 9)
    pts = [(x, y0 - m) for x in xs] + [(x, y0 + sr * sq + m) for x in xs]
    pts += [(x0 - m, y) for y in ys] + [(x0 + sc * sq + m, y) for y in ys]
    return np.array([(x, y, 0.0) for x, y in pts])


def _valid_pose(renderer: BoardRenderer, rng: np.random.Generator, outline: np.ndarray,
                centre: np.ndarray, z_range_m: tuple[float, float], max_tilt_deg: float,
                max_roll_deg: float, margin_px: float) -> tuple[np.ndarray, np.ndarray] | None:
    cal = renderer.cal
    w, h = cal.image_width, cal.image_height
    z = rng.uniform(*z_range_m)
    # Aim the board centre at a random pixel of the left image, shifted toward the right
    # camera by up to a baseline so that both views get their edges covered.
    ray = np.linalg.inv(cal.M1) @ np.array([rng.uniform(0, w), rng.uniform(0, h), 1.0])
    p = ray * z
    p[0] += cal.baseline_m * rng.uniform(0.0, 1.0)
    ax, ay = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
    az = math.radians(rng.uniform(-max_roll_deg, max_roll_deg))
    Rb = (cv2.Rodrigues(np.array([ax, 0.0, 0.0]))[0] @ cv2.Rodrigues(np.array([0.0, ay, 0.0]))[0]
          @ cv2.Rodrigues(np.array([0.0, 0.0, az]))[0])
    t = (p - Rb @ centre).reshape(3, 1)
    rvec = cv2.Rodrigues(Rb)[0].ravel()
    for which in ("left", "right"):
        Rc, tc = renderer.pose_in(rvec, t, which)
        if np.any((Rc @ outline.T + tc)[2] <= 0.1):
            return None
        pts = renderer.true_corners(rvec, t, which, outline)
        if (pts.min() < margin_px or pts[:, 0].max() > w - 1 - margin_px
                or pts[:, 1].max() > h - 1 - margin_px):
            return None
    return rvec, t.ravel()


def random_poses(renderer: BoardRenderer, n: int, rng: np.random.Generator,
                 z_range_m: tuple[float, float] = (1.4, 3.4), max_tilt_deg: float = 40.0,
                 max_roll_deg: float = 15.0, margin_px: float = 3.0, pool_factor: int = 12,
                 cells: int = 8, max_tries: int = 200000) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` board poses (rvec rad, tvec m; board -> left camera) with the whole board in
    view of both cameras, tilted up to ``max_tilt_deg``.

    A pool of ``pool_factor * n`` random valid poses is drawn, then poses are picked greedily
    to cover a ``cells`` x ``cells`` grid of both images (as a careful operator would), so
    that the image edges, where distortion is largest, are seen."""
    cal, board = renderer.cal, renderer.board
    w, h = cal.image_width, cal.image_height
    outline = _outline(board)
    obj = board.object_points.astype(np.float64)
    centre = 0.5 * (obj.min(axis=0) + obj.max(axis=0))
    pool: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(max_tries):
        if len(pool) >= pool_factor * n:
            break
        pose = _valid_pose(renderer, rng, outline, centre, z_range_m, max_tilt_deg,
                           max_roll_deg, margin_px)
        if pose is not None:
            pool.append(pose)
    if len(pool) < n:
        raise RuntimeError(f"found only {len(pool)} of {n} board poses visible in both cameras")
    masks = []
    for rvec, t in pool:
        m = np.zeros((2, cells, cells), bool)
        for k, which in enumerate(("left", "right")):
            pts = renderer.true_corners(rvec, t, which)
            cx = np.clip((pts[:, 0] / w * cells).astype(int), 0, cells - 1)
            cy = np.clip((pts[:, 1] / h * cells).astype(int), 0, cells - 1)
            m[k, cy, cx] = True
        masks.append(m.ravel())
    M = np.array(masks)
    counts = np.zeros(M.shape[1])
    chosen: list[int] = []
    for _ in range(n):
        gain = (M / (1.0 + counts)).sum(axis=1) + rng.uniform(0, 1e-3, len(M))
        gain[chosen] = -np.inf
        k = int(np.argmax(gain))
        chosen.append(k)
        counts += M[k]
    return [pool[k] for k in chosen]


def make_pairs(n: int = 16, cal: StereoCalibration | None = None, board: BoardSpec | None = None,
               seed: int = 0, noise_dn: float = 1.5, blur_px: float = 0.8, supersample: int = 3,
               **pose_kw: float) -> SyntheticPairs:
    """Render ``n`` stereo pairs of ``board`` (default 9x6, 40 mm) seen by ``cal`` (default
    :func:`default_rig`) at random poses (seeded)."""
    cal = cal or default_rig()
    board = board or default_board()
    rng = np.random.default_rng(seed)
    r = BoardRenderer(cal, board, supersample=supersample)
    poses = random_poses(r, n, rng, **pose_kw)  # type: ignore[arg-type]
    out = SyntheticPairs([], [], [], [], cal, board)
    for rvec, tvec in poses:
        out.left.append(r.render(rvec, tvec, "left", rng, noise_dn, blur_px))
        out.right.append(r.render(rvec, tvec, "right", rng, noise_dn, blur_px))
        out.rvecs.append(rvec)
        out.tvecs.append(tvec)
        out.corners_left.append(r.true_corners(rvec, tvec, "left"))
        out.corners_right.append(r.true_corners(rvec, tvec, "right"))
    return out
