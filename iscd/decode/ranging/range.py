"""From LED positions in a stereo pair to range: patches, disparity, Z = f b / d (eq. 2.2).

The whole-pixel part of the disparity comes from where the patches are cut (the LED's
detected position in each camera), the sub-pixel rest from a shift estimator
(:mod:`iscd.decode.ranging.estimators`). With a rectified calibration, the two matched points are
mapped into rectified coordinates (``cv2.undistortPoints`` with R1/P1 and R2/P2) before
their x difference is taken, so lens distortion and a small rotation between the cameras
are accounted for; the patches themselves are not resampled. :class:`LedRanger` does it for
LED positions in one stereo pair (per LED, or per group); the live pipeline's block ranger
is :class:`iscd.decode.ranging.stereo.StereoRanger`, which uses the same formulas.

The calibration is any object with ``focal_px`` (f/rho, px) and ``baseline_m`` (b, m) --
e.g. ``iscd.calibration.io.StereoCalibration`` -- and optionally ``M1 D1 R1 P1 M2 D2 R2 P2``
(OpenCV ``stereoRectify`` conventions) for the rectification.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iscd.decode.ranging.estimators import Estimator, ShiftEstimate, get_estimator

Which = Literal["left", "right"]

DEFAULT_MIN_QUALITY = {"iscd": 0.75}
"""Per-method default quality threshold (iscd: dark/no-LED pairs score below 0.5, a spot of
15 DN above 0.9, docs/ranging.md); 0 (accept all) for methods whose quality has another
scale."""
Rectifier = Callable[[NDArray[np.float64], Which], NDArray[np.float64]]


def range_from_disparity(disparity_px: ArrayLike, focal_px: float, baseline_m: float) -> NDArray[np.float64]:
    """Z = f b / (rho d) (eq. 2.2), m, with ``focal_px`` = f/rho.

    Parameters
    ----------
    disparity_px : array_like
        Disparity d, px.
    focal_px : float
        f / rho, px.
    baseline_m : float
        Baseline b, m.

    Returns
    -------
    ndarray of float64
        Z, m; NaN where d <= 0 or is not finite.

    References
    ----------
    Dissertation, eq. (2.2).
    """
    d = np.asarray(disparity_px, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = focal_px * baseline_m / d
    return np.where(np.isfinite(d) & (d > 0), z, np.nan)


def disparity_from_range(z_m: ArrayLike, focal_px: float, baseline_m: float) -> NDArray[np.float64]:
    """d = f b / Z, px (the inverse of :func:`range_from_disparity`).

    Parameters
    ----------
    z_m : array_like
        Range Z, m.
    focal_px : float
        f / rho, px.
    baseline_m : float
        Baseline b, m.

    Returns
    -------
    ndarray of float64
        d, px.

    References
    ----------
    Dissertation, eq. (2.2).
    """
    return focal_px * baseline_m / np.asarray(z_m, dtype=np.float64)


def range_sigma(z_m: ArrayLike, sigma_d_px: ArrayLike, focal_px: float, baseline_m: float) -> NDArray[np.float64]:
    """Standard deviation of Z from that of the disparity: sigma_Z = Z^2 / (f b) * sigma_d.

    Parameters
    ----------
    z_m : array_like
        Range Z, m.
    sigma_d_px : array_like
        Standard deviation of the disparity, px.
    focal_px : float
        f / rho, px.
    baseline_m : float
        Baseline b, m.

    Returns
    -------
    ndarray of float64
        sigma_Z, m.

    References
    ----------
    Dissertation, eq. (2.2) (differentiated).
    """
    z = np.asarray(z_m, dtype=np.float64)
    return z * z / (focal_px * baseline_m) * np.asarray(sigma_d_px, dtype=np.float64)


def cut_patches(image: ArrayLike, centres_xy: ArrayLike, size: int | tuple[int, int]
                ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Cut (n, h, w) patches centred (to the nearest pixel) on ``centres_xy``.

    Patch pixel (j, i) is image pixel (y0 + j, x0 + i). Pixels outside the image repeat the
    nearest edge pixel. One fancy-indexing gather, no loops.

    Parameters
    ----------
    image : array_like
        (H, W) image, DN.
    centres_xy : array_like
        (n, 2) centres (x, y), px.
    size : int or (int, int)
        Patch side, or (h, w), px.

    Returns
    -------
    patches : ndarray of float64
        (n, h, w), DN.
    origins : ndarray of int64
        (n, 2) top-left corners (x0, y0), px.
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image: expected a 2-D grey image, got shape {img.shape}")
    h, w = (size, size) if isinstance(size, (int, np.integer)) else size
    c = np.asarray(centres_xy, dtype=np.float64).reshape(-1, 2)
    if not np.isfinite(c).all():
        raise ValueError("centres_xy: NaN or infinite LED position")
    x0 = np.round(c[:, 0] - (w - 1) / 2.0).astype(np.int64)
    y0 = np.round(c[:, 1] - (h - 1) / 2.0).astype(np.int64)
    ys = np.clip(y0[:, None] + np.arange(h)[None, :], 0, img.shape[0] - 1)
    xs = np.clip(x0[:, None] + np.arange(w)[None, :], 0, img.shape[1] - 1)
    patches = img[ys[:, :, None], xs[:, None, :]].astype(np.float64)
    return patches, np.stack([x0, y0], axis=1)


def opencv_rectifier(calibration: Any) -> Rectifier | None:
    """A point rectifier from a calibration's M/D/R/P matrices.

    Uses ``cv2.undistortPoints(pts, M, D, R=R, P=P)``; without R1/P1 it only undistorts
    (P = M). Points are (n, 2) raw pixel (x, y).

    Parameters
    ----------
    calibration : object
        With ``M1``, ``M2`` (and optionally ``D1``, ``D2``, ``R1``, ``P1``, ``R2``, ``P2``).

    Returns
    -------
    Rectifier or None
        ``rectify(pts (n, 2) px, "left"|"right") -> (n, 2) px``; None if it has no M1/M2.
    """
    import cv2

    m1, m2 = getattr(calibration, "M1", None), getattr(calibration, "M2", None)
    if m1 is None or m2 is None:
        return None
    mats = {}
    for which, (m, d, r, p) in {"left": ("M1", "D1", "R1", "P1"), "right": ("M2", "D2", "R2", "P2")}.items():
        mm = np.asarray(getattr(calibration, m), dtype=np.float64)
        dd = getattr(calibration, d, None)
        rr, pp = getattr(calibration, r, None), getattr(calibration, p, None)
        mats[which] = (mm, np.zeros(5) if dd is None else np.asarray(dd, dtype=np.float64),
                       None if rr is None else np.asarray(rr, dtype=np.float64),
                       mm if pp is None else np.asarray(pp, dtype=np.float64))

    def rectify(pts: NDArray[np.float64], which: Which) -> NDArray[np.float64]:
        m, d, r, p = mats[which]
        out = cv2.undistortPoints(np.asarray(pts, dtype=np.float64).reshape(-1, 1, 2), m, d, R=r, P=p)
        return out.reshape(-1, 2)

    return rectify


def disparity_offset_px(calibration: Any) -> float:
    """cx_left - cx_right of the (rectified if available) cameras: d = f b / Z + offset.

    Parameters
    ----------
    calibration : object
        A calibration (P1/P2, else M1/M2).

    Returns
    -------
    float
        The offset, px (0 without either pair).
    """
    for a, b in (("P1", "P2"), ("M1", "M2")):
        pa, pb = getattr(calibration, a, None), getattr(calibration, b, None)
        if pa is not None and pb is not None:
            return float(np.asarray(pa)[0, 2] - np.asarray(pb)[0, 2])
    return 0.0


@dataclass(frozen=True)
class RangeEstimate:
    """Per-LED (or per-group) ranges of one stereo frame; all fields (n,)."""

    z_m: NDArray[np.float64]
    disparity_px: NDArray[np.float64]
    sigma_m: NDArray[np.float64]
    sigma_px: NDArray[np.float64]
    quality: NDArray[np.float64]
    dy_px: NDArray[np.float64]
    """vertical offset of the matched points after rectification, px (about 0 when the
    calibration is right and the match is true)."""
    valid: NDArray[np.bool_]
    """finite, positive disparity and quality >= the ranger's ``min_quality``."""


class LedRanger:
    """Ranges of LEDs in one stereo pair with one shift estimator (default: the project's 2-D
    ``"iscd"``), stateless: LED positions in, one range per LED (or one per group) out. For
    per-LED ranges and offline work; the live pipeline ranges whole blocks of frames of a
    tracked transmitter with :class:`iscd.decode.ranging.stereo.StereoRanger` instead.

    ``calibration``: object with ``focal_px`` and ``baseline_m`` (+ optional M/D/R/P
    matrices, see the module doc). ``rectify``: ``"auto"`` (use the calibration's matrices
    when present), ``None`` (raw x difference) or a callable ``(pts (n, 2), "left"|"right")
    -> rectified pts``. ``min_quality``: estimates below it are not ``valid`` (None = the
    method's default, :data:`DEFAULT_MIN_QUALITY`). ``patch_px``: side of a single-LED patch
    before any interpolation (16: an LED spot is 3-6 px). Estimator options (``**options``)
    go to :func:`iscd.decode.ranging.estimators.get_estimator`.
    """

    def __init__(self, calibration: Any, method: str = "iscd", patch_px: int = 16,
                 rectify: Rectifier | str | None = "auto", min_quality: float | None = None,
                 **options: Any) -> None:
        try:
            self.focal_px = float(calibration.focal_px)
            self.baseline_m = float(calibration.baseline_m)
        except AttributeError as e:
            raise ValueError(f"calibration: needs focal_px and baseline_m ({e})") from None
        if not (self.focal_px > 0 and self.baseline_m > 0):
            raise ValueError(f"calibration: focal_px and baseline_m must be > 0, got "
                             f"{self.focal_px}, {self.baseline_m}")
        if patch_px < 4:
            raise ValueError(f"patch_px: expected at least 4, got {patch_px}")
        self.method = method
        self.estimator: Estimator = get_estimator(method, **options)
        self.patch_px = int(patch_px)
        self.min_quality = float(DEFAULT_MIN_QUALITY.get(method, 0.0) if min_quality is None else min_quality)
        if rectify == "auto":
            self.rectify: Rectifier | None = opencv_rectifier(calibration)
        elif rectify is None or callable(rectify):
            self.rectify = rectify  # type: ignore[assignment]
        else:
            raise ValueError(f"rectify: expected 'auto', None or a callable, got {rectify!r}")
        self.offset_px = disparity_offset_px(calibration) if self.rectify is not None or rectify == "auto" else 0.0

    # -- core -----------------------------------------------------------------------------
    def _finish(self, est: ShiftEstimate, origin_l: NDArray[np.int64], origin_r: NDArray[np.int64],
                ref: NDArray[np.float64]) -> RangeEstimate:
        p_l = origin_l + ref                                     # a point of the left patch
        p_r = origin_r + ref - np.stack([est.dx, est.dy], axis=1)   # the same point in the right image
        if self.rectify is not None:
            ok = np.isfinite(p_r).all(axis=1)
            p_l = self.rectify(p_l, "left")
            rect_r = np.full_like(p_r, np.nan)
            if ok.any():
                rect_r[ok] = self.rectify(p_r[ok], "right")
            p_r = rect_r
        d = p_l[:, 0] - p_r[:, 0] - self.offset_px
        dy = p_l[:, 1] - p_r[:, 1]
        z = range_from_disparity(d, self.focal_px, self.baseline_m)
        sig_m = range_sigma(z, est.sigma_px, self.focal_px, self.baseline_m)
        valid = np.isfinite(z) & (est.quality >= self.min_quality)
        return RangeEstimate(z_m=z, disparity_px=d, sigma_m=sig_m, sigma_px=est.sigma_px,
                             quality=est.quality, dy_px=dy, valid=valid)

    def measure(self, left_image: ArrayLike, right_image: ArrayLike, left_xy: ArrayLike, right_xy: ArrayLike,
                background: tuple[ArrayLike, ArrayLike] | None = None) -> RangeEstimate:
        """One range per LED.

        When LEDs are closer together than half a patch (an array), each patch also holds
        neighbours: patches shrink to about 3 LED spacings, the integer peak search is
        limited to half the spacing and (iscd) a Gaussian window of 0.7 x the spacing,
        centred on the LED in both patches, keeps the patch edges out of the match
        (docs/ranging.md: 0.13-0.31 -> 0.03 m per LED at 50 m).

        Parameters
        ----------
        left_image, right_image : array_like
            (H, W) raw left and right images, DN.
        left_xy, right_xy : array_like
            (n, 2) each LED's (x, y) in the raw left/right images, px (detection accuracy ~1 px is
            enough).
        background : (array_like, array_like), optional
            Dark left/right images (an all-dark symbol) to subtract, DN (iscd method only).

        Returns
        -------
        RangeEstimate
            Per LED (n,): range and sigma, m; disparity and sigma, px; quality, validity.

        References
        ----------
        Dissertation, eq. (2.2).
        """
        lxy = np.asarray(left_xy, dtype=np.float64).reshape(-1, 2)
        rxy = np.asarray(right_xy, dtype=np.float64).reshape(-1, 2)
        if lxy.shape != rxy.shape:
            raise ValueError(f"left_xy and right_xy differ in shape: {lxy.shape} vs {rxy.shape}")
        size = self.patch_px
        est_obj = self.estimator
        spacing = _min_spacing(lxy)
        if spacing is not None and spacing < self.patch_px / 2:
            size = int(max(8, min(self.patch_px, round(3 * spacing))))
            est_obj = _with_options(est_obj, max_shift_px=max(1.0, spacing / 2.0),
                                    window_sigma_px=max(1.5, 0.7 * spacing), window_rounds=1)
        pl, ol = cut_patches(left_image, lxy, size)
        pr, orr = cut_patches(right_image, rxy, size)
        kw: dict[str, Any] = {}
        if background is not None:
            kw["background"] = (cut_patches(background[0], lxy, size)[0],
                                cut_patches(background[1], rxy, size)[0])
        est = est_obj.estimate(pl, pr, **kw)
        ref = np.array([(size - 1) / 2.0, (size - 1) / 2.0])
        return self._finish(est, ol, orr, ref)

    def measure_group(self, left_image: ArrayLike, right_image: ArrayLike, left_xy: ArrayLike, right_xy: ArrayLike,
                      margin_px: int = 4, background: tuple[ArrayLike, ArrayLike] | None = None) -> RangeEstimate:
        """One range for a whole LED array (n = 1).

        One patch spanning all its LEDs plus ``margin_px``, in each camera. The integer peak
        search is limited to half the smallest LED spacing so that a periodic array cannot
        match one LED off.

        Parameters
        ----------
        left_image, right_image : array_like
            (H, W) raw left and right images, DN.
        left_xy, right_xy : array_like
            (m, 2) the LEDs' (x, y) in each image, px.
        margin_px : int
            Margin around the LEDs, px.
        background : (array_like, array_like), optional
            Dark left/right images to subtract, DN.

        Returns
        -------
        RangeEstimate
            n = 1.

        References
        ----------
        Dissertation, eq. (2.2).
        """
        lxy = np.asarray(left_xy, dtype=np.float64).reshape(-1, 2)
        rxy = np.asarray(right_xy, dtype=np.float64).reshape(-1, 2)
        if lxy.shape != rxy.shape or lxy.shape[0] == 0:
            raise ValueError(f"left_xy and right_xy: expected the same non-empty (m, 2), got {lxy.shape}, {rxy.shape}")
        span = lxy.max(axis=0) - lxy.min(axis=0)
        w = int(np.ceil(span[0])) + 2 * margin_px + 1
        h = int(np.ceil(span[1])) + 2 * margin_px + 1
        cl = (lxy.max(axis=0) + lxy.min(axis=0)) / 2.0
        cr = (rxy.max(axis=0) + rxy.min(axis=0)) / 2.0
        pl, ol = cut_patches(left_image, cl[None], (h, w))
        pr, orr = cut_patches(right_image, cr[None], (h, w))
        est_obj = self.estimator
        spacing = _min_spacing(lxy)
        if spacing is not None:
            est_obj = _with_options(est_obj, max_shift_px=max(1.0, spacing / 2.0))
        kw: dict[str, Any] = {}
        if background is not None:
            kw["background"] = (cut_patches(background[0], cl[None], (h, w))[0],
                                cut_patches(background[1], cr[None], (h, w))[0])
        est = est_obj.estimate(pl, pr, **kw)
        ref = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
        return self._finish(est, ol, orr, ref)


def _min_spacing(xy: NDArray[np.float64]) -> float | None:
    """Smallest distance between two of the points (px), None for fewer than two."""
    if xy.shape[0] < 2:
        return None
    dd = np.sqrt(((xy[:, None, :] - xy[None, :, :]) ** 2).sum(-1))
    dd = dd[dd > 0.5]
    return float(dd.min()) if dd.size else None


def _with_options(est: Estimator, **options: Any) -> Estimator:
    """A copy of a dataclass estimator with those of ``options`` it has (others ignored)."""
    fields = {f.name for f in dataclasses.fields(est)} if dataclasses.is_dataclass(est) else set()
    use = {k: v for k, v in options.items() if k in fields}
    return dataclasses.replace(est, **use) if use else est  # type: ignore[type-var]
