"""Check new board pairs against a stored calibration (``iscd calibrate --verify``).

Three measures, each sensitive to a different way a rig goes out of calibration:

- epipolar error: RMS vertical offset y_left - y_right (px) of corresponding corners after
  rectification with the stored calibration. A camera tilted or rolled by a knock shows here
  first; ranging needs it well under a pixel (the dissertation assumes Delta y ~ 0, sec. 3.2).
- transfer error: the board pose is found from the left image alone (cv2.solvePnP with M1,
  D1), carried into the right camera with R, T and projected with M2, D2; RMS distance to the
  detected right corners, px. Sensitive to any change of R, T or the intrinsics.
- scale error: corners triangulated with the stored calibration; the median distance between
  neighbouring corners against the board's square size. A baseline or focal-length error
  scales every range by the same factor (Z = f*b/d, eq. 2.2), so it shows here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from iscd.calibration.boards import BoardSpec
from iscd.calibration.detect import PairObservation
from iscd.calibration.io import StereoCalibration, rectify_points


@dataclass
class VerifyThresholds:
    """Limits above which ``--verify`` says RECALIBRATE."""

    max_epipolar_px: float = 0.5
    max_transfer_px: float = 1.0
    max_scale_error: float = 0.01


@dataclass
class PairCheck:
    name: str
    epipolar_rms_px: float
    transfer_rms_px: float
    scale_error: float


@dataclass
class VerifyResult:
    """The measures over all pairs (RMS over every corner; scale: median of the pairs) and
    the verdict ``ok``; ``reasons`` lists the limits that were exceeded."""

    pairs: list[PairCheck]
    epipolar_rms_px: float
    epipolar_max_px: float
    transfer_rms_px: float
    scale_error: float
    thresholds: VerifyThresholds
    ok: bool
    reasons: list[str] = field(default_factory=list)

    @property
    def verdict(self) -> str:
        return "OK" if self.ok else "RECALIBRATE"

    def summary(self) -> str:
        """One line: verdict and the numbers."""
        nums = (f"epipolar RMS {self.epipolar_rms_px:.3f} px (limit {self.thresholds.max_epipolar_px:g}), "
                f"transfer RMS {self.transfer_rms_px:.3f} px (limit {self.thresholds.max_transfer_px:g}), "
                f"scale error {self.scale_error * 100:+.2f} % (limit {self.thresholds.max_scale_error * 100:g} %), "
                f"{len(self.pairs)} pairs")
        if self.ok:
            return f"OK: calibration still fits: {nums}"
        return f"RECALIBRATE: {'; '.join(self.reasons)} ({nums})"


def _neighbour_pairs(obs: PairObservation, board: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) of corners one square apart on the board."""
    P = obs.object_points[:, :2].astype(np.float64)
    d = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2)
    i, j = np.nonzero(np.abs(d - board.square_m) < 1e-3 * board.square_m)
    keep = i < j
    return i[keep], j[keep]


def check_pair(cal: StereoCalibration, obs: PairObservation, board: BoardSpec) -> tuple[PairCheck, np.ndarray]:
    """The three measures for one pair; also returns the epipolar offsets (px) of its corners."""
    rl = rectify_points(cal, obs.left_points, "left")
    rr = rectify_points(cal, obs.right_points, "right")
    dy = rl[:, 1] - rr[:, 1]
    obj = obs.object_points.astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, obs.left_points.astype(np.float64), cal.M1, cal.D1,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if ok:
        Rb = cv2.Rodrigues(rvec)[0]
        rvec_r = cv2.Rodrigues(cal.R @ Rb)[0]
        tvec_r = cal.R @ tvec.reshape(3, 1) + cal.T
        proj, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec_r, tvec_r, cal.M2, cal.D2)
        transfer = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - obs.right_points) ** 2, axis=1))))
    else:
        transfer = float("inf")
    # Triangulate in the rectified frame: X = (x - cx) Z / f, Z = f b / d.
    X = cv2.triangulatePoints(cal.P1, cal.P2, rl.T, rr.T)
    X = (X[:3] / X[3]).T
    i, j = _neighbour_pairs(obs, board)
    if i.size:
        dist = np.linalg.norm(X[i] - X[j], axis=1)
        scale = float(np.median(dist) / board.square_m - 1.0)
    else:
        scale = float("nan")
    rms = float(np.sqrt(np.mean(dy ** 2)))
    return PairCheck(obs.name, rms, transfer, scale), dy


def verify_calibration(cal: StereoCalibration, observations: list[PairObservation],
                       board: BoardSpec, thresholds: VerifyThresholds | None = None) -> VerifyResult:
    """Measure how well ``cal`` explains new pairs and decide OK / RECALIBRATE."""
    th = thresholds or VerifyThresholds()
    c = cal if cal.is_rectified else cal.with_rectification()
    checks, dys, transfers = [], [], []
    for o in observations:
        pc, dy = check_pair(c, o, board)
        checks.append(pc)
        dys.append(dy)
        transfers.append((pc.transfer_rms_px, len(o.object_points)))
    dy_all = np.concatenate(dys) if dys else np.zeros(0)
    epi_rms = float(np.sqrt(np.mean(dy_all ** 2))) if dy_all.size else float("nan")
    epi_max = float(np.max(np.abs(dy_all))) if dy_all.size else float("nan")
    n = np.array([t[1] for t in transfers], float)
    tr = np.array([t[0] for t in transfers], float)
    transfer = float(np.sqrt(np.sum(n * tr ** 2) / n.sum())) if n.size else float("nan")
    scales = np.array([p.scale_error for p in checks], float)
    scale = float(np.nanmedian(scales)) if np.isfinite(scales).any() else float("nan")
    reasons = []
    if not epi_rms <= th.max_epipolar_px:
        reasons.append(f"epipolar error {epi_rms:.2f} px exceeds {th.max_epipolar_px:g} px "
                       "(a camera has tilted or rolled)")
    if not transfer <= th.max_transfer_px:
        reasons.append(f"left-to-right transfer error {transfer:.2f} px exceeds "
                       f"{th.max_transfer_px:g} px (cameras moved against each other)")
    if not abs(scale) <= th.max_scale_error:
        reasons.append(f"reconstructed squares are {scale * 100:+.2f} % off "
                       f"(limit {th.max_scale_error * 100:g} %): ranges would be scaled wrongly")
    return VerifyResult(checks, epi_rms, epi_max, transfer, scale, th, not reasons, reasons)
