"""Per-frame stereo ranging of a tracked transmitter in the live pipeline: patches -> range.

This is the ranger of :class:`iscd.decode.stream.StreamDecoder` (``iscd run``/``replay``) and of
``iscd eval``: it ranges a whole block of stereo frames in one call from the tracked grid
fits. (:class:`iscd.decode.ranging.range.LedRanger` is the stateless per-LED ranger: LED positions
in one stereo pair in, one range per LED out.)

For each block the transmitter's patch -- the whole array plus ``margin_px`` -- is cut from
the left and right images at whole-pixel positions (rectified: only the patch's pixels are
remapped, never the whole frame) and

1. **background**: a running per-pixel minimum of each camera's patch over the last
   ``background_frames`` frames (:class:`RunningMinimum`) is the background plus the dark
   level -- every LED sends level 1 often (header '-' chips, training, data) and a frame
   inside a dark symbol sees only the background. It is kept between blocks in image
   coordinates, so it follows the patch when the tracked fit moves by whole pixels. With
   a textured background every shift estimator otherwise locks partly onto the background,
   which has another disparity (docs/ranging.md: -0.01 to -0.03 px bias at 30-60 m);
2. **signal-to-noise ratio** of each frame's spot after that subtraction (a matched
   filter at the fitted LED positions, :func:`spot_snr`): frames below ``min_snr`` in
   either camera (a dark symbol, a lost LED) give no range;
3. the sub-pixel **shift** of the left vs the right patch (:mod:`iscd.decode.ranging.estimators`;
   default ``"iscd-fast"``, the 1-D projected method of :mod:`iscd.decode.ranging.projected`,
   given the LED centres, pitch and spot size of the fits);
4. **range** (eq. 2.2) and its standard deviation with the codebase's one formula
   (:func:`iscd.decode.ranging.range.range_from_disparity`, :func:`~iscd.decode.ranging.range.range_sigma`):

    d = (x0_left - x0_right) + shift          [px, rectified]
    Z = f * b / d;  sigma_Z = Z^2 / (f * b) * sigma_d
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from iscd.calibration.io import StereoCalibration, rectify_points
from iscd.decode.ranging.config import PROJECT_METHODS, RangingSettings
from iscd.decode.ranging.estimators import Estimator, get_estimator
from iscd.decode.ranging.project_kernel import _range_live, range_block_args
from iscd.decode.ranging.projected import Plan, ProjectedShift, make_plan, ring_indices, robust_level
from iscd.decode.ranging.range import DEFAULT_MIN_QUALITY, range_from_disparity, range_sigma
from iscd.decode.tracking.detect import GridFit

__all__ = ["RangingSettings", "RangeResult", "RunningMinimum", "StereoRanger", "snr_weights", "spot_snr"]

_QUANT_NOISE_DN = 0.5
"""floor of the per-pixel noise estimate, grey levels (8-bit quantization alone is 0.29)."""


@dataclass
class RangeResult:
    """Per-frame results for one block, all (n,) arrays.

    ``z_m``/``sigma_m`` are NaN where the frame gives no range (``valid`` False: dark
    spot, failed match, low quality); ``disparity_px`` and ``quality`` are what the
    estimator found (NaN when it found nothing). ``snr``: the weaker camera's spot
    signal-to-noise ratio after background removal."""

    z_m: np.ndarray
    disparity_px: np.ndarray
    sigma_m: np.ndarray
    quality: np.ndarray
    valid: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    snr: np.ndarray = field(default_factory=lambda: np.zeros(0))


class RunningMinimum:
    """Per-pixel minimum of one camera's patch over the last ``frames`` frames.

    Kept as one minimum image per block with its position in the image, so that the
    estimate follows the patch when it is cut elsewhere (the tracked fit moved by a pixel,
    or the patch grew): each stored block contributes where it overlaps the new patch;
    pixels no stored block covers have only the current block's minimum.
    """

    def __init__(self, frames: int = 64) -> None:
        if frames < 1:
            raise ValueError(f"frames: expected >= 1, got {frames}")
        self.frames = int(frames)
        self._blocks: deque[tuple[int, int, np.ndarray, int]] = deque()
        self._held = 0

    def reset(self) -> None:
        self._blocks.clear()
        self._held = 0

    @property
    def frames_held(self) -> int:
        return self._held

    def update(self, patches: np.ndarray, x0: int, y0: int) -> np.ndarray:
        """Add a block of patches (n, h, w) cut at image position (x0, y0) and return the
        (h, w) minimum over it and the stored blocks (float32, grey levels).

        Parameters
        ----------
        patches : ndarray
            (n, h, w) patches of one camera, DN.
        x0, y0 : int
            Image position of the patches' top-left pixel, px.

        Returns
        -------
        ndarray of float32
            (h, w) per-pixel minimum, DN.
        """
        n = patches.shape[0]
        return self.update_min(patches.min(axis=0).astype(np.float32), x0, y0, n)

    def update_min(self, cur: np.ndarray, x0: int, y0: int, n: int) -> np.ndarray:
        """:meth:`update` given the block's own per-pixel minimum ``cur`` (h, w) of ``n``
        frames (:func:`iscd.decode.ranging.project_kernel.patch_minimum`).

        Parameters
        ----------
        cur : ndarray of float32
            (h, w) the block's per-pixel minimum, DN (kept: do not reuse it).
        x0, y0 : int
            Image position of its top-left pixel, px.
        n : int
            Frames in the block.

        Returns
        -------
        ndarray of float32
            (h, w) per-pixel minimum over this and the held blocks, DN.
        """
        held = self.held_min(x0, y0, *cur.shape)
        bg = cur.copy() if held is None else np.minimum(cur, held)
        self.push(cur, x0, y0, n)
        return bg

    def held_min(self, x0: int, y0: int, h: int, w: int) -> np.ndarray | None:
        """The per-pixel minimum over the held blocks of the (h, w) patch at image position
        (x0, y0), +inf where none of them overlaps it; None if none does (:meth:`update_min`
        is ``minimum(cur, held_min)`` then :meth:`push`).

        Parameters
        ----------
        x0, y0 : int
            Image position of the patch's top-left pixel, px.
        h, w : int
            Patch size, px.

        Returns
        -------
        ndarray of float32 or None
            (h, w), DN; read only (it may be a held block itself).
        """
        out: np.ndarray | None = None
        owned = False
        for bx, by, bmin, _ in self._blocks:
            bh, bw = bmin.shape
            if bx == x0 and by == y0 and bh == h and bw == w:  # the same patch (the usual case)
                if out is None:
                    out = bmin
                elif owned:
                    np.minimum(out, bmin, out=out)
                else:
                    out, owned = np.minimum(out, bmin), True
                continue
            xa, xb = max(x0, bx), min(x0 + w, bx + bw)
            ya, yb = max(y0, by), min(y0 + h, by + bh)
            if xa < xb and ya < yb:
                if not owned:
                    out = np.full((h, w), np.inf, np.float32) if out is None else out.copy()
                    owned = True
                assert out is not None
                dst = out[ya - y0:yb - y0, xa - x0:xb - x0]
                np.minimum(dst, bmin[ya - by:yb - by, xa - bx:xb - bx], out=dst)
        return out

    def push(self, cur: np.ndarray, x0: int, y0: int, n: int) -> None:
        """Hold a block's own per-pixel minimum ``cur`` (h, w) of ``n`` frames at image
        position (x0, y0) (kept: do not reuse it), and let go of the oldest blocks beyond
        ``frames`` frames.

        Parameters
        ----------
        cur : ndarray of float32
            (h, w) the block's per-pixel minimum, DN.
        x0, y0 : int
            Image position of its top-left pixel, px.
        n : int
            Frames in the block.
        """
        self._blocks.append((int(x0), int(y0), cur, int(n)))
        self._held += int(n)
        while len(self._blocks) > 1 and self._held - self._blocks[0][3] >= self.frames:
            self._held -= self._blocks.popleft()[3]


def snr_weights(h: int, w: int, centres_xy: np.ndarray, spot_px: float) -> np.ndarray:
    """(h*w,) matched filter of the LED spots for :func:`spot_snr`: a Gaussian of sigma
    ``max(0.8, spot_px / 2.5)`` px at each LED centre (patch px), summed, unit norm.

    Parameters
    ----------
    h, w : int
        Patch size, px.
    centres_xy : ndarray
        (N, 2) LED centres (x, y) in the patch, px.
    spot_px : float
        Spot diameter, px.

    Returns
    -------
    ndarray
        (h*w,) weights, unit L2 norm.
    """
    s = max(0.8, spot_px / 2.5)
    c = np.asarray(centres_xy, dtype=np.float64).reshape(-1, 2)
    gy = np.exp(-0.5 * ((np.arange(h)[None, :] - c[:, 1:2]) / s) ** 2)      # (N, h)
    gx = np.exp(-0.5 * ((np.arange(w)[None, :] - c[:, 0:1]) / s) ** 2)      # (N, w)
    wgt = (gy.T @ gx).ravel()
    norm = float(np.sqrt(wgt @ wgt))
    return wgt / norm if norm > 0 else wgt


def spot_snr(residual: np.ndarray, weights: np.ndarray, noise_dn: float | np.ndarray) -> np.ndarray:
    """Signal-to-noise ratio of the LEDs in background-removed patches (n, h, w): the
    matched-filter output ``sum(W * residual) / noise`` (``W`` from :func:`snr_weights`,
    unit norm; ``noise_dn`` the per-pixel noise, grey levels). About N(0, 1) for a dark
    frame; the flux of the spots over its noise for a lit one.

    Parameters
    ----------
    residual : ndarray
        (n, h, w) patches with the background removed, DN.
    weights : ndarray
        (h*w,) matched filter (:func:`snr_weights`).
    noise_dn : float or ndarray
        Per-pixel noise, DN (scalar or (n,)).

    Returns
    -------
    ndarray
        (n,) signal-to-noise ratios.
    """
    n = residual.shape[0]
    return (residual.reshape(n, -1) @ weights) / np.asarray(noise_dn, dtype=np.float64)


@dataclass(frozen=True)
class _Geometry:
    """Everything that depends only on the grid fits (cached between blocks)."""

    x0l: int
    y0: int
    x0r: int
    w: int
    h: int
    centres_left: np.ndarray
    centres_right: np.ndarray
    snr_left: np.ndarray
    snr_right: np.ndarray
    ring: np.ndarray
    plan: Plan | None


def _is_identity(cal: StereoCalibration) -> bool:
    if cal.R1 is None or cal.P1 is None or cal.R2 is None or cal.P2 is None:
        return not np.any(cal.D1) and not np.any(cal.D2) and np.allclose(cal.R, np.eye(3))
    return (not np.any(cal.D1) and not np.any(cal.D2) and np.allclose(cal.R1, np.eye(3))
            and np.allclose(cal.R2, np.eye(3)) and np.allclose(cal.P1[:3, :3], cal.M1)
            and np.allclose(cal.P2[:3, :3], cal.M2))


class StereoRanger:
    """Ranges a tracked transmitter frame by frame (see the module docstring).

    Holds state between blocks (the running background of each camera): one ranger per
    tracked transmitter; :meth:`reset` when it is re-acquired elsewhere (not required: a
    background that does not overlap the new patch is ignored).
    """

    def __init__(self, cal: StereoCalibration, settings: RangingSettings | None = None, *,
                 compiled: bool = True) -> None:
        """``compiled``: the live case on the kernels of :mod:`iscd.decode.ranging.project_kernel`
        (``False``: the numpy reference throughout; the same ranges to float tolerance)."""
        self.compiled = compiled
        self.cal = cal if cal.is_rectified else cal.with_rectification()
        self.settings = settings or RangingSettings()
        s = self.settings
        try:
            self.estimator: Estimator = get_estimator(s.method, **s.estimator_options())
        except ValueError as e:
            raise ValueError(f"ranging: {e}") from None
        self.f_px = float(self.cal.focal_px)
        self.b_m = float(self.cal.baseline_m)
        self.identity = _is_identity(self.cal)
        self.subtract_background = s.subtracts_background()
        self.native_background = s.method in PROJECT_METHODS
        q = s.quality_threshold()
        self.min_quality = float(DEFAULT_MIN_QUALITY.get(s.method, 0.0) if q is None else q)
        self.background = {"left": RunningMinimum(s.background_frames), "right": RunningMinimum(s.background_frames)}
        self._maps: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        if not self.identity:
            for which in ("left", "right"):
                self._maps[which] = self.cal.rectification_maps(which)  # type: ignore[arg-type]
        self._est_cache: dict[tuple[float | None, float], Estimator] = {}
        self._geo_key: tuple | None = None
        self._geo: _Geometry | None = None
        # the last fits (frozen: the same objects, the same answers) and what follows from them
        self._pg_last: tuple[GridFit, GridFit, tuple[int, int, int, int, int]] | None = None
        self._live: tuple[GridFit, GridFit, np.dtype, _Geometry, Estimator, tuple] | None = None

    def reset(self) -> None:
        """Forget the running background (e.g. after re-acquisition)."""
        for b in self.background.values():
            b.reset()

    # ------------------------------------------------------------------ geometry
    def _rect(self, pts: np.ndarray, which: str) -> np.ndarray:
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if self.identity:
            return p
        return rectify_points(self.cal, p, which)  # type: ignore[arg-type]

    def _cut(self, frames: np.ndarray, which: str, x0: int, y0: int, w: int, h: int) -> np.ndarray:
        """(n, h, w) float32 patches of rectified ``frames`` with top-left (x0, y0); pixels
        outside the image are 0."""
        n, H, W = frames.shape
        out = np.zeros((n, h, w), np.float32)
        if self.identity:
            xa, ya = max(0, x0), max(0, y0)
            xb, yb = min(W, x0 + w), min(H, y0 + h)
            if xb > xa and yb > ya:
                out[:, ya - y0:yb - y0, xa - x0:xb - x0] = frames[:, ya:yb, xa:xb]
            return out
        mx, my = self._maps[which]
        ya, xa = max(0, y0), max(0, x0)
        sx = mx[ya:y0 + h, xa:x0 + w]
        sy = my[ya:y0 + h, xa:x0 + w]
        if sx.size == 0:
            return out
        for i in range(n):  # one remap per frame of the patch's pixels only
            p = cv2.remap(frames[i], sx, sy, cv2.INTER_LINEAR)
            out[i, ya - y0:ya - y0 + p.shape[0], xa - x0:xa - x0 + p.shape[1]] = p
        return out

    def patch_geometry(self, fit_l: GridFit, fit_r: GridFit) -> tuple[int, int, int, int, int]:
        """(x0_left, y0, x0_right, w, h) of the patches in rectified px.

        Parameters
        ----------
        fit_l, fit_r : GridFit
            The left and right grid fits, raw image px.

        Returns
        -------
        tuple of int
            (x0_left, y0, x0_right, w, h), rectified px.
        """
        last = self._pg_last
        if last is not None and last[0] is fit_l and last[1] is fit_r:
            return last[2]
        if self.identity:
            cl, cr = fit_l.center, fit_r.center
        else:
            cl = self._rect(np.array(fit_l.center), "left")[0]
            cr = self._rect(np.array(fit_r.center), "right")[0]
        ext_x = (fit_l.cols - 1) * fit_l.pitch_px + fit_l.spot_px + 2 * self.settings.margin_px
        ext_y = (fit_l.rows - 1) * fit_l.pitch_px + fit_l.spot_px + 2 * self.settings.margin_px
        w = int(min(self.settings.max_patch_px, 2 * int(np.ceil(ext_x / 2))))
        h = int(min(self.settings.max_patch_px, 2 * int(np.ceil(ext_y / 2))))
        x0l = int(round(cl[0] - w / 2))
        y0 = int(round((cl[1] + cr[1]) / 2 - h / 2))
        x0r = int(round(cr[0] - w / 2))
        self._pg_last = (fit_l, fit_r, (x0l, y0, x0r, w, h))
        return x0l, y0, x0r, w, h

    def saturation_level(self, frames: np.ndarray) -> float:
        """Grey level at which the sensor clips: ``[ranging] saturation_dn`` if set, else
        the largest value of the frames' integer type (255 for 8-bit; set it for 10/12-bit
        data stored in 16 bits).

        Parameters
        ----------
        frames : ndarray
            Frames of the block (only the dtype is read).

        Returns
        -------
        float
            The clipping level, DN.
        """
        if self.settings.saturation_dn > 0:
            return float(self.settings.saturation_dn)
        dt = np.asarray(frames).dtype
        return float(np.iinfo(dt).max) if dt.kind in "ui" else 255.0

    def _estimator_for(self, pitch_px: float, saturation: float = 255.0) -> Estimator:
        """The estimator with its integer-peak search limited to half the LED spacing (a
        periodic array must not match one LED off; unchanged for one LED) and the sensor's
        clip level."""
        shift = round(max(1.0, pitch_px / 2.0), 2) if pitch_px > 0 else None
        key = (shift, saturation)
        est = self._est_cache.get(key)
        if est is None:
            names = {f.name for f in dataclasses.fields(self.estimator)} if dataclasses.is_dataclass(self.estimator) else set()
            changes = {k: v for k, v in (("max_shift_px", shift), ("saturation", saturation))
                       if k in names and v is not None}
            est = dataclasses.replace(self.estimator, **changes) if changes else self.estimator  # type: ignore[type-var]
            self._est_cache[key] = est
        return est

    def _geometry(self, fit_l: GridFit, fit_r: GridFit) -> _Geometry:
        """The patch geometry, LED centres in the patches, SNR weights and the estimator's
        plan for these fits; reused while the fits move by less than 0.05 px (tracking
        re-fits every few blocks and the fit wanders by hundredths of a pixel)."""
        x0l, y0, x0r, w, h = self.patch_geometry(fit_l, fit_r)
        key = (x0l, y0, x0r, w, h, fit_l.rows, fit_l.cols,
               *(round(v * 20) for v in (*fit_l.origin, *fit_r.origin, fit_l.pitch_px, fit_r.pitch_px)),
               round(fit_l.spot_px * 4), round(fit_r.spot_px * 4))
        if self._geo_key == key and self._geo is not None:
            return self._geo
        cl = self._rect(fit_l.centers, "left") - (x0l, y0)      # LED centres, patch px
        cr = self._rect(fit_r.centers, "right") - (x0r, y0)
        plan = None
        if isinstance(self.estimator, ProjectedShift):
            plan = make_plan(h, w, cl, cr, fit_l.pitch_px, fit_l.spot_px, self.estimator.max_shift_px)
        geo = _Geometry(x0l, y0, x0r, w, h, cl, cr, snr_weights(h, w, cl, fit_l.spot_px),
                        snr_weights(h, w, cr, fit_r.spot_px), ring_indices(h, w), plan)
        self._geo_key, self._geo = key, geo
        return geo

    # ------------------------------------------------------------------ ranging
    def measure(self, left: np.ndarray, right: np.ndarray, fit_l: GridFit, fit_r: GridFit) -> RangeResult:
        """Range for each stereo frame of a block: ``left``/``right`` (n, H, W) images of
        the same pairs, ``fit_l``/``fit_r`` the transmitter's grid fits (raw image px).

        Parameters
        ----------
        left, right : ndarray
            (n, H, W) images of the same pairs, DN.
        fit_l, fit_r : GridFit
            The transmitter's grid fits, raw image px.

        Returns
        -------
        RangeResult
            Per frame the range Z = f b / d (m), disparity (px), sigma (m), quality, validity
            and SNR.

        References
        ----------
        Dissertation, eq. (2.2).
        """
        n = left.shape[0]
        live = self._live
        if (live is not None and live[0] is fit_l and live[1] is fit_r and live[2] == left.dtype
                and self.compiled and n > 0):
            # the same fits as the last block (frozen: the same geometry): nothing to look up
            return self._measure_live(left, right, live[5])
        g = self._geometry(fit_l, fit_r)
        est_obj = self._estimator_for(fit_l.pitch_px, self.saturation_level(left))
        if (self.compiled and self.identity and g.plan is not None and self.subtract_background
                and isinstance(est_obj, ProjectedShift) and not est_obj.declips(g.plan)
                and g.plan.weights_left is not None and left.dtype.kind in "ui" and n > 0):
            if live is not None and live[3] is g and live[4] is est_obj and live[2] == left.dtype:
                args = live[5]  # other fits, the same geometry (it moved by < 0.05 px)
            else:
                args = self._live_args(g, est_obj)
            self._live = (fit_l, fit_r, left.dtype, g, est_obj, args)
            return self._measure_live(left, right, args)
        self._live = None
        pl = self._cut(left, "left", g.x0l, g.y0, g.w, g.h)
        pr = self._cut(right, "right", g.x0r, g.y0, g.w, g.h)
        bl = self.background["left"].update(pl, g.x0l, g.y0)
        br = self.background["right"].update(pr, g.x0r, g.y0)
        # pedestal (border median) and noise of what the running background leaves
        ring_l = pl.reshape(n, -1)[:, g.ring] - bl.ravel()[g.ring]
        ring_r = pr.reshape(n, -1)[:, g.ring] - br.ravel()[g.ring]
        ped, mad = robust_level(np.concatenate([ring_l, ring_r]), spread=True)
        assert mad is not None
        ped_l, ped_r = ped[:n], ped[n:]
        mad = mad.reshape(2, n)
        mad.sort(axis=1)
        noise_l, noise_r = np.maximum(mad[:, n // 2], _QUANT_NOISE_DN)   # per-block noise, grey levels
        # matched filter (linear): W.(p - bg - ped) = W.p - W.bg - ped * sum(W)
        snr = np.minimum(
            (pl.reshape(n, -1) @ g.snr_left - bl.ravel() @ g.snr_left - ped_l * g.snr_left.sum()) / noise_l,
            (pr.reshape(n, -1) @ g.snr_right - br.ravel() @ g.snr_right - ped_r * g.snr_right.sum()) / noise_r)
        if g.plan is not None:
            kw = {"background": (bl, br), "pedestal": (ped_l, ped_r)} if self.subtract_background else {}
            est = est_obj.estimate(pl, pr, plan=g.plan, compiled=self.compiled, **kw)
        elif self.subtract_background and self.native_background:
            est = est_obj.estimate(pl, pr, background=(bl, br))
        elif self.subtract_background:
            est = est_obj.estimate(pl - bl - ped_l[:, None, None], pr - br - ped_r[:, None, None])
        else:
            est = est_obj.estimate(pl, pr)
        return self._result(g, est, snr)

    def _live_args(self, g: _Geometry, est_obj: ProjectedShift) -> tuple:
        """Everything :meth:`_measure_live` passes the kernel that does not change between
        blocks of the same fits, made once (writable contiguous arrays: the kernel's types)."""
        plan = g.plan
        assert plan is not None and plan.weights_left is not None and plan.weights_right is not None
        (ring, snr_l, snr_r, row_l, row_r, cos_t, sin_t, omega, mult, band, w2, w2m, beta, max_shift,
         iterations, tiny, floor_px, fb, quant, min_snr, min_q) = range_block_args(
            g.w, g.ring, g.snr_left, g.snr_right, plan.weights_left, plan.weights_right,
            beta=est_obj.beta, band_cutoff=est_obj.band_cutoff, max_shift_px=plan.max_shift_px,
            iterations=est_obj.iterations, sigma_floor_px=est_obj.sigma_floor_px, focal_px=self.f_px,
            baseline_m=self.b_m, quant_noise_dn=_QUANT_NOISE_DN, min_snr=self.settings.min_snr,
            min_quality=self.min_quality)
        geo = np.array([g.x0l, g.x0r, g.y0, iterations], np.int64)
        par = np.array([beta, max_shift, tiny, floor_px, fb, quant, min_snr, min_q], np.float64)
        kernel_args = (geo, par, ring, np.stack([snr_l, snr_r]), np.stack([row_l, row_r]), cos_t, sin_t,
                       np.stack([omega, mult, band, w2, w2m]))
        return int(g.x0l), int(g.x0r), int(g.y0), int(g.h), int(g.w), kernel_args, \
            np.full((g.h, g.w), np.inf, np.float32)

    def _measure_live(self, left: np.ndarray, right: np.ndarray, args: tuple) -> RangeResult:
        """:meth:`measure` for the live case (identity rectification, ``"iscd-fast"`` with
        its row weights, no core refill) in one compiled call
        (:func:`~iscd.decode.ranging.project_kernel._range_live`: the same numbers as
        :func:`~iscd.decode.ranging.project_kernel.block_minima`, the running background and
        :func:`~iscd.decode.ranging.project_kernel.range_block`) on the arguments
        :meth:`_live_args` made for these fits: one pass over each patch's pixels, no (n, h, w)
        temporaries, no per-frame Python."""
        x0l, x0r, y0, h, w, kernel_args, none_held = args
        fl, fr_ = left.flags, right.flags
        L = left if fl.c_contiguous and fl.writeable else np.require(left, requirements=["C", "W"])
        R = (right if fr_.c_contiguous and fr_.writeable and right.dtype == L.dtype
             else np.require(right, dtype=L.dtype, requirements=["C", "W"]))
        n = L.shape[0]
        back_l, back_r = self.background["left"], self.background["right"]
        held_l = back_l.held_min(x0l, y0, h, w)
        held_r = back_r.held_min(x0r, y0, h, w)
        cur_l = np.empty((h, w), np.float32)
        cur_r = np.empty((h, w), np.float32)
        out = np.empty((5, n))
        valid = np.empty(n, np.bool_)
        _range_live(L, R, *kernel_args, none_held if held_l is None else held_l,
                    none_held if held_r is None else held_r, cur_l, cur_r, out, valid)
        back_l.push(cur_l, x0l, y0, n)
        back_r.push(cur_r, x0r, y0, n)
        return RangeResult(z_m=out[0], disparity_px=out[1], sigma_m=out[2], quality=out[3], valid=valid,
                           snr=out[4])

    def _result(self, g: _Geometry, est, snr: np.ndarray) -> RangeResult:  # est: ShiftEstimate
        d = (g.x0l - g.x0r) + np.asarray(est.dx, dtype=np.float64)
        z = range_from_disparity(d, self.f_px, self.b_m)
        quality = np.asarray(est.quality, dtype=np.float64)
        valid = np.isfinite(z) & (snr >= self.settings.min_snr) & (quality >= self.min_quality)
        sig = range_sigma(z, est.sigma_px, self.f_px, self.b_m)
        return RangeResult(z_m=np.where(valid, z, np.nan), disparity_px=d,
                           sigma_m=np.where(valid, sig, np.nan), quality=quality, valid=valid, snr=snr)
