"""Level noise: how much each PWM level's light scatters in a simulated one-LED scene, measured
at the true LED centres, with parts of the scene's physics switched off -- to tell what makes
a level noisy, apart from what the receiver's following and channel estimate add.

    python -m iscd.eval.levelnoise [--case KEY] [--seed S] [--model M] [--off PARTS] [--frames N]

The scene is a motion case through the randomized physics (:func:`iscd.eval.suites.motion_cfg`,
as ``iscd eval --suite motion --randomize`` draws it); ``--off`` switches off any of
``approach`` (speed 0), ``vibration`` (rig vibration and air jitter 0), ``lateral`` (lateral
drift 0) and ``texture`` (a flat background). Each camera's light is a Gaussian-weighted mean
(sigma ``sigma_px``) of the frame less the per-pixel median of the 4 nearest all-dark frames,
around the true centre; the clean frames of each level are split into bins of ``bin_frames``
frames, a straight line is fitted to each level in each bin (the approach's brightening), and
the scatter about it is the level's noise. Session 32 found with it that a clipped spot
moving over the pixel grid, not the sensor, makes the top levels noisy (docs/eval.md).
Units: px, DN, % of the level range (level M's light less level 1's, per bin).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from iscd.core.config import Config
from iscd.eval.oracle import nearest_dark

PARTS = {"approach": {"speed_mps": 0.0}, "vibration": {"vibration_px": 0.0, "jitter_px": 0.0},
         "lateral": {"lateral_speed_mps": 0.0}, "texture": {"background_contrast": 0.0}}
"""What ``--off`` switches off: the [scene] keys set for each part."""

HALF_PX = 8
"""Half-size of the patch around each true centre, px (17 x 17 pixels)."""


@dataclass(frozen=True)
class LevelNoise:
    """Per camera (0 left, 1 right): ``noise_pct`` (2, M) each level's scatter about its
    trend, the median over the bins, % of the level range; ``d_prime`` (2, B) per bin the
    least separation of neighbouring levels, (mu_{k+1} - mu_k) / sqrt((s_k^2 + s_{k+1}^2) / 2)
    (NaN where a bin lacks a level); ``frames`` rendered; ``z_m`` (first, last) distance, m;
    ``light`` (2, frames) each frame's measured light, DN, and ``level`` (frames,) the level
    at mid-exposure, 1 .. M, with ``clean`` (frames,) the frames inside one symbol."""

    noise_pct: np.ndarray
    d_prime: np.ndarray
    frames: int
    z_m: tuple[float, float]
    light: np.ndarray
    level: np.ndarray
    clean: np.ndarray


def scene_config(key: str, seed: int, model: str | None = None, off: Sequence[str] = ()) -> Config:
    """The randomized config of motion case ``key`` at ``seed`` (vibration ``model`` or the
    case's own) with the parts in ``off`` (:data:`PARTS`) switched off.

    Raises
    ------
    ValueError
        An unknown case, part, or a case of more than one LED.
    """
    from iscd.core.config import default_config
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next((c for c in MOTION_CASES if c.key == key), None)
    if case is None:
        raise ValueError(f"unknown case {key!r} (known: {', '.join(c.key for c in MOTION_CASES)})")
    if case.leds != 1:
        raise ValueError(f"case {key!r}: one LED only (this one has {case.leds})")
    bad = [p for p in off if p not in PARTS]
    if bad:
        raise ValueError(f"unknown part(s) {', '.join(bad)} (known: {', '.join(PARTS)})")
    cfg, _ = motion_cfg(default_config(), case, seed, scene=None if model is None else {"vibration_model": model},
                        randomize=True)
    keys = {k: v for p in off for k, v in PARTS[p].items()}
    return cfg.replace(scene=replace(cfg.scene, **keys)) if keys else cfg


def measure(cfg: Config, frames: int = 2700, *, sigma_px: float = 1.8, bin_frames: int = 130,
            block: int = 64) -> LevelNoise:
    """Render ``frames`` stereo pairs of a one-LED scene and measure its levels' noise.

    Parameters
    ----------
    cfg : Config
        The scene (one LED).
    frames : int
        Stereo pairs to render (2700: two packets of the motion cases), >= 2 bins.
    sigma_px : float
        Gaussian window sigma, px.
    bin_frames : int
        Frames per bin of the trend fits.
    block : int
        Pairs rendered at a time (memory).

    Returns
    -------
    LevelNoise

    Raises
    ------
    ValueError
        More than one LED, too few frames, no all-dark frame, or a bad argument.
    """
    from iscd.sim.scene import Scene

    if cfg.transmitter.n_leds != 1:
        raise ValueError(f"one LED only (the scene has {cfg.transmitter.n_leds})")
    if not (sigma_px > 0 and math.isfinite(sigma_px)):
        raise ValueError(f"sigma: expected a window sigma > 0 px, got {sigma_px}")
    if bin_frames < 8 or block < 1:
        raise ValueError(f"bin_frames must be >= 8 and block >= 1, got {bin_frames} and {block}")
    if frames < 2 * bin_frames:
        raise ValueError(f"frames: {frames} is fewer than two bins of {bin_frames}")
    sc = Scene(cfg)
    tr = sc.truth(np.arange(frames))
    dark = np.flatnonzero(tr.on_fraction.max(axis=1) <= 0.0)
    if dark.size == 0:
        raise ValueError("no all-dark frame to take the background from")
    H, W = sc.height, sc.width
    K = 2 * HALF_PX + 1
    centres = [np.stack([tr.u_left[:, 0], tr.v_left[:, 0]], 1), np.stack([tr.u_right[:, 0], tr.v_right[:, 0]], 1)]
    x0 = [np.clip(np.rint(c[:, 0]).astype(np.int64) - HALF_PX, 0, W - K) for c in centres]
    y0 = [np.clip(np.rint(c[:, 1]).astype(np.int64) - HALF_PX, 0, H - K) for c in centres]
    # the dark frames' crops over every patch's place (the background, per pixel)
    box = [(int(x.min()), int(y.min()), int(x.max()) + K, int(y.max()) + K) for x, y in zip(x0, y0)]
    crops: list[list[np.ndarray]] = [[], []]
    Lb = np.empty((H, W), np.uint8)
    Rb = np.empty_like(Lb)
    for k in dark:
        sc.render_pair_into(int(k), Lb, Rb)
        for c, img in enumerate((Lb, Rb)):
            bx0, by0, bx1, by1 = box[c]
            crops[c].append(img[by0:by1, bx0:bx1].astype(np.float32))
    stacks = [np.stack(cr) for cr in crops]
    light = np.empty((2, frames))
    Lk = np.empty((block, H, W), np.uint8)
    Rk = np.empty_like(Lk)
    ax = np.arange(K, dtype=np.float64)
    for s in range(0, frames, block):
        ids = np.arange(s, min(frames, s + block))
        for j, f in enumerate(ids):
            sc.render_pair_into(int(f), Lk[j], Rk[j])
        near = nearest_dark(dark, ids)
        for c, imgs in enumerate((Lk, Rk)):
            bx0, by0 = box[c][0], box[c][1]
            for j, f in enumerate(ids):
                xa, ya = int(x0[c][f]), int(y0[c][f])
                pix = imgs[j, ya:ya + K, xa:xa + K].astype(np.float32)
                bg = np.median(stacks[c][near[j], ya - by0:ya - by0 + K, xa - bx0:xa - bx0 + K], axis=0)
                wx = np.exp(-(xa + ax - centres[c][f, 0]) ** 2 / (2 * sigma_px ** 2))
                wy = np.exp(-(ya + ax - centres[c][f, 1]) ** 2 / (2 * sigma_px ** 2))
                w = wy[:, None] * wx[None, :]
                light[c, f] = float((w * (pix - bg)).sum() / w.sum())
    level = tr.levels[tr.symbol_mid - tr.symbol_index[0], 0].astype(np.int64)
    M = cfg.transmitter.levels
    noise = np.full((2, M), np.nan)
    bins = list(range(0, frames - bin_frames + 1, bin_frames))
    dp = np.full((2, len(bins)), np.nan)
    t = np.arange(frames, dtype=np.float64)
    for c in range(2):
        rel = []
        for b, s in enumerate(bins):
            mu, sd = _trend_fits(light[c], level, tr.clean, t, s, s + bin_frames, M)
            gap = (mu[1:] - mu[:-1]) / np.sqrt((sd[1:] ** 2 + sd[:-1] ** 2) / 2)
            if np.isfinite(gap).any():
                dp[c, b] = float(np.nanmin(gap))
            rel.append(100.0 * sd / (mu[-1] - mu[0]))
        with np.errstate(all="ignore"):
            noise[c] = np.nanmedian(np.array(rel), axis=0)
    return LevelNoise(noise, dp, frames, (float(tr.z_m[0]), float(tr.z_m[-1])), light, level, tr.clean.copy())


def _trend_fits(x: np.ndarray, level: np.ndarray, clean: np.ndarray, t: np.ndarray, a: int, b: int, M: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per level 1 .. M over the clean frames a .. b - 1: the fitted line's value at the bin's
    middle and the scatter about it (NaN with fewer than 4 frames)."""
    mu = np.full(M, np.nan)
    sd = np.full(M, np.nan)
    for v in range(1, M + 1):
        k = np.flatnonzero(clean[a:b] & (level[a:b] == v)) + a
        if k.size > 3:
            A = np.stack([np.ones(k.size), t[k] - (a + b) / 2], 1)
            coef, *_ = np.linalg.lstsq(A, x[k], rcond=None)
            r = x[k] - A @ coef
            mu[v - 1] = coef[0]
            sd[v - 1] = math.sqrt(float(r @ r) / (k.size - 2))
    return mu, sd


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m iscd.eval.levelnoise",
        description="Each PWM level's noise in a simulated one-LED scene at the true LED centres, with parts of "
                    "the physics switched off: what makes a level noisy before the receiver's following and "
                    "channel estimate (docs/eval.md, session 32).")
    ap.add_argument("--case", default="1led-40kmh-0.5px", help="a one-LED motion case (default 1led-40kmh-0.5px)")
    ap.add_argument("--seed", type=int, default=285800105, help="the scene's seed (default 285800105, set 72001)")
    ap.add_argument("--model", default="engine", help="vibration model: smooth, engine or bumps (default engine)")
    ap.add_argument("--off", default="", metavar="PARTS",
                    help=f"comma-separated parts to switch off: {', '.join(PARTS)} (default none)")
    ap.add_argument("--frames", type=int, default=2700, help="stereo pairs to render (default 2700: two packets)")
    ap.add_argument("--sigma", type=float, default=1.8, help="Gaussian window sigma, px (default 1.8)")
    args = ap.parse_args(argv)
    try:
        off = [p for p in args.off.split(",") if p]
        cfg = scene_config(args.case, args.seed, args.model, off)
        r = measure(cfg, args.frames, sigma_px=args.sigma)
    except ValueError as e:
        print(f"levelnoise: {e}", file=sys.stderr)
        return 2
    print(f"{args.case} seed {args.seed} {args.model}, off: {', '.join(off) or 'nothing'}; {r.frames} frames, "
          f"{r.z_m[0]:.1f} -> {r.z_m[1]:.1f} m; each level's noise about its trend, % of the level range")
    M = r.noise_pct.shape[1]
    print("camera  " + " ".join(f"{'L' + str(v):>6}" for v in range(1, M + 1)) + "   d' min / median")
    for c, name in enumerate(("left", "right")):
        d = r.d_prime[c]
        dmin = f"{np.nanmin(d):.1f} / {np.nanmedian(d):.1f}" if np.isfinite(d).any() else "-"
        print(f"{name:7s} " + " ".join(f"{v:6.2f}" for v in r.noise_pct[c]) + f"   {dmin}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
