"""A per-pixel background held in the moving image's own frame (the luminance of one LED
over a textured background on a vibrating rig).

The contract, once: each camera keeps a map ``bg`` of what every scene point of the
background shows when no LED lights it (each point's least value over the frames that
showed it, relaxed upward by ``rise_dn`` once per block that touches it, as
:class:`~iscd.decode.tracking.luminance.PixelBackground`), but indexed by the background's
position *in the scene*, not in the image: frame f shows scene point q at image pixel
``p = q + s_f``, where ``s_f`` (px, whole pixels, (x, y)) is how far the rig's vibration has
moved the image. A luminance window that follows the LED then subtracts, in every frame,
the background that is under it in that frame, however far the image has moved.

Why: rig vibration moves the whole image -- the LED's spot and the background texture
behind it together. An image-indexed least value (PixelBackground) holds, at each pixel,
the darkest texture that vibration has brought there, so the light above it changes as
the image moves: at 100 m one PWM level is ~10 DN of a single LED's light, and a texture
edge moved 1 px under the window shifted the luminance by 0.2-0.9 of a level for the
tens of frames the image stayed moved (randomized 100 km/h scenes: bursts of 7-16
consecutive symbols one level off, the first packet lost; with the background taken at
the image's own shift, none).

The shift is measured, not assumed: per frame, the whole-pixel shift within one pixel of
the last frame's that best matches a ring of background pixels around the LEDs (between
the luminance window and ``ring_px`` beyond it) to the map -- the least variance of
their difference (an offset, e.g. the map's noise floor or glare, does not count). A
shift is taken only when it matches clearly better (:data:`SWITCH`) than the last; where
the background is flat every shift matches alike and the last one stays (and there it
does not matter). Nothing is assumed about why the image moved (vibration, a bump, the
LED's own slow drift across the texture is followed by the map's relaxation).

:func:`measure_block` is the compiled kernel (per frame: match, fold in; then, the whole
block folded in, per frame: measure); :func:`measure_block_reference` the pure-numpy
reference the tests compare it with.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from iscd.core.jit import njit

MAX_SHIFT_PX = 8
"""Largest image shift held, px (the map's margin): a road bump of 0.5 px RMS swings the
image up to ~4 px."""

RING_PX = 3
"""The ring of background pixels that measures the shift: this far beyond the luminance
window's box, px."""

SWITCH = 0.6
"""A new shift is taken when its ring matches with at most this share of the last
shift's variance. On a flat background the shifts' variances differ by noise alone (their
estimates from ~150 pixels scatter by ~10 %: 0.6 is 4 of those apart, and the shift must
not wander); a texture misregistered by a pixel: 2-25x the variance of the right shift on
randomized scenes. (A test of the improvement against its standard error was tried too:
texture edges make the per-pixel differences heavy-tailed, a 13x better shift scored
2.0 standard errors, and moves were missed; a missed move folds misregistered frames into
the map, which then matches neither shift well.)"""


SEARCH_RATIO = 1.5
"""The other shifts are tried in a frame whose ring variance at the last shift is more
than this times its running level (:data:`LEVEL_RISE`), and in every
:data:`SEARCH_EVERY`-th frame: a pixel's move raises it 2-25x; most frames have not moved,
and one pass over the ring is all they cost."""

LEVEL_RISE = 1.05
"""The running level is the least ring variance taken lately: it follows a lower one at
once and rises by at most this factor a frame (the texture or the LED's glare in the ring
may grow)."""

SEARCH_EVERY = 8
"""... and every this many frames the other shifts are tried anyway (a level taken while
the map was still being built at a wrong shift is then corrected)."""

MAX_RESIDUAL_PX = 0.75
"""Largest residual (subpixel) shift taken, px: a whole-pixel shift leaves at most 0.5 (more
is a poor fit: the ring's texture too flat or its light not the background's)."""

MIN_RESIDUAL_PIXELS = 8
"""Least ring pixels (with their map neighbours seen) the residual shift is fitted on."""

MIN_RESIDUAL_DET = 1.0
"""Least determinant of the ring gradients' covariance per pixel squared ((DN/px)^4): the
ring's texture must have a gradient of ~1 DN/px in both directions for a residual shift to
be fitted (flat: none, and none needed -- the light moves with it by as little)."""

MIN_SEEN = 0.6
"""Share of the ring's pixels the map must already hold for a shift to be judged."""

HINT_SWITCH = 1.0
"""A hinted move (the other camera's, :meth:`RegisteredBackground.measure` ``hint``) is
taken when the ring matches the moved shift at least as well as the last one (at most this
share of its variance): the cameras of a rigid rig move together, so a move the sharper
camera saw needs no more from the other than that its own ring does not speak against it (a
defocused camera's texture blurs, and its own evidence for a 1 px move is then often below
:data:`SWITCH`)."""


def window_half(sigma_px: float) -> int:
    """Half-size of the Gaussian luminance window's box
    (:func:`iscd.decode.tracking.luminance.gauss_mean`'s default radius).

    Parameters
    ----------
    sigma_px : float
        Gaussian window sigma, px.

    Returns
    -------
    int
        ceil(3.5 sigma), px.
    """
    return int(np.ceil(3.5 * float(sigma_px)))


class RegisteredBackground:
    """One camera's background map in the scene's frame (module docstring) and the image's
    current whole-pixel shift.

    Parameters
    ----------
    shape : tuple of int
        (H, W) of the camera's frames, px.
    rise_dn : float
        Upward relaxation per block that touches a point, DN.
    """

    def __init__(self, shape: tuple[int, int], rise_dn: float = 0.25, *, subpixel: bool = False) -> None:
        if not rise_dn >= 0:
            raise ValueError(f"rise_dn: expected >= 0 DN per block, got {rise_dn}")
        m = MAX_SHIFT_PX
        H, W = int(shape[0]), int(shape[1])
        self.shape = (H, W)
        self.bg = np.full((H + 2 * m, W + 2 * m), np.inf, np.float32)
        self.stamp = np.zeros(self.bg.shape, np.int64)
        self.block = 0
        self.rise_dn = float(rise_dn)
        self.shift = np.zeros(2, np.int64)
        """The last frame's image shift (x, y), px."""
        self.contrast = np.zeros(0)
        """Per frame of the last block how clearly the ring told the shifts apart: the
        second-least ring variance over the least among the shifts tried (>= 1; NaN where
        only the last shift was judged). A sharp texture: 2-25; a blurred or flat one: ~1."""
        self._hint_last: np.ndarray | None = None
        """The last hint row of the previous block (the move into this block's first frame)."""
        self.subpixel = bool(subpixel)
        """Also the residual (subpixel) shift of each frame, and the light above the map moved
        on by it (:func:`measure_block_reference`)."""
        self.residual = np.zeros((0, 2))
        """(F, 2) the last block's residual shifts (x, y), px (zeros without ``subpixel``)."""
        self.level = np.array([np.inf, 0.0])
        """The running ring variance at the shift taken, DN^2 (:data:`SEARCH_RATIO`), and
        the frames judged so far."""

    def measure(self, frames: np.ndarray, centres: np.ndarray, sigma_px: float, *,
                hint: np.ndarray | None = None, compiled: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Fold one block in and measure each LED's light above the background under it.

        Parameters
        ----------
        frames : ndarray
            (F, H, W) one camera's frames, DN (uint8 or uint16).
        centres : ndarray
            (F, N, 2) LED centres (x, y) in each frame, px.
        sigma_px : float
            Gaussian luminance window, px (> 0).
        hint : ndarray, optional
            (F, 2) int the shifts another camera of the rig found in the same frames, px.
            Where that camera's shift moved (from its previous frame, the last block's last
            included) and this one's own search did not, this camera makes the same move if
            its ring matches the moved shift at least as well (:data:`HINT_SWITCH`). Only
            the moves count: the two cameras' shifts may differ by a constant (each map's
            own origin).
        compiled : bool
            The compiled kernel (else the numpy reference: the same numbers).

        Returns
        -------
        lum : ndarray
            (F, N) float64 Gaussian-weighted mean of the light above the background, DN.
        shifts : ndarray
            (F, 2) int64 the image shift (x, y) found in each frame, px.
        """
        c = self._checked(frames, centres, sigma_px)
        self.block += 1
        F, N = c.shape[0], c.shape[1]
        lum = np.zeros((F, N))
        shifts = np.zeros((F, 2), np.int64)
        h = self._hint_rows(hint, F)
        self._hint_last = None if hint is None else h[-1:].copy()
        self.contrast = np.full(F, np.nan)
        self.residual = np.zeros((F, 2))
        fn = measure_block if compiled else measure_block_reference
        fn(np.ascontiguousarray(frames), np.ascontiguousarray(c), float(sigma_px), window_half(sigma_px),
           RING_PX, self.bg, self.stamp, self.block, self.rise_dn, MAX_SHIFT_PX, self.shift, self.level, lum, shifts,
           h, self.contrast, True, self.subpixel, self.residual)
        return lum, shifts

    def predict_shifts(self, frames: np.ndarray, centres: np.ndarray, sigma_px: float, *,
                       hint: np.ndarray | None = None, compiled: bool = True) -> np.ndarray:
        """The image shifts of a block found against the map as it is, before the block is
        measured: what :meth:`measure` finds with these ``centres``, except that the block's
        own earlier frames are not yet folded in. Nothing of the state changes (map, last
        shift, running level, hint), so :meth:`measure` of the same block follows as usual.

        One LED's following uses them to work in the background's own frame
        (:mod:`iscd.decode.tracking.stabilize`): where the LED will be is not known yet, so
        ``centres`` are where it was (the ring only has to lie on background the map holds).

        Parameters
        ----------
        frames : ndarray
            (F, H, W) one camera's frames, DN.
        centres : ndarray
            (F, N, 2) where the LEDs are expected (x, y), px.
        sigma_px : float
            Gaussian luminance window, px (> 0): the ring starts beyond its box.
        hint : ndarray, optional
            (F, 2) another camera's shifts in the same frames, px (as :meth:`measure`).
        compiled : bool
            The compiled kernel (else the numpy reference).

        Returns
        -------
        ndarray
            (F, 2) int64 image shift (x, y) in each frame, px.
        """
        c = self._checked(frames, centres, sigma_px)
        F = c.shape[0]
        shifts = np.zeros((F, 2), np.int64)
        fn = measure_block if compiled else measure_block_reference
        fn(np.ascontiguousarray(frames), np.ascontiguousarray(c), float(sigma_px), window_half(sigma_px),
           RING_PX, self.bg, self.stamp, self.block + 1, self.rise_dn, MAX_SHIFT_PX, self.shift.copy(),
           self.level.copy(), np.zeros((F, c.shape[1])), shifts, self._hint_rows(hint, F), np.full(F, np.nan), False,
           False, np.zeros((F, 2)))
        return shifts

    def _checked(self, frames: np.ndarray, centres: np.ndarray, sigma_px: float) -> np.ndarray:
        """``centres`` as (F, N, 2) float64 after checking the block's arguments (ValueError
        naming the bad one)."""
        if frames.ndim != 3 or tuple(frames.shape[1:]) != self.shape:
            raise ValueError(f"frames: expected (F, {self.shape[0]}, {self.shape[1]}), got {frames.shape}")
        c = np.asarray(centres, dtype=np.float64)
        if c.ndim != 3 or c.shape[0] != frames.shape[0] or c.shape[2] != 2:
            raise ValueError(f"centres: expected ({frames.shape[0]}, N, 2), got {c.shape}")
        if not sigma_px > 0:
            raise ValueError(f"sigma_px: expected > 0, got {sigma_px}")
        return c

    def _hint_rows(self, hint: np.ndarray | None, F: int) -> np.ndarray:
        """The kernel's hint: (F + 1, 2) int64, the other camera's shift in the frame before
        the block (its last hint, else its first) and in each of its frames ((0, 2): none)."""
        if hint is None:
            return np.zeros((0, 2), np.int64)
        h = np.asarray(hint, dtype=np.int64)
        if h.shape != (F, 2):
            raise ValueError(f"hint: expected ({F}, 2) shifts, got {h.shape}")
        first = h[:1] if self._hint_last is None else self._hint_last
        return np.ascontiguousarray(np.concatenate([first, h]))  # (F + 1, 2): the moves are its steps


class ShiftLeader:
    """Which camera of a rigid stereo rig leads the other's image shift (the ``hint`` of
    :meth:`RegisteredBackground.measure`): the one whose ring tells the shifts apart more
    clearly (:attr:`RegisteredBackground.contrast`: the second-least ring variance over the
    least among the shifts tried). A camera that sees the texture sharply has a contrast of
    2-25; a defocused one, or one whose ring a spot's glare fills, ~1-2, and it misses moves
    or makes spurious ones. The leader is measured first without a hint, the follower with
    the leader's shifts as its hint. Each camera's running mean of log(contrast) over the
    frames that tried other shifts decays by :attr:`DECAY` a block; the lead changes when the
    other camera's is higher by :attr:`MARGIN`.

    Cameras are 0 (left) and 1 (right)."""

    DECAY = 0.9
    """Share of the running evidence kept from block to block (~10 blocks' memory)."""
    MARGIN = float(np.log(1.25))
    """The lead changes when the other camera's running log-contrast is higher by this."""

    def __init__(self) -> None:
        self.lead = 0
        self.sums = np.zeros(2)
        self.weights = np.zeros(2)

    @property
    def log_contrast(self) -> np.ndarray:
        """(2,) running mean log-contrast per camera (NaN before any frame tried a shift)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.weights > 0, self.sums / np.maximum(self.weights, 1e-300), np.nan)

    def update(self, contrasts: Sequence[np.ndarray]) -> None:
        """Fold one block in and hand the lead over where the other camera is clearly better.

        Parameters
        ----------
        contrasts : sequence of ndarray
            Per camera (0 left, 1 right) the block's :attr:`RegisteredBackground.contrast`,
            (F,) (NaN: no other shift tried in that frame).
        """
        self.sums *= self.DECAY
        self.weights *= self.DECAY
        for c in (0, 1):
            x = np.asarray(contrasts[c], dtype=np.float64)
            x = x[np.isfinite(x) & (x > 0)]
            self.sums[c] += float(np.log(x).sum())
            self.weights[c] += x.size
        lc = self.log_contrast
        other = 1 - self.lead
        if np.isfinite(lc[other]) and (not np.isfinite(lc[self.lead]) or lc[other] > lc[self.lead] + self.MARGIN):
            self.lead = other


def _box(cx: float, cy: float, half: int, H: int, W: int) -> tuple[int, int, int, int]:
    """The box of half-size ``half`` around round(centre), inside the frame: x0, y0, x1, y1."""
    xr, yr = int(np.rint(cx)), int(np.rint(cy))
    return max(xr - half, 0), max(yr - half, 0), min(xr + half + 1, W), min(yr + half + 1, H)


def _paired_vars_reference(pix_r: np.ndarray, ys_r: np.ndarray, xs_r: np.ndarray, b0: np.ndarray,
                           bg: np.ndarray, m: int, sx: int, sy: int, n_all: int) -> tuple[bool, float, float]:
    """The ring's residual variances (DN^2) against the map under it at the last shift (``b0``)
    and at (sx, sy), over the ring pixels where the map holds both; ok is False where it
    holds too few (:data:`MIN_SEEN`). The reference of the kernel's ``_paired_vars``."""
    bc = bg[ys_r - sy + m, xs_r - sx + m].astype(np.float64)
    ok = np.isfinite(b0) & np.isfinite(bc)
    k = int(ok.sum())
    if n_all == 0 or k < MIN_SEEN * n_all or k < 2:
        return False, 0.0, 0.0
    return True, float(np.var(pix_r[ok] - b0[ok])), float(np.var(pix_r[ok] - bc[ok]))


def map_gradient(bg: np.ndarray, qy: int, qx: int) -> tuple[float, float, bool]:
    """The map's central-difference gradient at map point (qy, qx).

    Parameters
    ----------
    bg : ndarray
        (Hm, Wm) the map, float32 DN (+inf: unseen).
    qy, qx : int
        Map row and column, px.

    Returns
    -------
    gx, gy : float
        d/dx and d/dy, DN/px; (0, 0) where it is not known.
    ok : bool
        The point and its four neighbours are on the map and seen.
    """
    Hm, Wm = bg.shape
    if qy < 1 or qx < 1 or qy > Hm - 2 or qx > Wm - 2:
        return 0.0, 0.0, False
    a, b = float(bg[qy, qx - 1]), float(bg[qy, qx + 1])
    c, d = float(bg[qy - 1, qx]), float(bg[qy + 1, qx])
    if not (a < np.inf and b < np.inf and c < np.inf and d < np.inf and bg[qy, qx] < np.inf):
        return 0.0, 0.0, False
    return 0.5 * (b - a), 0.5 * (d - c), True


def _residual_reference(img: np.ndarray, ys_r: np.ndarray, xs_r: np.ndarray, bg: np.ndarray, m: int,
                        sx: int, sy: int) -> tuple[float, float]:
    """The residual (subpixel) image shift (rx, ry) px beyond the whole-pixel (sx, sy): the
    least-squares fit of ``frame - map = -grad(map) . r + c`` over the ring pixels where the
    map and its neighbours are seen (one Lucas-Kanade step); (0, 0) when the ring's
    gradients do not determine it, clipped to :data:`MAX_RESIDUAL_PX`."""
    rows = []
    for y, x in zip(ys_r.tolist(), xs_r.tolist()):
        qy, qx = y - sy + m, x - sx + m
        gx, gy, ok = map_gradient(bg, qy, qx)
        if ok:
            rows.append((gx, gy, float(img[y, x]) - float(bg[qy, qx])))
    return _residual_solve(np.array(rows, dtype=np.float64).reshape(-1, 3))


def _residual_solve(rows: np.ndarray) -> tuple[float, float]:
    """(rx, ry) from the ring's (gx, gy, e) rows (:func:`_residual_reference`)."""
    n = rows.shape[0]
    if n < MIN_RESIDUAL_PIXELS:
        return 0.0, 0.0
    mean = rows.mean(axis=0)
    g = rows[:, :2] - mean[:2]
    e = rows[:, 2] - mean[2]
    cxx, cxy, cyy = float(g[:, 0] @ g[:, 0]), float(g[:, 0] @ g[:, 1]), float(g[:, 1] @ g[:, 1])
    bx, by = float(g[:, 0] @ e), float(g[:, 1] @ e)
    det = cxx * cyy - cxy * cxy
    if not det > MIN_RESIDUAL_DET * n * n:
        return 0.0, 0.0
    rx = -(cyy * bx - cxy * by) / det
    ry = -(cxx * by - cxy * bx) / det
    lim = MAX_RESIDUAL_PX
    return min(max(float(rx), -lim), lim), min(max(float(ry), -lim), lim)


def measure_block_reference(frames: np.ndarray, centres: np.ndarray, sigma: float, half: int, ring: int,
                            bg: np.ndarray, stamp: np.ndarray, blk: int, rise: float, m: int,
                            shift: np.ndarray, level: np.ndarray, out_lum: np.ndarray,
                            out_shift: np.ndarray, hint: np.ndarray | None = None,
                            out_contrast: np.ndarray | None = None, fold: bool = True,
                            subpixel: bool = False, out_res: np.ndarray | None = None) -> None:
    """Pure-numpy reference of :func:`measure_block` (see
    :meth:`RegisteredBackground.measure`). Per frame: the shift (ring match), then the
    block's relaxation and the least value folded in over each LED's outer box; then, the
    whole block folded in, per frame the Gaussian-weighted mean of ``frame - bg`` over each
    LED's window box.

    Parameters
    ----------
    frames : ndarray
        (F, H, W) one camera's frames, DN.
    centres : ndarray
        (F, N, 2) LED centres (x, y), px.
    sigma : float
        Gaussian window sigma, px.
    half : int
        Half-size of the window's box, px (:func:`window_half`).
    ring : int
        Width of the ring of background pixels beyond it, px (:data:`RING_PX`).
    bg, stamp : ndarray
        The map (H + 2m, W + 2m) float32 DN (+inf: never seen) and the block that last
        relaxed each point, int64 (updated in place).
    blk : int
        This block's number.
    rise : float
        Relaxation per block, DN.
    m : int
        The map's margin, px (:data:`MAX_SHIFT_PX`).
    shift : ndarray
        (2,) int64 the last frame's shift (x, y), px (updated in place).
    level : ndarray
        (2,) float64 the running ring variance (DN^2) and the frames judged (updated).
    out_lum : ndarray
        (F, N) float64 output: light above the map, DN.
    out_shift : ndarray
        (F, 2) int64 output: the shift found in each frame, px.
    hint : ndarray, optional
        (F + 1, 2) int64 another camera's shifts in the frame before these and in these, px
        ((0, 2): none); its steps are the moves hinted.
    out_contrast : ndarray, optional
        (F,) float64 output: the second-least over the least ring variance of the shifts
        tried (NaN: none tried), :attr:`RegisteredBackground.contrast`.
    fold : bool
        False: the shifts only (the map is not touched, ``out_lum`` not written).
    subpixel : bool
        Also the residual shift beyond the whole pixels, per frame (:func:`_residual_reference`,
        against the map before the frame is folded in), and the light above the map moved
        on by it to first order: ``frame - (map - grad(map) . r)``.
    out_res : ndarray, optional
        (F, 2) float64 output: the residual shift (x, y) of each frame, px (0 without
        ``subpixel``).
    """
    F, H, W = frames.shape
    hint = np.zeros((0, 2), np.int64) if hint is None else hint
    N = centres.shape[1]
    outer = half + ring
    for f in range(F):
        img = frames[f].astype(np.float64)
        boxes = [_box(centres[f, i, 0], centres[f, i, 1], outer, H, W) for i in range(N)]
        inner = [_box(centres[f, i, 0], centres[f, i, 1], half, H, W) for i in range(N)]
        # ---- the shift: candidates within 1 px of the last, judged on the ring pixels
        # against the last shift's (paired, where the map holds both)
        bx, by = int(shift[0]), int(shift[1])
        best, best_var = (bx, by), np.inf
        rings = []
        for (x0, y0, x1, y1), (ix0, iy0, ix1, iy1) in zip(boxes, inner):
            ys, xs = np.mgrid[y0:y1, x0:x1]
            keep = ~((xs >= ix0) & (xs < ix1) & (ys >= iy0) & (ys < iy1))
            rings.append((ys[keep], xs[keep], img[ys[keep], xs[keep]]))
        n_all = sum(r[0].size for r in rings)
        ys_r = np.concatenate([r[0] for r in rings]) if rings else np.zeros(0, np.int64)
        xs_r = np.concatenate([r[1] for r in rings]) if rings else np.zeros(0, np.int64)
        pix_r = np.concatenate([r[2] for r in rings]) if rings else np.zeros(0)
        b0 = bg[ys_r - by + m, xs_r - bx + m].astype(np.float64)
        seen0 = np.isfinite(b0)
        k0 = int(seen0.sum())
        judged = n_all > 0 and k0 >= MIN_SEEN * n_all and k0 >= 2
        v_now = float(np.var(pix_r[seen0] - b0[seen0])) if judged else np.inf
        search = judged and (not v_now <= SEARCH_RATIO * float(level[0]) or int(level[1]) % SEARCH_EVERY == 0)
        tried = [v_now]
        for dy in (-1, 0, 1) if search else ():
            for dx in (-1, 0, 1):
                sx, sy = bx + dx, by + dy
                if (dx == 0 and dy == 0) or abs(sx) > m or abs(sy) > m:
                    continue
                ok, v0, vc = _paired_vars_reference(pix_r, ys_r, xs_r, b0, bg, m, sx, sy, n_all)
                if not ok:
                    continue
                tried.append(vc)
                if vc < SWITCH * v0 and vc < best_var:
                    best, best_var = (sx, sy), vc
        if out_contrast is not None and len(tried) >= 2:
            lo2 = sorted(tried)[:2]
            out_contrast[f] = lo2[1] / max(lo2[0], 1e-12)
        if judged and best == (bx, by) and f + 1 < hint.shape[0]:
            hx = bx + int(hint[f + 1, 0]) - int(hint[f, 0])
            hy = by + int(hint[f + 1, 1]) - int(hint[f, 1])
            if (hx, hy) != (bx, by) and abs(hx) <= m and abs(hy) <= m:
                ok, v0, vc = _paired_vars_reference(pix_r, ys_r, xs_r, b0, bg, m, hx, hy, n_all)
                if ok and vc <= HINT_SWITCH * v0:
                    best, best_var = (hx, hy), vc
        shift[0], shift[1] = best
        taken = best_var if best != (bx, by) else v_now
        if judged:
            level[0] = min(taken, float(level[0]) * LEVEL_RISE)
            level[1] += 1
        sx, sy = int(shift[0]), int(shift[1])
        out_shift[f, 0], out_shift[f, 1] = sx, sy
        if subpixel and judged and out_res is not None:
            out_res[f] = _residual_reference(img, ys_r, xs_r, bg, m, sx, sy)
        if not fold:
            continue
        # ---- fold the frame in: relax once per block, then the least value
        for x0, y0, x1, y1 in boxes:
            ys, xs = np.mgrid[y0:y1, x0:x1]
            qy, qx = ys - sy + m, xs - sx + m
            fresh = stamp[qy, qx] != blk
            bg[qy[fresh], qx[fresh]] += np.float32(rise)
            stamp[qy, qx] = blk
            bg[qy, qx] = np.minimum(bg[qy, qx], img[y0:y1, x0:x1].astype(np.float32))
    # ---- the light above it (every frame of the block folded in first, as
    # PixelBackground): Gaussian weights around the exact centre, normalized
    a = -0.5 / sigma ** 2
    for f in range(F if fold else 0):
        img = frames[f].astype(np.float64)
        sx, sy = int(out_shift[f, 0]), int(out_shift[f, 1])
        inner = [_box(centres[f, i, 0], centres[f, i, 1], half, H, W) for i in range(N)]
        for i, (x0, y0, x1, y1) in enumerate(inner):
            cx, cy = centres[f, i]
            wx = np.exp(a * np.square(np.arange(x0, x1) - cx))
            wy = np.exp(a * np.square(np.arange(y0, y1) - cy))
            light = img[y0:y1, x0:x1] - bg[y0 - sy + m:y1 - sy + m, x0 - sx + m:x1 - sx + m].astype(np.float64)
            if subpixel and out_res is not None and (out_res[f, 0] != 0.0 or out_res[f, 1] != 0.0):
                rx, ry = float(out_res[f, 0]), float(out_res[f, 1])
                for yy in range(y0, y1):
                    for xx in range(x0, x1):
                        gx, gy, _ = map_gradient(bg, yy - sy + m, xx - sx + m)
                        light[yy - y0, xx - x0] += gx * rx + gy * ry
            s = wy.sum() * wx.sum()
            out_lum[f, i] = float(wy @ light @ wx) / s if s > 0 else 0.0


def _warm_args() -> tuple:
    fr = np.zeros((2, 24, 24), np.uint8)
    bg = np.full((24 + 2 * MAX_SHIFT_PX, 24 + 2 * MAX_SHIFT_PX), np.inf, np.float32)
    return (fr, np.full((2, 1, 2), 12.0), 1.0, 4, RING_PX, bg, np.zeros(bg.shape, np.int64), 1, 0.25,
            MAX_SHIFT_PX, np.zeros(2, np.int64), np.array([np.inf, 0.0]), np.zeros((2, 1)), np.zeros((2, 2), np.int64),
            np.zeros((0, 2), np.int64), np.zeros(2), True, False, np.zeros((2, 2)))


def _warm_args16() -> tuple:
    a = list(_warm_args())
    a[0] = np.zeros((2, 24, 24), np.uint16)
    return tuple(a)


@njit(inline="always")
def _paired_vars(frame: np.ndarray, ring_y: np.ndarray, ring_x: np.ndarray, n_all: int, bg: np.ndarray,
                 m: int, bx: int, by: int, sx: int, sy: int) -> tuple[bool, float, float]:
    """The ring's residual variances (DN^2) against the map at shift (bx, by) and at (sx, sy),
    over the ring pixels where the map holds both; ok is False where it holds too few
    (:data:`MIN_SEEN`)."""
    k = 0
    m0 = 0.0
    mc = 0.0
    q0 = 0.0
    qc = 0.0
    for j in range(n_all):
        y, x = ring_y[j], ring_x[j]
        b0 = bg[y - by + m, x - bx + m]
        bc = bg[y - sy + m, x - sx + m]
        if b0 < np.inf and bc < np.inf:
            v = float(frame[y, x])
            e0 = v - float(b0)
            ec = v - float(bc)
            m0 += e0
            mc += ec
            q0 += e0 * e0
            qc += ec * ec
            k += 1
    if n_all == 0 or k < MIN_SEEN * n_all or k < 2:
        return False, 0.0, 0.0
    m0 /= k
    mc /= k
    return True, max(q0 / k - m0 * m0, 0.0), max(qc / k - mc * mc, 0.0)


@njit(inline="always")
def _gradient(bg: np.ndarray, qy: int, qx: int) -> tuple[float, float, bool]:
    """:func:`map_gradient` (compiled)."""
    Hm, Wm = bg.shape
    if qy < 1 or qx < 1 or qy > Hm - 2 or qx > Wm - 2:
        return 0.0, 0.0, False
    a = bg[qy, qx - 1]
    b = bg[qy, qx + 1]
    c = bg[qy - 1, qx]
    d = bg[qy + 1, qx]
    if not (a < np.inf and b < np.inf and c < np.inf and d < np.inf and bg[qy, qx] < np.inf):
        return 0.0, 0.0, False
    return 0.5 * (float(b) - float(a)), 0.5 * (float(d) - float(c)), True


@njit
def _residual(frame: np.ndarray, ring_y: np.ndarray, ring_x: np.ndarray, n_all: int, bg: np.ndarray,
              m: int, sx: int, sy: int) -> tuple[float, float]:
    """:func:`_residual_reference` (compiled; two passes: the means, then the centred sums)."""
    n = 0
    mx = 0.0
    my = 0.0
    me = 0.0
    for j in range(n_all):
        qy, qx = ring_y[j] - sy + m, ring_x[j] - sx + m
        gx, gy, ok = _gradient(bg, qy, qx)
        if ok:
            mx += gx
            my += gy
            me += float(frame[ring_y[j], ring_x[j]]) - float(bg[qy, qx])
            n += 1
    if n < MIN_RESIDUAL_PIXELS:
        return 0.0, 0.0
    mx /= n
    my /= n
    me /= n
    cxx = 0.0
    cxy = 0.0
    cyy = 0.0
    bx = 0.0
    by = 0.0
    for j in range(n_all):
        qy, qx = ring_y[j] - sy + m, ring_x[j] - sx + m
        gx, gy, ok = _gradient(bg, qy, qx)
        if ok:
            ux = gx - mx
            uy = gy - my
            e = float(frame[ring_y[j], ring_x[j]]) - float(bg[qy, qx]) - me
            cxx += ux * ux
            cxy += ux * uy
            cyy += uy * uy
            bx += ux * e
            by += uy * e
    det = cxx * cyy - cxy * cxy
    if not det > MIN_RESIDUAL_DET * n * n:
        return 0.0, 0.0
    rx = -(cyy * bx - cxy * by) / det
    ry = -(cxx * by - cxy * bx) / det
    lim = MAX_RESIDUAL_PX
    return min(max(rx, -lim), lim), min(max(ry, -lim), lim)


@njit(warm=_warm_args)
def measure_block(frames: np.ndarray, centres: np.ndarray, sigma: float, half: int, ring: int,
                  bg: np.ndarray, stamp: np.ndarray, blk: int, rise: float, m: int,
                  shift: np.ndarray, level: np.ndarray, out_lum: np.ndarray, out_shift: np.ndarray,
                  hint: np.ndarray, out_contrast: np.ndarray, fold: bool, subpixel: bool,
                  out_res: np.ndarray) -> None:
    """One camera's block (:meth:`RegisteredBackground.measure`): per frame the image shift
    (ring match within 1 px of the last, or the move of another camera's shifts ``hint``
    (F + 1, 2) -- (0, 2): none -- where that matches at least as well; how clearly the ring
    told the shifts apart into ``out_contrast`` (F,)) and the frame folded into the map ``bg`` (H + 2m,
    W + 2m) float32 / ``stamp`` int64 (relaxed by ``rise`` DN once per block ``blk``); then
    per frame each LED's Gaussian-weighted mean light above the map (``sigma`` px over the box of
    half-size ``half`` px) into out_lum (F, N); the shifts into out_shift (F, 2), the last
    one into ``shift`` (2,) and the running ring variance and the frames judged into ``level`` (2,).
    With ``fold`` False only the shifts: nothing is folded into the map (``bg``, ``stamp``
    untouched) and ``out_lum`` is not written. With ``subpixel`` also each frame's residual
    shift beyond the whole pixels into ``out_res`` (F, 2) and the light above the map moved
    on by it (:func:`measure_block_reference`). The same numbers as
    :func:`measure_block_reference` (float64 sums in a different order: ~1e-12 relative)."""
    F, H, W = frames.shape
    N = centres.shape[1]
    outer = half + ring
    a = -0.5 / (sigma * sigma)
    box = np.empty((N, 4), np.int64)
    inner = np.empty((N, 4), np.int64)
    ring_y = np.empty(N * (2 * outer + 1) ** 2, np.int64)  # every LED's outer box: enough
    ring_x = np.empty(ring_y.size, np.int64)
    wx = np.empty(2 * half + 1)
    for f in range(F):
        for i in range(N):
            xr = int(np.rint(centres[f, i, 0]))
            yr = int(np.rint(centres[f, i, 1]))
            box[i, 0], box[i, 1] = max(xr - outer, 0), max(yr - outer, 0)
            box[i, 2], box[i, 3] = min(xr + outer + 1, W), min(yr + outer + 1, H)
            inner[i, 0], inner[i, 1] = max(xr - half, 0), max(yr - half, 0)
            inner[i, 2], inner[i, 3] = min(xr + half + 1, W), min(yr + half + 1, H)
        # ---- the shift: the ring pixels and the map under them at the last shift
        bx, by = shift[0], shift[1]
        n_all = 0
        for i in range(N):
            for y in range(box[i, 1], box[i, 3]):
                inside_y = inner[i, 1] <= y < inner[i, 3]
                for x in range(box[i, 0], box[i, 2]):
                    if inside_y and inner[i, 0] <= x < inner[i, 2]:
                        continue
                    ring_y[n_all] = y
                    ring_x[n_all] = x
                    n_all += 1
        # the ring's variance at the last shift: the other shifts only when it has risen
        k0 = 0
        s1 = 0.0
        s2 = 0.0
        for j in range(n_all):
            b0 = bg[ring_y[j] - by + m, ring_x[j] - bx + m]
            if b0 < np.inf:  # (the map holds +inf where nothing was seen yet)
                v = float(frames[f, ring_y[j], ring_x[j]]) - float(b0)
                s1 += v
                s2 += v * v
                k0 += 1
        judged = n_all > 0 and k0 >= MIN_SEEN * n_all and k0 >= 2
        v_now = np.inf
        if judged:
            mu = s1 / k0
            v_now = max(s2 / k0 - mu * mu, 0.0)
        search = judged and (not v_now <= SEARCH_RATIO * level[0] or int(level[1]) % SEARCH_EVERY == 0)
        best_x, best_y = bx, by
        best_var = np.inf
        lo1 = v_now  # the least and second-least variance of the shifts tried
        lo2 = np.inf
        n_tried = 1 if judged else 0
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                sx, sy = bx + dx, by + dy
                if not search or (dx == 0 and dy == 0) or abs(sx) > m or abs(sy) > m:
                    continue
                ok, v0, vc = _paired_vars(frames[f], ring_y, ring_x, n_all, bg, m, bx, by, sx, sy)
                if not ok:
                    continue
                n_tried += 1
                if vc < lo1:
                    lo2 = lo1
                    lo1 = vc
                elif vc < lo2:
                    lo2 = vc
                if vc < SWITCH * v0 and vc < best_var:
                    best_x, best_y, best_var = sx, sy, vc
        if n_tried >= 2 and f < out_contrast.shape[0]:
            out_contrast[f] = lo2 / max(lo1, 1e-12)
        if judged and best_x == bx and best_y == by and f + 1 < hint.shape[0]:
            hx = bx + hint[f + 1, 0] - hint[f, 0]
            hy = by + hint[f + 1, 1] - hint[f, 1]
            if (hx != bx or hy != by) and abs(hx) <= m and abs(hy) <= m:
                ok, v0, vc = _paired_vars(frames[f], ring_y, ring_x, n_all, bg, m, bx, by, hx, hy)
                if ok and vc <= HINT_SWITCH * v0:
                    best_x, best_y, best_var = hx, hy, vc
        shift[0], shift[1] = best_x, best_y
        taken = best_var if (best_x != bx or best_y != by) else v_now
        if judged:
            level[0] = min(taken, level[0] * LEVEL_RISE)
            level[1] += 1
        sx, sy = shift[0], shift[1]
        out_shift[f, 0], out_shift[f, 1] = sx, sy
        if subpixel and judged:
            out_res[f, 0], out_res[f, 1] = _residual(frames[f], ring_y, ring_x, n_all, bg, m, sx, sy)
        if not fold:
            continue
        # ---- fold the frame in
        for i in range(N):
            for y in range(box[i, 1], box[i, 3]):
                qy = y - sy + m
                for x in range(box[i, 0], box[i, 2]):
                    qx = x - sx + m
                    if stamp[qy, qx] != blk:
                        bg[qy, qx] += np.float32(rise)
                        stamp[qy, qx] = blk
                    v = np.float32(frames[f, y, x])
                    if v < bg[qy, qx]:
                        bg[qy, qx] = v
    # ---- the light above it (the whole block folded in first)
    for f in range(F if fold else 0):
        sx, sy = out_shift[f, 0], out_shift[f, 1]
        rx = out_res[f, 0] if subpixel else 0.0
        ry = out_res[f, 1] if subpixel else 0.0
        moved = rx != 0.0 or ry != 0.0
        for i in range(N):
            xr = int(np.rint(centres[f, i, 0]))
            yr = int(np.rint(centres[f, i, 1]))
            inner[i, 0], inner[i, 1] = max(xr - half, 0), max(yr - half, 0)
            inner[i, 2], inner[i, 3] = min(xr + half + 1, W), min(yr + half + 1, H)
        for i in range(N):
            cx, cy = centres[f, i, 0], centres[f, i, 1]
            x0, x1 = inner[i, 0], inner[i, 2]
            wsx = 0.0
            for x in range(x0, x1):
                wx[x - x0] = np.exp(a * (x - cx) * (x - cx))
                wsx += wx[x - x0]
            s = 0.0
            wsy = 0.0
            for y in range(inner[i, 1], inner[i, 3]):
                wy = np.exp(a * (y - cy) * (y - cy))
                wsy += wy
                r = 0.0
                if moved:
                    for x in range(x0, x1):
                        gx, gy, _ = _gradient(bg, y - sy + m, x - sx + m)
                        r += (float(frames[f, y, x]) - float(bg[y - sy + m, x - sx + m]) + (gx * rx + gy * ry)) * wx[x - x0]
                else:
                    for x in range(x0, x1):
                        r += (float(frames[f, y, x]) - float(bg[y - sy + m, x - sx + m])) * wx[x - x0]
                s += wy * r
            out_lum[f, i] = s / (wsx * wsy) if wsx * wsy > 0 else 0.0


from iscd.core.jit import register_warm  # noqa: E402

register_warm(measure_block, _warm_args16)
