"""The fast project method ("iscd-fast"): horizontal shift from row-weighted 1-D projections.

After rectification a disparity is purely horizontal, so the x shift of two LED patches
needs only their horizontal structure. Each (background-removed, saturation-refilled)
patch is projected onto x with row weights that follow the LED rows (a Gaussian per LED
row at the detected y, the matched filter for the spot's vertical profile), and the 1-D
profiles are matched exactly like the 2-D ``"iscd"`` method does it: a cross-power
spectrum weighted ``X/|X|^beta`` with a Gaussian band limit, and the exact maximum of the
resulting trigonometric polynomial (Newton steps on its analytic derivatives, the 1-D form
of :func:`iscd.decode.ranging.poc.continuous_peak`), with a standard deviation from the residual
phases. Everything is batched: one call ranges a block of frames.

Why it is enough: by the projection-slice theorem the 1-D spectrum of the projection is the
ky = 0 row of the 2-D spectrum, which carries the x shift; the other rows add little for a
spot a few pixels high, and the row weights keep the noise of empty rows out. Measured on
rendered frames (docs/ranging.md) it is as accurate as the 2-D method for one LED, 2-3x
less accurate for an 8x8 array (whose clipped cores it does not refill by default) and
2-15x cheaper: the cost is a few numpy calls per block, not per frame.

Saturation: :func:`declip_cells` refills each clipped LED core from a log-quadratic fit of
the unsaturated pixels around it (the idea of :func:`iscd.decode.ranging.estimators.declip`), but
with one fixed cell per LED instead of labelled blobs, so that it is a few dense matrix
products for a whole block.

Conventions as in :mod:`iscd.decode.ranging.estimators`: shifts are left position - right
position, px; patches (n, h, w); LED centres (x, y) in patch pixels (pixel centres at
integers).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iscd.decode.ranging.declip_kernel import declip_one_cell
from iscd.decode.ranging.shift import ShiftEstimate
from iscd.decode.ranging.spectral import _TINY, Peak1D, _spectral, row_weights

@lru_cache(maxsize=64)
def _search_penalty(w: int, max_shift_px: float) -> NDArray[np.float64]:
    """(w,) 0 for lags within +-max_shift_px, -inf beyond (added to the correlation)."""
    lag = np.abs(np.fft.fftfreq(w) * w)
    pen = np.where(lag <= max_shift_px, 0.0, -np.inf)
    pen.setflags(write=False)
    return pen


_PARABOLA = np.array([-1, 0, 1])


def correlate_1d(left: NDArray[np.floating], right: NDArray[np.floating], beta: float = 0.5,
                 band_cutoff: float | None = 0.12, max_shift_px: float | None = None,
                 iterations: int = 2) -> Peak1D:
    """Sub-pixel shift of each pair of 1-D profiles (n, w).

    The maximum of the correlation of the weighted cross-power spectrum ``X/|X|^beta``
    (``X = F_l conj(F_r)``, eq. 3.5 for beta = 1) times ``exp(-f^2 / 2 f_c^2)`` (f in
    cycles/px).

    The correlation ``c(x) = sum_k m_k Re(R_k exp(i w_k x))`` (m_k: bin multiplicity) is the
    trigonometric interpolant of its inverse DFT (eq. 3.6, continuous); starting from the
    integer peak (searched within ``max_shift_px`` when given) refined by a parabola,
    ``iterations`` Newton steps (clipped to 0.5 px) find its maximum. The standard deviation
    linearises the estimator in the residual phases ``e_k = arg(R_k exp(i w_k dx))``:
    ``var = 2 sum m |R|^2 w^2 sin^2 e / (sum m |R| w^2 cos e)^2``. Written for few numpy
    calls: it runs once per block of frames in the live pipeline.

    Parameters
    ----------
    left, right : ndarray of float
        (n, w) profiles, DN.
    beta : float
        Spectral weighting exponent, 0-1.
    band_cutoff : float or None
        Gaussian band limit f_c, cycles/px (None: full band).
    max_shift_px : float or None
        Limit of the integer peak search, px.
    iterations : int
        Newton steps.

    Returns
    -------
    Peak1D
        Shifts (left - right), px, peak heights and standard deviations, px; all (n,).

    References
    ----------
    Dissertation, eqs. (3.5), (3.6).
    """
    n, w = left.shape
    omega, mult, band, w2, w2m = _spectral(int(w), band_cutoff)
    x = np.fft.rfft(left, axis=1)
    x *= np.fft.rfft(right, axis=1).conj()
    if beta:
        x *= (np.abs(x) + _TINY) ** (-beta)
    x *= band
    surf = np.fft.irfft(x, n=w, axis=1)
    search = surf + _search_penalty(int(w), float(max_shift_px)) if max_shift_px is not None else surf
    i0 = np.argmax(search, axis=1)
    lo, c0, hi = surf[np.arange(n)[:, None], (i0[:, None] + _PARABOLA) % w].T
    den = lo - 2.0 * c0 + hi
    off = 0.5 * (lo - hi) / np.where(den < -_TINY, den, -np.inf)      # 0 where not a maximum
    pos = (i0 - w * (i0 >= (w + 1) // 2)) + np.minimum(np.maximum(off, -0.5), 0.5)
    xm = x * mult
    for _ in range(iterations):
        rot = xm * np.exp(1j * np.multiply.outer(pos, omega))
        a = rot.imag @ omega                   # -c'(pos)
        b = rot.real @ w2                      # -c''(pos), > 0 at a maximum
        step = -a / np.where(b > _TINY, b, np.inf)
        pos += np.minimum(np.maximum(step, -0.5), 0.5)
    rot = xm * np.exp(1j * np.multiply.outer(pos, omega))
    total = np.abs(xm).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        height = rot.real.sum(axis=1) / total
        hess = rot.real @ w2
        sigma = np.sqrt(2.0 * ((rot.imag ** 2) @ w2m)) / np.where(hess > _TINY, hess, 0.0)
    return Peak1D(dx=pos, height=height, sigma=sigma)


def data_row_weights(left: NDArray[np.floating], right: NDArray[np.floating]) -> NDArray[np.float64]:
    """Projection weights from the data when the LED rows are not known.

    The mean vertical profile (positive part) of both background-removed batches, max 1.

    Parameters
    ----------
    left, right : ndarray of float
        (n, h, w) background-removed patches, DN.

    Returns
    -------
    ndarray of float64
        (h,) weights, max 1.
    """
    prof = np.maximum(left.sum(axis=2), 0.0).mean(axis=0) + np.maximum(right.sum(axis=2), 0.0).mean(axis=0)
    m = prof.max()
    return prof / m if m > 0 else np.ones(left.shape[1])


@lru_cache(maxsize=32)
def _cell_design(ch: int, cw: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Columns 1, x, y, x^2 + y^2 over a (ch, cw) cell (centred coordinates), (ch*cw, 4),
    and their pairwise products (ch*cw, 16), for the weighted least-squares normal
    equations of a round log-quadratic (Gaussian-like) spot."""
    yy, xx = np.mgrid[0:ch, 0:cw].astype(np.float64)
    xx -= (cw - 1) / 2.0
    yy -= (ch - 1) / 2.0
    a = np.stack([np.ones_like(xx), xx, yy, xx * xx + yy * yy], axis=-1).reshape(-1, 4)
    a2 = (a[:, :, None] * a[:, None, :]).reshape(-1, 16)
    a.setflags(write=False)
    a2.setflags(write=False)
    return a, a2


@dataclass(frozen=True)
class Cells:
    """One rectangular cell of patch pixels per LED (for :func:`declip_cells`): flat pixel
    indices ``index`` (N, ch, cw) into an (h, w) patch, ``member`` (N, ch, cw) the pixels
    that belong to that LED, and ``owner`` (h*w,) the LED owning each patch pixel (-1:
    none)."""

    index: NDArray[np.int64]
    member: NDArray[np.bool_]
    owner: NDArray[np.int64]


def led_cells(h: int, w: int, centres_xy: ArrayLike | None, pitch_px: float = 0.0,
              spot_px: float | None = None) -> Cells:
    """The declip cells of the LEDs at ``centres_xy`` in (h, w) patches.

    A pixel belongs to the LED it is nearest to in x and y within half the pitch (the
    Voronoi cell of a square grid; exact ties go to one of them) and within
    ``spot_px / 2 + 1.5`` px of it (a clipped core plus the ring its fit needs). One LED (or
    no centres): the whole patch is one cell.

    Parameters
    ----------
    h, w : int
        Patch size, px.
    centres_xy : array_like or None
        (N, 2) LED centres (x, y), patch px.
    pitch_px : float
        LED spacing, px (0 for one LED).
    spot_px : float, optional
        Spot diameter, px.

    Returns
    -------
    Cells
    """
    if centres_xy is None or pitch_px <= 0:
        idx = np.arange(h * w, dtype=np.int64).reshape(1, h, w)
        return Cells(idx, np.ones((1, h, w), dtype=bool), np.zeros(h * w, dtype=np.int64))
    c = np.asarray(centres_xy, dtype=np.float64).reshape(-1, 2)
    half = pitch_px / 2.0
    reach = half if spot_px is None else min(half, spot_px / 2.0 + 1.5)
    r = max(1, int(np.floor(reach + 0.5)))
    off = np.arange(-r, r + 1)
    ix = np.rint(c[:, 0]).astype(np.int64)[:, None, None] + off[None, None, :]
    iy = np.rint(c[:, 1]).astype(np.int64)[:, None, None] + off[None, :, None]
    dx, dy = np.abs(ix - c[:, 0, None, None]), np.abs(iy - c[:, 1, None, None])
    member = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h) & (dx <= reach) & (dy <= reach)
    idx = np.clip(iy, 0, h - 1) * w + np.clip(ix, 0, w - 1)
    owner = np.full(h * w, -1, dtype=np.int64)
    led = np.broadcast_to(np.arange(c.shape[0])[:, None, None], idx.shape)
    # nearest first wins: write the far pixels first, the near ones last
    d = np.maximum(dx, dy)[member]
    order = np.argsort(-d, kind="stable")
    owner[idx[member][order]] = led[member][order]
    member &= owner[idx] == led
    return Cells(idx, member, owner)


def declip_cells(patches: NDArray[np.floating], saturated: NDArray[np.bool_], top: ArrayLike,
                 cells: Cells, top_map: NDArray[np.floating] | None = None, fit_floor: float = 0.03,
                 min_pixels: int = 5, max_gain: float = 30.0, *,
                 compiled: bool = False) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Refill clipped LED cores, per LED cell.

    Per LED cell with saturated pixels, ``log(value)`` of the unsaturated pixels within 1 px
    (chessboard) of them and above ``fit_floor * top`` is fitted by a round log-quadratic
    ``c0 + c1 x + c2 y + c3 (x^2 + y^2)`` (weighted least squares, weight = value) and the
    saturated pixels get the fitted surface, clamped to ``[top, max_gain * top]``. A cell
    whose fit is not a peak (or has fewer than ``min_pixels`` usable pixels) stays clipped.
    Only the cells that hold a saturated pixel are touched, with a few dense products over
    them.

    Parameters
    ----------
    patches : ndarray of float
        (n, h, w) background-removed patches, DN.
    saturated : ndarray of bool
        (n, h, w) the clipped pixels.
    top : array_like
        Scalar or (n,); plus ``top_map``, the value a clipped pixel has after the background
        removal, DN.
    cells : Cells
        From :func:`led_cells`.
    top_map : ndarray of float, optional
        (h, w) or (n, h, w), DN.
    fit_floor : float
        Fraction of ``top`` below which pixels are left out of the fit.
    min_pixels : int
        Fewest usable pixels for a fit.
    max_gain : float
        Upper clamp of the refilled values, multiples of ``top``.
    compiled : bool
        Keyword-only. One cell per patch (a single LED) by
        :func:`iscd.decode.ranging.declip_kernel.declip_one_cell` (the same refill to ~1e-9
        relative, without this function's Python overhead).

    Returns
    -------
    patches : ndarray of float64
        (n, h, w), DN.
    refilled : ndarray of bool
        (n,) True where some cell was refilled.
    """
    n, h, w = patches.shape
    if compiled and cells.index.shape[0] == 1:
        return declip_one_cell(patches, saturated, top, cells.index[0], cells.member[0], top_map,
                               fit_floor=fit_floor, min_pixels=min_pixels, max_gain=max_gain)
    out = np.array(patches, dtype=np.float64, copy=True)
    refilled = np.zeros(n, dtype=bool)
    satf = np.flatnonzero(saturated)
    if satf.size == 0:
        return out, refilled
    nc, ch, cw = cells.index.shape
    f, pix = np.divmod(satf, h * w)
    o = cells.owner[pix]
    counts = np.bincount(f[o >= 0] * nc + o[o >= 0], minlength=n * nc)
    act = np.flatnonzero(counts)
    if act.size == 0:
        return out, refilled
    index, member = cells.index, cells.member
    if nc > 1:
        # only as much of each cell as the largest clipped core needs (its radius + the ring)
        r = int(np.ceil(np.sqrt(counts.max() / np.pi) + 1.5))
        cut_y, cut_x = max(0, (ch - 1) // 2 - r), max(0, (cw - 1) // 2 - r)
        if cut_y or cut_x:
            index = index[:, cut_y:ch - cut_y, cut_x:cw - cut_x]
            member = member[:, cut_y:ch - cut_y, cut_x:cw - cut_x]
            ch, cw = index.shape[1:]
    act_f, act_c = np.divmod(act, nc)
    cidx = index[act_c]                                                  # (m, ch, cw)
    gidx = cidx + (act_f * (h * w))[:, None, None]                       # into the flat batch
    flat = out.reshape(-1)
    vals = flat.take(gidx)
    mem = member[act_c]
    sat = saturated.reshape(-1).take(gidx) & mem
    t = np.asarray(top, dtype=np.float64)
    if top_map is None:
        tm = 0.0
    else:
        tmap = np.asarray(top_map, dtype=np.float64)
        tm = tmap.reshape(-1).take(gidx) if tmap.ndim == 3 else tmap.reshape(-1).take(cidx)
    topv = np.broadcast_to((t[act_f][:, None, None] if t.ndim else t) + tm, vals.shape)
    ring = sat.copy()                                                    # chessboard dilation by 1
    ring[:, 1:] |= sat[:, :-1]
    ring[:, :-1] |= sat[:, 1:]
    ring2 = ring.copy()
    ring2[:, :, 1:] |= ring[:, :, :-1]
    ring2[:, :, :-1] |= ring[:, :, 1:]
    use = ring2 & ~sat & mem & (vals > fit_floor * topv)
    m = act.size
    wv = (vals * use).reshape(m, -1)
    a, a2 = _cell_design(ch, cw)
    ata = (wv @ a2).reshape(m, 4, 4)
    ata[:, range(4), range(4)] += 1e-9
    atb = (wv * np.log(np.maximum(vals, 1e-6)).reshape(m, -1)) @ a
    coef = np.linalg.solve(ata, atb[:, :, None])[..., 0]
    ok = (coef[:, 3] < 0) & (use.reshape(m, -1).sum(axis=1) >= min_pixels)
    put = (sat & ok[:, None, None]).reshape(m, -1)
    model = np.exp(np.minimum((coef @ a.T)[put], 60.0))
    tv = topv.reshape(m, -1)[put]
    flat[gidx.reshape(m, -1)[put]] = np.minimum(np.maximum(model, tv), max_gain * tv)
    refilled[act_f[ok]] = True
    return out, refilled


@lru_cache(maxsize=32)
def ring_indices(h: int, w: int) -> NDArray[np.int64]:
    """Flat indices of the outer ring of pixels of an (h, w) patch (the pedestal estimate).

    Parameters
    ----------
    h, w : int
        Patch size, px.

    Returns
    -------
    ndarray of int64
        Cached.
    """
    m = np.zeros((h, w), dtype=bool)
    m[0, :] = m[-1, :] = m[:, 0] = m[:, -1] = True
    idx = np.flatnonzero(m)
    idx.setflags(write=False)
    return idx


def robust_level(values: NDArray[np.floating], spread: bool = False
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Median of each row of ``values``, and with ``spread`` its robust standard deviation.

    The standard deviation is 1.4826 MAD. Sorts ``values`` in place.

    Parameters
    ----------
    values : ndarray of float
        (n, k), DN.
    spread : bool
        Also the standard deviation.

    Returns
    -------
    median : ndarray of float64
        (n,), DN.
    sigma : ndarray of float64 or None
        (n,), DN; None without ``spread``.
    """
    k = values.shape[1]
    values.sort(axis=1)
    med = values[:, k // 2] if k % 2 else 0.5 * (values[:, k // 2 - 1] + values[:, k // 2])
    if not spread:
        return med, None
    dev = np.abs(values - med[:, None])
    dev.sort(axis=1)
    mad = dev[:, k // 2] if k % 2 else 0.5 * (dev[:, k // 2 - 1] + dev[:, k // 2])
    return med, 1.4826 * mad


def ring_level(patches: NDArray[np.floating], ring: NDArray[np.int64] | None = None
               ) -> NDArray[np.float64]:
    """Median of each patch's outer ring of pixels.

    Parameters
    ----------
    patches : ndarray of float
        (n, h, w), DN.
    ring : ndarray of int64, optional
        From :func:`ring_indices` (computed if not given).

    Returns
    -------
    ndarray of float64
        (n,), DN.
    """
    n, h, w = patches.shape
    return robust_level(patches.reshape(n, -1)[:, ring_indices(h, w) if ring is None else ring])[0]


@dataclass(frozen=True)
class Plan:
    """What the fast method needs about one patch geometry (computed once per grid fit):
    the row weights of each camera, the declip cells, the integer-peak search limit."""

    h: int
    w: int
    weights_left: NDArray[np.float64] | None
    weights_right: NDArray[np.float64] | None
    cells_left: Cells
    cells_right: Cells
    max_shift_px: float | None
    leds: int | None = None
    """LEDs per patch (None: not known, the plan was made without centres)."""


def make_plan(h: int, w: int, centres_left: ArrayLike | None = None, centres_right: ArrayLike | None = None,
              pitch_px: float = 0.0, spot_px: float | None = None, max_shift_px: float | None = None) -> Plan:
    """A :class:`Plan` for (h, w) patches with the LEDs at ``centres_left``/``centres_right``.

    The peak search is limited to ``max_shift_px`` if given, else to half the spacing for an
    array.

    Parameters
    ----------
    h, w : int
        Patch size, px.
    centres_left, centres_right : array_like, optional
        (N, 2) LED centres (x, y), patch px; None: row weights from the data, one declip cell.
    pitch_px : float
        LED spacing, px (0 for one LED).
    spot_px : float, optional
        Spot diameter, px.
    max_shift_px : float, optional
        Limit of the integer peak search, px.

    Returns
    -------
    Plan
    """
    sig_y = max(0.8, (spot_px if spot_px else 3.0) / 2.5)
    wl = wr = None
    if centres_left is not None and centres_right is not None:
        cl = np.asarray(centres_left, dtype=np.float64).reshape(-1, 2)
        cr = np.asarray(centres_right, dtype=np.float64).reshape(-1, 2)
        wl, wr = row_weights(h, cl[:, 1], sig_y), row_weights(h, cr[:, 1], sig_y)
        leds: int | None = cl.shape[0]
    else:
        cl = cr = None  # type: ignore[assignment]
        leds = None
    ms = max_shift_px if max_shift_px is not None else (max(1.0, pitch_px / 2.0) if pitch_px > 0 else None)
    return Plan(h, w, wl, wr, led_cells(h, w, cl, pitch_px, spot_px), led_cells(h, w, cr, pitch_px, spot_px), ms,
                leds)


def _compact(saturated: NDArray[np.bool_]) -> bool:
    """True when every patch's saturated pixels fit in a box of a third of the patch (one
    clipped spot, not several LEDs of an array in one cell)."""
    n, h, w = saturated.shape
    rows, cols = saturated.any(axis=2), saturated.any(axis=1)
    has = rows.any(axis=1)
    ext_y = h - np.argmax(rows[:, ::-1], axis=1) - np.argmax(rows, axis=1)
    ext_x = w - np.argmax(cols[:, ::-1], axis=1) - np.argmax(cols, axis=1)
    return bool(np.all(~has | ((ext_y <= max(3, h // 3)) & (ext_x <= max(3, w // 3)))))


@dataclass
class ProjectedShift:
    """The fast project method (module docstring): 1-D matching of row-weighted projections.

    ``beta``, ``band_cutoff``: spectral weighting as in the 2-D ``"iscd"`` method.
    ``saturation``: grey level at which the sensor clips (255 for 8-bit); ``declip``:
    refill clipped cores (:func:`declip_cells`): True, False, or None = only in one-LED
    patches (without LED centres: when each patch's clipped pixels are one compact spot;
    an 8x8 array has hundreds of clipped cores per block: refilling them halves
    its error, 0.016 -> 0.007 px at 30 m, but costs 5x the rest of the method;
    docs/ranging.md). ``max_shift_px``: limit of the integer
    peak search (default: half the LED spacing for an array, none for one LED).
    ``sigma_floor_px`` and ``sigma_saturated_px``: added in quadrature to the residual-phase
    sigma, as in the 2-D method. ``dy`` is not measured (returned as 0, ``sigma_y_px`` NaN):
    rectified rows are assumed to match.

    :meth:`estimate` takes raw (n, h, w) patches and optionally ``background`` (left, right),
    each broadcastable to the patches (a dark-symbol or running-minimum background); what
    is left after subtracting it (or, without one, the raw patch) has its border median
    removed as a pedestal (``pedestal`` (left (n,), right (n,)) if the caller has it).
    ``plan`` (:func:`make_plan`, cache it per geometry) or ``centres_left``/
    ``centres_right`` (N, 2) LED centres in patch px, ``pitch_px`` and ``spot_px`` give the
    row weights and the declip cells; without them the weights come from the data and the
    whole patch is one cell. ``quality``: the normalised correlation peak height
    (1 = identical profiles; it stays high for noise-only 1-D profiles, so dark frames are
    rejected by the caller's signal-to-noise test, not by it).
    """

    name: str = "iscd-fast"
    beta: float = 0.5
    band_cutoff: float | None = 0.12
    saturation: float = 255.0
    declip: bool | None = None
    max_shift_px: float | None = None
    iterations: int = 2
    sigma_floor_px: float = 0.006
    sigma_saturated_px: float = 0.008

    def __post_init__(self) -> None:
        if not 0.0 <= self.beta <= 1.0:
            raise ValueError(f"beta: expected 0 <= beta <= 1, got {self.beta}")
        if self.band_cutoff is not None and self.band_cutoff < 0:
            raise ValueError(f"band_cutoff: expected >= 0 cycles/px or None, got {self.band_cutoff}")

    def estimate(self, left: ArrayLike, right: ArrayLike, *,
                 background: tuple[ArrayLike, ArrayLike] | None = None,
                 pedestal: tuple[ArrayLike, ArrayLike] | None = None, plan: Plan | None = None,
                 centres_left: ArrayLike | None = None, centres_right: ArrayLike | None = None,
                 pitch_px: float = 0.0, spot_px: float | None = None, compiled: bool = False,
                 **kw: Any):  # -> ShiftEstimate
        """Shifts of the patch pairs by the fast method (see the class).

        Parameters
        ----------
        left, right : array_like
            (n, h, w) raw patch pairs, DN.
        background : (array_like, array_like), optional
            Keyword-only. Left and right backgrounds, broadcastable to the patches, DN.
        pedestal : (array_like, array_like), optional
            Keyword-only. Left (n,) and right (n,) pedestals, DN, if the caller has them.
        plan : Plan, optional
            Keyword-only. From :func:`make_plan` (cache it per geometry).
        centres_left, centres_right : array_like, optional
            Keyword-only. (N, 2) LED centres, patch px (used without ``plan``).
        pitch_px : float
            Keyword-only. LED spacing, px.
        spot_px : float, optional
            Keyword-only. Spot diameter, px.
        compiled : bool
            Keyword-only. The profiles' correlation (as :meth:`from_profiles`) and a single
            LED's core refill (:func:`declip_cells`) by the compiled kernels (the live
            pipeline).
        **kw
            Ignored (the common estimator interface).

        Returns
        -------
        ShiftEstimate
            dx, px (dy 0, ``sigma_y_px`` NaN); quality the normalised peak height; sigma_px, px.

        References
        ----------
        Dissertation, eqs. (3.5) (here weighted; beta = 1 is POC), (3.6) (continuous form).
        """
        if isinstance(left, np.ndarray) and left.ndim == 3 and isinstance(right, np.ndarray) \
                and left.shape == right.shape and left.dtype.kind == "f":
            lf, rt = left, right          # the live path: trusted float batches (no copy)
        else:
            from iscd.decode.ranging.poc import check_pair
            lf, rt = check_pair(left, right)
        n, h, w = lf.shape
        if plan is None or (plan.h, plan.w) != (h, w):
            plan = make_plan(h, w, centres_left, centres_right, pitch_px, spot_px, self.max_shift_px)
        bl = br = None
        if background is not None:
            bl = np.asarray(background[0])
            br = np.asarray(background[1])
            if bl.dtype.kind != "f" or br.dtype.kind != "f":
                bl, br = bl.astype(np.float64), br.astype(np.float64)
        sat_any = False
        any_l = any_r = None
        if self.declips(plan):
            sat_l = lf >= self.saturation - 0.5
            sat_r = rt >= self.saturation - 0.5
            any_l, any_r = sat_l.any(axis=(1, 2)), sat_r.any(axis=(1, 2))
            sat_any = bool(any_l.any() or any_r.any())
            if sat_any and plan.leds is None and not self.declip:   # auto, geometry unknown
                sat_any = _compact(sat_l) and _compact(sat_r)
        if pedestal is not None and plan.weights_left is not None and not sat_any:
            # the live path: projection is linear, so project the raw patches and remove
            # the background's and the pedestal's projections (no (n, h, w) temporaries)
            wl = plan.weights_left.astype(lf.dtype)
            wr = plan.weights_right.astype(rt.dtype)  # type: ignore[union-attr]
            ped_l = np.asarray(pedestal[0], np.float64)
            ped_r = np.asarray(pedestal[1], np.float64)
            prof_l = (wl @ lf).astype(np.float64) - (ped_l * float(wl.sum()))[:, None]
            prof_r = (wr @ rt).astype(np.float64) - (ped_r * float(wr.sum()))[:, None]
            if bl is not None:
                prof_l -= wl @ bl
                prof_r -= wr @ br
        else:
            l0 = lf - bl if bl is not None else lf
            r0 = rt - br if br is not None else rt
            if pedestal is None:
                ring = ring_indices(h, w)
                ped_l, ped_r = ring_level(l0, ring), ring_level(r0, ring)
            else:
                ped_l, ped_r = np.asarray(pedestal[0], np.float64), np.asarray(pedestal[1], np.float64)
            l0 = l0 - ped_l[:, None, None]
            r0 = r0 - ped_r[:, None, None]
            if sat_any:
                map_l = None if bl is None else -np.broadcast_to(bl, lf.shape)
                map_r = None if br is None else -np.broadcast_to(br, rt.shape)
                if plan.cells_left.index.shape[0] == 1 and plan.cells_right.index.shape[0] == 1:
                    # one cell per patch: both cameras in one call
                    both, _ = declip_cells(np.concatenate([l0, r0]), np.concatenate([sat_l, sat_r]),
                                           self.saturation - np.concatenate([ped_l, ped_r]), plan.cells_left,
                                           None if bl is None else np.concatenate([map_l, map_r]),
                                           compiled=compiled)
                    l0, r0 = both[:n], both[n:]
                else:
                    l0, _ = declip_cells(l0, sat_l, self.saturation - ped_l, plan.cells_left, map_l, compiled=compiled)
                    r0, _ = declip_cells(r0, sat_r, self.saturation - ped_r, plan.cells_right, map_r, compiled=compiled)
            if plan.weights_left is not None:
                wl, wr = plan.weights_left, plan.weights_right
            else:
                wl = wr = data_row_weights(l0, r0)
            prof_l = (wl @ l0).astype(np.float64)                          # (n, w)
            prof_r = (wr @ r0).astype(np.float64)  # type: ignore[operator]
        return self.from_profiles(prof_l, prof_r, plan,
                                  saturated=(any_l | any_r) if sat_any else None, compiled=compiled)

    def declips(self, plan: Plan) -> bool:
        """Whether :meth:`estimate` looks for clipped cores with this plan.

        ``declip``, or by default for one-LED patches and patches of unknown geometry.

        Parameters
        ----------
        plan : Plan
            The patch geometry.

        Returns
        -------
        bool
        """
        return bool(self.declip or (self.declip is None and plan.leds in (1, None)))

    def from_profiles(self, prof_l: NDArray[np.float64], prof_r: NDArray[np.float64], plan: Plan,
                      saturated: NDArray[np.bool_] | None = None, *, compiled: bool = False
                      ):  # -> ShiftEstimate
        """The shift estimate from the row-weighted profiles of both cameras.

        The second half of :meth:`estimate`.

        Parameters
        ----------
        prof_l, prof_r : ndarray of float64
            (n, w) profiles, DN.
        plan : Plan
            The patch geometry (:func:`make_plan`).
        saturated : ndarray of bool, optional
            (n,) frames with a refilled core.
        compiled : bool
            Keyword-only. Use :func:`iscd.decode.ranging.project_kernel.correlate_1d_compiled` (the same
            peak to ~1e-13 px).

        Returns
        -------
        ShiftEstimate
        """

        n = prof_l.shape[0]
        if compiled:
            from iscd.decode.ranging.project_kernel import correlate_1d_compiled as corr
        else:
            corr = correlate_1d
        p = corr(prof_l, prof_r, self.beta, self.band_cutoff, plan.max_shift_px, self.iterations)
        if saturated is not None:
            floor = np.sqrt(self.sigma_floor_px ** 2 + saturated * self.sigma_saturated_px ** 2)
        else:
            floor = self.sigma_floor_px
        dead = ~(np.isfinite(p.height) & np.isfinite(p.dx))
        dx = np.where(dead, np.nan, p.dx)
        return ShiftEstimate(dx=dx, dy=dx * 0.0, quality=np.where(dead, 0.0, p.height),
                             sigma_px=np.sqrt(p.sigma ** 2 + floor ** 2), sigma_y_px=np.full(n, np.nan))
