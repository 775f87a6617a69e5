"""Run several shift estimators on the same patch pairs against ground truth (one harness).

Pure functions: the caller supplies (n, h, w) left/right patches and the true shifts (left
position - right position, px); :func:`compare` returns one row of error statistics per
method. Used by the tests, docs/ranging.md's tables and (later) the evaluation on simulated
frames, so that every method is judged on identical inputs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iscd.decode.ranging.estimators import get_estimator

PEERS = ("dissertation", "poc", "cv2", "skimage", "centroid", "iscd")
"""The methods of the issue's comparison table, in order."""


@dataclass(frozen=True)
class MethodScore:
    """Error statistics of one method on a set of pairs (px unless noted)."""

    method: str
    n: int
    mae: float
    """mean absolute error of the x shift."""
    rmse: float
    p95: float
    """95th percentile of the absolute error."""
    max_abs: float
    bias: float
    failed: int
    """estimates that were NaN/inf (not included in the statistics)."""
    sigma_ratio: float
    """RMS of (error / reported sigma): about 1 when the reported uncertainty is right."""
    us_per_pair: float
    """wall time per pair, microseconds (indicative only; benchmarks measure speed)."""

    def row(self) -> str:
        return (f"| {self.method} | {self.mae:.4f} | {self.rmse:.4f} | {self.p95:.4f} | {self.max_abs:.4f} "
                f"| {self.bias:+.4f} | {self.sigma_ratio:.2f} | {self.failed} |")


TABLE_HEADER = ("| method | MAE px | RMSE px | p95 px | max px | bias px | err/sigma RMS | failed |\n"
                "|---|---|---|---|---|---|---|---|")


def score(method: str, left: ArrayLike, right: ArrayLike, truth_dx: ArrayLike,
          options: dict[str, Any] | None = None, **estimate_kw: Any) -> MethodScore:
    """Run ``method`` on the pairs and compare its x shift with ``truth_dx``.

    Parameters
    ----------
    method : str
        Estimator name (one of :data:`iscd.decode.ranging.estimators.METHODS`).
    left, right : array_like
        (n, h, w) patch pairs, DN.
    truth_dx : array_like
        (n,) true x shifts (left - right), px.
    options : dict, optional
        Estimator options, to :func:`~iscd.decode.ranging.estimators.get_estimator`.
    **estimate_kw
        Passed to the estimator's ``estimate`` (e.g. ``background``).

    Returns
    -------
    MethodScore
        Error statistics (px), failures and time per pair (us).
    """
    est = get_estimator(method, **(options or {}))
    t0 = time.perf_counter()
    r = est.estimate(left, right, **estimate_kw)
    dt = time.perf_counter() - t0
    truth = np.asarray(truth_dx, dtype=np.float64)
    err = r.dx - truth
    ok = np.isfinite(err)
    e = err[ok]
    if e.size == 0:
        nan = float("nan")
        return MethodScore(method, truth.size, nan, nan, nan, nan, nan, int((~ok).sum()), nan,
                           dt / max(truth.size, 1) * 1e6)
    sig = r.sigma_px[ok]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = e / sig
    z = z[np.isfinite(z)]
    return MethodScore(
        method=method, n=int(truth.size), mae=float(np.mean(np.abs(e))), rmse=float(np.sqrt(np.mean(e * e))),
        p95=float(np.percentile(np.abs(e), 95)), max_abs=float(np.max(np.abs(e))), bias=float(np.mean(e)),
        failed=int((~ok).sum()), sigma_ratio=float(np.sqrt(np.mean(z * z))) if z.size else float("nan"),
        us_per_pair=dt / truth.size * 1e6)


def compare(left: ArrayLike, right: ArrayLike, truth_dx: ArrayLike,
            methods: Iterable[str] = PEERS, **estimate_kw: Any) -> list[MethodScore]:
    """:func:`score` for every method on the same pairs.

    Parameters
    ----------
    left, right : array_like
        (n, h, w) patch pairs, DN.
    truth_dx : array_like
        (n,) true x shifts, px.
    methods : iterable of str
        Estimator names (default :data:`PEERS`).
    **estimate_kw
        Passed to each estimator's ``estimate``.

    Returns
    -------
    list of MethodScore
        One per method, in order.
    """
    return [score(m, left, right, truth_dx, **estimate_kw) for m in methods]


def markdown_table(scores: list[MethodScore]) -> str:
    """The scores as a Markdown table.

    Parameters
    ----------
    scores : list of MethodScore
        Rows of the table.

    Returns
    -------
    str
        Header and one row per score.
    """
    return "\n".join([TABLE_HEADER, *(s.row() for s in scores)])


def errors(method: str, left: ArrayLike, right: ArrayLike, truth_dx: ArrayLike,
           **options: Any) -> NDArray[np.float64]:
    """Signed x-shift errors of one method (NaN where it failed).

    Parameters
    ----------
    method : str
        Estimator name.
    left, right : array_like
        (n, h, w) patch pairs, DN.
    truth_dx : array_like
        (n,) true x shifts, px.
    **options
        Estimator options, to :func:`~iscd.decode.ranging.estimators.get_estimator`.

    Returns
    -------
    ndarray of float64
        (n,) estimated minus true shift, px.
    """
    r = get_estimator(method, **options).estimate(left, right)
    return r.dx - np.asarray(truth_dx, dtype=np.float64)


# ----------------------------------------------------------------------------- the synthetic suite

F_PX = 3500.0
LED_DIAMETER_M = 0.03


@dataclass(frozen=True)
class Case:
    """One set of patch pairs with ground truth; ``z_m``/``baseline_m`` convert px to m."""

    name: str
    left: NDArray[np.float64]
    right: NDArray[np.float64]
    truth_dx: NDArray[np.float64]
    z_m: float | None = None
    baseline_m: float | None = None
    estimate_kw: dict[str, Any] | None = None


def _single_led(rng: np.random.Generator, n: int, z_m: float, brightness: float, right_gain: float = 1.0,
                size: int = 16) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Patch pairs of one LED at ``z_m``: a disk of the LED's apparent radius blurred by a
    0.6 px PSF, surface brightness ``brightness`` DN (the right camera x ``right_gain``),
    40 DN background, shot (78 e/DN) and read (0.26 DN) noise, 8 bits. Patch positions come
    from a +-0.5 px detection, so the residual shifts are within +-1 px."""
    from iscd.decode.ranging.synth import disk_spots, sensor

    radius = F_PX * LED_DIAMETER_M / 2 / z_m
    d = rng.uniform(-1.0, 1.0, n)
    cx = (size - 1) / 2 + rng.uniform(-0.5, 0.5, n)
    cy = (size - 1) / 2 + rng.uniform(-0.5, 0.5, n)
    left = disk_spots(n, (size, size), cx + d / 2, cy, radius, peak=brightness)
    right = disk_spots(n, (size, size), cx - d / 2, cy, radius, peak=brightness * right_gain)
    return (sensor(left, rng, 40, 0.26, 78), sensor(right, rng, 40 * right_gain, 0.26, 78), d)


def standard_suite(n: int = 200, seed: int = 1) -> list[Case]:
    """The cases of docs/ranging.md (fixed seed).

    One LED at 20-60 m unsaturated and saturated (chapter 3 rig, b = 0.6 m), an HDR pair
    (right camera 4x darker, chapter 4), a dim LED on a textured background (with and without
    dark-symbol subtraction), and an 8x8 array at 50 m (b = 0.25 m) as one whole-array patch.

    Parameters
    ----------
    n : int
        Patch pairs per case.
    seed : int
        Random seed.

    Returns
    -------
    list of Case
        The cases, with ground truth (px) and, where known, range and baseline (m).
    """
    from scipy.ndimage import gaussian_filter

    from iscd.decode.ranging.synth import disk_spots, fourier_shift, sensor

    rng = np.random.default_rng(seed)
    cases: list[Case] = []
    y, x = np.mgrid[0:16, 0:16] - 7.5
    env = np.exp(-(x ** 2 + y ** 2) / (2 * 2.3 ** 2))
    base = gaussian_filter(rng.normal(size=(n, 16, 16)), (0, 0.8, 0.8), mode="wrap") * env * 100 + 100
    d = rng.uniform(-3, 3, n)
    cases.append(Case("Fourier-shifted blobs, no noise", fourier_shift(base, d / 2), fourier_shift(base, -d / 2), d))
    for z in (20.0, 30.0, 40.0, 50.0, 60.0):
        for label, bright in (("dim (80 DN)", 80.0), ("bright (600 DN, saturates)", 600.0)):
            lf, rt, dd = _single_led(rng, n, z, bright)
            cases.append(Case(f"1 LED {z:.0f} m, {label}", lf, rt, dd, z, 0.6))
    lf, rt, dd = _single_led(rng, n, 30.0, 600.0, right_gain=0.25)
    cases.append(Case("HDR f/4 + f/8 at 30 m (right 4x darker)", lf, rt, dd, 30.0, 0.25))
    # dim LED on a textured background with another disparity, dark-symbol frames available
    bg_l = gaussian_filter(rng.normal(size=(n, 16, 16)), (0, 1.2, 1.2)) * 30 + 60
    bg_r = np.roll(bg_l, 4, axis=2)
    d = rng.uniform(-1, 1, n)
    c = 7.5 + rng.uniform(-0.5, 0.5, n)
    sl = disk_spots(n, (16, 16), c + d / 2, c, 0.7, peak=120)
    sr = disk_spots(n, (16, 16), c - d / 2, c, 0.7, peak=120)
    lf, rt = sensor(bg_l + sl, rng, 0, 0.26, 78), sensor(bg_r + sr, rng, 0, 0.26, 78)
    dark = (sensor(bg_l, rng, 0, 0.26, 78), sensor(bg_r, rng, 0, 0.26, 78))
    cases.append(Case("dim LED on textured background", lf, rt, d, 40.0, 0.6))
    cases.append(Case("same, iscd given dark-symbol patches", lf, rt, d, 40.0, 0.6, {"background": dark}))
    # 8x8 array at 50 m, b = 0.25: 4.2 px pitch; one 40 x 40 patch per camera
    m = max(n // 4, 10)
    pitch = F_PX * 0.06 / 50.0
    g = (np.arange(8) - 3.5) * pitch
    gx, gy = np.meshgrid(g, g)
    d = rng.uniform(-1, 1, m)
    off = rng.uniform(-0.5, 0.5, (m, 2))
    levels = rng.integers(1, 9, (m, 64)) / 8.0 * 500            # PWM-8 levels of a data symbol
    cxl = 19.5 + off[:, :1] + gx.ravel()[None] + d[:, None] / 2
    cxr = 19.5 + off[:, :1] + gx.ravel()[None] - d[:, None] / 2
    cyy = 19.5 + off[:, 1:] + gy.ravel()[None]
    radius = F_PX * LED_DIAMETER_M / 2 / 50.0
    lf = sensor(disk_spots(m, (40, 40), cxl, cyy, radius, peak=levels), rng, 40, 0.26, 78)
    rt = sensor(disk_spots(m, (40, 40), cxr, cyy, radius, peak=levels), rng, 40, 0.26, 78)
    cases.append(Case("8x8 array at 50 m, whole array in one estimate", lf, rt, d, 50.0, 0.25))
    return cases


def suite_table(cases: list[Case], methods: Iterable[str] = PEERS) -> str:
    """MAE per case and method (px; and the range error it means, m, where known).

    Parameters
    ----------
    cases : list of Case
        From :func:`standard_suite`.
    methods : iterable of str
        Estimator names (default :data:`PEERS`).

    Returns
    -------
    str
        A Markdown table, one row per case.
    """
    methods = list(methods)
    lines = ["| case | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for c in cases:
        cells = []
        for m in methods:
            kw = dict(c.estimate_kw or {})
            if "background" in kw and m not in ("iscd", "iscd-fast"):
                kw = {}
            if "background" in kw:
                s = score(m, c.left, c.right, c.truth_dx, background=kw["background"])
            else:
                s = score(m, c.left, c.right, c.truth_dx)
            if c.z_m is not None and c.baseline_m is not None:
                cells.append(f"{s.mae:.4f} ({s.mae * c.z_m ** 2 / (F_PX * c.baseline_m):.3f} m)")
            else:
                cells.append(f"{s.mae:.4f}")
        lines.append(f"| {c.name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m iscd.decode.ranging.compare [--n N]``: print the synthetic comparison tables.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status (0).
    """
    import argparse

    ap = argparse.ArgumentParser(description="Compare shift estimators on the synthetic suite (docs/ranging.md).")
    ap.add_argument("--n", type=int, default=200, help="pairs per case (default 200)")
    ap.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    ap.add_argument("--methods", default=",".join(PEERS), help="comma-separated methods")
    args = ap.parse_args(argv)
    cases = standard_suite(args.n, args.seed)
    print(f"Mean absolute error of the x shift, px (range error at that distance), n = {args.n}, seed {args.seed}\n")
    print(suite_table(cases, [m for m in args.methods.split(",") if m]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
