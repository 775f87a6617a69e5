"""LED luminance from frames: ROI mean (3.10), saturation- and crosstalk-aware estimates.

All functions take a block of frames ``(F, H, W)`` (any integer or float dtype) and LED
centres in px (x right, y down, pixel centres at integers), either fixed ``(N, 2)`` or per
frame ``(F, N, 2)`` (tracked), and return ``(F, N)`` float64 luminance in DN. LED windows
are gathered for all LEDs and frames at once with fancy indexing; pixels of a window
outside the image are left out of its mean (a window entirely outside gives NaN).

* :func:`roi_mean` -- the dissertation's luminance (3.10): the mean of the pixel values in
  the LED's rectangular ROI.
* :func:`gauss_mean` -- the pipeline's: (3.10) with Gaussian weights around the exact
  sub-pixel LED position, the same at every sub-pixel phase (a box is not).
* :func:`refine_centres` -- each frame's LED positions: the array's shift and scale in that
  frame from spot centroids (rig vibration, an approaching array).
  :func:`follow_and_measure` does both for both cameras from one patch gather
  (:func:`gather_patches`).
* :class:`SpotLuminance` -- per frame, least squares of all windows' pixels against
  per-LED spot templates (estimated from the data by alternating least squares, each
  template confined to its LED's window, with a static per-pixel background). Pixels at
  the saturation level are left out of the fit (censored), so an LED whose core clips is
  measured from its unsaturated flanks: the estimate stays linear in the LED's light
  where the ROI mean bends over. Neighbouring LEDs of an array (4 px pitch at 50 m) are
  separated because every pixel is explained by the sum of the templates that reach it.
  The output is scaled like an ROI mean (DN): background mean of the window + the LED's
  own contribution averaged over the window.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


def _window(size: int | tuple[int, int]) -> tuple[int, int]:
    w, h = (size, size) if isinstance(size, (int, np.integer)) else size
    if w < 1 or h < 1:
        raise ValueError(f"ROI size must be >= 1 px, got {size}")
    return int(w), int(h)


def window_indices(centres: np.ndarray, size: int | tuple[int, int], shape: tuple[int, int]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row and column indices of each LED's window and a validity mask.

    Parameters
    ----------
    centres : ndarray
        (..., N, 2) LED centres (x, y), px.
    size : int or (int, int)
        Window width w, or (w, h), px.
    shape : (int, int)
        Image shape (H, W), px.

    Returns
    -------
    rows : ndarray of intp
        (..., N, h, 1) row indices, clipped into the image.
    cols : ndarray of intp
        (..., N, 1, w) column indices, clipped into the image.
    valid : ndarray of bool
        (..., N, h, w) window cells inside the image.
    """
    w, h = _window(size)
    c = np.asarray(centres, dtype=np.float64)
    x0 = np.rint(c[..., 0] - (w - 1) / 2).astype(np.intp)
    y0 = np.rint(c[..., 1] - (h - 1) / 2).astype(np.intp)
    rows = y0[..., None] + np.arange(h)
    cols = x0[..., None] + np.arange(w)
    H, W = shape
    vr = (rows >= 0) & (rows < H)
    vc = (cols >= 0) & (cols < W)
    valid = vr[..., :, None] & vc[..., None, :]
    return np.clip(rows, 0, H - 1)[..., :, None], np.clip(cols, 0, W - 1)[..., None, :], valid


def gather_windows(frames: np.ndarray, centres: np.ndarray, size: int | tuple[int, int]
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of every LED window in every frame: (F, N, h, w) and validity (.., N, h, w).

    Parameters
    ----------
    frames : ndarray
        (F, H, W) frames, DN.
    centres : ndarray
        (N, 2) or (F, N, 2) LED centres (x, y), px.
    size : int or (int, int)
        Window width w, or (w, h), px.

    Returns
    -------
    pix : ndarray
        (F, N, h, w) pixel values, DN, the dtype of ``frames`` (cells outside the image hold
        the nearest edge pixel).
    valid : ndarray of bool
        (N, h, w) or (F, N, h, w), like ``centres``: cells inside the image.
    """
    fr = np.asarray(frames)
    if fr.ndim != 3:
        raise ValueError(f"expected frames (F, H, W), got shape {fr.shape}")
    c = np.asarray(centres, dtype=np.float64)
    if c.ndim == 2:
        rows, cols, valid = window_indices(c, size, fr.shape[1:])
        return fr[:, rows, cols], valid
    if c.ndim == 3 and c.shape[0] == fr.shape[0]:
        rows, cols, valid = window_indices(c, size, fr.shape[1:])
        f = np.arange(fr.shape[0]).reshape(-1, 1, 1, 1)
        return fr[f, rows, cols], valid
    raise ValueError(f"centres must be (N, 2) or (F, N, 2) with F = {fr.shape[0]}, got {c.shape}")


def roi_mean(frames: np.ndarray, centres: np.ndarray, size: int | tuple[int, int] = 3) -> np.ndarray:
    """Mean pixel value of each LED's ROI (3.10): (F, N) DN.

    The window is centred on the rounded LED centre (for even sizes, on the pixel corner
    nearest to it).

    Parameters
    ----------
    frames : ndarray
        (F, H, W) frames, DN.
    centres : ndarray
        (N, 2) or (F, N, 2) LED centres (x, y), px.
    size : int or (int, int)
        ROI width (and height), or (w, h), px.

    Returns
    -------
    ndarray of float64
        (F, N) luminance, DN; NaN for a window entirely outside the image.

    References
    ----------
    Dissertation, eq. (3.10).
    """
    pix, valid = gather_windows(frames, centres, size)
    s = (pix.astype(np.float64) * valid).sum(axis=(-2, -1))
    cnt = np.broadcast_to(valid, pix.shape).sum(axis=(-2, -1))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = s / cnt
    out[cnt == 0] = np.nan
    return out


@dataclass
class Patches:
    """The pixels around each LED in each frame, gathered once: ``pix`` (F, N, K, K)
    float32, whose first column and row are image pixels ``x0``, ``y0`` (F, N). A patch
    at the image edge is moved inside the image (so an LED there is off its centre)."""

    pix: np.ndarray
    x0: np.ndarray
    y0: np.ndarray

    @property
    def xs(self) -> np.ndarray:
        """(F, N, K) x of the patch columns, px."""
        return (self.x0[..., None] + np.arange(self.pix.shape[-1])).astype(np.float32)

    @property
    def ys(self) -> np.ndarray:
        """(F, N, K) y of the patch rows, px."""
        return (self.y0[..., None] + np.arange(self.pix.shape[-2])).astype(np.float32)


def gather_patches(frames: np.ndarray, centres: np.ndarray, half: int,
                   out: np.ndarray | None = None) -> Patches:
    """(2 half + 1)^2 px patches around the rounded centres (N, 2) or (F, N, 2), px;
    written into ``out`` (F, N, K, K) float32 when given.

    A patch at the image edge is moved inside the image; in an image smaller than a patch
    the edge pixels repeat.

    Parameters
    ----------
    frames : ndarray
        (F, H, W) frames, DN.
    centres : ndarray
        (N, 2) or (F, N, 2) LED centres (x, y), px.
    half : int
        Patch half-size, px (K = 2 half + 1).
    out : ndarray, optional
        (F, N, K, K) float32 array to write the pixels into.

    Returns
    -------
    Patches
        Pixels (F, N, K, K) float32, DN, and the patches' first column and row ``x0``,
        ``y0`` (F, N), px.
    """
    fr = np.asarray(frames)
    if fr.ndim != 3:
        raise ValueError(f"expected frames (F, H, W), got shape {fr.shape}")
    F, H, W = fr.shape
    c = np.asarray(centres, dtype=np.float64)
    if c.ndim not in (2, 3) or c.shape[-1] != 2 or (c.ndim == 3 and c.shape[0] != F):
        raise ValueError(f"centres must be (N, 2) or (F, N, 2) with F = {F}, got {c.shape}")
    c = np.broadcast_to(c, (F,) + c.shape[-2:])
    K = 2 * half + 1
    x0 = np.rint(c[..., 0]).astype(np.intp) - half
    y0 = np.rint(c[..., 1]).astype(np.intp) - half
    if H >= K and W >= K:
        # whole K x K blocks out of a sliding-window view (4x faster than pixel indexing);
        # a patch that would cross the image edge is moved inside it
        x0 = np.clip(x0, 0, W - K)
        y0 = np.clip(y0, 0, H - K)
        view = sliding_window_view(fr, (K, K), axis=(1, 2))
        blocks = view[np.arange(F)[:, None], y0, x0]
        if out is None:
            pix = blocks.astype(np.float32)
        else:
            np.copyto(out, blocks)
            pix = out
    else:  # an image smaller than a patch: edge pixels repeat
        k = np.arange(K)
        xs = np.clip(x0[..., None] + k, 0, W - 1)[..., None, :]
        ys = np.clip(y0[..., None] + k, 0, H - 1)[..., :, None]
        pix = fr[np.arange(F)[:, None, None, None], ys, xs].astype(np.float32)
        if out is not None:
            out[...] = pix
            pix = out
    return Patches(pix=pix, x0=x0, y0=y0)


def box_cover(c: np.ndarray, px: np.ndarray, w: int) -> np.ndarray:
    """Fraction of each pixel (centres ``px`` (..., K), pixel j covering [px_j - 0.5,
    px_j + 0.5]) inside a sub-pixel box of width ``w`` px centred at c (...): (..., K)
    float32, summing to w when the box lies inside.

    Parameters
    ----------
    c : ndarray
        (...) box centres, px.
    px : ndarray
        (..., K) pixel centres, px.
    w : int
        Box width, px.

    Returns
    -------
    ndarray of float32
        (..., K) covered fractions, 0 .. 1.
    """
    a = (np.asarray(c, dtype=np.float32) - np.float32(w / 2.0))[..., None]
    return np.clip(np.minimum(a + np.float32(w), px + 0.5) - np.maximum(a, px - 0.5), 0.0, 1.0)


def gauss_in_patches(p: Patches, centres: np.ndarray, sigma_px: float | np.ndarray) -> np.ndarray:
    """Gaussian-weighted mean (F, N) of each patch around sub-pixel centres (F, N, 2)
    (see :func:`gauss_mean`).

    Parameters
    ----------
    p : Patches
        (F, N, K, K) patches (:func:`gather_patches`), DN.
    centres : ndarray
        (F, N, 2) sub-pixel LED centres (x, y), px.
    sigma_px : float or ndarray
        Gaussian window sigma, px: one, or one per frame (F,).

    Returns
    -------
    ndarray of float32
        (F, N) luminance, DN.

    References
    ----------
    Dissertation, eq. (3.10) (with Gaussian weights).
    """
    sig = np.asarray(sigma_px, dtype=np.float64)
    if not np.all(sig > 0):
        raise ValueError(f"sigma_px must be > 0, got {sigma_px}")
    a = (-0.5 / sig ** 2).astype(np.float32)
    if a.ndim:
        a = a[:, None, None]
    c = np.asarray(centres, dtype=np.float32)
    wx = np.exp(a * np.square(p.xs - c[..., 0:1]))
    wy = np.exp(a * np.square(p.ys - c[..., 1:2]))
    wx /= wx.sum(-1, keepdims=True)
    wy /= wy.sum(-1, keepdims=True)
    rows = np.matmul(wy[..., None, :], p.pix)[..., 0, :]  # (F, N, K)
    return np.einsum("fnk,fnk->fn", rows, wx)


def gauss_mean(frames: np.ndarray, centres: np.ndarray, sigma_px: float = 1.0,
               radius: int | None = None) -> np.ndarray:
    """Gaussian-weighted mean grey level around each LED: (F, N) float32 DN.

    The weights ``exp(-d^2 / (2 sigma^2))`` are evaluated at the pixel centres around the
    exact (sub-pixel) LED position, over (2 radius + 1)^2 pixels (radius = ceil(3.5
    sigma) by default), and normalized to sum 1. Unlike a box, whose sharp edges make
    the captured light depend on where the spot sits within its pixel (a few % of an
    unsaturated spot with 0.3 px of vibration: the dominant noise of the f/8 camera of an
    HDR pair), a smooth window sampled on the pixel grid gives a sum that is the same at
    every sub-pixel phase to a few times exp(-2 pi^2 s^2), s^2 = 1 / (1/sigma^2 +
    1/sigma_spot^2) (Poisson summation; 0.3 % for sigma = 0.85 px on a 0.85 px spot, where
    a 3x3 box varies by 7 %), and it weights the pixels by how much of the LED's light they
    hold (a matched filter).

    Parameters
    ----------
    frames : ndarray
        (F, H, W) frames, DN.
    centres : ndarray
        (N, 2) or (F, N, 2) LED centres (x, y), px.
    sigma_px : float
        Gaussian window sigma, px (> 0).
    radius : int, optional
        Window half-size, px (default ceil(3.5 sigma)).

    Returns
    -------
    ndarray of float32
        (F, N) luminance, DN.

    References
    ----------
    Dissertation, eq. (3.10) (with Gaussian weights).
    """
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be > 0, got {sigma_px}")
    R = int(np.ceil(3.5 * sigma_px)) if radius is None else int(radius)
    p = gather_patches(frames, centres, R)
    c = np.broadcast_to(np.asarray(centres, dtype=np.float64), p.x0.shape + (2,))
    return gauss_in_patches(p, c, sigma_px)


def refine_in_patches(p: Patches, centres: np.ndarray, size: int = 3, iterations: int = 3,
                      scale: bool = True, max_px: float = 1.5, groups: int = 1,
                      use: np.ndarray | None = None, accelerate: bool = True,
                      lit_light: np.ndarray | None = None, info: dict | None = None,
                      bg_pix: np.ndarray | None = None, spot_radius_px: float | None = None,
                      subtract: bool = True) -> np.ndarray:
    """:func:`refine_centres` on patches gathered around ``centres`` (F, N, 2) px (the
    patches must reach size / 2 + max_px px around them).

    An LED steers a frame only with ``LIT_SHARE`` of a lit LED's light (``lit_light``) or
    of this block's 90th percentile, whichever is more (in a block where every LED is dark
    -- zero padding -- that percentile is noise, and noise would walk the centres away).
    With ``bg_pix``, which LEDs are lit is judged on the light above it, and (``subtract``)
    the centroids are taken of that light instead of the light above each patch's darkest
    pixel (a textured background then pulls no centroid).

    Parameters
    ----------
    p : Patches
        (F, N, K, K) patches (:func:`gather_patches`), DN.
    centres : ndarray
        (F, N, 2) LED centres (x, y) the patches were gathered around, px.
    size : int
        Centroid box width, px.
    iterations : int
        Centroid rounds.
    scale : bool
        Also fit a scale of the array (with more than one LED in ``use``).
    max_px : float
        Largest correction per LED and axis, px.
    groups : int
        The frames are that many equal runs from different cameras (their light levels
        differ), each with its own least-light threshold.
    use : ndarray, optional
        Indices of the LEDs whose centroids are measured (all by default); the shift and
        scale they give move every LED.
    accelerate : bool
        The second round extrapolates the geometric series of the rounds' steps (3 rounds
        then do what 6 plain ones would).
    lit_light : ndarray, optional
        (groups,) patch light of a lit LED known from earlier blocks, DN summed over the
        patch.
    info : dict, optional
        Filled with this block's 90th percentile of the patch light per group
        (``"light"``, DN summed over the patch), to keep as the next block's ``lit_light``,
        and with ``"spot_area"`` (see ``spot_radius_px``).
    bg_pix : ndarray, optional
        (F, N, K, K) per-pixel background of each patch, DN (:class:`PixelBackground`, held
        across blocks).
    spot_radius_px : float, optional
        Also measure the lit spots' size (:func:`half_max_area`, into ``info["spot_area"]``,
        (groups,) px^2) within this radius of their refined centres, px.
    subtract : bool
        With ``bg_pix``: take the centroids of the light above it.

    Returns
    -------
    ndarray of float64
        (F, N, 2) refined centres (x, y), px.
    """
    w = _window(size)[0]
    c0 = np.asarray(centres, dtype=np.float64)
    F, N = c0.shape[:2]
    sel = np.arange(N) if use is None else np.asarray(use, dtype=np.intp)
    pix = p.pix[:, sel]
    n = sel.size
    # which LEDs are lit in which frame: their patch's light above each pixel's least value
    # over the block (a textured background cancels there, so a dark frame shows nothing),
    # against a quarter of a lit LED's (this block's 90th percentile, or what earlier
    # blocks showed: in a block where every LED is dark that percentile is noise)
    if bg_pix is None:
        shown = (pix - _background(pix, p.x0[:, sel], p.y0[:, sel], groups)).sum(axis=(-2, -1))
    else:
        shown = (pix.astype(np.float64) - bg_pix[:, sel]).sum(axis=(-2, -1))
    per = np.percentile(shown.reshape(groups, -1), 90, axis=1)  # (groups,)
    if info is not None:
        info["light"] = per
    ref = per if lit_light is None else np.maximum(per, np.asarray(lit_light, dtype=np.float64))
    lit = shown >= np.repeat(LIT_SHARE * ref, F // groups)[:, None]
    # the centroids: light above the patch's darkest pixel (a spot that moves within the
    # block keeps its shape there)
    if bg_pix is None or not subtract:
        img = pix - pix.reshape(F, n, -1).min(-1)[..., None, None]
    else:
        img = pix - bg_pix[:, sel]
    xs, ys = p.xs[:, sel], p.ys[:, sel]
    cc = c0.copy()
    prev: tuple[np.ndarray, np.ndarray] | None = None
    for it in range(iterations):
        cs = cc[:, sel]
        wx = box_cover(cs[..., 0], xs, w)
        wy = box_cover(cs[..., 1], ys, w)
        m_x = np.matmul(wy[..., None, :], img)[..., 0, :]  # (F, n, K): rows weighted, summed
        m_y = np.matmul(img, wx[..., :, None])[..., 0]  # (F, n, K)
        tot = np.einsum("fnk,fnk->fn", m_x, wx)
        safe = np.where(tot > 0, tot, 1.0)
        off = np.stack([np.einsum("fnk,fnk,fnk->fn", m_x, wx, xs) / safe - cs[..., 0],
                        np.einsum("fnk,fnk,fnk->fn", m_y, wy, ys) / safe - cs[..., 1]], -1)
        wt = np.where(lit, np.maximum(tot, 0.0), 0.0).astype(np.float64)
        norm = wt.sum(1, keepdims=True)  # (F, 1)
        safe_n = np.where(norm > 0, norm, 1.0)
        d = np.einsum("fn,fnk->fk", wt, off) / safe_n  # (F, 2)
        sc = np.zeros(F)
        ctr = np.zeros((F, 2))
        if scale and n > 1:
            ctr = np.einsum("fn,fnk->fk", wt, cs) / safe_n
            g = cs - ctr[:, None, :]
            den = np.einsum("fn,fnk,fnk->f", wt, g, g)
            sc = np.einsum("fn,fnk,fnk->f", wt, g, off) / np.where(den > 0, den, 1.0)
        if it == 1 and accelerate and prev is not None:
            # a box truncates the spot, so each round recovers the same share of what is
            # left: the rounds form a geometric series; add its remaining terms at once
            # (the ratio pooled over the block's frames)
            for cur, last in ((d, prev[0]), (sc, prev[1])):
                den2 = float(np.sum(last * last))
                rho = float(np.clip(np.sum(cur * last) / den2, 0.0, 0.8)) if den2 > 0 else 0.0
                cur *= 1.0 / (1.0 - rho)
        prev = (d.copy(), sc.copy())
        step = d[:, None, :] + sc[:, None, None] * (cc - ctr[:, None, :])
        cc = c0 + np.clip(cc + step - c0, -max_px, max_px)
    if info is not None and spot_radius_px is not None:
        info["spot_area"] = half_max_area(img, xs, ys, cc[:, sel], lit, groups, spot_radius_px)
    return cc


def half_max_area(img: np.ndarray, xs: np.ndarray, ys: np.ndarray, centres: np.ndarray,
                  lit: np.ndarray, groups: int, radius_px: float) -> np.ndarray:
    """Mean area (px^2) above half its peak of the lit spots, per group (camera): (groups,).

    Per lit spot, the pixels within ``radius_px`` of its centre (an array's neighbours stay
    out) above half the brightest of them are counted. A spot whose core clips has a wide
    plateau at its peak, so its half-maximum area is that of the plateau and its rim: the
    window that reaches the unsaturated wings. ``sqrt(area / pi) / 1.1774`` is the sigma of
    a Gaussian with that half-maximum area (FWHM = 2.3548 sigma).

    Parameters
    ----------
    img : ndarray
        (F, n, K, K) light above the background, DN.
    xs, ys : ndarray
        (F, n, K) pixel coordinates of the patch columns and rows, px.
    centres : ndarray
        (F, n, 2) spot centres (x, y), px.
    lit : ndarray of bool
        (F, n) lit spots.
    groups : int
        The frames are that many equal runs, one per camera.
    radius_px : float
        Radius around each centre that is searched, px.

    Returns
    -------
    ndarray of float64
        (groups,) mean area, px^2; NaN for a group without a lit spot.
    """
    F, n = img.shape[:2]
    d2 = (xs - centres[..., 0:1])[..., None, :] ** 2 + (ys - centres[..., 1:2])[..., :, None] ** 2
    inside = d2 <= radius_px * radius_px  # (F, n, K, K)
    v = np.where(inside, img, -np.inf)
    peak = v.reshape(F, n, -1).max(-1)  # (F, n)
    area = (v > 0.5 * peak[..., None, None]).sum(axis=(-2, -1)).astype(np.float64)
    ok = lit & (peak > 0)
    Fg = F // groups
    out = np.full(groups, np.nan)
    for g in range(groups):
        a, m = area[g * Fg:(g + 1) * Fg], ok[g * Fg:(g + 1) * Fg]
        if m.any():
            out[g] = float(a[m].mean())
    return out


def area_sigma(area_px2: float | np.ndarray) -> float | np.ndarray:
    """Sigma (px) of the Gaussian whose half-maximum area is ``area_px2`` (px^2).

    Parameters
    ----------
    area_px2 : float or ndarray
        Half-maximum area, px^2.

    Returns
    -------
    float or ndarray
        Sigma, px, the shape of ``area_px2``.
    """
    return np.sqrt(np.asarray(area_px2, dtype=np.float64) / np.pi) / 1.1774


LIT_SHARE = 0.25
"""An LED steers the following in a frame when its patch shows this share of a lit LED's light."""


def _background(pix: np.ndarray, x0: np.ndarray, y0: np.ndarray, groups: int) -> np.ndarray:
    """What is not LED light in patches (F, n, K, K): per pixel the least value over the
    frames of its group (camera) when the patches stay put over them (a textured background
    then cancels: in a dark frame nothing is left to pull a centroid, and every lit spot
    keeps its shape), else the patch's darkest pixel."""
    F, n = pix.shape[:2]
    Fg = F // groups
    if Fg > 1 and groups * Fg == F:
        xs, ys = x0.reshape(groups, Fg, n), y0.reshape(groups, Fg, n)
        if bool((xs == xs[:, :1]).all() and (ys == ys[:, :1]).all()):
            bg = pix.reshape(groups, Fg, n, *pix.shape[2:]).min(axis=1)  # (groups, n, K, K)
            return np.repeat(bg, Fg, axis=0)
    return pix.reshape(F, n, -1).min(-1)[..., None, None]


def grid_sample(rows: int, cols: int, per_axis: int = 4) -> np.ndarray:
    """Row-major indices of a ``per_axis`` x ``per_axis`` sample of a rows x cols grid
    that includes its corners (all LEDs when the grid is that small): enough centroids
    to fix a shift and a scale, at a quarter of the work for an 8x8 array.

    Parameters
    ----------
    rows, cols : int
        The grid's layout.
    per_axis : int
        Samples along each axis.

    Returns
    -------
    ndarray of intp
        Row-major LED indices, ascending.
    """
    r = np.unique(np.rint(np.linspace(0, rows - 1, min(rows, per_axis))).astype(np.intp))
    c = np.unique(np.rint(np.linspace(0, cols - 1, min(cols, per_axis))).astype(np.intp))
    return (r[:, None] * cols + c[None, :]).ravel()


def follow_and_measure(frames: list[np.ndarray], starts: list[np.ndarray], size: int,
                       sigmas: list[float], use: np.ndarray | None = None, iterations: int = 3,
                       lit_light: np.ndarray | None = None, info: dict | None = None,
                       backgrounds: list["PixelBackground"] | None = None,
                       spot_radius_px: float | None = None, subtract: bool = True,
                       new_block: bool = True) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Follow the LEDs and measure their luminance in each camera, in one vectorized pass.

    One patch gather per camera serves both steps: :func:`refine_in_patches` (shift and
    scale of each frame) and :func:`gauss_in_patches`.

    With ``backgrounds``, each is first updated with this block's patches
    (:meth:`PixelBackground.update`); which LEDs are lit is then judged on the light above
    it (it holds across blocks, so a short block judges as well as a long one), and with
    ``subtract`` the centroids and the luminance are of that light too (the luminance: the
    Gaussian-weighted mean of ``pixel - background``, which a textured background moving
    under the window does not change).

    Parameters
    ----------
    frames : list of ndarray
        Per camera (F, H, W) frames, DN.
    starts : list of ndarray
        Per camera (N, 2) or (F, N, 2) px, where the LEDs are thought to be.
    size : int
        The following box, px.
    sigmas : list of float
        Per camera the Gaussian window sigma, px.
    use : ndarray, optional
        Indices of the LEDs whose centroids steer (all by default).
    iterations : int
        Centroid rounds.
    lit_light : ndarray, optional
        Per camera the patch light of a lit LED from earlier blocks, DN summed over the patch
        (as in :func:`refine_in_patches`).
    info : dict, optional
        Gets ``"light"`` per camera (and ``"spot_area"``), as in :func:`refine_in_patches`.
    backgrounds : list of PixelBackground, optional
        Per camera the per-pixel background, updated in place.
    spot_radius_px : float, optional
        Measure the lit spots' half-maximum area too (``info["spot_area"]`` (C,) px^2,
        :func:`half_max_area`) within this radius (at most the patch's half-size), px.
    subtract : bool
        With ``backgrounds``: centroids and luminance of the light above the background.
    new_block : bool
        These frames are a new block for the backgrounds (False: the same block again, from
        other starts -- :func:`iscd.decode.tracking.trajectory.follow_path`'s later passes;
        the backgrounds are not relaxed a second time).

    Returns
    -------
    centres : list of ndarray
        Per camera the refined centres (F, N, 2), px.
    luminance : list of ndarray
        Per camera the luminance (F, N), DN.

    References
    ----------
    Dissertation, eq. (3.10) (with Gaussian weights).
    """
    F = frames[0].shape[0]
    # the Gaussian reaches 3.5 sigma on every side however the LED sits in its patch (a
    # truncated window would depend on the sub-pixel position again)
    half = max(patch_half(size), int(np.ceil(3.5 * max(sigmas))) + 1)
    st = [np.broadcast_to(np.asarray(s, dtype=np.float64), (F,) + np.shape(s)[-2:]) for s in starts]
    N = st[0].shape[1]
    K = 2 * half + 1
    pix = np.empty((len(frames) * F, N, K, K), np.float32)  # every camera's patches, stacked
    ps = [gather_patches(fr, s, half, out=pix[k * F:(k + 1) * F]) for k, (fr, s) in enumerate(zip(frames, st))]
    p = Patches(pix=pix, x0=np.concatenate([q.x0 for q in ps]), y0=np.concatenate([q.y0 for q in ps]))
    bg_pix = None
    if backgrounds is not None:
        if len(backgrounds) != len(frames):
            raise ValueError(f"backgrounds: one per camera ({len(frames)}), got {len(backgrounds)}")
        if subtract:
            bg_pix = np.concatenate([b.update(q, new_block) for b, q in zip(backgrounds, ps)])
        else:  # only the LEDs whose lit judgement needs it (the kernel does the same)
            sel = np.arange(N) if use is None else np.asarray(use, dtype=np.intp)
            bg_pix = np.full(pix.shape, np.nan, np.float32)
            for k, (b, q) in enumerate(zip(backgrounds, ps)):
                part = b.update(Patches(pix=q.pix[:, sel], x0=q.x0[:, sel], y0=q.y0[:, sel]), new_block)
                bg_pix[k * F:(k + 1) * F, sel] = part
    c = refine_in_patches(p, np.concatenate(st), size, iterations, groups=len(frames), use=use,
                          lit_light=lit_light, info=info, bg_pix=bg_pix,
                          spot_radius_px=None if spot_radius_px is None else min(spot_radius_px, half),
                          subtract=subtract)
    sig = np.repeat(np.asarray(sigmas, dtype=np.float64), F)
    if bg_pix is None or not subtract:
        lum = gauss_in_patches(p, c, sig)
    else:
        lum = gauss_in_patches(Patches(pix=pix - bg_pix, x0=p.x0, y0=p.y0), c, sig)
    n = len(frames)
    return [c[k * F:(k + 1) * F] for k in range(n)], [lum[k * F:(k + 1) * F] for k in range(n)]


class PixelBackground:
    """Per-pixel background of one camera, DN: what a pixel shows when no LED lights it.

    Each pixel's least value over the frames whose LED patches covered it, relaxed upward
    by ``rise_dn`` once per block that covers it (so a background that brightens, or a
    pixel that a spot covered in every frame of a while, is followed back up). Every
    packet's header and training hold level-1 (dark) symbols, so the pixels under an LED
    see its dark frames within a packet; their least value is then the background there
    (with its noise's lower tail: a constant offset, which the channel absorbs). Unlike
    the patch's darkest pixel, it keeps the texture of the background, so the light above
    it does not change as vibration or an approach moves the window over that texture.

    ``bg`` (H, W) float32 (+inf where no patch has been yet) and ``stamp`` (H, W) int64
    (the last block that relaxed each pixel) are the state; the compiled kernel
    (:func:`iscd.decode.tracking.follow_kernel.follow_and_measure_compiled`) updates the same
    arrays the same way.
    """

    def __init__(self, shape: tuple[int, int], rise_dn: float = 0.25) -> None:
        if not rise_dn >= 0:
            raise ValueError(f"rise_dn: expected >= 0 DN per block, got {rise_dn}")
        self.bg = np.full(shape, np.inf, np.float32)
        self.stamp = np.zeros(shape, np.int64)
        self.block = 0
        self.rise_dn = float(rise_dn)

    def update(self, p: Patches, new_block: bool = True) -> np.ndarray:
        """Fold one block's patches (one camera, :func:`gather_patches`) in; returns the
        background under each patch pixel (F, N, K, K) float32 DN after the update.

        Parameters
        ----------
        p : Patches
            (F, N, K, K) patches of one camera, DN.
        new_block : bool
            A new block (False: patches of the block folded in last, taken again from other
            places: a pixel already relaxed in it is not relaxed again).

        Returns
        -------
        ndarray of float32
            (F, N, K, K) background under each patch pixel, DN.
        """
        if new_block:
            self.block += 1
        K = p.pix.shape[-1]
        ys = (p.y0[..., None] + np.arange(K))[..., :, None]  # (F, N, K, 1)
        xs = (p.x0[..., None] + np.arange(K))[..., None, :]  # (F, N, 1, K)
        ys, xs = np.broadcast_arrays(ys, xs)
        flat = (ys * self.bg.shape[1] + xs).ravel()
        touched = np.unique(flat)
        bg, stamp = self.bg.reshape(-1), self.stamp.reshape(-1)
        fresh = touched[stamp[touched] != self.block]
        bg[fresh] += np.float32(self.rise_dn)
        stamp[fresh] = self.block
        np.minimum.at(bg, flat, p.pix.reshape(-1).astype(np.float32))
        return bg[flat].reshape(p.pix.shape)


def patch_half(size: int, max_px: float = 1.5) -> int:
    """Patch half-size that holds a ``size`` px box moved up to max_px.

    Parameters
    ----------
    size : int
        Box width, px.
    max_px : float
        Largest move of the box, px.

    Returns
    -------
    int
        ceil(size / 2 + max_px), px.
    """
    return int(np.ceil(size / 2.0 + max_px))


def refine_centres(frames: np.ndarray, centres: np.ndarray, size: int = 3, iterations: int = 3,
                   scale: bool = True, max_px: float = 1.5, accelerate: bool = True) -> np.ndarray:
    """LED centres in each frame: ``centres`` moved by the frame's own image shift (and
    scale), common to all LEDs of the array: (F, N, 2) px.

    Rig vibration moves every spot of a camera together, frame by frame (up to tens of
    Hz), and an approaching array grows (its pitch from 4.2 to 6 px within one packet at
    40 km/h), faster than a grid fitted over tens of frames follows. Per frame and LED the
    centroid of the light above the background is taken in a ``size`` px
    sub-pixel box (:func:`box_cover`) around the current estimate (the light above each
    pixel's least value over the block, which removes a textured background); the LEDs' offsets,
    weighted by their light (LEDs with less than a quarter of a lit LED's light, measured
    above each pixel's least value over the block, count for nothing), are fitted by a shift (dx, dy) and, with ``scale`` and more than one LED, a
    scale about their weighted centre (least squares); the boxes are recentred and, since
    a box truncates the spot and recovers only part of an offset, a few rounds converge.
    A frame without light keeps its centres.

    Parameters
    ----------
    frames : ndarray
        (F, H, W) frames, DN.
    centres : ndarray
        (N, 2) or (F, N, 2) LED centres (x, y), px.
    size : int
        Centroid box width, px.
    iterations : int
        Centroid rounds.
    scale : bool
        Also fit a scale of the array.
    max_px : float
        Largest correction per LED and axis, px.
    accelerate : bool
        Extrapolate the rounds' geometric series in the second round
        (:func:`refine_in_patches`).

    Returns
    -------
    ndarray of float64
        (F, N, 2) refined centres (x, y), px.
    """
    p = gather_patches(frames, centres, patch_half(size, max_px))
    c = np.broadcast_to(np.asarray(centres, dtype=np.float64), p.x0.shape + (2,))
    return refine_in_patches(p, c, size, iterations, scale, max_px, accelerate=accelerate)


@dataclass
class _Layout:
    """Pixels of the union of all windows and which LED windows cover each of them."""

    pix_r: np.ndarray  # (P,) rows
    pix_c: np.ndarray  # (P,) cols
    led: np.ndarray  # (P, K) LED index covering the pixel, -1 = none
    win: np.ndarray  # (N, h*w) pixel index of each window cell (-1 outside the image)
    wh: int


def _layout(centres: np.ndarray, size: int | tuple[int, int], shape: tuple[int, int]) -> _Layout:
    w, h = _window(size)
    rows, cols, valid = window_indices(centres, size, shape)
    N = centres.shape[0]
    rr = np.broadcast_to(rows, (N, h, w)).reshape(N, -1)
    cc = np.broadcast_to(cols, (N, h, w)).reshape(N, -1)
    vv = valid.reshape(N, -1)
    lin = rr * shape[1] + cc
    uniq, inv = np.unique(lin[vv], return_inverse=True)
    win = np.full(lin.shape, -1, dtype=np.intp)
    win[vv] = inv
    # LEDs covering each pixel (padded to the largest overlap)
    pi = win[vv]
    li = np.broadcast_to(np.arange(N)[:, None], lin.shape)[vv]
    order = np.lexsort((li, pi))
    pi, li = pi[order], li[order]
    cnt = np.bincount(pi, minlength=uniq.size)
    K = int(cnt.max())
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    slot = np.arange(pi.size) - start[pi]
    led = np.full((uniq.size, K), -1, dtype=np.intp)
    led[pi, slot] = li
    return _Layout(pix_r=uniq // shape[1], pix_c=uniq % shape[1], led=led, win=win, wh=w * h)


class SpotLuminance:
    """Crosstalk- and saturation-aware LED luminance (module docstring).

    centres: (N, 2) LED centres, px (fixed over the frames it is used on; refit when the
    LEDs move by a pixel). size: window px. saturation_dn: pixels at or above it are
    ignored (None: no saturation handling). iterations: alternating least-squares rounds.
    ridge: relative Tikhonov weight keeping amplitudes finite when an LED's window is
    entirely saturated (then the amplitude is raised to the least value that saturates
    the pixels it dominates). init_sigma_px: the Gaussian spot the fit starts from, px.
    """

    def __init__(self, centres: np.ndarray, size: int | tuple[int, int] = 5,
                 saturation_dn: float | None = 255.0, iterations: int = 3,
                 ridge: float = 1e-7, init_sigma_px: float = 1.0) -> None:
        self.centres = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
        self.size = size
        self.saturation_dn = saturation_dn
        self.iterations = iterations
        self.ridge = ridge
        self.init_sigma_px = init_sigma_px
        self._lay: _Layout | None = None
        self.templates: np.ndarray | None = None  # (P, K) weight of led[p, k] at pixel p
        self.background: np.ndarray | None = None  # (P,)

    @property
    def n_leds(self) -> int:
        return self.centres.shape[0]

    def _pixels(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lay = self._lay
        assert lay is not None
        y = np.asarray(frames)[:, lay.pix_r, lay.pix_c].astype(np.float64)  # (F, P)
        ok = np.ones(y.shape, bool) if self.saturation_dn is None else y < self.saturation_dn
        return y, ok

    def fit(self, frames: np.ndarray) -> "SpotLuminance":
        """Estimate templates and background from a block of frames (F, H, W); the LEDs
        should change level over the block (e.g. a few hundred frames of data).

        Parameters
        ----------
        frames : ndarray
            (F, H, W) frames, DN, F >= 8.

        Returns
        -------
        SpotLuminance
            ``self``, fitted.

        Raises
        ------
        ValueError
            If ``frames`` is not a block of at least 8 frames.
        """
        fr = np.asarray(frames)
        if fr.ndim != 3 or fr.shape[0] < 8:
            raise ValueError(f"need a block of >= 8 frames (F, H, W), got shape {fr.shape}")
        self._lay = lay = _layout(self.centres, self.size, fr.shape[1:])
        y, ok = self._pixels(fr)
        F, P = y.shape
        N = self.n_leds
        # start: Gaussian spots of sigma init_sigma_px at the LED centres over a background of
        # each pixel's 2nd percentile, amplitudes by the censored least squares below
        K = lay.led.shape[1]
        has = lay.led >= 0
        ci = self.centres[np.maximum(lay.led, 0)]  # (P, K, 2)
        d2 = (lay.pix_c[:, None] - ci[..., 0]) ** 2 + (lay.pix_r[:, None] - ci[..., 1]) ** 2
        T0 = np.where(has, np.exp(-d2 / (2 * self.init_sigma_px ** 2)), 0.0)
        tot = np.bincount(lay.led[has], weights=T0[has], minlength=N)
        self.templates = np.where(has, T0 / np.maximum(tot, 1e-12)[np.maximum(lay.led, 0)], 0.0)
        self.background = np.percentile(np.where(ok, y, np.nan), 2, axis=0) if ok.all() else \
            np.nan_to_num(np.nanpercentile(np.where(ok, y, np.nan), 2, axis=0), nan=0.0)
        A = self._amplitudes(y, ok)
        for _ in range(max(1, self.iterations)):
            # templates: per pixel, y_p = c_p + sum_k T_pk A_{led[p,k]}, unsaturated frames
            X = np.concatenate([np.ones((F, P, 1)),
                                np.where(has[None], A[:, np.maximum(lay.led, 0)], 0.0)], axis=2)
            wgt = ok.astype(np.float64)
            G = np.einsum("fp,fpi,fpj->pij", wgt, X, X)
            b = np.einsum("fp,fpi,fp->pi", wgt, X, y)
            reg = 1e-9 * np.trace(G, axis1=1, axis2=2)[:, None, None] * np.eye(K + 1)
            # a missing LED slot must not be singular
            G[:, 1:, 1:] += np.where(has[:, :, None] & has[:, None, :], 0.0,
                                     np.eye(K)[None]) * 1.0
            sol = np.linalg.solve(G + reg, b[..., None])[..., 0]
            self.background = sol[:, 0]
            self.templates = np.where(has, sol[:, 1:], 0.0)
            # normalize each LED's template to unit sum over its window
            tot = np.bincount(lay.led[has], weights=self.templates[has], minlength=N)
            tot = np.where(np.abs(tot) > 1e-12, tot, 1.0)
            self.templates = np.where(has, self.templates / tot[np.maximum(lay.led, 0)], 0.0)
            A = self._amplitudes(y, ok)
        return self

    def _design(self):  # -> scipy.sparse.csr_matrix
        from scipy import sparse

        lay = self._lay
        assert lay is not None and self.templates is not None
        has = lay.led >= 0
        p_idx = np.broadcast_to(np.arange(lay.led.shape[0])[:, None], lay.led.shape)[has]
        return sparse.csr_matrix((self.templates[has], (p_idx, lay.led[has])),
                                 shape=(lay.led.shape[0], self.n_leds))

    def _amplitudes(self, y: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Per frame least squares (F, N) of (y - background) on the templates."""
        from scipy import sparse

        T = self._design()  # (P, N) sparse
        N = self.n_leds
        r = y - self.background[None, :]
        TtT = (T.T @ T).toarray()
        lam = self.ridge * float(np.trace(TtT)) / N
        A = np.empty((y.shape[0], N))
        full = ok.all(1)
        if full.any():  # no saturated pixel in the frame: one shared solve
            A[full] = np.linalg.solve(TtT + lam * np.eye(N), (T.T @ r[full].T)).T
        part = np.flatnonzero(~full)
        if part.size:
            # per-frame normal matrices sum_p w_fp T_p T_p^T via a sparse (P, N*N) map
            lay = self._lay
            assert lay is not None
            has = lay.led >= 0
            Kp = lay.led.shape[1]
            pa = np.broadcast_to(np.arange(lay.led.shape[0])[:, None, None], (lay.led.shape[0], Kp, Kp))
            ia = np.broadcast_to(lay.led[:, :, None], pa.shape)
            ib = np.broadcast_to(lay.led[:, None, :], pa.shape)
            va = self.templates[:, :, None] * self.templates[:, None, :]
            m = has[:, :, None] & has[:, None, :]
            Q = sparse.csr_matrix((va[m], (pa[m], ia[m] * N + ib[m])),
                                  shape=(lay.led.shape[0], N * N))
            w = ok[part].astype(np.float64)
            G = np.asarray((sparse.csr_matrix(w) @ Q).todense()).reshape(-1, N, N)
            rhs = np.asarray((sparse.csr_matrix(w * r[part]) @ T).todense())
            G += lam * np.eye(N)[None]
            A[part] = np.linalg.solve(G, rhs[..., None])[..., 0]
            A[part] = np.maximum(A[part], self._saturation_bound(~ok[part]))
        return A

    def _saturation_bound(self, sat: np.ndarray) -> np.ndarray:
        """Least amplitude (F, N) of each LED consistent with the saturated pixels it
        dominates (its template is the largest there): ``(saturation - background) / T``."""
        lay = self._lay
        assert lay is not None and self.templates is not None and self.background is not None
        N = self.n_leds
        k = self.templates.argmax(1)
        dom = lay.led[np.arange(k.size), k]
        t = self.templates[np.arange(k.size), k]
        usable = (dom >= 0) & (t > 1e-6)
        level = float(self.saturation_dn if self.saturation_dn is not None else np.inf)
        b = np.where(usable, (level - self.background) / np.where(usable, t, 1.0), 0.0)  # (P,)
        B = np.where(sat & usable[None, :], b[None, :], 0.0)  # (F, P)
        order = np.argsort(dom, kind="stable")
        order = order[dom[order] >= 0]
        out = np.zeros((sat.shape[0], N))
        if order.size:
            d = dom[order]
            starts = np.flatnonzero(np.r_[True, d[1:] != d[:-1]])
            out[:, d[starts]] = np.maximum.reduceat(B[:, order], starts, axis=1)
        return out

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        """Luminance (F, N), DN, of each LED in ``frames`` (F, H, W)."""
        if self.templates is None:
            raise RuntimeError("SpotLuminance.fit(frames) must be called first")
        y, ok = self._pixels(frames)
        A = self._amplitudes(y, ok)
        lay = self._lay
        assert lay is not None and self.background is not None
        winbg = np.where(lay.win >= 0, self.background[np.maximum(lay.win, 0)], 0.0)
        nvalid = np.maximum((lay.win >= 0).sum(1), 1)
        return winbg.sum(1)[None, :] / nvalid[None, :] + A / lay.wh
