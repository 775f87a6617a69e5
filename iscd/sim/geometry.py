"""Stereo pinhole geometry, transmitter motion, rig vibration and air jitter.

Left camera at the origin, right camera at x = +baseline_m, both looking down +z; image
x right, y down; principal point at the image centre (cx, cy) = (W/2 - 0.5, H/2 - 0.5) in
pixel-centre coordinates (pixel (0, 0) is centred at (0, 0)). A point (X, Y, Z) images at

    u_L = cx + f_px X / Z,   u_R = u_L - f_px b / Z,   v = cy + f_px Y / Z        [px]

with f_px = f / rho (dissertation eq. 2.2: Z = f b / (rho d), d = u_L - u_R).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from iscd.config import CameraConfig, SceneConfig, TransmitterConfig

if TYPE_CHECKING:  # pragma: no cover
    from calibration.io import StereoCalibration


@dataclass(frozen=True)
class StereoGeometry:
    """Intrinsics shared by both cameras and the baseline."""

    focal_px: float
    baseline_m: float
    width: int
    height: int

    @classmethod
    def from_config(cls, cam: CameraConfig) -> "StereoGeometry":
        return cls(cam.focal_px, cam.baseline_m, cam.width, cam.height)

    @property
    def cx(self) -> float:
        return self.width / 2 - 0.5

    @property
    def cy(self) -> float:
        return self.height / 2 - 0.5

    def disparity(self, z_m: np.ndarray | float) -> np.ndarray:
        """d = f_px b / Z, px."""
        return self.focal_px * self.baseline_m / np.asarray(z_m, dtype=np.float64)

    def project(self, x_m: np.ndarray, y_m: np.ndarray, z_m: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u_left, u_right, v) in px of points (X, Y, Z) in m (broadcasting)."""
        z = np.asarray(z_m, dtype=np.float64)
        ul = self.cx + self.focal_px * np.asarray(x_m) / z
        v = self.cy + self.focal_px * np.asarray(y_m) / z
        return ul, ul - self.focal_px * self.baseline_m / z, v


def project_rig(rig: "StereoCalibration", x_m: np.ndarray, y_m: np.ndarray, z_m: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(u_left, v_left, u_right, v_right) in px of points (X, Y, Z) in m (left-camera
    coordinates, broadcasting) as imaged by a non-ideal rig: each camera's intrinsics and lens
    distortion and the right camera's pose (R, T), via
    :func:`calibration.io.project_points` (cv2.projectPoints). A rig equal to the ideal one
    gives :meth:`StereoGeometry.project` up to rounding."""
    from calibration.io import project_points

    x, y, z = np.broadcast_arrays(np.asarray(x_m, np.float64), np.asarray(y_m, np.float64),
                                  np.asarray(z_m, np.float64))
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    left = project_points(rig, pts, "left")
    right = project_points(rig, pts, "right")
    shp = x.shape
    return (left[:, 0].reshape(shp), left[:, 1].reshape(shp),
            right[:, 0].reshape(shp), right[:, 1].reshape(shp))


def led_offsets(tx: TransmitterConfig) -> np.ndarray:
    """(N, 2) LED (x, y) offsets from the array centre, m, row-major:
    x = (c - (cols-1)/2) pitch, y = (r - (rows-1)/2) pitch."""
    r, c = np.divmod(np.arange(tx.rows * tx.cols), tx.cols)
    return np.stack([(c - (tx.cols - 1) / 2) * tx.pitch_m,
                     (r - (tx.rows - 1) / 2) * tx.pitch_m], axis=1)


def distance(t_s: np.ndarray, scene: SceneConfig) -> np.ndarray:
    """Z(t) = max(distance_m - speed_mps t, min_distance_m), m (t in s, camera clock)."""
    z = scene.distance_m - scene.speed_mps * np.asarray(t_s, dtype=np.float64)
    return np.maximum(z, scene.min_distance_m)


class Vibration:
    """Rig vibration: an image shift (px) common to both cameras, a smooth random process.

    Per axis a sum of ``n_tones`` sinusoids with random frequencies (log-uniform in
    ``band_hz``) and phases, scaled so that the RMS shift per axis is ``rms_px``.
    Deterministic in (seed, t): random access.
    """

    def __init__(self, rms_px: float, seed: int, n_tones: int = 8,
                 band_hz: tuple[float, float] = (1.0, 40.0)) -> None:
        rng = np.random.default_rng([seed & 0xFFFFFFFF, 0x71B])
        self.rms_px = float(rms_px)
        self.freq = np.exp(rng.uniform(np.log(band_hz[0]), np.log(band_hz[1]), size=(2, n_tones)))
        self.phase = rng.uniform(0, 2 * np.pi, size=(2, n_tones))
        self.amp = self.rms_px * np.sqrt(2.0 / n_tones)

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        """(F, 2) shift (dx, dy) in px at times t_s (s)."""
        t = np.asarray(t_s, dtype=np.float64).reshape(-1)
        if self.rms_px == 0:
            return np.zeros((t.size, 2))
        arg = 2 * np.pi * self.freq[None] * t[:, None, None] + self.phase[None]
        return self.amp * np.sin(arg).sum(axis=2)


class Jitter:
    """Air jitter: independent Gaussian image shifts per camera and frame (RMS ``rms_px``
    per axis), fresh each frame, random access in (seed, camera, frame)."""

    BLOCK = 4096

    def __init__(self, rms_px: float, seed: int, camera: int) -> None:
        self.rms_px = float(rms_px)
        self.seed = seed & 0xFFFFFFFF
        self.camera = camera
        self._cache: dict[int, np.ndarray] = {}

    def _block(self, b: int) -> np.ndarray:
        blk = self._cache.get(b)
        if blk is None:
            rng = np.random.default_rng([self.seed, 0x417, self.camera, b])
            blk = rng.standard_normal((self.BLOCK, 2)) * self.rms_px
            if len(self._cache) > 16:
                self._cache.clear()
            self._cache[b] = blk
        return blk

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        """(F, 2) shift (dx, dy) in px of frame indices ``frames``."""
        f = np.asarray(frames, dtype=np.int64).reshape(-1)
        if self.rms_px == 0 or f.size == 0:
            return np.zeros((f.size, 2))
        b, off = np.divmod(f, self.BLOCK)
        out = np.empty((f.size, 2))
        for blk in np.unique(b):
            m = b == blk
            out[m] = self._block(int(blk))[off[m]]
        return out
