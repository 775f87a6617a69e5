"""One LED far away (100 m: a spot under a pixel) beside a steady lamp whose edges vibration
makes the most active pixels: acquisition must take the LED, not a fragment of the lamp.

The one-LED detection keeps a blob only if the flux in a box around it changes
(:func:`iscd.decode.tracking.detect.flux_modulation`): vibration moves a steady light but does
not change its flux. A box around one edge of a 22 px lamp cut through the lamp, so its border
(the background it subtracted) lay partly on the lamp and the edge's motion read as a
modulation of 0.5-0.75 under engine vibration; the lamp's edge won, the receiver followed it
for the whole approach and found no packet (issue 12, randomized physics). The box now
holds the whole source the blob belongs to (:func:`iscd.decode.tracking.detect.source_box`).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from iscd.decode.stream import StreamDecoder
from iscd.decode.tracking.detect import (MIN_FLUX_MODULATION, activity_map, detect_array, find_blobs,
                                         flux_modulation, source_box)
from test_acquisition_pace import randomized_first_frames


def _lamp_and_led(n: int = 64, amplitude_px: float = 0.85, hz: float = 30.0, seed: int = 3) -> np.ndarray:
    """(n, 96, 96) uint8 frames at 1000 fps: a steady 22 px lamp (160 DN over 23 DN) and a
    sub-pixel LED (PSF sigma 0.6 px, PWM-8 levels at 500 symbols/s, 60 DN at level 8),
    both moved vertically by engine vibration (``amplitude_px`` at ``hz``), 1 DN noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:96, 0:96].astype(np.float64)
    levels = rng.integers(1, 9, size=n // 2 + 1)
    out = np.empty((n, 96, 96), np.uint8)
    for k in range(n):
        s = amplitude_px * np.sin(2 * np.pi * hz * k / 1000.0)
        lamp = 160.0 * np.clip(11.5 - np.hypot(xx - 30.0, yy - 30.0 - s), 0.0, 1.0)
        led = levels[k // 2] / 8.0 * 60.0 * np.exp(-((xx - 70.3) ** 2 + (yy - 70.6 - s) ** 2) / (2 * 0.36))
        img = 23.0 + ndimage.gaussian_filter(lamp, 0.6) + led + rng.normal(0.0, 1.0, lamp.shape)
        out[k] = np.clip(np.round(img), 0, 255)
    return out


def _cut_box_modulation(frames: np.ndarray, bbox: tuple[int, int, int, int], pad: int = 4) -> float:
    """The flux modulation in the blob's own box (as before the source box)."""
    x0, y0, x1, y1 = bbox
    box = frames[:, y0 - pad:y1 + pad, x0 - pad:x1 + pad].astype(np.float64)
    border = np.concatenate([box[:, 0, :], box[:, -1, :], box[:, 1:-1, 0], box[:, 1:-1, -1]], axis=1)
    flux = box.sum(axis=(1, 2)) - border.mean(axis=1) * box.shape[1] * box.shape[2]
    lo, hi = np.percentile(flux, [5, 95])
    return float((hi - lo) / max(float(flux.mean()), 1.0))


def test_a_lamp_edge_is_measured_with_the_whole_lamp() -> None:
    frames = _lamp_and_led()
    mean = frames.mean(axis=0, dtype=np.float32)
    blobs = find_blobs(activity_map(frames), mean)
    lamp = [b for b in blobs if np.hypot(b.x - 30.0, b.y - 30.0) < 14]
    led = [b for b in blobs if np.hypot(b.x - 70.3, b.y - 70.6) < 2]
    assert len(lamp) >= 2 and len(led) == 1
    # the lamp's edges are the most active blobs, and cut by their own boxes they look modulated
    assert blobs[0] in lamp and blobs[0].peak * blobs[0].area > led[0].peak * led[0].area
    assert all(_cut_box_modulation(frames, b.bbox) >= MIN_FLUX_MODULATION for b in lamp[:2])
    for b in lamp:
        x0, y0, x1, y1 = source_box(mean, b.bbox)
        assert x0 <= 20 and y0 <= 20 and x1 >= 41 and y1 >= 41  # the disc (half max 19.5 .. 40.5 px)
        assert flux_modulation(frames, b.bbox, mean=mean) < 0.05  # its flux stays put
    # an LED's blob is its whole spot (its half-maximum area at most a pixel beyond it)
    assert np.abs(np.subtract(source_box(mean, led[0].bbox), led[0].bbox)).max() <= 1
    assert flux_modulation(frames, led[0].bbox, mean=mean) > 1.0
    fit = detect_array(frames, 1, 1)
    assert fit is not None and abs(fit.center[0] - 70.3) < 1 and abs(fit.center[1] - 70.6) < 1.5


@pytest.mark.parametrize("key, seed", [
    ("1led-100kmh-0.5px", 1569949901),  # engine vibration (38 Hz), flat background: the lamp was taken in both cameras
    ("1led-100kmh-0.3px", 2093833030),  # smooth vibration, textured background: the lamp's side in the left camera
])
def test_the_far_led_is_acquired_beside_the_lamp(key: str, seed: int) -> None:
    """Randomized physics (seeds not among those the cause was diagnosed on): the daemon's
    decoder, fed blocks of 16 pairs, acquires the LED at 100 m in both cameras on its first
    attempt."""
    cfg, L, R, tr = randomized_first_frames(key, seed)
    n = L.shape[0]
    assert cfg.scene.distractors  # the steady lamp at 40 m
    dec = StreamDecoder(cfg)
    try:
        for s in range(0, n, 16):
            ids = np.arange(s, s + 16)
            dec.push(ids, ids / cfg.camera.fps, L[ids], R[ids])
        assert dec.track is not None, "nothing acquired"
        for fit, u, v in ((dec.track.left, tr.u_left, tr.v_left), (dec.track.right, tr.u_right, tr.v_right)):
            assert abs(fit.center[0] - float(u[-1, 0])) < 2.0 and abs(fit.center[1] - float(v[-1, 0])) < 2.0, \
                (fit.center, float(u[-1, 0]), float(v[-1, 0]))
    finally:
        dec.close()
