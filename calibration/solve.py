"""Stereo calibration from paired board observations (pure numerics, no file I/O).

1. Intrinsics per camera: cv2.calibrateCamera (Zhang's method + Levenberg-Marquardt).
2. Extrinsics R, T: cv2.stereoCalibrate with CALIB_FIX_INTRINSIC, then (by default) a joint
   refinement of all parameters from there (CALIB_USE_INTRINSIC_GUESS): the maximum-likelihood
   estimate, the same optimum a direct cv2.stereoCalibrate reaches on the same corners.
3. Outliers: the pair with the largest per-view RMS reprojection error is dropped while it is
   more than ``outlier_factor`` x the median (and above ``outlier_floor_px``), then 1-2 rerun.
4. Rectification: cv2.stereoRectify (CALIB_ZERO_DISPARITY), and the epipolar error: the
   vertical offset y_left - y_right of every corner pair after rectification, px.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from datetime import datetime, timezone

import cv2
import numpy as np

from iscd.calibration.detect import PairObservation
from iscd.calibration.io import CalibrationError, StereoCalibration, rectify_points

log = logging.getLogger(__name__)

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)

DIST_MODELS = {
    "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2k3": cv2.CALIB_ZERO_TANGENT_DIST,
    "standard": 0,
    "rational": cv2.CALIB_RATIONAL_MODEL,
}
"""Distortion models (``--dist-model``): ``standard`` is OpenCV's k1 k2 p1 p2 k3."""


@dataclass
class PairStatus:
    """What happened to one input pair: ``used`` or ``rejected`` with a reason; the per-view
    RMS reprojection errors (px) of the final model when used."""

    name: str
    used: bool
    reason: str = ""
    err_left_px: float | None = None
    err_right_px: float | None = None
    epipolar_rms_px: float | None = None


@dataclass
class CalibrationResult:
    """A calibration and how well it fits. Errors in px."""

    calibration: StereoCalibration
    pairs: list[PairStatus]
    rms_mono_left: float
    rms_mono_right: float
    rms_stereo: float
    rms_stereo_left: float
    rms_stereo_right: float
    epipolar_rms_px: float
    epipolar_max_px: float
    joint: bool
    rvecs: list[np.ndarray] = field(default_factory=list)
    tvecs: list[np.ndarray] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def used(self) -> list[PairStatus]:
        return [p for p in self.pairs if p.used]

    @property
    def rejected(self) -> list[PairStatus]:
        return [p for p in self.pairs if not p.used]


@dataclass
class _Fit:
    rms_l: float
    rms_r: float
    M1: np.ndarray
    D1: np.ndarray
    M2: np.ndarray
    D2: np.ndarray
    rms: float
    R: np.ndarray
    T: np.ndarray
    E: np.ndarray
    F: np.ndarray
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]
    view_err: np.ndarray  # (n, 2) stereo per-view RMS
    mono_err: np.ndarray  # (n, 2) mono per-view RMS


def _fit(obs: list[PairObservation], size: tuple[int, int], flags: int, joint: bool) -> _Fit:
    obj = [o.object_points.astype(np.float32).reshape(-1, 1, 3) for o in obs]
    il = [o.left_points.astype(np.float32).reshape(-1, 1, 2) for o in obs]
    ir = [o.right_points.astype(np.float32).reshape(-1, 1, 2) for o in obs]
    try:
        rl, M1, D1, _, _, _, _, el = cv2.calibrateCameraExtended(
            obj, il, size, None, None, flags=flags, criteria=_CRITERIA)
        rr, M2, D2, _, _, _, _, er = cv2.calibrateCameraExtended(
            obj, ir, size, None, None, flags=flags, criteria=_CRITERIA)
        R0, T0 = np.eye(3), np.zeros((3, 1))
        out = cv2.stereoCalibrateExtended(
            obj, il, ir, M1, D1, M2, D2, size, R0, T0, flags=cv2.CALIB_FIX_INTRINSIC,
            criteria=_CRITERIA)
        if joint:
            out = cv2.stereoCalibrateExtended(
                obj, il, ir, out[1], out[2], out[3], out[4], size, out[5], out[6],
                flags=cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_USE_EXTRINSIC_GUESS | flags,
                criteria=_CRITERIA)
    except cv2.error as e:
        msg = " ".join(str(e).split())
        raise CalibrationError(f"OpenCV calibration failed: {msg[-160:]}") from None
    rms, M1, D1, M2, D2, R, T, E, F, rvecs, tvecs, view_err = out
    return _Fit(float(rl), float(rr), M1, D1, M2, D2, float(rms), R, T, E, F,
                [np.asarray(v).reshape(3) for v in rvecs], [np.asarray(v).reshape(3) for v in tvecs],
                np.asarray(view_err, np.float64).reshape(-1, 2),
                np.column_stack([np.ravel(el), np.ravel(er)]))


def _split_rms(obs: list[PairObservation], view_err: np.ndarray) -> tuple[float, float]:
    n = np.array([len(o.object_points) for o in obs], np.float64)
    return (float(np.sqrt(np.sum(n * view_err[:, 0] ** 2) / n.sum())),
            float(np.sqrt(np.sum(n * view_err[:, 1] ** 2) / n.sum())))


def epipolar_errors(cal: StereoCalibration, obs: list[PairObservation]) -> list[np.ndarray]:
    """Per pair: the vertical offsets y_left - y_right (px) of corresponding corners after
    rectification with ``cal``; 0 for a perfect calibration."""
    c = cal if cal.is_rectified else cal.with_rectification()
    out = []
    for o in obs:
        yl = rectify_points(c, o.left_points, "left")[:, 1]
        yr = rectify_points(c, o.right_points, "right")[:, 1]
        out.append(yl - yr)
    return out


def calibrate_stereo(observations: list[PairObservation], image_size: tuple[int, int], *,
                     rejected: list[PairStatus] | None = None, min_pairs: int = 6,
                     outlier_factor: float = 3.0, outlier_floor_px: float = 0.2,
                     dist_model: str = "standard", joint: bool = True, alpha: float = -1.0,
                     board_label: str | None = None) -> CalibrationResult:
    """Calibrate a stereo rig from board corners seen in both cameras.

    observations: the usable pairs (see :func:`iscd.calibration.detect.pair_detections`).
    image_size: (width, height) px. rejected: pairs already dropped (e.g. board not found),
    carried into the result. min_pairs: fewer usable pairs is an error. outlier_factor,
    outlier_floor_px: a pair is dropped while its per-view RMS error (either camera, mono or
    stereo) exceeds both ``outlier_factor`` x the median and ``outlier_floor_px``.
    dist_model: a key of :data:`DIST_MODELS`. joint: refine intrinsics and extrinsics
    together after the fixed-intrinsics stereo step. alpha: see
    :meth:`StereoCalibration.with_rectification`.
    Raises :class:`CalibrationError` with a one-line reason.
    """
    if dist_model not in DIST_MODELS:
        raise CalibrationError(f"unknown distortion model {dist_model!r} "
                               f"(choose from {', '.join(DIST_MODELS)})")
    flags = DIST_MODELS[dist_model]
    statuses = list(rejected or [])
    obs = list(observations)
    min_pairs = max(int(min_pairs), 3)
    if len(obs) < min_pairs:
        reasons = _reason_summary(statuses)
        raise CalibrationError(
            f"only {len(obs)} usable pair{'s' if len(obs) != 1 else ''} (need at least "
            f"{min_pairs}){': ' + reasons if reasons else ''}")
    warnings: list[str] = []
    while True:
        fit = _fit(obs, image_size, flags, joint)
        errs = np.column_stack([fit.view_err, fit.mono_err])  # (n, 4)
        worst_per_view = errs.max(axis=1)
        med = float(np.median(worst_per_view))
        i = int(np.argmax(worst_per_view))
        worst = float(worst_per_view[i])
        if worst > outlier_factor * med and worst > outlier_floor_px:
            if len(obs) - 1 < min_pairs:
                warnings.append(f"pair {obs[i].name} has a reprojection error of {worst:.2f} px "
                                f"({worst / med:.1f}x the median {med:.2f} px) but was kept: "
                                f"dropping it would leave fewer than {min_pairs} pairs")
                break
            cam = ["left", "right", "left", "right"][int(np.argmax(errs[i]))]
            reason = (f"reprojection error {worst:.2f} px in the {cam} image is "
                      f"{worst / med:.1f}x the median {med:.2f} px")
            log.info("rejecting pair %s: %s", obs[i].name, reason)
            statuses.append(PairStatus(obs[i].name, False, reason))
            del obs[i]
            continue
        break
    size = image_size
    cal = StereoCalibration(size[0], size[1], fit.M1, fit.D1, fit.M2, fit.D2, fit.R, fit.T,
                            E=fit.E, F=fit.F).with_rectification(alpha=alpha)
    epi = epipolar_errors(cal, obs)
    all_dy = np.concatenate(epi)
    epi_rms = float(np.sqrt(np.mean(all_dy ** 2)))
    epi_max = float(np.max(np.abs(all_dy)))
    rl, rr = _split_rms(obs, fit.view_err)
    cal.rms_left, cal.rms_right, cal.rms_stereo = fit.rms_l, fit.rms_r, fit.rms
    cal.epipolar_rms_px = epi_rms
    cal.n_pairs = len(obs)
    cal.board = board_label
    cal.created = datetime.now(timezone.utc).isoformat(timespec="seconds")
    used = [PairStatus(o.name, True, "", float(fit.view_err[k, 0]), float(fit.view_err[k, 1]),
                       float(np.sqrt(np.mean(epi[k] ** 2)))) for k, o in enumerate(obs)]
    all_status = sorted(used + statuses, key=lambda p: p.name)
    return CalibrationResult(cal, all_status, fit.rms_l, fit.rms_r, fit.rms, rl, rr, epi_rms,
                             epi_max, joint, fit.rvecs, fit.tvecs, warnings)


def _reason_summary(statuses: list[PairStatus]) -> str:
    """``"board not found in right image: 3 pairs; ..."`` for an error message."""
    counts: dict[str, int] = {}
    for s in statuses:
        if not s.used:
            counts[s.reason] = counts.get(s.reason, 0) + 1
    return "; ".join(f"{r} ({n} pair{'s' if n > 1 else ''})" for r, n in
                     sorted(counts.items(), key=lambda kv: -kv[1]))
