"""Per-frame stereo ranging of a tracked transmitter: patches -> disparity -> range.

For each stereo frame the transmitter's patch is cut from the left and right images at
whole-pixel positions (rectified: only the patch's pixels are remapped, never the whole
frame), the sub-pixel shift between them is estimated (:mod:`iscd.ranging.estimators`,
default the project's ``"iscd"`` method), and

    d = (x0_left - x0_right) + shift          [px]
    Z = f * b / d                            (2.2, f in px = f/rho)
    sigma_Z = Z^2 / (f * b) * sigma_d         [m]

The whole array is one estimate per frame (all its LEDs in one patch); ``per_led`` adds one
estimate per LED.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration.io import StereoCalibration, rectify_points
from iscd.ranging.estimators import get_estimator
from iscd.receiver.detect import GridFit


@dataclass(frozen=True)
class RangingSettings:
    """``[ranging]`` section: method (see iscd.ranging.estimators.METHODS), margin_px
    around the array's spots in the patch, per_led estimates, max_patch_px side cap."""

    method: str = field(default="iscd", metadata={"doc": "shift estimator"})
    margin_px: int = field(default=5, metadata={"lo": 1, "hi": 64, "doc": "patch margin, px"})
    per_led: bool = field(default=False, metadata={"doc": "also one estimate per LED"})
    max_patch_px: int = field(default=96, metadata={"lo": 8, "hi": 512, "doc": "largest patch side, px"})
    kalman: bool = field(default=False, metadata={"doc": "also emit Kalman-filtered ranges"})


@dataclass
class RangeResult:
    """Per-frame results for one block, all (n,) arrays; NaN where not measurable."""

    z_m: np.ndarray
    disparity_px: np.ndarray
    sigma_m: np.ndarray
    quality: np.ndarray


def _is_identity(cal: StereoCalibration) -> bool:
    if cal.R1 is None or cal.P1 is None or cal.R2 is None or cal.P2 is None:
        return not np.any(cal.D1) and not np.any(cal.D2) and np.allclose(cal.R, np.eye(3))
    return (not np.any(cal.D1) and not np.any(cal.D2) and np.allclose(cal.R1, np.eye(3))
            and np.allclose(cal.R2, np.eye(3)) and np.allclose(cal.P1[:3, :3], cal.M1)
            and np.allclose(cal.P2[:3, :3], cal.M2))


class StereoRanger:
    """Ranges a tracked transmitter frame by frame (see module docstring)."""

    def __init__(self, cal: StereoCalibration, settings: RangingSettings | None = None) -> None:
        self.cal = cal if cal.is_rectified else cal.with_rectification()
        self.settings = settings or RangingSettings()
        self.estimator = get_estimator(self.settings.method)
        self.f_px = float(self.cal.focal_px)
        self.b_m = float(self.cal.baseline_m)
        self.identity = _is_identity(self.cal)
        self._maps: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        if not self.identity:
            for which in ("left", "right"):
                self._maps[which] = self.cal.rectification_maps(which)  # type: ignore[arg-type]

    def _rect_center(self, fit: GridFit, which: str) -> np.ndarray:
        c = np.asarray(fit.center, dtype=np.float64)[None, :]
        if self.identity:
            return c[0]
        return rectify_points(self.cal, c, which)[0]  # type: ignore[arg-type]

    def _cut(self, frames: np.ndarray, which: str, x0: int, y0: int, w: int, h: int) -> np.ndarray:
        """(n, h, w) float32 patches of rectified ``frames`` with top-left (x0, y0)."""
        n, H, W = frames.shape
        if self.identity:
            xa, ya = max(0, x0), max(0, y0)
            xb, yb = min(W, x0 + w), min(H, y0 + h)
            out = np.zeros((n, h, w), np.float32)
            if xb > xa and yb > ya:
                out[:, ya - y0:yb - y0, xa - x0:xb - x0] = frames[:, ya:yb, xa:xb]
            return out
        mx, my = self._maps[which]
        sx = mx[max(0, y0):y0 + h, max(0, x0):x0 + w]
        sy = my[max(0, y0):y0 + h, max(0, x0):x0 + w]
        out = np.zeros((n, h, w), np.float32)
        for i in range(n):  # one remap per frame of the patch's pixels only
            p = cv2.remap(frames[i], sx, sy, cv2.INTER_LINEAR)
            out[i, :p.shape[0], :p.shape[1]] = p
        return out

    def patch_geometry(self, fit_l: GridFit, fit_r: GridFit) -> tuple[int, int, int, int, int]:
        """(x0_left, y0, x0_right, w, h) of the patches in rectified px."""
        cl = self._rect_center(fit_l, "left")
        cr = self._rect_center(fit_r, "right")
        ext_x = (fit_l.cols - 1) * fit_l.pitch_px + fit_l.spot_px + 2 * self.settings.margin_px
        ext_y = (fit_l.rows - 1) * fit_l.pitch_px + fit_l.spot_px + 2 * self.settings.margin_px
        w = int(min(self.settings.max_patch_px, 2 * int(np.ceil(ext_x / 2))))
        h = int(min(self.settings.max_patch_px, 2 * int(np.ceil(ext_y / 2))))
        x0l = int(round(cl[0] - w / 2))
        y0 = int(round((cl[1] + cr[1]) / 2 - h / 2))
        x0r = int(round(cr[0] - w / 2))
        return x0l, y0, x0r, w, h

    def measure(self, left: np.ndarray, right: np.ndarray, fit_l: GridFit, fit_r: GridFit) -> RangeResult:
        """Range for each stereo frame of a block: ``left``/``right`` (n, H, W)."""
        x0l, y0, x0r, w, h = self.patch_geometry(fit_l, fit_r)
        pl = self._cut(left, "left", x0l, y0, w, h)
        pr = self._cut(right, "right", x0r, y0, w, h)
        est = self.estimator.estimate(pl, pr)
        d = (x0l - x0r) + np.asarray(est.dx, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(d > 0, self.f_px * self.b_m / d, np.nan)
            sig = z ** 2 / (self.f_px * self.b_m) * np.asarray(est.sigma_px, dtype=np.float64)
        return RangeResult(z_m=z, disparity_px=d, sigma_m=sig, quality=np.asarray(est.quality, np.float64))
