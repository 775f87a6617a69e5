"""Daylight background and distractor lights.

The background is a procedural texture at one distance Z_bg (a wall of buildings, trees,
sky): multi-scale smoothed noise plus random rectangular blocks with hard edges, mean
``background_dn`` (DN at f/4 and 1 ms). The right camera sees it shifted by its own
disparity d_bg = f_px b / Z_bg (right(u) = left(u + d_bg)). ``flat`` is a constant
``background_dn``, ``none`` is black.

Distractors are disks like LEDs (same optics) at their own 3-D position; ``flicker_hz`` > 0
modulates them as (1 - cos(2 pi f t + phi)) (``waveform = "sine"``, mean = brightness_dn) or
as a square wave on for the first ``duty`` of each period 1/f (``waveform = "square"``: a
PWM-dimmed LED lamp, brightness_dn while on, mean duty brightness_dn), integrated exactly
over the exposure (:func:`flicker_gain`). They never carry data.
"""

from __future__ import annotations

import cv2
import numpy as np

from iscd.core.config import DistractorConfig


def texture(shape: tuple[int, int], mean_dn: float, rng: np.random.Generator,
            contrast: float = 0.35, n_blocks: int = 40) -> np.ndarray:
    """Procedural texture (float32, DN) of ``shape`` with mean ``mean_dn``, >= 0.

    Parameters
    ----------
    shape : tuple of int
        (h, w), px.
    mean_dn : float
        Mean grey level, DN.
    rng : numpy.random.Generator
        Source of the noise and the blocks.
    contrast : float
        Relative RMS contrast before clipping at 0 (the mean is restored after it).
    n_blocks : int
        Hard-edged rectangles (buildings, signs, poles) added to the smoothed noise.

    Returns
    -------
    ndarray of float32
        (h, w) texture, DN.
    """
    h, w = shape
    tex = np.zeros((h, w), np.float32)
    for sigma, weight in ((1.0, 0.25), (4.0, 0.5), (16.0, 1.0), (48.0, 1.0)):
        n = rng.standard_normal((h, w), dtype=np.float32)
        b = cv2.GaussianBlur(n, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        b /= max(float(b.std()), 1e-9)
        tex += weight * b
    for _ in range(n_blocks):  # buildings, signs, poles: hard edges
        bw, bh = rng.integers(8, max(9, w // 3)), rng.integers(8, max(9, h // 3))
        x0, y0 = rng.integers(-bw // 2, w), rng.integers(-bh // 2, h)
        tex[max(y0, 0):y0 + bh, max(x0, 0):x0 + bw] += rng.normal(0.0, 1.5)
    tex -= tex.mean()
    tex /= max(float(tex.std()), 1e-9)
    out = mean_dn * (1.0 + contrast * tex)
    np.maximum(out, 0.0, out=out)
    if out.mean() > 0:
        out *= mean_dn / out.mean()
    return out.astype(np.float32)


def background_pair(kind: str, shape: tuple[int, int], mean_dn: float, disparity_px: float,
                    rng: np.random.Generator, contrast: float = 0.35
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) noise-free backgrounds (float32 DN, before aperture scaling) of
    ``shape``; the right one is the left scene shifted by ``disparity_px`` (cubic);
    ``contrast``: the texture's relative RMS contrast.

    Parameters
    ----------
    kind : {"texture", "flat", "none"}
        ``scene.background``.
    shape : tuple of int
        (h, w), px.
    mean_dn : float
        Mean grey level at f/4 and 1 ms, DN.
    disparity_px : float
        Disparity d_bg = f_px b / Z_bg of the background, px: right(u) = left(u + d_bg).
    rng : numpy.random.Generator
        Source of the texture (unused for ``flat`` and ``none``).
    contrast : float
        Relative RMS contrast of the texture.

    Returns
    -------
    left, right : ndarray of float32
        Each (h, w), DN.
    """
    h, w = shape
    if kind == "none":
        z = np.zeros(shape, np.float32)
        return z, z.copy()
    if kind == "flat":
        f = np.full(shape, mean_dn, np.float32)
        return f, f.copy()
    pad = int(np.ceil(abs(disparity_px))) + 4
    big = texture((h, w + 2 * pad), mean_dn, rng, contrast=contrast)
    left = np.ascontiguousarray(big[:, pad:pad + w])
    m = np.array([[1.0, 0.0, pad + disparity_px], [0.0, 1.0, 0.0]])
    right = cv2.warpAffine(big, m, (w, h), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REFLECT)
    np.maximum(right, 0.0, out=right)
    return left, right.astype(np.float32)


def flicker_gain(d: DistractorConfig, t0_s: np.ndarray, exposure_s: float,
                 phase_rad: float = 0.0) -> np.ndarray:
    """Mean of the distractor's modulation over [t0, t0 + exposure] (1 for a steady light).

    ``waveform = "sine"``: 1 - cos(2 pi f t + phi) (0-2, mean 1). ``"square"``: 1 while
    frac(f t + phi / (2 pi)) < duty, else 0 (0-1, mean ``duty``): the on-fraction of the
    exposure, :func:`square_on_fraction`.

    Parameters
    ----------
    d : DistractorConfig
        The distractor; its ``flicker_hz`` is f, Hz (<= 0: steady), ``waveform``, ``duty``.
    t0_s : ndarray
        Exposure start times, s (camera clock).
    exposure_s : float
        Exposure time, s.
    phase_rad : float
        phi, rad.

    Returns
    -------
    ndarray of float64
        Gain on ``brightness_dn``, the shape of ``t0_s``.
    """
    t0 = np.asarray(t0_s, dtype=np.float64)
    if d.flicker_hz <= 0:
        return np.ones_like(t0)
    if d.waveform == "square":
        return square_on_fraction(t0, exposure_s, d.flicker_hz, d.duty,
                                  phase_rad / (2 * np.pi * d.flicker_hz))
    w = 2 * np.pi * d.flicker_hz
    return 1.0 - (np.sin(w * (t0 + exposure_s) + phase_rad) - np.sin(w * t0 + phase_rad)) / (
        w * exposure_s)


def square_on_fraction(t0_s: np.ndarray, exposure_s: float, freq_hz: float, duty: float,
                       offset_s: float = 0.0) -> np.ndarray:
    """On-fraction of [t0, t0 + exposure] of a square wave of period P = 1/f that is on
    for the first ``duty`` P of each period, periods starting at t = k P - offset_s.

    Exact: C(t) = floor(t'/P) duty P + min(t' - floor(t'/P) P, duty P), t' = t + offset_s,
    is the on-time since t' = 0; the fraction is (C(t0 + e) - C(t0)) / e.

    Parameters
    ----------
    t0_s : ndarray
        Exposure start times, s.
    exposure_s : float
        Exposure time e, s (> 0).
    freq_hz : float
        f, Hz (> 0).
    duty : float
        On-fraction of a period, 0..1.
    offset_s : float
        Time shift of the wave, s.

    Returns
    -------
    ndarray of float64
        On-fractions 0..1, the shape of ``t0_s``.
    """
    P = 1.0 / float(freq_hz)
    on = float(duty) * P

    def cum(t: np.ndarray) -> np.ndarray:
        k = np.floor(t / P)
        return k * on + np.minimum(t - k * P, on)

    t0 = np.asarray(t0_s, dtype=np.float64) + offset_s
    return np.clip((cum(t0 + exposure_s) - cum(t0)) / exposure_s, 0.0, 1.0)
