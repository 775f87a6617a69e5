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
bilinearly) in compiled loops; :func:`square_grid_compiled` is
:func:`iscd.decode.tracking.detect.square_grid` (an array's centres put back on a square grid).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from iscd.core.jit import njit, register_warm
from iscd.decode.tracking.detect import GridFit, track_on_light


@njit
def _fold(frames, x0: int, y0: int, acc_sum: np.ndarray, acc_min: np.ndarray) -> None:
    """acc_sum (int64) += frames' window, acc_min (the frames' dtype) = min(acc_min,
    window); window (h, w) at x0, y0. Native integer arithmetic: it vectorizes (8 and 16
    bits: :func:`_fold_part`, narrow partial sums)."""
    n = frames.shape[0]
    h, w = acc_sum.shape
    if n == 0:
        return
    probe = np.zeros(1, frames.dtype)
    probe[0] = -1
    unsigned = probe[0] > 0
    if frames.itemsize == 1 and unsigned:  # 16-bit sums of up to 257 frames (255 * 257 = 65535)
        _fold_part(frames, x0, y0, acc_sum, acc_min, np.empty((h, w), np.uint16), 257)
    elif frames.itemsize == 1:  # int8: 32-bit sums
        _fold_part(frames, x0, y0, acc_sum, acc_min, np.empty((h, w), np.int32), 1 << 23)
    elif frames.itemsize == 2 and unsigned:  # 32-bit sums of up to 65537 frames
        _fold_part(frames, x0, y0, acc_sum, acc_min, np.empty((h, w), np.uint32), 65537)
    else:  # wider integers: straight into int64
        for f in range(n):
            for a in range(h):
                row = frames[f, y0 + a, x0:x0 + w]
                sa = acc_sum[a]
                ma = acc_min[a]
                for b in range(w):
                    sa[b] += row[b]
                    ma[b] = min(ma[b], row[b])


@njit
def _fold_part(frames, x0: int, y0: int, acc_sum: np.ndarray, acc_min: np.ndarray, part: np.ndarray,
               chunk: int) -> None:
    """:func:`_fold` with the frames summed ``chunk`` at a time in ``part`` (h, w) of a narrow
    type they cannot overflow (twice the lanes of int32 for 8-bit frames), two frames per
    pass over the window (half the passes over the sums and minima, which stay in cache)."""
    n = frames.shape[0]
    h, w = acc_sum.shape
    f0 = 0
    while f0 < n:
        f1 = min(n, f0 + chunk)
        part[:] = 0
        f = f0
        while f + 2 <= f1:
            for a in range(h):
                r0 = frames[f, y0 + a, x0:x0 + w]
                r1 = frames[f + 1, y0 + a, x0:x0 + w]
                pa = part[a]
                ma = acc_min[a]
                for b in range(w):
                    pa[b] += r0[b] + r1[b]
                    ma[b] = min(ma[b], min(r0[b], r1[b]))
            f += 2
        if f < f1:
            for a in range(h):
                r0 = frames[f, y0 + a, x0:x0 + w]
                pa = part[a]
                ma = acc_min[a]
                for b in range(w):
                    pa[b] += r0[b]
                    ma[b] = min(ma[b], r0[b])
        for a in range(h):
            sa = acc_sum[a]
            pa = part[a]
            for b in range(w):
                sa[b] += pa[b]
        f0 = f1


@njit
def _light(acc_sum: np.ndarray, acc_min: np.ndarray, frames: int, out: np.ndarray) -> None:
    """out (h, w) float32 = acc_sum / frames - acc_min (numpy's arithmetic: float64, then
    rounded to float32)."""
    h, w = acc_sum.shape
    for a in range(h):
        sa = acc_sum[a]
        ma = acc_min[a]
        oa = out[a]
        for b in range(w):
            oa[b] = np.float32(sa[b] / frames - ma[b])


def _warm(dtype: type) -> tuple:
    return (np.zeros((2, 4, 4), dtype), 0, 0, np.zeros((2, 2), np.int64), np.zeros((2, 2), dtype))


def _warm_l(dtype: type) -> tuple:
    return (np.zeros((2, 2), np.int64), np.zeros((2, 2), dtype), 2, np.empty((2, 2), np.float32))


for _dt in (np.uint8, np.uint16):
    register_warm(_fold, lambda _dt=_dt: _warm(_dt))
    register_warm(_light, lambda _dt=_dt: _warm_l(_dt))


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
            fl = fr.flags
            _fold(fr if fl.c_contiguous and fl.writeable else np.require(fr, requirements=["C", "W"]),
                  x0, y0, self._sum, self._min)
        self.frames += fr.shape[0]

    def light_map(self) -> np.ndarray:
        """(h, w) float32: temporal mean minus temporal minimum over the frames added."""
        if self.frames == 0:
            raise ValueError("no frames added")
        if self._min is None or not self._sum.size:
            mn = self._min if self._min is not None else np.zeros(self._sum.shape, np.uint8)
            return (self._sum / self.frames - mn).astype(np.float32)
        out = np.empty(self._sum.shape, np.float32)
        _light(self._sum, self._min, int(self.frames), out)
        return out


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
def _bin_of(hist: np.ndarray, nbins: int, kth: int) -> tuple[int, int, int]:
    """The bin of the ``kth`` smallest (0-based) value counted in ``hist`` (``nbins`` bins, 4
    interleaved copies: bin j's count is hist[4 j:4 j + 4].sum()), the rank of that value
    within its bin and the bin's count."""
    c = 0
    for j in range(nbins):
        cj = hist[4 * j] + hist[4 * j + 1] + hist[4 * j + 2] + hist[4 * j + 3]
        if c + cj > kth:
            return j, kth - c, cj
        c += cj
    return nbins - 1, 0, 0  # (not reached: kth < the count)


@njit
def _median_f32(x: np.ndarray) -> float:
    """np.median of the float32 values ``x`` (1-D) as float64, exactly (the same order
    statistics, the same ``(a + b) / 2``), by a radix selection on their bits (11, 11 and 10
    bits; the values' keys ordered as the floats): three counting passes instead of a
    quickselect's data-dependent partitions. NaN anywhere: np.median."""
    n = x.size
    if n == 0:
        return np.nan
    for i in range(n):
        if x[i] != x[i]:
            return np.median(x.astype(np.float64))
    u = x.view(np.uint32)
    keys = np.empty(n, np.uint32)
    for i in range(n):  # order-preserving keys: negatives all bits flipped, others the sign bit set
        v = np.uint32(u[i])
        keys[i] = ~v if (v >> np.uint32(31)) != 0 else v | np.uint32(0x80000000)
    half = n >> 1
    even = (n & 1) == 0
    kth = half - 1 if even else half
    hist = np.zeros(4 * 2048, np.int32)  # 4 interleaved copies: shorter chains of equal bins
    for i in range(n):
        hist[(np.int64(keys[i] >> np.uint32(21)) << 2) | (i & 3)] += 1
    b1, r, _ = _bin_of(hist, 2048, kth)
    cand = np.empty(n, np.uint32)
    m = 0
    for i in range(n):  # branch-free compaction (about half of them match: unpredictable)
        kv = keys[i]
        cand[m] = kv
        m += 1 if np.int64(kv >> np.uint32(21)) == b1 else 0
    hist[:] = 0
    for i in range(m):
        hist[(np.int64((cand[i] >> np.uint32(10)) & np.uint32(0x7FF)) << 2) | (i & 3)] += 1
    b2, r, _ = _bin_of(hist, 2048, r)
    pre = (b1 << 11) | b2
    m2 = 0
    for i in range(m):
        kv = cand[i]
        cand[m2] = kv
        m2 += 1 if np.int64(kv >> np.uint32(10)) == pre else 0
    hist[:4096] = 0
    for i in range(m2):
        hist[(np.int64(cand[i] & np.uint32(0x3FF)) << 2) | (i & 3)] += 1
    b3, r, cnt = _bin_of(hist, 1024, r)
    ka = (pre << 10) | b3
    a = _f32_of_key(ka)
    if not even:
        return a
    if r + 1 < cnt:  # the next order statistic is the same value
        return (a + a) / 2
    nxt = np.uint32(0xFFFFFFFF)  # else the smallest key above
    kka = np.uint32(ka)
    for i in range(n):
        kv = keys[i]
        if kv > kka and kv < nxt:
            nxt = kv
    return (a + _f32_of_key(np.int64(nxt))) / 2


@njit
def _f32_of_key(k: int) -> float:
    """The float32 value (as float64) of an order-preserving key (:func:`_median_f32`)."""
    v = np.uint32(k)
    bits = v & np.uint32(0x7FFFFFFF) if (v >> np.uint32(31)) != 0 else ~v
    arr = np.empty(1, np.uint32)
    arr[0] = bits
    return np.float64(arr.view(np.float32)[0])


@njit
def _smooth_light(light: np.ndarray, sigma: float, out: np.ndarray) -> bool:
    """out (h, w) float64 = gaussian_filter(max(light - median(light), 0), sigma) (scipy's
    separable filter, rows first, 'reflect' edges); False if nothing is above the median.
    The median by :func:`_median_f32` (exact); each output the same sums in the same order
    as scipy's loops, the inner loops along rows (they vectorize)."""
    h, w = light.shape
    med = _median_f32(light.reshape(h * w))
    act = np.empty((h, w))
    anything = False
    for a in range(h):
        la = light[a]
        aa = act[a]
        for b in range(w):
            v = float(la[b]) - med
            aa[b] = v if v > 0 else 0.0
    for a in range(h):
        aa = act[a]
        for b in range(w):
            if aa[b] > 0:
                anything = True
                break
        if anything:
            break
    _gauss_filter(act, _gauss_taps(sigma), out)
    return anything


@njit
def _gauss_filter(act: np.ndarray, k: np.ndarray, out: np.ndarray) -> None:
    """out (h, w) = the separable filter ``k`` (2 r + 1 taps) of ``act`` (h, w), rows first,
    'reflect' edges: each output the sum over the taps in order from 0.0 (scipy's
    arithmetic). Seven taps (sigma 0.7, the tracking's) summed in registers along the rows
    (it vectorizes); other sizes tap by tap."""
    h, w = act.shape
    r = (k.size - 1) // 2
    tmp = np.empty((h, w + 2 * r)) if r == 3 else np.zeros((h, w + 2 * r))
    if r == 3:
        k0, k1, k2, k3, k4, k5, k6 = k[0], k[1], k[2], k[3], k[4], k[5], k[6]
        for a in range(h):  # axis 0, reflected rows read in place
            ta = tmp[a, 3:3 + w]
            q0 = act[_reflect(a - 3, h)]
            q1 = act[_reflect(a - 2, h)]
            q2 = act[_reflect(a - 1, h)]
            q3 = act[a]
            q4 = act[_reflect(a + 1, h)]
            q5 = act[_reflect(a + 2, h)]
            q6 = act[_reflect(a + 3, h)]
            for b in range(w):
                ta[b] = ((((((0.0 + k0 * q0[b]) + k1 * q1[b]) + k2 * q2[b]) + k3 * q3[b]) + k4 * q4[b])
                         + k5 * q5[b]) + k6 * q6[b]
    else:
        for a in range(h):
            ta = tmp[a, r:r + w]
            for t in range(2 * r + 1):
                kt = k[t]
                pa = act[_reflect(a + t - r, h)]
                for b in range(w):
                    ta[b] += kt * pa[b]
    for a in range(h):
        for t in range(r):
            tmp[a, t] = tmp[a, r + _reflect(t - r, w)]
            tmp[a, r + w + t] = tmp[a, r + _reflect(w + t, w)]
    if r == 3:
        k0, k1, k2, k3, k4, k5, k6 = k[0], k[1], k[2], k[3], k[4], k[5], k[6]
        for a in range(h):  # axis 1
            oa = out[a]
            ta = tmp[a]
            for b in range(w):
                oa[b] = ((((((0.0 + k0 * ta[b]) + k1 * ta[b + 1]) + k2 * ta[b + 2]) + k3 * ta[b + 3])
                          + k4 * ta[b + 4]) + k5 * ta[b + 5]) + k6 * ta[b + 6]
    else:
        for a in range(h):
            oa = out[a]
            for b in range(w):
                oa[b] = 0.0
            for t in range(2 * r + 1):
                kt = k[t]
                ta = tmp[a, t:t + w]
                for b in range(w):
                    oa[b] += kt * ta[b]


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


@njit
def square_grid_compiled(centres: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """:func:`iscd.decode.tracking.detect.square_grid` in one loop (the same closed form):
    (rows * cols, 2) centres (x, y), px, onto the nearest square grid, px."""
    n = rows * cols
    mx = 0.0
    my = 0.0
    for i in range(n):
        mx += centres[i, 0]
        my += centres[i, 1]
    mx /= n
    my /= n
    hc = (cols - 1) / 2.0
    hr = (rows - 1) / 2.0
    num = 0.0
    den = 0.0
    for i in range(n):
        gc = float(i % cols) - hc
        gr = float(i // cols) - hr
        num += gc * (centres[i, 0] - mx) + gr * (centres[i, 1] - my)
        den += gc * gc + gr * gr
    p = num / den if den > 0 else 0.0
    out = np.empty((n, 2))
    for i in range(n):
        out[i, 0] = mx + p * (float(i % cols) - hc)
        out[i, 1] = my + p * (float(i // cols) - hr)
    return out


register_warm(square_grid_compiled, lambda: (np.zeros((4, 2)), 2, 2))
