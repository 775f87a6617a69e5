"""Stereo pinhole geometry, transmitter motion, rig vibration and air jitter.

Rig vibration models (``scene.vibration_model``, all scaled to ``scene.vibration_px``,
deterministic in (seed, t) and random access): :class:`Vibration` (``smooth``),
:class:`BumpVibration` (``bumps``) and :class:`EngineVibration` (``engine``);
:func:`make_vibration` picks one from the config.

Left camera at the origin, right camera at x = +baseline_m, both looking down +z; image
x right, y down; principal point at the image centre (cx, cy) = (W/2 - 0.5, H/2 - 0.5) in
pixel-centre coordinates (pixel (0, 0) is centred at (0, 0)). A point (X, Y, Z) images at

    u_L = cx + f_px X / Z,   u_R = u_L - f_px b / Z,   v = cy + f_px Y / Z        [px]

with f_px = f / rho (dissertation eq. 2.2: Z = f b / (rho d), d = u_L - u_R).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from iscd.core.config import CameraConfig, SceneConfig, TransmitterConfig

if TYPE_CHECKING:  # pragma: no cover
    from iscd.calibration.io import StereoCalibration


@dataclass(frozen=True)
class StereoGeometry:
    """Intrinsics shared by both cameras and the baseline."""

    focal_px: float
    baseline_m: float
    width: int
    height: int

    @classmethod
    def from_config(cls, cam: CameraConfig) -> "StereoGeometry":
        """The ideal rig of ``[camera]``: f/rho, baseline and image size.

        Parameters
        ----------
        cam : CameraConfig
            The camera section.

        Returns
        -------
        StereoGeometry
        """
        return cls(cam.focal_px, cam.baseline_m, cam.width, cam.height)

    @property
    def cx(self) -> float:
        return self.width / 2 - 0.5

    @property
    def cy(self) -> float:
        return self.height / 2 - 0.5

    def disparity(self, z_m: np.ndarray | float) -> np.ndarray:
        """d = f_px b / Z, px.

        Parameters
        ----------
        z_m : float or ndarray
            Distance Z, m.

        Returns
        -------
        ndarray of float64
            Disparity d, px, the shape of ``z_m``.

        References
        ----------
        Dissertation, eq. (2.2).
        """
        return self.focal_px * self.baseline_m / np.asarray(z_m, dtype=np.float64)

    def project(self, x_m: np.ndarray, y_m: np.ndarray, z_m: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u_left, u_right, v) in px of points (X, Y, Z) in m (broadcasting).

        Parameters
        ----------
        x_m, y_m, z_m : ndarray
            Point coordinates in the left camera's frame (x right, y down, z forward), m.

        Returns
        -------
        u_left, u_right, v : ndarray of float64
            Image coordinates, px (pixel-centre convention); the broadcast shape of the inputs.

        References
        ----------
        Dissertation, eq. (2.2).
        """
        z = np.asarray(z_m, dtype=np.float64)
        ul = self.cx + self.focal_px * np.asarray(x_m) / z
        v = self.cy + self.focal_px * np.asarray(y_m) / z
        return ul, ul - self.focal_px * self.baseline_m / z, v


def project_rig(rig: "StereoCalibration", x_m: np.ndarray, y_m: np.ndarray, z_m: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(u_left, v_left, u_right, v_right) in px of points (X, Y, Z) in m (left-camera
    coordinates, broadcasting) as imaged by a non-ideal rig: each camera's intrinsics and lens
    distortion and the right camera's pose (R, T), via
    :func:`iscd.calibration.io.project_points` (cv2.projectPoints). A rig equal to the ideal one
    gives :meth:`StereoGeometry.project` up to rounding.

    Parameters
    ----------
    rig : iscd.calibration.io.StereoCalibration
        The rig (M1, D1, M2, D2, R, T; T in m).
    x_m, y_m, z_m : ndarray
        Point coordinates in the left camera's frame, m.

    Returns
    -------
    u_left, v_left, u_right, v_right : ndarray of float64
        Image coordinates, px; the broadcast shape of the inputs.
    """
    from iscd.calibration.io import project_points

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
    x = (c - (cols-1)/2) pitch, y = (r - (rows-1)/2) pitch.

    Parameters
    ----------
    tx : TransmitterConfig
        ``rows``, ``cols`` and ``pitch_m`` (m).

    Returns
    -------
    ndarray of float64
        (N, 2) offsets, m, N = rows cols.
    """
    r, c = np.divmod(np.arange(tx.rows * tx.cols), tx.cols)
    return np.stack([(c - (tx.cols - 1) / 2) * tx.pitch_m,
                     (r - (tx.rows - 1) / 2) * tx.pitch_m], axis=1)


def lateral(t_s: np.ndarray, scene: SceneConfig) -> np.ndarray:
    """X(t) = lateral_m + lateral_speed_mps t, m (t in s, camera clock): the transmitter's
    lateral offset (right positive); it keeps moving when the approach has stopped.

    Parameters
    ----------
    t_s : ndarray
        Times, s (camera clock).
    scene : SceneConfig
        ``lateral_m`` (m) and ``lateral_speed_mps`` (m/s).

    Returns
    -------
    ndarray of float64
        X, m, the shape of ``t_s``.
    """
    t = np.asarray(t_s, dtype=np.float64)
    return scene.lateral_m + scene.lateral_speed_mps * t


def distance(t_s: np.ndarray, scene: SceneConfig) -> np.ndarray:
    """Z(t) = max(distance_m - speed_mps t, min_distance_m), m (t in s, camera clock).

    Parameters
    ----------
    t_s : ndarray
        Times, s (camera clock).
    scene : SceneConfig
        ``distance_m`` (m), ``speed_mps`` (m/s) and ``min_distance_m`` (m).

    Returns
    -------
    ndarray of float64
        Z, m, the shape of ``t_s``.
    """
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


class BumpVibration:
    """Road bumps: short pitch impulses, each followed by a damped ringing of the rig.

    Bump k (k >= 0) hits at t_k = (k + U_k) / rate (one per 1/rate s on average, U_k
    uniform in [0, 1): random times, never two in one slot) and rings as

        y_k(t) = A_k h_k(t - t_k),   h_k(tau) = e^{-zeta w_k tau} sin(w_d tau) / sqrt(E_k)
                                                                          (tau >= 0)

    with w_k = 2 pi f_k, f_k log-uniform in [f/1.5, 1.5 f] (``bump_freq_hz`` f),
    w_d = w_k sqrt(1 - zeta^2), E_k = int h^2 = w_d^2 / (4 a (a^2 + w_d^2)), a = zeta w_k
    (unit energy, s), A_k = random sign times uniform [0.5, 1.5]; the response is cut where
    the envelope is below 1e-4 (exactly 0 after). Mostly vertical: x_k = c_k y_k with c_k
    uniform in [-0.3, 0.3]. By Campbell's theorem the mean square of y is
    rate E[A^2] = rate 13/12, so the amplitudes are scaled to give RMS ``rms_px`` in y
    (x: about 0.17 of it). Deterministic in (seed, t), random access: the bump parameters
    come in blocks of 256 bumps seeded by (seed, block).
    """

    BLOCK = 256

    def __init__(self, rms_px: float, seed: int, rate_hz: float = 2.5, freq_hz: float = 10.0,
                 damping: float = 0.15) -> None:
        self.rms_px = float(rms_px)
        self.seed = seed & 0xFFFFFFFF
        self.rate = float(rate_hz)
        self.freq = float(freq_hz)
        self.zeta = float(damping)
        self.scale = self.rms_px / math.sqrt(self.rate * 13.0 / 12.0)
        a_min = self.zeta * 2 * math.pi * self.freq / 1.5
        self.t_cut = math.log(1e4) / a_min  # s: the longest ringing
        self._cache: dict[int, np.ndarray] = {}

    def _block(self, b: int) -> np.ndarray:
        """(BLOCK, 6) per bump: t_k, a, w_d, amplitude / sqrt(E), x coupling, t_cut."""
        blk = self._cache.get(b)
        if blk is None:
            rng = np.random.default_rng([self.seed, 0xB0B, b])
            n = self.BLOCK
            k = b * n + np.arange(n)
            t = (k + rng.uniform(0.0, 1.0, n)) / self.rate
            f = self.freq * np.exp(rng.uniform(-np.log(1.5), np.log(1.5), n))
            w = 2 * np.pi * f
            a = self.zeta * w
            wd = w * math.sqrt(1.0 - self.zeta ** 2)
            energy = wd ** 2 / (4 * a * (a * a + wd * wd))
            amp = rng.choice([-1.0, 1.0], n) * rng.uniform(0.5, 1.5, n) * self.scale
            cx = rng.uniform(-0.3, 0.3, n)
            blk = np.stack([t, a, wd, amp / np.sqrt(energy), cx, np.log(1e4) / a], axis=1)
            if len(self._cache) > 16:
                self._cache.clear()
            self._cache[b] = blk
        return blk

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        """(F, 2) shift (dx, dy) in px at times t_s (s, >= 0)."""
        t = np.asarray(t_s, dtype=np.float64).reshape(-1)
        out = np.zeros((t.size, 2))
        if self.rms_px == 0 or t.size == 0:
            return out
        k_lo = max(int(math.floor((t.min() - self.t_cut) * self.rate)) - 1, 0)
        k_hi = max(int(math.floor(t.max() * self.rate)) + 1, 0)
        blk = np.concatenate([self._block(b) for b in range(k_lo // self.BLOCK,
                                                             k_hi // self.BLOCK + 1)])
        tk = blk[:, 0]
        blk = blk[(tk <= t.max()) & (tk + blk[:, 5] > t.min())]
        # one bump at a time, in bump order: a frame's sum does not depend on the query
        # (bumps out of reach add exact zeros), so frames are random access
        for tk, a, wd, amp, cx, tc in blk:
            tau = t - tk
            m = (tau >= 0) & (tau < tc)
            y = amp * np.exp(-a * tau[m]) * np.sin(wd * tau[m])
            out[m, 1] += y
            out[m, 0] += cx * y
        return out


class EngineVibration:
    """Engine vibration: a narrow-band tone with its 2nd harmonic, slowly wandering.

    The fundamental's frequency f0(t) = f_e + W w(t) with w(t) = sum_i c_i sin(2 pi nu_i t
    + theta_i), sum |c_i| = 1 (so |w| <= 1), nu_i log-uniform in 0.05-0.5 Hz; its phase
    phi(t) = 2 pi int_0^t f0 is integrated exactly. Per axis

        y(t) = a1 [sin(phi + psi_1) + h sin(2 phi + psi_2)],   a1 = rms sqrt(2 / (1 + h^2))

    (``engine_hz`` f_e, ``engine_wander_hz`` W, ``engine_harmonic`` h), RMS ``rms_px`` in y;
    x is the same with its own phases and half the amplitude. Deterministic in (seed, t).
    """

    def __init__(self, rms_px: float, seed: int, freq_hz: float = 30.0,
                 wander_hz: float = 3.0, harmonic: float = 0.4) -> None:
        rng = np.random.default_rng([seed & 0xFFFFFFFF, 0xE4E])
        self.rms_px = float(rms_px)
        self.f0 = float(freq_hz)
        self.wander = float(wander_hz)
        self.h = float(harmonic)
        c = rng.uniform(0.2, 1.0, 3)
        self.c = c / c.sum()
        self.nu = np.exp(rng.uniform(np.log(0.05), np.log(0.5), 3))
        self.theta = rng.uniform(0, 2 * np.pi, 3)
        self.psi = rng.uniform(0, 2 * np.pi, (2, 2))  # (axis x/y, harmonic 1/2)
        self.a1 = self.rms_px * math.sqrt(2.0 / (1.0 + self.h ** 2)) * np.array([0.5, 1.0])

    def phase(self, t_s: np.ndarray) -> np.ndarray:
        """phi(t) = 2 pi (f_e t + W sum_i c_i (cos theta_i - cos(2 pi nu_i t + theta_i))
        / (2 pi nu_i)), rad.

        Parameters
        ----------
        t_s : ndarray
            Times, s (flattened).

        Returns
        -------
        ndarray of float64
            (F,) phase of the fundamental, rad.
        """
        t = np.asarray(t_s, dtype=np.float64).reshape(-1, 1)
        w = self.nu * 2 * np.pi
        integ = (self.c * (np.cos(self.theta) - np.cos(w * t + self.theta)) / w).sum(axis=1)
        return 2 * np.pi * (self.f0 * t[:, 0] + self.wander * integ)

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        """(F, 2) shift (dx, dy) in px at times t_s (s)."""
        t = np.asarray(t_s, dtype=np.float64).reshape(-1)
        if self.rms_px == 0:
            return np.zeros((t.size, 2))
        ph = self.phase(t)[:, None]
        return self.a1 * (np.sin(ph + self.psi[:, 0]) + self.h * np.sin(2 * ph + self.psi[:, 1]))


def make_vibration(scene: SceneConfig, seed: int
                   ) -> Vibration | BumpVibration | EngineVibration:
    """The rig vibration of ``scene.vibration_model`` with RMS ``scene.vibration_px``.

    Parameters
    ----------
    scene : SceneConfig
        ``vibration_model``, ``vibration_px`` (px) and the model's parameters
        (``bump_*``, ``engine_*``).
    seed : int
        Random seed (the scene's).

    Returns
    -------
    Vibration or BumpVibration or EngineVibration
        Called with times t_s (s), gives the (F, 2) shift (dx, dy), px.
    """
    rms = scene.vibration_px
    if scene.vibration_model == "bumps":
        return BumpVibration(rms, seed, scene.bump_rate_hz, scene.bump_freq_hz,
                             scene.bump_damping)
    if scene.vibration_model == "engine":
        return EngineVibration(rms, seed, scene.engine_hz, scene.engine_wander_hz,
                               scene.engine_harmonic)
    return Vibration(rms, seed)


def vibration_margin(scene: SceneConfig) -> int:
    """Padding (px) of the pre-rendered background for the whole-pixel vibration shift:
    4 x RMS for ``smooth`` (as before), 8 x RMS for the impulsive ``bumps``, the peak
    2 x RMS for ``engine``; at most 64.

    Parameters
    ----------
    scene : SceneConfig
        ``vibration_model`` and ``vibration_px`` (px).

    Returns
    -------
    int
        Margin, px (0 without vibration).
    """
    factor = {"smooth": 4.0, "bumps": 8.0, "engine": 2.0}[scene.vibration_model]
    return min(int(math.ceil(factor * scene.vibration_px)), 64)
