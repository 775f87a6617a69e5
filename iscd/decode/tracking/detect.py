"""Detection of LEDs and LED arrays from spatial and temporal gradients, and grid fitting.

The dissertation finds the LED array with the spatial and temporal gradients of the image
sequence (Sobel on a frame and between neighbouring frames, its reference [71]) and each
LED's position by contour detection ([81]). Here:

1. :func:`activity_map`: the temporal gradient, mean |I[n+1] - I[n]| over a block of frames
   (grey levels per frame). A transmitting LED changes level every symbol, so it is
   active; a steady light (street lamp, glint) and the static background are not — their
   frame differences are only sensor noise.
2. :func:`spatial_gradient`: the Sobel gradient magnitude of the block's mean frame; a
   light source is a compact bright spot with strong edges.
3. :func:`find_blobs`: threshold the activity above the noise (robust MAD estimate),
   contours (``cv2.findContours``), keep blobs whose edges show in the spatial gradient.
4. :func:`fit_grid`: the configured ``rows x cols`` grid (row-major LED order, axis
   aligned; a car's roll is small) fitted to the activity map: pitch and origin maximise
   the activity sampled at the grid points. At 50 m the LEDs of an 8x8 array are 4.2 px
   apart and their spots touch, so the grid is fitted to the whole array, never to single
   contours.

All coordinates are in px, x right and y down, pixel centres at integers.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from functools import cached_property

import cv2
import numpy as np
from scipy import ndimage, optimize

from iscd.decode.tracking.maps_kernel import activity_map, look_maps  # noqa: F401 (activity_map: part of this module's API)


@functools.lru_cache(maxsize=64)
def _grid_index(rows: int, cols: int) -> np.ndarray:
    """(rows * cols, 2) float64 (column, row) of each LED, row-major LED order (read-only)."""
    r, c = np.divmod(np.arange(rows * cols, dtype=np.float64), cols)
    out = np.stack([c, r], axis=1)
    out.setflags(write=False)
    return out


@dataclass(frozen=True)
class GridFit:
    """An LED array (or one LED) located in one camera.

    origin: (x, y) of LED 0 (top-left), px. pitch_px: LED spacing, px (0 for one LED).
    rows, cols: the configured layout. score: mean activity at the grid points (grey
    levels per frame). spot_px: estimated spot diameter, px.
    """

    origin: tuple[float, float]
    pitch_px: float
    rows: int
    cols: int
    score: float
    spot_px: float = 3.0

    @cached_property
    def centers(self) -> np.ndarray:
        """(N, 2) LED centres (x, y) in px, row-major LED order (read-only; computed once:
        the fit is frozen)."""
        out = _grid_index(self.rows, self.cols) * self.pitch_px
        out[:, 0] += self.origin[0]
        out[:, 1] += self.origin[1]
        out.setflags(write=False)
        return out

    @property
    def center(self) -> tuple[float, float]:
        """Centre of the array, px."""
        return (self.origin[0] + (self.cols - 1) / 2 * self.pitch_px,
                self.origin[1] + (self.rows - 1) / 2 * self.pitch_px)

    def bbox(self, margin: float = 0.0) -> tuple[int, int, int, int]:
        """Integer (x0, y0, x1, y1) bounds (x1, y1 exclusive) of the array plus ``margin`` px.

        Parameters
        ----------
        margin : float
            Added on every side beyond the LED spots (half ``spot_px`` around the outer
            centres), px.

        Returns
        -------
        tuple of int
            (x0, y0, x1, y1), px (not clipped to the image).
        """
        half = self.spot_px / 2 + margin
        xs = (self.origin[0], self.origin[0] + (self.cols - 1) * self.pitch_px)
        ys = (self.origin[1], self.origin[1] + (self.rows - 1) * self.pitch_px)
        return (int(np.floor(xs[0] - half)), int(np.floor(ys[0] - half)),
                int(np.ceil(xs[1] + half)) + 1, int(np.ceil(ys[1] + half)) + 1)

    def shifted(self, dx: float, dy: float) -> "GridFit":
        """The same fit with its origin moved by (dx, dy).

        Parameters
        ----------
        dx, dy : float
            Shift, px.

        Returns
        -------
        GridFit
            A copy with ``origin`` + (dx, dy).
        """
        return GridFit((self.origin[0] + dx, self.origin[1] + dy), self.pitch_px, self.rows, self.cols,
                       self.score, self.spot_px)


def square_grid(centres: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """The square, axis-aligned grid nearest to an array's LED centres, px.

    The model of :class:`GridFit` (an origin and one pitch, row-major LED order), fitted by
    least squares in closed form: with each LED's column c and row r,
    p = sum((c - c_mean)(x - x_mean) + (r - r_mean)(y - y_mean)) / sum((c - c_mean)^2 + (r - r_mean)^2),
    the grid centred on the centres' mean. The reference of
    :func:`iscd.decode.tracking.track_kernel.square_grid_compiled`.

    Parameters
    ----------
    centres : ndarray
        (rows * cols, 2) LED centres (x, y), px.
    rows, cols : int
        The array's shape (more than one LED).

    Returns
    -------
    ndarray
        (rows * cols, 2) the grid's LED centres, px.
    """
    g = _grid_index(rows, cols) - np.array([(cols - 1) / 2, (rows - 1) / 2])
    m = centres.mean(axis=0)
    p = float((g * (centres - m)).sum() / (g * g).sum())
    return m + p * g


@dataclass(frozen=True)
class Blob:
    """A connected active region: centroid (x, y) px, area px², peak activity, bbox."""

    x: float
    y: float
    area: float
    peak: float
    bbox: tuple[int, int, int, int]


def light_map(frames: np.ndarray) -> np.ndarray:
    """Modulated light: temporal mean minus temporal minimum, (H, W) float32 grey levels.

    Peaks at each LED's centre even when the LED saturates (its core then sits at 255 for
    all bright levels and shows little temporal gradient, so the activity map is a ring);
    a steady light or the background gives only a few noise RMS.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN.

    Returns
    -------
    ndarray of float32
        (H, W) modulated light, DN.
    """
    f = np.asarray(frames)
    return f.mean(axis=0, dtype=np.float32) - f.min(axis=0).astype(np.float32)


def spatial_gradient(image: np.ndarray) -> np.ndarray:
    """Sobel gradient magnitude of ``image`` (grey levels per px), float32.

    Parameters
    ----------
    image : ndarray
        (H, W) image, DN.

    Returns
    -------
    ndarray of float32
        (H, W) gradient magnitude (3x3 Sobel), DN/px.
    """
    im = np.asarray(image, dtype=np.float32)
    gx = cv2.Sobel(im, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(im, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.magnitude(gx, gy)


def noise_level(act: np.ndarray) -> float:
    """Robust noise level of an activity map: median + 1.4826 * MAD (grey levels/frame).

    Parameters
    ----------
    act : ndarray
        (H, W) activity map (:func:`activity_map`), DN per frame.

    Returns
    -------
    float
        The noise level, DN per frame.
    """
    med = float(np.median(act))
    mad = float(np.median(np.abs(act - med)))
    return med + 1.4826 * mad


def find_blobs(act: np.ndarray, mean_frame: np.ndarray | None = None, *, k_sigma: float = 8.0,
               min_activity: float = 4.0, min_edge: float = 8.0) -> list[Blob]:
    """Active compact regions of an activity map, strongest first.

    A pixel is active above ``max(min_activity, median + k_sigma * 1.4826 MAD)`` (MAD at
    least 0.05). Each contour's blob must show a spatial edge (Sobel magnitude of
    ``mean_frame`` >= ``min_edge`` grey levels/px somewhere inside) when ``mean_frame`` is
    given.

    Parameters
    ----------
    act : ndarray
        (H, W) activity map (:func:`activity_map`), DN per frame.
    mean_frame : ndarray, optional
        (H, W) mean frame of the same block, DN; None skips the edge test.
    k_sigma : float
        Threshold above the median, robust noise RMS.
    min_activity : float
        Least threshold, DN per frame.
    min_edge : float
        Least Sobel magnitude inside a blob, DN/px.

    Returns
    -------
    list of Blob
        Sorted by peak activity x area, largest first.
    """
    med = float(np.median(act))
    mad = float(np.median(np.abs(act - med)))
    thr = max(min_activity, med + k_sigma * 1.4826 * max(mad, 0.05))
    mask = (act > thr).astype(np.uint8)
    if not mask.any():
        return []
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    grad = spatial_gradient(mean_frame) if mean_frame is not None else None
    blobs: list[Blob] = []
    for c in contours:
        x, y, w, h = cv2.boundingRect(c)
        sub = act[y:y + h, x:x + w]
        m = mask[y:y + h, x:x + w].astype(bool)
        wts = np.where(m, sub - thr, 0.0)
        tot = float(wts.sum())
        if tot <= 0:
            continue
        if grad is not None:
            g = grad[max(0, y - 1):y + h + 1, max(0, x - 1):x + w + 1]
            if float(g.max()) < min_edge:
                continue
        yy, xx = np.mgrid[y:y + h, x:x + w]
        blobs.append(Blob(x=float((wts * xx).sum() / tot), y=float((wts * yy).sum() / tot),
                          area=float(m.sum()), peak=float(sub.max()), bbox=(x, y, x + w, y + h)))
    blobs.sort(key=lambda b: -b.peak * b.area)
    return blobs


def group_blobs(blobs: list[Blob], max_gap: float) -> list[list[Blob]]:
    """Cluster blobs whose bounding boxes are closer than ``max_gap`` px (single linkage).

    Parameters
    ----------
    blobs : list of Blob
        The blobs (:func:`find_blobs`).
    max_gap : float
        Largest gap between two bounding boxes (Chebyshev, inclusive) that joins them, px.

    Returns
    -------
    list of list of Blob
        The clusters, by summed peak x area, largest first.
    """
    n = len(blobs)
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            a, b = blobs[i].bbox, blobs[j].bbox
            gx = max(a[0] - b[2], b[0] - a[2], 0)
            gy = max(a[1] - b[3], b[1] - a[3], 0)
            if max(gx, gy) <= max_gap:
                parent[find(i)] = find(j)
    groups: dict[int, list[Blob]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(blobs[i])
    return sorted(groups.values(), key=lambda g: -sum(b.peak * b.area for b in g))


def _grid_score(smooth: np.ndarray, origin: np.ndarray, pitch: float, rows: int, cols: int) -> float:
    r, c = np.mgrid[0:rows, 0:cols]
    xs = origin[0] + c.ravel() * pitch
    ys = origin[1] + r.ravel() * pitch
    vals = ndimage.map_coordinates(smooth, [ys, xs], order=1, mode="constant", cval=0.0)
    return float(vals.mean())


def fit_grid(act: np.ndarray, rows: int, cols: int, region: tuple[int, int, int, int] | None = None,
             pitch_guess: float | None = None, origin_guess: tuple[float, float] | None = None,
             pitch_range: tuple[float, float] = (1.5, 200.0)) -> GridFit:
    """Fit a ``rows x cols`` LED grid to an activity map (see module docstring).

    Without guesses the pitch starts from the second moments of the activity (a uniform grid
    of n points at pitch p has variance p²(n²-1)/12 along that axis) and the origin from its
    centroid.

    Parameters
    ----------
    act : ndarray
        (H, W) activity map, DN per frame (or a light map, :func:`light_map`, DN).
    rows, cols : int
        The configured layout.
    region : (int, int, int, int), optional
        (x0, y0, x1, y1) px to look in (default: the whole map).
    pitch_guess : float, optional
        A previous fit's pitch to refine (tracking), px.
    origin_guess : (float, float), optional
        A previous fit's origin (x, y) to refine, px.
    pitch_range : (float, float)
        Smallest and largest pitch, px.

    Returns
    -------
    GridFit
        Origin and pitch, px; score, the units of ``act``; spot diameter, px.

    Raises
    ------
    ValueError
        If the region is empty or has no activity.
    """
    H, W = act.shape
    x0, y0, x1, y1 = region if region is not None else (0, 0, W, H)
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(W, x1), min(H, y1)
    if x1 - x0 < 2 or y1 - y0 < 2:
        raise ValueError(f"empty region {region}")
    sub = act[y0:y1, x0:x1].astype(np.float64)
    base = np.median(sub) if sub.size > 16 else 0.0
    wts = np.clip(sub - base, 0, None)
    smooth = ndimage.gaussian_filter(wts, 0.7)
    tot = wts.sum()
    if tot <= 0:
        raise ValueError("no activity in the region")
    yy, xx = np.mgrid[0:sub.shape[0], 0:sub.shape[1]]
    mx, my = (wts * xx).sum() / tot, (wts * yy).sum() / tot
    # spot size from the activity above half its peak, per LED
    n_leds = rows * cols
    spot = max(1.0, 2.0 * np.sqrt((wts > 0.5 * wts.max()).sum() / max(n_leds, 1) / np.pi))
    if pitch_guess is None:
        ests = []
        if cols > 1:
            vx = (wts * (xx - mx) ** 2).sum() / tot
            ests.append(np.sqrt(max(vx - (spot / 2.5) ** 2, 1e-6) * 12 / (cols ** 2 - 1)))
        if rows > 1:
            vy = (wts * (yy - my) ** 2).sum() / tot
            ests.append(np.sqrt(max(vy - (spot / 2.5) ** 2, 1e-6) * 12 / (rows ** 2 - 1)))
        pitch_guess = float(np.mean(ests)) if ests else 0.0
    if n_leds == 1:
        return GridFit(origin=(x0 + mx, y0 + my), pitch_px=0.0, rows=1, cols=1,
                       score=float(smooth.max()), spot_px=float(spot))
    if origin_guess is None:
        og = np.array([mx - (cols - 1) / 2 * pitch_guess, my - (rows - 1) / 2 * pitch_guess])
    else:
        og = np.array([origin_guess[0] - x0, origin_guess[1] - y0])
    lo, hi = pitch_range
    best = (-np.inf, og, pitch_guess)
    # coarse search over pitch scale and sub-pitch offsets, then a local polish
    for s in np.linspace(0.9, 1.1, 9):
        p = float(np.clip(pitch_guess * s, lo, hi))
        c0 = np.array([mx, my]) - np.array([(cols - 1) / 2, (rows - 1) / 2]) * p if origin_guess is None else og
        for dx in np.linspace(-0.5, 0.5, 5) * p:
            for dy in np.linspace(-0.5, 0.5, 5) * p:
                o = c0 + (dx, dy)
                sc = _grid_score(smooth, o, p, rows, cols)
                if sc > best[0]:
                    best = (sc, o, p)

    def neg(v: np.ndarray) -> float:
        return -_grid_score(smooth, v[:2], float(np.clip(v[2], lo, hi)), rows, cols)

    res = optimize.minimize(neg, np.array([*best[1], best[2]]), method="Nelder-Mead",
                            options={"xatol": 1e-3, "fatol": 1e-6, "maxiter": 400})
    v = res.x if -res.fun >= best[0] else np.array([*best[1], best[2]])
    p = float(np.clip(v[2], lo, hi))
    return GridFit(origin=(x0 + float(v[0]), y0 + float(v[1])), pitch_px=p, rows=rows, cols=cols,
                   score=float(-neg(v)), spot_px=float(spot))


# --------------------------------------------------------------------------- the array's shape
MAX_GRID_SIDE = 64
"""Largest rows or cols :func:`infer_grid` reports (the PHY header's and the config's limit)."""

MIN_GRID_PITCH_PX = 2.5
"""Least pitch :func:`infer_grid` resolves, px: closer spots merge in the lit map (an 8x8
array of 6 cm pitch at 84 m with the chapter 4 cameras)."""

SPOT_LEVELS = (0.4, 0.55, 0.7)
"""Cuts of the lit map, shares of its robust peak, that :func:`infer_grid` tries: a spot is
a connected region above the cut. Between two LEDs 4.2 px apart the lit map falls to
10-25 % of a spot's peak, 3 px apart (an 8x8 array at 70 m) to about 50 %."""

MIN_GRID_FILL = 0.75
"""Least share of an inferred grid's points with a spot within :data:`GRID_MATCH_PITCH` of
a pitch: a few LEDs that stayed dark over the window are allowed, a scatter is no grid."""

GRID_MATCH_PITCH = 0.35
"""A spot belongs to a grid point within this share of a pitch."""


@dataclass(frozen=True)
class GridShape:
    """An LED grid inferred from the spots of its lit LEDs (:func:`infer_grid`).

    rows, cols: the layout. pitch_px: LED spacing, px (0 for one LED). origin: (x, y) of the
    top-left grid point, px in the map's coordinates. spots: centroids found. fill: share of
    the grid points with a spot.
    """

    rows: int
    cols: int
    pitch_px: float
    origin: tuple[float, float]
    spots: int
    fill: float


def lit_map(frames: np.ndarray) -> np.ndarray:
    """Any-lit map: temporal maximum minus minimum, (H, W) float32, DN.

    Every LED that was lit at some level in the window shows with its brightest spot,
    whatever its PWM levels were on average (a light map, :func:`light_map`, weighs a
    mostly dim LED less); a steady light shows only its noise and vibration.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN.

    Returns
    -------
    ndarray of float32
        (H, W) lit map, DN.
    """
    f = np.asarray(frames)
    return f.max(axis=0).astype(np.float32) - f.min(axis=0).astype(np.float32)


def spot_centroids(lit: np.ndarray, level: float = SPOT_LEVELS[0]) -> np.ndarray:
    """Centroids of the separate lit spots of a lit map.

    The map less its median, smoothed (Gaussian 0.5 px), is cut at ``level`` times its
    robust peak (the 90th percentile of its 3x3 local maxima above half the highest, so a
    few saturated spots or one hot pixel do not set it); each connected region above it is
    one spot, its centroid weighted by the light above the cut.

    Parameters
    ----------
    lit : ndarray
        (h, w) lit map (:func:`lit_map`) of the region holding the source, DN.
    level : float
        The cut, share of the robust peak.

    Returns
    -------
    ndarray
        (n, 2) float64 spot centroids (x, y), px in the map's coordinates (n = 0 if none).
    """
    a = np.asarray(lit, dtype=np.float64)
    if a.ndim != 2 or a.size == 0:
        return np.zeros((0, 2))
    a = np.clip(a - np.median(a), 0.0, None)
    sm = ndimage.gaussian_filter(a, 0.5)
    top = float(sm.max())
    if top <= 0:
        return np.zeros((0, 2))
    peaks = sm[(sm == ndimage.maximum_filter(sm, size=3)) & (sm >= 0.5 * top)]
    thr = level * float(np.percentile(peaks, 90))
    lab, n = ndimage.label(sm > thr)
    if n == 0:
        return np.zeros((0, 2))
    w = np.where(lab > 0, sm - thr, 0.0)
    idx = np.arange(1, n + 1)
    tot = ndimage.sum(w, lab, idx)
    yy, xx = np.indices(sm.shape, dtype=np.float64)
    cx = ndimage.sum(w * xx, lab, idx) / tot
    cy = ndimage.sum(w * yy, lab, idx) / tot
    return np.stack([cx, cy], axis=1)


def _lattice_1d(v: np.ndarray, pitch: float) -> tuple[int, float, float, np.ndarray]:
    """Spots' coordinates ``v`` (px) along one axis on a lattice of about ``pitch`` px.

    The coordinates are clustered (a gap over half a pitch starts a new lattice line);
    each gap between consecutive lines is a whole number of pitches (at least one), rounded
    gap by gap, so that a pitch slightly off does not add up over many lines; the lines'
    positions against their indices give the pitch (least squares).

    Returns
    -------
    tuple
        (lines n, fitted pitch px or nan for one line, position of line 0 px, (len(v),)
        int lattice index of each coordinate).
    """
    order = np.argsort(v)
    vs = v[order]
    cut = np.concatenate([[0], np.flatnonzero(np.diff(vs) > 0.5 * pitch) + 1, [len(vs)]])
    centres = np.array([vs[a:b].mean() for a, b in zip(cut[:-1], cut[1:])])
    steps = np.maximum(1, np.rint(np.diff(centres) / pitch))
    k = np.concatenate([[0.0], np.cumsum(steps)])
    idx = np.empty(len(v), dtype=np.int64)
    for j, (a, b) in enumerate(zip(cut[:-1], cut[1:])):
        idx[order[a:b]] = int(k[j])
    n = int(k[-1]) + 1
    if n == 1:
        return 1, math.nan, float(centres[0]), idx
    A = np.stack([np.ones_like(k), k], axis=1)
    (a0, p), *_ = np.linalg.lstsq(A, centres, rcond=None)
    return n, float(p), float(a0), idx


def infer_grid(lit: np.ndarray, *, min_pitch_px: float = MIN_GRID_PITCH_PX) -> GridShape | None:
    """The rows x cols grid (row-major, axis aligned) of the spots of a lit map.

    For each cut of :data:`SPOT_LEVELS`:

    1. :func:`spot_centroids`: one centroid per lit spot.
    2. Pitch: the median distance of each spot to its nearest neighbour (most spots of a
       grid have one a pitch away, whatever few are dark).
    3. The centroids' x and their y are put on lattices of that pitch (each coordinate's
       lattice index rounded from the leftmost / topmost spot; least squares line of
       coordinate against index): cols and rows are the index ranges, so a dark LED --
       even a whole dark inner column -- leaves the shape as it is. The pitch is the mean
       of the two axes' fits (the grid is square).
    4. Accepted if every spot is within :data:`GRID_MATCH_PITCH` of a pitch of its grid
       point (a stray light in the region makes it no grid) and at least
       :data:`MIN_GRID_FILL` of the grid points have a spot.

    The accepted grid of the most spots wins (spots that touch at a low cut are one spot,
    and a grid of merged spots is a coarser grid, never a finer one).

    Parameters
    ----------
    lit : ndarray
        (h, w) lit map (:func:`lit_map`) of the region holding the source, DN.
    min_pitch_px : float
        Spots closer than this are one spot (no grid is inferred finer), px.

    Returns
    -------
    GridShape or None
        The grid (origin px in the map's coordinates); one spot gives 1x1 with pitch 0 (an
        array too far to resolve is one spot too: :func:`detect_auto` tells them apart);
        None when nothing is lit or the spots make no grid.
    """
    best: GridShape | None = None
    for level in SPOT_LEVELS:
        g = _grid_of_spots(spot_centroids(lit, level), min_pitch_px)
        if g is not None and (best is None or g.spots > best.spots):
            best = g
    return best


def _grid_of_spots(pts: np.ndarray, min_pitch_px: float) -> GridShape | None:
    """Steps 2-4 of :func:`infer_grid` on spot centroids ``pts`` (n, 2) px."""
    n = len(pts)
    if n == 0:
        return None
    if n == 1:
        return GridShape(1, 1, 0.0, (float(pts[0, 0]), float(pts[0, 1])), 1, 1.0)
    d = np.sqrt(((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    p0 = float(np.median(d.min(axis=1)))
    if not p0 >= min_pitch_px:
        return None
    cols, px, _, ix = _lattice_1d(pts[:, 0], p0)
    rows, py, _, iy = _lattice_1d(pts[:, 1], p0)
    ps = [p for p in (px, py) if math.isfinite(p)]
    pitch = float(np.mean(ps)) if ps else p0
    if not (pitch >= min_pitch_px and abs(pitch - p0) <= 0.25 * p0):
        return None
    if rows > MAX_GRID_SIDE or cols > MAX_GRID_SIDE:
        return None
    # the grid through the spots: origin from every spot's lattice index
    ox = float(np.mean(pts[:, 0] - ix * pitch))
    oy = float(np.mean(pts[:, 1] - iy * pitch))
    off = np.hypot(pts[:, 0] - ox - ix * pitch, pts[:, 1] - oy - iy * pitch)
    if (off > GRID_MATCH_PITCH * pitch).any():
        return None
    fill = len({(int(a), int(b)) for a, b in zip(ix, iy)}) / (rows * cols)
    if fill < MIN_GRID_FILL:
        return None
    return GridShape(rows, cols, pitch, (ox, oy), n, float(fill))


MAX_SINGLE_CANDIDATES = 12
"""Active blobs a one-LED detection looks at (strongest first). On a textured background
under rig vibration the LED at 100 m can be far down the list: on the first 64 frames of 540
randomized one-LED scenes it was the strongest in 442, and ranked as low as 9th; with the
pace test (:data:`MIN_FAST_FLUX_SHARE`) the patches before it are passed over."""

MIN_FLUX_MODULATION = 0.5
"""Least :func:`flux_modulation` of a transmitter candidate: a PWM LED sending data swings
its flux by about its light or more (levels 1 .. M within any 64 frames; 1.5-2.4 measured),
a steady lamp under rig vibration by the shot noise of its disc (0.006 for a 25 cm lamp at
40 m with 0.5 px of vibration). An active blob on a lamp's edge is measured over the whole
lamp (:func:`source_box`): a box that cut through the lamp read 0.26-0.33 under smooth
vibration and 0.43-0.75 under 26-38 Hz engine vibration (its border on the lamp, so the
background it subtracted was the lamp's own light)."""

SOURCE_WINDOW_PX = 64
"""How far around an active blob :func:`source_box` looks for the rest of a steady light,
px (a 25 cm lamp is 22 px across at 40 m, 44 px at 20 m)."""

SOURCE_SPREAD_K = 4.0
"""A pixel is part of a light source only above the background's median by this many
robust standard deviations of the mean frame around it (a textured background's own
bright patches are not a source)."""


def source_box(mean: np.ndarray, bbox: tuple[int, int, int, int], *,
               window: int = SOURCE_WINDOW_PX) -> tuple[int, int, int, int]:
    """The bounding box of the whole light source that an active blob belongs to.

    Rig vibration moves a steady light without changing its flux, but only its edges show
    in the temporal gradient: a blob on a lamp's edge is a fragment of a larger source. The
    source is the connected region of the block's mean frame brighter than half the blob's
    peak above the background (and than the background's own spread,
    :data:`SOURCE_SPREAD_K`) that touches the blob, looked for within ``window`` px. An LED's
    blob covers its whole spot (all of it blinks), so its box stays its own.

    Parameters
    ----------
    mean : ndarray
        (H, W) mean frame of the block, DN.
    bbox : (int, int, int, int)
        The blob's (x0, y0, x1, y1), px (x1, y1 exclusive).
    window : int
        Search distance around ``bbox``, px.

    Returns
    -------
    tuple of int
        (x0, y0, x1, y1) px: ``bbox`` grown to the source (at most ``window`` px each side).
    """
    m = np.asarray(mean)
    H, W = m.shape
    x0, y0, x1, y1 = max(0, bbox[0]), max(0, bbox[1]), min(W, bbox[2]), min(H, bbox[3])
    if x1 <= x0 or y1 <= y0:
        return bbox
    wx0, wy0, wx1, wy1 = max(0, x0 - window), max(0, y0 - window), min(W, x1 + window), min(H, y1 + window)
    win = m[wy0:wy1, wx0:wx1].astype(np.float32)
    bg = float(np.median(win))
    spread = 1.4826 * float(np.median(np.abs(win - bg)))
    inner = win[y0 - wy0:y1 - wy0, x0 - wx0:x1 - wx0]
    peak = float(inner.max())
    level = max(bg + 0.5 * (peak - bg), bg + SOURCE_SPREAD_K * spread)
    if peak <= level:
        return bbox
    lab, _ = ndimage.label(win > level)
    ids = np.unique(lab[y0 - wy0:y1 - wy0, x0 - wx0:x1 - wx0])
    ids = ids[ids > 0]
    if ids.size == 0:
        return bbox
    ys, xs = np.nonzero(np.isin(lab, ids))
    return (min(bbox[0], wx0 + int(xs.min())), min(bbox[1], wy0 + int(ys.min())),
            max(bbox[2], wx0 + int(xs.max()) + 1), max(bbox[3], wy0 + int(ys.max()) + 1))


FLUX_PAD_PX = 4
"""How far a source's box is grown on every side for its flux (so that the whole source
stays inside while the rig vibrates), px."""


def _source_flux(frames: np.ndarray, bbox: tuple[int, int, int, int], pad: int,
                 mean: np.ndarray | None) -> np.ndarray | None:
    """Per-frame flux (n,) of the light source that the blob ``bbox`` belongs to, DN: the
    sum over its :func:`source_box` grown by ``pad`` px, less the box's border pixels' mean
    per pixel (the background); None when the clipped box is smaller than 3x3 px."""
    f = np.asarray(frames)
    H, W = f.shape[1:]
    if mean is None:
        mean = f.mean(axis=0, dtype=np.float32)
    bbox = source_box(mean, bbox)
    x0, y0 = max(0, bbox[0] - pad), max(0, bbox[1] - pad)
    x1, y1 = min(W, bbox[2] + pad), min(H, bbox[3] + pad)
    box = f[:, y0:y1, x0:x1].astype(np.float64)
    if box.shape[1] < 3 or box.shape[2] < 3:
        return None
    border = np.concatenate([box[:, 0, :], box[:, -1, :], box[:, 1:-1, 0], box[:, 1:-1, -1]], axis=1)
    return box.sum(axis=(1, 2)) - border.mean(axis=1) * box.shape[1] * box.shape[2]


def flux_modulation(frames: np.ndarray, bbox: tuple[int, int, int, int], pad: int = FLUX_PAD_PX,
                    mean: np.ndarray | None = None) -> float:
    """How much the light of a candidate changes, relative to the light itself (0 for a
    steady light, ~1 for an LED that switches between dark and full).

    The flux is the per-frame sum of the pixels in the candidate's source box
    (:func:`source_box`: ``bbox`` grown to the whole light it is part of, so a lamp's edge
    is measured with the rest of the lamp) grown by ``pad`` px (so the whole source stays
    inside while the rig vibrates), minus the box's border pixels' mean per pixel (the
    background): ``(p95 - p5 of the flux over frames) / max(mean flux, 1 DN)``.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN.
    bbox : (int, int, int, int)
        The candidate's (x0, y0, x1, y1), px.
    pad : int
        Growth of the box on every side, px.
    mean : ndarray, optional
        (H, W) mean frame of ``frames`` (computed when not given), DN.

    Returns
    -------
    float
        The relative modulation (0 when the clipped box is smaller than 3x3 px).
    """
    flux = _source_flux(frames, bbox, pad, mean)
    return 0.0 if flux is None else _modulation(flux)


def _modulation(flux: np.ndarray) -> float:
    """:func:`flux_modulation` of a source's flux (n,), DN."""
    lo, hi = np.percentile(flux, [5, 95])
    return float((hi - lo) / max(float(flux.mean()), 1.0))


FAST_FLUX_FRACTION = 0.2
"""The band of :func:`fast_flux_share` starts at this fraction of the symbol rate (100 Hz
for 500 symbols/s; rig vibration, 20-40 Hz engine vibration included, lies below it)."""

MIN_FAST_FLUX_SHARE = 0.22
"""Least :func:`fast_flux_share` of a one-LED candidate. Random symbols held for 2 frames
put 0.61 of their variance above a fifth of the symbol rate (a cos^2 spectrum); a light
moved by rig vibration, little. Measured on the first 64 frames of 540 randomized motion
scenes (15 seed sets x 3 vibration models, 1 LED, 40-100 km/h, 0.3-0.5 px; the threshold
set on 13 of the sets, the other two looked at after): the LED 0.30-0.64 (median 0.49;
lowest at 100 m under 0.5 px), the textured background patches that outranked it in 3 of
them 0.13-0.17 (their ``flux_modulation`` was 10^2-10^4: a background-subtracted mean flux
near 0), other candidates 0.07-0.83."""


def fast_flux_share(frames: np.ndarray, bbox: tuple[int, int, int, int], symbol_frames: float, *,
                    pad: int = FLUX_PAD_PX, mean: np.ndarray | None = None) -> float:
    """How much of a candidate's flux changes at the pace of symbols rather than of motion.

    The flux of the light source (as :func:`flux_modulation` takes it), its linear trend
    (an approach's brightening) removed: the share of its periodogram's power above
    :data:`FAST_FLUX_FRACTION` of the symbol rate. An LED sending random symbols changes its
    light every symbol; a textured background under rig vibration, or a lamp's edge, changes
    its flux only as the rig moves -- slowly, whatever the size of the change.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN, n >= 8.
    bbox : (int, int, int, int)
        The candidate's (x0, y0, x1, y1), px.
    symbol_frames : float
        The symbol period, frames (fps / symbol rate).
    pad : int
        Growth of the box on every side, px.
    mean : ndarray, optional
        (H, W) mean frame of ``frames`` (computed when not given), DN.

    Returns
    -------
    float
        The share, 0 .. 1 (0 when the box is smaller than 3x3 px or the flux is a line).
    """
    if not symbol_frames > 0:
        raise ValueError(f"fast_flux_share: symbol_frames must be > 0, got {symbol_frames!r}")
    flux = _source_flux(frames, bbox, pad, mean)
    return 0.0 if flux is None else _fast_share(flux, symbol_frames)


def _periodogram(flux: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """A source's flux (n,), DN, with its linear trend removed: (frequencies, cycles per
    frame; power; the level below which a band's power is rounding only: what a line
    leaves)."""
    t = np.arange(flux.shape[0], dtype=np.float64)
    x = flux - np.polyval(np.polyfit(t, flux, 1), t)
    return np.fft.rfftfreq(flux.shape[0]), np.abs(np.fft.rfft(x)) ** 2, \
        1e-12 * flux.shape[0] * float(np.dot(flux, flux))


def _fast_share(flux: np.ndarray, symbol_frames: float,
                spectrum: tuple[np.ndarray, np.ndarray, float] | None = None) -> float:
    """:func:`fast_flux_share` of a source's flux (n,), DN; ``symbol_frames`` > 0;
    ``spectrum``: its :func:`_periodogram` if already made."""
    freq, power, floor = spectrum or _periodogram(flux)
    total = float(power[1:].sum())
    if not total > floor:  # a line (rounding only)
        return 0.0
    return float(power[freq > FAST_FLUX_FRACTION / symbol_frames].sum() / total)


NULL_BAND = 0.8
""":func:`symbol_null_ratio` compares the flux's power within ``1 - NULL_BAND`` of the symbol
rate (from this fraction of it to ``2 - NULL_BAND`` of it, up to the frame rate's Nyquist
frequency) with its power between :data:`FAST_FLUX_FRACTION` and this fraction."""

NULL_PREFERENCE = 3.0
"""One-LED detection passes over a candidate that passes the swing and pace tests when
another that passes them has a :func:`symbol_null_ratio` more than this many times lower
(a deeper null at the symbol rate). Set on the first 64 frames of 1620 randomized one-LED
motion scenes (45 seed sets x 4 cases x 3 seeds x 3 vibration models), half the sets to
choose, half to check, then on 756 HDR one-LED scenes and 756 windows 0.7 s into the
approach: the pick changed in 6 windows, each time from a textured edge under engine
vibration to the LED. The LED's ratio was 0.0006-0.139 (median 0.018-0.034 in the three
groups), that of the passing candidates ranked above it 0.055 or more. Chosen from 1.5, 2,
3, 4 and 6: with 1.5 three right picks turned wrong (HDR sets 71001 and 73001, set 56001),
with 2 one (set 56001); with 6 fewer windows were mended."""


def symbol_null_ratio(frames: np.ndarray, bbox: tuple[int, int, int, int], symbol_frames: float, *,
                      pad: int = FLUX_PAD_PX, mean: np.ndarray | None = None) -> float:
    """How deep a candidate's flux spectrum dips at the symbol rate (the lower, the deeper).

    Symbols held for ``symbol_frames`` frames are a staircase: the spectrum of random levels
    held that long is ``sinc^2``, with its null at the symbol rate itself (at the frame
    rate's Nyquist frequency for 2 frames a symbol). Sensor noise and a textured background
    moved by rig jitter are white there; rig vibration is slow (:func:`fast_flux_share`).
    The ratio: the flux's power (linear trend removed) between :data:`NULL_BAND` and
    ``2 - NULL_BAND`` of the symbol rate over its power between :data:`FAST_FLUX_FRACTION`
    and :data:`NULL_BAND` of it. White noise: ~0.33 (2 frames a symbol). Held random
    symbols: ~0.02 in theory (a cos^2 spectrum); measured on 64 frames, the window's leakage
    fills the null: 0.05-0.13 for a bright LED with sensor noise (tests), 0.0006-0.14
    (median 0.02-0.03) for the randomized motion scenes' LED (:data:`NULL_PREFERENCE`).

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN, n >= 8.
    bbox : (int, int, int, int)
        The candidate's (x0, y0, x1, y1), px.
    symbol_frames : float
        The symbol period, frames (fps / symbol rate); > 1 / (2 NULL_BAND) (the band must
        lie below the Nyquist frequency).
    pad : int
        Growth of the box on every side, px.
    mean : ndarray, optional
        (H, W) mean frame of ``frames`` (computed when not given), DN.

    Returns
    -------
    float
        The ratio (inf when the box is smaller than 3x3 px or the flux is a line).
    """
    if not symbol_frames > 1.0 / (2.0 * NULL_BAND):
        raise ValueError(f"symbol_null_ratio: symbol_frames must be > {1.0 / (2.0 * NULL_BAND):g}, "
                         f"got {symbol_frames!r}")
    flux = _source_flux(frames, bbox, pad, mean)
    return math.inf if flux is None else _null_ratio(flux, symbol_frames)


def _null_ratio(flux: np.ndarray, symbol_frames: float,
                spectrum: tuple[np.ndarray, np.ndarray, float] | None = None) -> float:
    """:func:`symbol_null_ratio` of a source's flux (n,), DN; ``spectrum``: its
    :func:`_periodogram` if already made."""
    freq, power, floor = spectrum or _periodogram(flux)
    top = float(power[(freq > NULL_BAND / symbol_frames) & (freq < (2.0 - NULL_BAND) / symbol_frames)].sum())
    mid = float(power[(freq > FAST_FLUX_FRACTION / symbol_frames) & (freq <= NULL_BAND / symbol_frames)].sum())
    if not mid > floor:  # a line (rounding only)
        return math.inf
    return top / mid


def _one_led_changes(frames: np.ndarray, bbox: tuple[int, int, int, int], mean: np.ndarray,
                     symbol_frames: float | None) -> bool:
    """A one-LED candidate's light really changes (:data:`MIN_FLUX_MODULATION`), and, with
    a known symbol period, at the pace of symbols (:data:`MIN_FAST_FLUX_SHARE`): both on
    the one flux of its source."""
    return _changing_flux(frames, bbox, mean, symbol_frames) is not None


def _changing_flux(frames: np.ndarray, bbox: tuple[int, int, int, int], mean: np.ndarray,
                   symbol_frames: float | None) -> tuple[np.ndarray, tuple | None] | None:
    """The flux of a one-LED candidate that passes :func:`_one_led_changes` and, with a
    symbol period, its :func:`_periodogram`; None if it does not pass."""
    flux = _source_flux(frames, bbox, FLUX_PAD_PX, mean)
    if flux is None or _modulation(flux) < MIN_FLUX_MODULATION:
        return None
    if symbol_frames is None:
        return flux, None
    spectrum = _periodogram(flux)
    if _fast_share(flux, symbol_frames, spectrum) < MIN_FAST_FLUX_SHARE:
        return None
    return flux, spectrum


def _one_led_candidate(frames: np.ndarray, blobs: list[Blob], mean: np.ndarray,
                       symbol_frames: float | None) -> Blob | None:
    """One-LED detection's pick among the strongest blobs: the strongest whose light changes
    (:func:`_one_led_changes`), unless another that passes has a null at the symbol rate
    more than :data:`NULL_PREFERENCE` times deeper (:func:`symbol_null_ratio`; with a
    known symbol period of more than 1 / (2 NULL_BAND) frames)."""
    if symbol_frames is None or not symbol_frames > 1.0 / (2.0 * NULL_BAND):
        return next((b for b in blobs[:MAX_SINGLE_CANDIDATES] if _one_led_changes(frames, b.bbox, mean, symbol_frames)),
                    None)
    passing = []
    for b in blobs[:MAX_SINGLE_CANDIDATES]:
        got = _changing_flux(frames, b.bbox, mean, symbol_frames)
        if got is not None:
            passing.append((b, _null_ratio(got[0], symbol_frames, got[1])))
    if not passing:
        return None
    deepest = min(r for _, r in passing)
    return next(b for b, r in passing if r <= NULL_PREFERENCE * deepest)


def detect_array(frames: np.ndarray, rows: int, cols: int, *, exclude: list[tuple[int, int, int, int]] | None = None,
                 symbol_frames: float | None = None) -> GridFit | None:
    """Find the transmitter (a ``rows x cols`` array, or one LED) in a block of frames.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN, n >= 8, that include symbol changes (any 64 frames of a packet
        do).
    rows, cols : int
        The configured layout.
    exclude : list of (int, int, int, int), optional
        (x0, y0, x1, y1) px boxes of candidates already rejected (e.g. a flickering lamp that
        never sent a header); blobs centred inside them are ignored.
    symbol_frames : float, optional
        The symbol period, frames: one LED's candidate must also change its flux at the
        pace of symbols (:func:`fast_flux_share`); without it, only by how much.

    Returns
    -------
    GridFit or None
        The best fit, px; None if nothing blinks.
    """
    if symbol_frames is not None and not symbol_frames > 0:
        raise ValueError(f"detect_array: symbol_frames must be > 0, got {symbol_frames!r}")
    act, mean, lo, _ = look_maps(frames)  # one compiled pass (the same values as numpy)
    light = mean - lo.astype(np.float32)
    blobs = find_blobs(act, mean)
    if exclude:
        blobs = [b for b in blobs if not any(e[0] <= b.x < e[2] and e[1] <= b.y < e[3] for e in exclude)]
    if not blobs:
        return None
    n = rows * cols
    if n == 1:
        # the strongest blob whose light really changes: a steady lamp under vibration
        # shows pixel activity at its edges, but its integrated flux stays put; a textured
        # background under vibration changes its flux, but at the pace of the motion
        # (and of those, one whose flux dips at the symbol rate as held symbols do)
        b = _one_led_candidate(frames, blobs, mean, symbol_frames)
        if b is None:
            return None
        pad = 3
        return fit_grid(light, 1, 1, region=(b.bbox[0] - pad, b.bbox[1] - pad, b.bbox[2] + pad, b.bbox[3] + pad))
    # group blobs of one array: LEDs of an array are at most ~a pitch apart; a pitch is at
    # most about the size of a blob's spot -- the median blob's (the largest may be a big
    # blinking lamp elsewhere: a 93 px one merged a randomized scene's 13 blobs into one
    # group, and the grid fitted over all of them, pitch 41 px, hid the array)
    size = float(np.median([max(b.bbox[2] - b.bbox[0], b.bbox[3] - b.bbox[1]) for b in blobs[:n]]))
    groups = group_blobs(blobs, max_gap=max(3.0, 2.0 * size))
    best: GridFit | None = None
    for g in groups[:3]:
        bx0 = min(b.bbox[0] for b in g) - 3
        by0 = min(b.bbox[1] for b in g) - 3
        bx1 = max(b.bbox[2] for b in g) + 3
        by1 = max(b.bbox[3] for b in g) + 3
        try:
            fit = fit_grid(light, rows, cols, region=(bx0, by0, bx1, by1))
        except ValueError:
            continue
        if best is None or fit.score > best.score:
            best = fit
    return best


MIN_ONE_LED_CORRELATION = 0.6
"""Least :func:`halves_correlation` of a spot taken for one LED: one LED's light changes in
every pixel of its spot together (0.99 at 50 m still; with 0.5 px RMS rig vibration, which
moves light between the halves, 0.94 at 20 m and 0.81 at 60 m); the merged spot of an array
too far to resolve (halves of LEDs each sending their own data) less (8x8 at 80 and 90 m:
0.38, 0.39; 4x4 at 100 m: -0.02). Measured on 64 rendered frames, PWM-8, seed 3."""


def halves_correlation(frames: np.ndarray, box: tuple[int, int, int, int]) -> float:
    """How much the two halves of a spot change together: the least Pearson correlation,
    over the frames, of the summed light in the left and right halves of ``box`` and in its
    top and bottom halves.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN.
    box : (int, int, int, int)
        The spot's (x0, y0, x1, y1), px (x1, y1 exclusive).

    Returns
    -------
    float
        The correlation (1 for one LED without noise; 1.0 when the box is too small to
        halve or a half does not change).
    """
    f = np.asarray(frames)
    H, W = f.shape[1:]
    x0, y0, x1, y1 = max(0, box[0]), max(0, box[1]), min(W, box[2]), min(H, box[3])
    sub = f[:, y0:y1, x0:x1].astype(np.float64)
    out = 1.0
    for axis in (2, 1):
        m = sub.shape[axis]
        if m < 2:
            continue
        a = np.take(sub, np.arange(m // 2), axis=axis).sum(axis=(1, 2))
        b = np.take(sub, np.arange(m - m // 2, m), axis=axis).sum(axis=(1, 2))
        if a.std() > 0 and b.std() > 0:
            out = min(out, float(np.corrcoef(a, b)[0, 1]))
    return out


def detect_auto(frames: np.ndarray, *, exclude: list[tuple[int, int, int, int]] | None = None,
                symbol_frames: float | None = None) -> GridFit | None:
    """Find a transmitter of unknown shape (an array of any rows x cols, or one LED).

    As :func:`detect_array`, but each of the (at most 3) strongest groups of active blobs
    gets its shape from the spots of its lit map (:func:`lit_map`, :func:`infer_grid`):
    the group's box (3 px around its blobs) holds the source. A group of one spot is one
    LED: it must change its light (:func:`flux_modulation`), and in all of its spot
    together (:func:`halves_correlation`: an array too far to resolve is one spot too, but
    its halves send different data); an array's grid is then fitted
    exactly as :func:`detect_array` fits a configured one (:func:`fit_grid`), refitted from
    the inferred pitch and origin if the two disagree by more than 15 %. The group with the
    best grid score wins.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN, n >= 8, that include symbol changes.
    exclude : list of (int, int, int, int), optional
        (x0, y0, x1, y1) px boxes of candidates already rejected; blobs centred inside
        them are ignored.
    symbol_frames : float, optional
        The symbol period, frames: a one-LED group must also change its flux at the pace
        of symbols (:func:`fast_flux_share`).

    Returns
    -------
    GridFit or None
        The best fit (``rows`` and ``cols`` inferred), px; None if nothing blinks or no
        group makes a grid.
    """
    if symbol_frames is not None and not symbol_frames > 0:
        raise ValueError(f"detect_auto: symbol_frames must be > 0, got {symbol_frames!r}")
    act, mean, lo, hi = look_maps(frames)  # one compiled pass (the same values as numpy)
    blobs = find_blobs(act, mean)
    if exclude:
        blobs = [b for b in blobs if not any(e[0] <= b.x < e[2] and e[1] <= b.y < e[3] for e in exclude)]
    if not blobs:
        return None
    light = mean - lo.astype(np.float32)
    lit = hi.astype(np.float32) - lo.astype(np.float32)  # lit_map(frames)
    H, W = lit.shape
    size = max(max(b.bbox[2] - b.bbox[0], b.bbox[3] - b.bbox[1]) for b in blobs[:MAX_GRID_SIDE])
    best: GridFit | None = None
    groups = group_blobs(blobs, max_gap=max(3.0, 2.0 * size))[:3]
    tried = 0
    while groups:
        g = groups.pop(0)
        pad = 3
        x0 = max(0, min(b.bbox[0] for b in g) - pad)
        y0 = max(0, min(b.bbox[1] for b in g) - pad)
        x1 = min(W, max(b.bbox[2] for b in g) + pad)
        y1 = min(H, max(b.bbox[3] for b in g) + pad)
        if x1 - x0 < 2 or y1 - y0 < 2:
            continue
        shape = infer_grid(lit[y0:y1, x0:x1])
        if shape is None:
            if len(g) > 1 and tried < 6:
                # blobs of unlike sizes (an array lit as one area during its header beside a
                # far single LED) grouped by the largest one's gap: regrouped by their
                # typical size, if that parts them (the fragments of one source do not part)
                sides = [max(b.bbox[2] - b.bbox[0], b.bbox[3] - b.bbox[1]) for b in g]
                sub = group_blobs(g, max_gap=max(3.0, 2.0 * float(np.median(sides))))
                if len(sub) > 1:
                    groups = sub + groups
                    tried += len(sub)
            continue
        try:
            if shape.rows * shape.cols == 1:
                box = (x0 + pad, y0 + pad, x1 - pad, y1 - pad)
                if not _one_led_changes(frames, box, mean, symbol_frames) or \
                        halves_correlation(frames, box) < MIN_ONE_LED_CORRELATION:
                    continue  # a steady light, or an array too far to resolve
                fit = fit_grid(light, 1, 1, region=(x0, y0, x1, y1))
            else:
                fit = fit_grid(light, shape.rows, shape.cols, region=(x0, y0, x1, y1))
                if abs(fit.pitch_px - shape.pitch_px) > 0.15 * shape.pitch_px:
                    fit = fit_grid(light, shape.rows, shape.cols, region=(x0, y0, x1, y1),
                                   pitch_guess=shape.pitch_px,
                                   origin_guess=(x0 + shape.origin[0], y0 + shape.origin[1]))
        except ValueError:
            continue
        if best is None or fit.score > best.score:
            best = fit
    return best


def track_array(frames: np.ndarray, prev: GridFit, *, margin: float | None = None) -> GridFit:
    """Refine ``prev`` on a new block of frames (the array moved and grew a little).

    Only a window of ``margin`` px (default: 2 pitches + 4 px) around the previous fit is
    read, so tracking touches only the pixels it needs. The window's light map
    (:func:`light_map`: temporal mean minus minimum, less its median, smoothed) is scored at
    the grid points (the mean of the light there) for a small set of shifts (+-0.5 px in
    0.25 px steps) and pitch scales (+-2 %) in one vectorized interpolation; there is no
    whole-pitch search, so each block moves the fit at most that far and tracking relies on
    being called often (a single LED is refitted in the window instead).

    Parameters
    ----------
    frames : ndarray
        (n, H, W) frames, DN.
    prev : GridFit
        The previous fit, px.
    margin : float, optional
        Window around the fit, px (default 2 pitches + 4 px).

    Returns
    -------
    GridFit
        The refined fit, image px.

    Raises
    ------
    ValueError
        If the window is (nearly) outside the image or has no activity.
    """
    x0, y0, x1, y1 = track_box(prev, frames.shape[1:], margin=margin)
    return track_on_light(light_map(frames[:, y0:y1, x0:x1]), prev, x0, y0)


def track_box(prev: GridFit, shape: tuple[int, int], *, margin: float | None = None
              ) -> tuple[int, int, int, int]:
    """The window (x0, y0, x1, y1) px that :func:`track_array` reads around ``prev``.

    ``margin`` px (default 2 pitches + 4 px) around the fit, clipped to the image.

    Parameters
    ----------
    prev : GridFit
        The previous fit, px.
    shape : (int, int)
        Image shape (H, W), px.
    margin : float, optional
        Window around the fit, px (default 2 pitches + 4 px).

    Returns
    -------
    tuple of int
        (x0, y0, x1, y1), px (x1, y1 exclusive).

    Raises
    ------
    ValueError
        If the window is (nearly) outside the image.
    """
    m = margin if margin is not None else 2 * prev.pitch_px + 4
    x0, y0, x1, y1 = prev.bbox(m)
    H, W = shape
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(W, x1), min(H, y1)
    if x1 - x0 < 2 or y1 - y0 < 2:
        raise ValueError("the tracked array left the image")
    return x0, y0, x1, y1


def track_on_light(light: np.ndarray, prev: GridFit, x0: int, y0: int) -> GridFit:
    """:func:`track_array` on the light map (:func:`light_map`) of its window, whose
    top-left pixel is (x0, y0) px in the image.

    Parameters
    ----------
    light : ndarray
        (h, w) light map of the window, DN.
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
    act = np.asarray(light, dtype=np.float64)
    act = np.clip(act - np.median(act), 0, None)
    if not act.any():
        raise ValueError("no modulated light in the tracking window")
    smooth = ndimage.gaussian_filter(act, 0.7)
    if prev.rows * prev.cols == 1:
        fit = fit_grid(smooth, 1, 1)
        return replace(fit, origin=(fit.origin[0] + x0, fit.origin[1] + y0))
    r, c = np.mgrid[0:prev.rows, 0:prev.cols]
    r, c = r.ravel().astype(np.float64), c.ravel().astype(np.float64)
    steps = np.arange(-0.5, 0.51, 0.25)
    scales = np.array([0.98, 1.0, 1.02])
    dx, dy, sc = (a.ravel() for a in np.meshgrid(steps, steps, scales, indexing="ij"))
    p = prev.pitch_px * sc
    # scale about the array centre, then shift
    cx, cy = prev.center
    cx, cy = cx - x0 + dx, cy - y0 + dy
    ox = cx - (prev.cols - 1) / 2 * p
    oy = cy - (prev.rows - 1) / 2 * p
    xs = ox[:, None] + c[None, :] * p[:, None]
    ys = oy[:, None] + r[None, :] * p[:, None]
    vals = ndimage.map_coordinates(smooth, [ys.ravel(), xs.ravel()], order=1, mode="constant", cval=0.0)
    score = vals.reshape(len(p), -1).mean(axis=1)
    k = int(np.argmax(score))
    return replace(prev, origin=(float(ox[k] + x0), float(oy[k] + y0)), pitch_px=float(p[k]),
                   score=float(score[k]))


def match_stereo(left: GridFit, right_candidates: list[GridFit], max_dy: float = 3.0,
                 max_disparity: float = 400.0) -> GridFit | None:
    """The right-camera fit that is the same transmitter as ``left`` (rectified images).

    Same rows (|dy| <= ``max_dy`` px), disparity -1 .. ``max_disparity`` px and a pitch
    within 15 %; the closest in y wins.

    Parameters
    ----------
    left : GridFit
        The left-camera fit, px.
    right_candidates : list of GridFit
        Right-camera fits, px.
    max_dy : float
        Largest vertical offset of the centres, px.
    max_disparity : float
        Largest disparity (left x - right x of the centres), px.

    Returns
    -------
    GridFit or None
        The match; None if no candidate qualifies.
    """
    best, best_dy = None, np.inf
    lx, ly = left.center
    for r in right_candidates:
        rx, ry = r.center
        d = lx - rx
        dy = abs(ly - ry)
        if dy > max_dy or not (-1.0 <= d <= max_disparity):
            continue
        if left.pitch_px > 0 and abs(r.pitch_px - left.pitch_px) > 0.15 * left.pitch_px:
            continue
        if dy < best_dy:
            best, best_dy = r, dy
    return best
