"""The tracking's light map accumulated block by block (compiled), instead of keeping the
frames of a tracking interval and reducing them at its end.

:func:`iscd.decode.tracking.detect.light_map` of a block of frames is the temporal mean minus the
temporal minimum of each pixel (grey levels). Both are running reductions, so
:class:`LightAccumulator` folds each block's window into a sum and a minimum as it
arrives (one pass over the window's pixels, no copies) and gives the same map at the end
of the interval (float tolerance: the mean is summed in float64 where the reference sums
in float32; ``tests/test_frame_kernels.py``).

:func:`track_on_light_compiled` is :func:`iscd.decode.tracking.detect.track_on_light` (the grid
search on that map: median removed, Gaussian smoothing, 75 candidate grids sampled
bilinearly) in compiled loops.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from iscd.core.jit import njit, register_warm
from iscd.decode.tracking.detect import GridFit, track_on_light


@njit
def _fold(frames, x0: int, y0: int, acc_sum: np.ndarray, acc_min: np.ndarray) -> None:
    """acc_sum (int64) += frames' window, acc_min (the frames' dtype) = min(acc_min,
    window); window (h, w) at x0, y0. Native integer arithmetic: it vectorizes."""
    h, w = acc_sum.shape
    for f in range(frames.shape[0]):
        for a in range(h):
            row = frames[f, y0 + a, x0:x0 + w]
            sa = acc_sum[a]
            ma = acc_min[a]
            for b in range(w):
                sa[b] += row[b]
                ma[b] = min(ma[b], row[b])


def _warm(dtype: type) -> tuple:
    return (np.zeros((2, 4, 4), dtype), 0, 0, np.zeros((2, 2), np.int64), np.zeros((2, 2), dtype))


register_warm(_fold, lambda: _warm(np.uint8))
register_warm(_fold, lambda: _warm(np.uint16))


class LightAccumulator:
    """Running sum and minimum of a fixed window (x0, y0, x1, y1) px over blocks of frames."""

    def __init__(self, window: tuple[int, int, int, int]) -> None:
        self.window = window
        x0, y0, x1, y1 = window
        h, w = max(0, y1 - y0), max(0, x1 - x0)
        self._sum = np.zeros((h, w), np.int64)
        self._min: np.ndarray | None = None  # of the frames' dtype, made by the first block
        self.frames = 0

    def add(self, frames: np.ndarray) -> None:
        """Fold a block (F, H, W) of integer frames in (its window's pixels only).

        Parameters
        ----------
        frames : ndarray
            (F, H, W) integer frames, DN; the window must lie inside them.

        Raises
        ------
        ValueError
            If the frames are not integer or the window lies outside them.
        """
        fr = np.asarray(frames)
        if fr.dtype.kind not in "ui":
            raise ValueError(f"LightAccumulator takes integer frames, got {fr.dtype}")
        if self._sum.size and fr.shape[0]:
            x0, y0, x1, y1 = self.window
            if x1 > fr.shape[2] or y1 > fr.shape[1]:
                raise ValueError(f"window {self.window} outside frames of {fr.shape[2]}x{fr.shape[1]}")
            if self._min is None or self._min.dtype != fr.dtype:
                self._min = np.full(self._sum.shape, np.iinfo(fr.dtype).max, fr.dtype)
            _fold(np.require(fr, requirements=["C", "W"]), x0, y0, self._sum, self._min)
        self.frames += fr.shape[0]

    def light_map(self) -> np.ndarray:
        """(h, w) float32: temporal mean minus temporal minimum over the frames added."""
        if self.frames == 0:
            raise ValueError("no frames added")
        mn = self._min if self._min is not None else np.zeros(self._sum.shape, np.uint8)
        return (self._sum / self.frames - mn).astype(np.float32)


# ---------------------------------------------------------------- the grid search on the map
_STEPS = np.arange(-0.5, 0.51, 0.25)
_SCALES = np.array([0.98, 1.0, 1.02])
_DX, _DY, _SC = (a.ravel() for a in np.meshgrid(_STEPS, _STEPS, _SCALES, indexing="ij"))


@njit
def _gauss_taps(sigma: float) -> np.ndarray:
    """scipy.ndimage.gaussian_filter's 1-D kernel (truncate = 4 sigma)."""
    r = int(4.0 * sigma + 0.5)
    k = np.empty(2 * r + 1)
    s = 0.0
    for i in range(-r, r + 1):
        k[i + r] = np.exp(-0.5 * i * i / (sigma * sigma))
        s += k[i + r]
    return k / s


@njit
def _reflect(i: int, n: int) -> int:
    """scipy's 'reflect' boundary (d c b a | a b c d | d c b a) for an index near the edge."""
    while i < 0 or i >= n:
        if i < 0:
            i = -i - 1
        if i >= n:
            i = 2 * n - i - 1
    return i


@njit
def _smooth_light(light: np.ndarray, sigma: float, out: np.ndarray) -> bool:
    """out (h, w) float64 = gaussian_filter(max(light - median(light), 0), sigma) (scipy's
    separable filter, rows first, 'reflect' edges); False if nothing is above the median."""
    h, w = light.shape
    act = np.empty((h, w))
    for a in range(h):
        for b in range(w):
            act[a, b] = light[a, b]
    med = np.median(act)
    anything = False
    for a in range(h):
        for b in range(w):
            v = act[a, b] - med
            if v > 0:
                anything = True
            act[a, b] = v if v > 0 else 0.0
    k = _gauss_taps(sigma)
    r = (k.size - 1) // 2
    # reflect-padded copies (scipy's 'reflect'), then plain separable loops
    pad = np.empty((h + 2 * r, w))
    for a in range(h + 2 * r):
        pad[a] = act[_reflect(a - r, h)]
    tmp = np.zeros((h, w + 2 * r))
    for a in range(h):  # axis 0
        ta = tmp[a, r:r + w]
        for t in range(2 * r + 1):
            kt = k[t]
            pa = pad[a + t]
            for b in range(w):
                ta[b] += kt * pa[b]
    for a in range(h):
        for t in range(r):
            tmp[a, t] = tmp[a, r + _reflect(t - r, w)]
            tmp[a, r + w + t] = tmp[a, r + _reflect(w + t, w)]
    for a in range(h):  # axis 1
        oa = out[a]
        ta = tmp[a]
        for b in range(w):
            s = 0.0
            for t in range(2 * r + 1):
                s += k[t] * ta[b + t]
            oa[b] = s
    return anything


@njit
def _sample(img: np.ndarray, y: float, x: float) -> float:
    """Bilinear sample at (y, x) px; 0 outside [0, h-1] x [0, w-1] (map_coordinates
    order=1, mode='constant', cval=0)."""
    h, w = img.shape
    if not (y >= 0.0 and y <= h - 1 and x >= 0.0 and x <= w - 1):
        return 0.0
    ya = int(np.floor(y))
    xa = int(np.floor(x))
    fy = y - ya
    fx = x - xa
    yb = min(ya + 1, h - 1)
    xb = min(xa + 1, w - 1)
    return ((1 - fy) * ((1 - fx) * img[ya, xa] + fx * img[ya, xb])
            + fy * ((1 - fx) * img[yb, xa] + fx * img[yb, xb]))


@njit
def _grid_scores(smooth: np.ndarray, ox: np.ndarray, oy: np.ndarray, p: np.ndarray, rows: int,
                 cols: int, out: np.ndarray) -> None:
    """Mean of ``smooth`` sampled at each candidate grid (origin ox, oy; pitch p), (m,)."""
    for k in range(ox.size):
        s = 0.0
        for r in range(rows):
            y = oy[k] + r * p[k]
            for c in range(cols):
                s += _sample(smooth, y, ox[k] + c * p[k])
        out[k] = s / (rows * cols)


register_warm(_smooth_light, lambda: (np.ones((8, 8), np.float32), 0.7, np.empty((8, 8))))
register_warm(_grid_scores, lambda: (np.ones((8, 8)), np.zeros(2), np.zeros(2), np.ones(2), 2, 2, np.empty(2)))


def track_on_light_compiled(light: np.ndarray, prev: GridFit, x0: int, y0: int) -> GridFit:
    """The compiled :func:`iscd.decode.tracking.detect.track_on_light` (same result to float
    tolerance) for an array; one LED goes to the reference.

    Parameters
    ----------
    light : ndarray
        (h, w) light map of the tracking window (:meth:`LightAccumulator.light_map`), DN.
    prev : GridFit
        The previous fit, image px.
    x0, y0 : int
        The window's top-left pixel in the image, px.

    Returns
    -------
    GridFit
        The refined fit, image px.

    Raises
    ------
    ValueError
        If the window has no modulated light.
    """
    if prev.rows * prev.cols == 1:
        return track_on_light(light, prev, x0, y0)
    lt = np.require(light, dtype=np.float32, requirements=["C", "W"])
    smooth = np.empty(lt.shape)
    if not _smooth_light(lt, 0.7, smooth):
        raise ValueError("no modulated light in the tracking window")
    p = prev.pitch_px * _SC
    cx, cy = prev.center
    cx, cy = cx - x0 + _DX, cy - y0 + _DY
    ox = cx - (prev.cols - 1) / 2 * p
    oy = cy - (prev.rows - 1) / 2 * p
    score = np.empty(p.size)
    _grid_scores(smooth, ox, oy, p, prev.rows, prev.cols, score)
    k = int(np.argmax(score))
    return replace(prev, origin=(float(ox[k] + x0), float(oy[k] + y0)), pitch_px=float(p[k]),
                   score=float(score[k]))
