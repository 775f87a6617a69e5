"""The transmitter in the second camera, found by its own data: a guided stereo search.

Acquisition (:func:`iscd.decode.tracking.detect.detect_array`) looks for the transmitter in
each camera on its own, then pairs the two fits. Where one camera sees it easily and the
other barely (the HDR pair's f/8 camera gets a quarter of the f/4 camera's light: one LED
at 100 m over a textured road scene is a few DN above a background of 50-80 DN), the
second camera's own detection finds nothing, or a texture edge, and the transmitter is not
acquired at all while the first camera could decode it.

Here the found camera says what to look for: each LED's light over the acquisition frames,
a time series that no static texture, steady lamp or rig vibration reproduces. In the
other camera, along the epipolar band (rectified images: the same rows within ``max_dy``,
the disparity ``d = x_ref - x_other`` in -1 .. ``max_disparity`` px), every candidate
shift (dx, dy) of the whole grid is scored by the mean over LEDs of the correlation
between that LED's series in the reference camera and the other camera's (spatially
smoothed) pixel series at the LED's centre moved by the shift. The best shift is accepted
when its correlation is high (:data:`MIN_PARTNER_CORRELATION`) and stands out from the
band's other shifts (:data:`MIN_PARTNER_CONTRAST` robust standard deviations), then
refined to sub-pixel.

Over n frames a pixel of pure noise correlates with a given series with an RMS of
1/sqrt(n) (0.125 at 64 frames); a band of ~4 000 shifts reaches ~0.5 by chance, which the
threshold (0.6) and the contrast test keep out.

All coordinates are in px, x right and y down, pixel centres at integers; frames in DN.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from iscd.decode.tracking.detect import GridFit, fit_grid, light_map

MIN_PARTNER_CORRELATION = 0.6
"""Least mean correlation (over LEDs, Pearson, over the acquisition frames) between the
reference camera's LED series and the other camera's pixels at the accepted shift."""

MIN_PARTNER_CONTRAST = 6.0
"""Least height of the accepted shift's score above the band's median score, in robust
standard deviations (1.4826 MAD) of the band's scores."""


def _zscore_series(x: np.ndarray) -> np.ndarray | None:
    """Each column of ``x`` (n, k) centred and scaled to unit RMS over axis 0; None if any
    column is constant (an LED whose light never changed over the window)."""
    x = x - x.mean(axis=0, keepdims=True)
    s = np.sqrt((x * x).mean(axis=0))
    if not np.all(s > 1e-9):
        return None
    return x / s


def reference_series(frames: np.ndarray, fit: GridFit, *, sigma_px: float | None = None) -> np.ndarray:
    """Each LED's light over the frames in the camera where it was found.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames of that camera, DN.
    fit : GridFit
        The transmitter's fit in that camera, px.
    sigma_px : float, optional
        Spatial smoothing before sampling, px (default: the spot's diameter / 2.5, at least
        0.7 px).

    Returns
    -------
    ndarray of float64
        (n, N) the smoothed frames sampled at the LED centres (bilinear), DN.
    """
    f = np.asarray(frames, dtype=np.float32)
    sig = sigma_px if sigma_px is not None else max(0.7, fit.spot_px / 2.5)
    x0, y0, x1, y1 = fit.bbox(margin=3 * sig + 2)
    H, W = f.shape[1:]
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(W, x1), min(H, y1)
    sub = ndimage.gaussian_filter(f[:, y0:y1, x0:x1], (0, sig, sig), mode="nearest")
    c = fit.centers - np.array([x0, y0], np.float64)
    return _bilinear(sub, c)


def _bilinear(stack: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(n, k) values of the (n, h, w) stack at the k points (x, y), px (clamped inside)."""
    h, w = stack.shape[1:]
    x = np.clip(pts[:, 0], 0, w - 1.000001)
    y = np.clip(pts[:, 1], 0, h - 1.000001)
    xi, yi = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - xi, y - yi
    a = stack[:, yi, xi] * (1 - fx) + stack[:, yi, xi + 1] * fx
    b = stack[:, yi + 1, xi] * (1 - fx) + stack[:, yi + 1, xi + 1] * fx
    return (a * (1 - fy) + b * fy).astype(np.float64)


def find_partner(frames: np.ndarray, ref: GridFit, series: np.ndarray, *, max_dy: float = 3.0,
                 max_disparity: float = 400.0, sigma_px: float | None = None,
                 min_correlation: float = MIN_PARTNER_CORRELATION,
                 min_contrast: float = MIN_PARTNER_CONTRAST) -> GridFit | None:
    """The same transmitter in the other camera of a rectified pair, found by its light.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) the other camera's frames, DN, the same instants as ``series``.
    ref : GridFit
        The transmitter's fit in the reference camera, px.
    series : ndarray
        (n, N) each LED's light in the reference camera (:func:`reference_series`), DN.
    max_dy : float
        Largest vertical offset between the cameras, px.
    max_disparity : float
        Largest disparity ``x_ref - x_other``, px (the smallest is -1 px).
    sigma_px : float, optional
        Spatial smoothing of the other camera's frames, px (default: the reference spot's
        diameter / 2.5, at least 0.7 px; the other camera's spot may be larger, defocused).
    min_correlation : float
        Least mean correlation at the accepted shift.
    min_contrast : float
        Least height of the accepted shift above the band, robust standard deviations.

    Returns
    -------
    GridFit or None
        The fit in the other camera, px; ``score`` the correlation. One LED: the centroid
        of the correlation peak. An array: the grid fitted to the other camera's light
        map at the best shift (to sub-pixel by a parabola through the scores). None when no
        shift qualifies.
    """
    f = np.asarray(frames)
    n, H, W = f.shape
    s = np.asarray(series, dtype=np.float64)
    if s.ndim != 2 or s.shape[0] != n or s.shape[1] != ref.rows * ref.cols:
        raise ValueError(f"series: expected ({n}, {ref.rows * ref.cols}), got {s.shape}")
    if n < 8:
        return None
    # frame-to-frame changes: a symbol changes every few frames, while vibration moves
    # texture smoothly (its slow series correlate with anything over few degrees of freedom)
    zs = _zscore_series(np.diff(s, axis=0))
    if zs is None:
        return None
    sig = sigma_px if sigma_px is not None else max(0.7, ref.spot_px / 2.5)
    # the band of candidate shifts: dx in -max_disparity .. +1, dy in -max_dy .. +max_dy
    dys = np.arange(-int(np.ceil(max_dy)), int(np.ceil(max_dy)) + 1)
    dxs = np.arange(-int(np.ceil(max_disparity)), 2)
    c = ref.centers
    pad = int(np.ceil(3 * sig)) + 1
    x0 = int(np.floor(c[:, 0].min() + dxs[0])) - pad
    x1 = int(np.ceil(c[:, 0].max() + dxs[-1])) + pad + 1
    y0 = int(np.floor(c[:, 1].min() + dys[0])) - pad
    y1 = int(np.ceil(c[:, 1].max() + dys[-1])) + pad + 1
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(W, x1), min(H, y1)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return None
    sub = np.diff(ndimage.gaussian_filter(f[:, y0:y1, x0:x1].astype(np.float32), (0, sig, sig), mode="nearest"),
                  axis=0)
    sub -= sub.mean(axis=0, keepdims=True)
    rms = np.sqrt((sub * sub).mean(axis=0))
    zr = sub / np.maximum(rms, 1e-6)[None]  # (n, h, w); a constant pixel correlates 0
    h, w = zr.shape[1:]
    # per LED its correlation map, sampled at the LED's centre moved by every shift
    score = np.zeros((dys.size, dxs.size))
    count = np.zeros_like(score)
    for i in range(zs.shape[1]):
        cmap = np.tensordot(zs[:, i], zr, axes=(0, 0)) / (n - 1)  # (h, w) Pearson correlation
        xi = np.rint(c[i, 0] + dxs - x0).astype(np.int64)
        yi = np.rint(c[i, 1] + dys - y0).astype(np.int64)
        okx = (xi >= 0) & (xi < w)
        oky = (yi >= 0) & (yi < h)
        sub_map = cmap[np.clip(yi, 0, h - 1)][:, np.clip(xi, 0, w - 1)]
        valid = oky[:, None] & okx[None, :]
        score += np.where(valid, sub_map, 0.0)
        count += valid
    score = np.where(count > 0, score / np.maximum(count, 1), -1.0)
    j = int(np.argmax(score))
    iy, ix = np.unravel_index(j, score.shape)
    best = float(score[iy, ix])
    inside = score[count > 0]
    med = float(np.median(inside))
    mad = 1.4826 * float(np.median(np.abs(inside - med)))
    if best < min_correlation or best - med < min_contrast * max(mad, 1e-3):
        return None
    dx = float(dxs[ix]) + _vertex(score[iy, ix - 1:ix + 2] if 0 < ix < dxs.size - 1 else None)
    dy = float(dys[iy]) + _vertex(score[iy - 1:iy + 2, ix] if 0 < iy < dys.size - 1 else None)
    guess = ref.shifted(dx, dy)
    if ref.rows * ref.cols == 1:
        # one LED: the centroid of the correlation peak (the light map's centroid would be
        # pulled by texture that vibration moves; the correlation is not)
        cx, cy = _peak_centroid(score, iy, ix)  # (shift index j samples pixel rint(c) + shift j)
        return GridFit((float(np.rint(c[0, 0])) + dxs[0] + cx, float(np.rint(c[0, 1])) + dys[0] + cy), 0.0, 1, 1,
                       score=best,
                       spot_px=ref.spot_px)
    # an array: the grid fitted to the other camera's light where the shift says it is (as
    # the camera's own detection fits it, :func:`iscd.decode.tracking.detect.detect_array`)
    lm = light_map(np.ascontiguousarray(f))
    try:
        fit = fit_grid(lm, ref.rows, ref.cols, region=guess.bbox(margin=3.0))
    except ValueError:
        fit = guess
    if np.hypot(fit.center[0] - guess.center[0], fit.center[1] - guess.center[1]) > 1.0 or \
            abs(fit.pitch_px - ref.pitch_px) > 0.15 * ref.pitch_px:
        fit = guess  # (texture in the box pulled the fit away)
    return GridFit(fit.origin, fit.pitch_px, ref.rows, ref.cols, score=best, spot_px=max(fit.spot_px, ref.spot_px))


def _peak_centroid(score: np.ndarray, iy: int, ix: int, half: int = 2) -> tuple[float, float]:
    """(x, y) index-space centroid of ``score`` above half its peak within ``half`` cells of
    the peak at (iy, ix)."""
    y0, y1 = max(0, iy - half), min(score.shape[0], iy + half + 1)
    x0, x1 = max(0, ix - half), min(score.shape[1], ix + half + 1)
    w = np.clip(score[y0:y1, x0:x1] - 0.5 * score[iy, ix], 0.0, None)
    tot = float(w.sum())
    if tot <= 0:
        return float(ix), float(iy)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    return float((w * xx).sum() / tot), float((w * yy).sum() / tot)


def _vertex(y3: np.ndarray | None) -> float:
    """Offset (-0.5 .. 0.5) of the vertex of the parabola through three equally spaced
    scores around a maximum (0 without neighbours or curvature)."""
    if y3 is None or y3.size != 3:
        return 0.0
    den = float(y3[0] - 2 * y3[1] + y3[2])
    if den >= 0:
        return 0.0
    return float(np.clip(0.5 * (y3[0] - y3[2]) / den, -0.5, 0.5))
