"""Sensor model: PRNU, photon shot noise, read noise, dark level, quantization, clipping.

A pixel with noise-free photo-signal S (DN, from the optics) reads

    DN = clip(round(dark_dn + p * S + n), 0, 2^bits - 1),   n ~ N(0, k p S + r^2)

with p the fixed PRNU gain (1 + prnu * N(0,1) per pixel), k = (2^bits - 1) / full_well_e
the conversion gain (DN per electron, so full_well_e electrons = the top grey level) and
r = read_noise_e * k. The shot noise is Gaussian with the Poisson variance (the electron
counts are in the hundreds to thousands, where the two agree). The Gaussian draws come
from OpenCV's ``cv2.randn`` (3-5x faster than numpy's here), seeded per call
(``noise_seed``) so that every frame is reproducible on its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from iscd.core.config import SensorConfig


@dataclass(frozen=True)
class SensorModel:
    """Noise parameters in DN (see module docstring)."""

    gain_dn_per_e: float
    read_dn: float
    dark_dn: float
    prnu: float
    max_dn: int = 255
    noise: bool = True

    @classmethod
    def from_config(cls, cfg: SensorConfig, bit_depth: int = 8, noise: bool = True) -> "SensorModel":
        """The model of ``[sensor]`` for ``bit_depth``-bit frames (see module docstring).

        Parameters
        ----------
        cfg : SensorConfig
            Full well and read noise (electrons), PRNU, dark level (DN).
        bit_depth : int
            Bits per pixel; the top grey level 2^bits - 1 is the full well.
        noise : bool
            Shot and read noise on (see :meth:`expose`).

        Returns
        -------
        SensorModel
        """
        top = (1 << bit_depth) - 1
        k = top / cfg.full_well_e
        return cls(k, cfg.read_noise_e * k, cfg.dark_dn, cfg.prnu, top, noise)

    def prnu_map(self, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
        """Fixed per-pixel gain map (float32), mean 1, RMS ``prnu``, never below 0.

        Parameters
        ----------
        shape : tuple of int
            (h, w), px.
        rng : numpy.random.Generator
            Source of the map.

        Returns
        -------
        ndarray of float32
            (h, w) gains.
        """
        m = 1.0 + self.prnu * rng.standard_normal(shape, dtype=np.float32)
        return np.maximum(m, 0.0, out=m)

    def expose(self, signal: np.ndarray, prnu: np.ndarray, noise_seed: int | None,
               out: np.ndarray) -> None:
        """Read out photo-signal ``signal`` (DN, float32, modified in place) into ``out``
        (uint8/uint16, same shape): PRNU, noise (if ``noise`` and ``noise_seed`` is not
        None), dark level, rounding, clipping.

        Parameters
        ----------
        signal : ndarray of float32
            Noise-free photo-signal S, DN (overwritten).
        prnu : ndarray of float32
            PRNU gain map p, the shape of ``signal``.
        noise_seed : int or None
            Seed of the Gaussian draws (``cv2.randn``); None: no noise.
        out : ndarray of uint8 or uint16
            Read-out frame, DN, the shape of ``signal``.
        """
        s = signal
        s *= prnu
        if self.noise and noise_seed is not None:
            sd = s * np.float32(self.gain_dn_per_e)
            sd += np.float32(self.read_dn ** 2)
            np.maximum(sd, 0.0, out=sd)
            np.sqrt(sd, out=sd)
            z = np.empty(s.shape, np.float32)
            cv2.setRNGSeed(noise_seed & 0x7FFFFFFF)
            cv2.randn(z, 0.0, 1.0)
            sd *= z
            s += sd
        s += np.float32(self.dark_dn + 0.5)
        np.clip(s, 0.0, np.float32(self.max_dn + 0.5 - 1e-3), out=s)
        out[...] = s  # float -> integer truncates: floor(x + 0.5) = rounding


def bloom_coefficients(spill: float, length_px: float) -> np.ndarray:
    """Blooming along a column: the float64 weights c_d, d = 1..D, of the charge moved from
    a saturated pixel to each of its neighbours d rows above and d rows below (the same
    both ways), c_d = spill (1 - q) q^(d-1) / (2 (1 - q^D)), q = exp(-1/length_px),
    D = ceil(4 length_px): the two sides together get ``spill`` of the excess (DN above
    full well, which the pixel loses). Empty when ``spill`` is 0.

    Parameters
    ----------
    spill : float
        ``sensor.blooming``: share of the excess that spills, 0..1.
    length_px : float
        ``sensor.bloom_length_px``: decay length along the column, px.

    Returns
    -------
    ndarray of float64
        (D,) weights c_1..c_D (sum spill / 2); (0,) when ``spill`` <= 0.
    """
    if spill <= 0:
        return np.zeros(0)
    D = int(np.ceil(4.0 * length_px))
    q = np.exp(-1.0 / length_px)
    w = q ** np.arange(D)
    return spill * w / (2.0 * w.sum())
