"""The LEDs' path through a block: per-frame centres smoothed in time, dark frames bridged.

Rig vibration (smooth sway, road bumps ringing at 6-15 Hz, engine shake at 20-40 Hz) moves
every spot by up to a few px within a block, faster than the grid fits follow. A frame in
which an LED is lit measures its own centre (:func:`~iscd.decode.tracking.luminance.
refine_in_patches`); a dark or dimly lit frame (a PWM symbol's off part) measures nothing, and
its luminance -- which the demodulator reads, partial frames included -- must still be taken
where the spot is. The path is the light-weighted local mean of the lit frames' centres,
a Gaussian in time of ``sigma_frames``; a frame with no lit frame near it takes the path
linearly between the lit frames around it (the anchor before the block's first frame, the
last lit frame after the block's last).

Pure functions of arrays; units px and frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

SIGMA_FRAMES = 1.5
"""Width of the smoothing in time, frames (1.5 ms at 1000 fps): a bump ringing at 15 Hz with
4 px peaks accelerates by ~0.04 px/frame^2, which such a window biases by ~0.04 px, while
it averages the centroid noise of 5-7 frames."""

REACH_SIGMAS = 4.0
"""The smoothing reads frames within this many ``sigma_frames`` of a frame."""

LIT_SHARE = 0.25
"""A frame steers the path when its LED light is at least this share of the block's
brightest frames' (90th percentile); dimmer frames are bridged."""


def frame_weights(lum: np.ndarray, floor: np.ndarray, use: np.ndarray | None = None,
                  *, lit_share: float = LIT_SHARE) -> np.ndarray:
    """Per-frame weight of the measured centres: the light of the lit LEDs, DN.

    Parameters
    ----------
    lum : ndarray
        (F, N) luminance of each LED, DN.
    floor : ndarray
        (N,) the luminance of a dark LED (background), DN.
    use : ndarray, optional
        Indices of the LEDs that steer (all by default).
    lit_share : float
        An LED counts in a frame when its light above ``floor`` is at least this share of
        its block's 90th percentile.

    Returns
    -------
    ndarray
        (F,) weights >= 0, DN (0: nothing lit).
    """
    above = np.asarray(lum, dtype=np.float64) - np.asarray(floor, dtype=np.float64)[None, :]
    if use is not None:
        above = above[:, np.asarray(use, dtype=np.intp)]
    above = np.where(np.isfinite(above), above, 0.0)
    ref = np.percentile(above, 90, axis=0) if above.shape[0] else np.zeros(above.shape[1])
    lit = (above >= lit_share * ref[None, :]) & (ref[None, :] > 0)
    return np.where(lit, above, 0.0).sum(axis=1)


def smooth_path(centres: np.ndarray, weights: np.ndarray, anchor: np.ndarray | None = None,
                *, sigma_frames: float = SIGMA_FRAMES) -> np.ndarray:
    """The LEDs' path through a block from per-frame centres.

    Parameters
    ----------
    centres : ndarray
        (F, N, 2) measured centres, px.
    weights : ndarray
        (F,) how much each frame's centres count (0: not lit, bridged), e.g.
        :func:`frame_weights`.
    anchor : ndarray, optional
        (N, 2) where the LEDs were just before the block's first frame, px (the last
        block's path): the left end of a bridge that starts the block.
    sigma_frames : float
        Gaussian width of the smoothing, frames (frames within :data:`REACH_SIGMAS` of it).

    Returns
    -------
    ndarray
        (F, N, 2) the path, px. Where no frame of the block is lit: the anchor (or
        ``centres`` when there is none).
    """
    c = np.asarray(centres, dtype=np.float64)
    w = np.clip(np.nan_to_num(np.asarray(weights, dtype=np.float64)), 0.0, None)
    F = c.shape[0]
    if F == 0:
        return c.copy()
    t = np.arange(F, dtype=np.float64)
    have = w > 0
    if not have.any():
        return c.copy() if anchor is None else np.broadcast_to(np.asarray(anchor, np.float64), c.shape).copy()
    dt = t[None, :] - t[:, None]  # (F, F) frame k - frame f
    g = np.where(np.abs(dt) <= REACH_SIGMAS * sigma_frames,
                 np.exp(-0.5 * (dt / sigma_frames) ** 2), 0.0) * w[None, :]  # (F, F)
    cf = c.reshape(F, -1)
    s0 = g.sum(axis=1)
    s1 = (g * dt).sum(axis=1)
    s2 = (g * dt * dt).sum(axis=1)
    m0 = g @ cf
    m1 = (g * dt) @ cf
    # locally linear (no lag where the lit frames lie on one side of a frame): the value
    # at dt = 0 of the weighted line; a local mean where the frames do not fix a slope
    det = s0 * s2 - s1 * s1
    lin = det > 1e-6 * np.maximum(s0 * s2, 1e-300)
    val = np.where(lin[:, None], (s2[:, None] * m0 - s1[:, None] * m1) / np.where(lin, det, 1.0)[:, None],
                   m0 / np.where(s0 > 0, s0, 1.0)[:, None])
    den = s0
    # frames with lit frames within ~2 sigma: the smoothed value; the others bridged
    near = np.exp(-0.5 * (2.0) ** 2) * w[have].min()
    ok = den >= near
    out = np.empty_like(c)
    out[ok] = val[ok].reshape((-1,) + c.shape[1:])
    if (~ok).any():
        kt = t[ok]
        kv = out[ok].reshape(kt.size, -1)
        if anchor is not None:
            kt = np.concatenate([[-1.0], kt])
            kv = np.concatenate([np.asarray(anchor, np.float64).reshape(1, -1), kv])
        miss = t[~ok]
        flat = np.empty((miss.size, kv.shape[1]))
        for j in range(kv.shape[1]):
            flat[:, j] = np.interp(miss, kt, kv[:, j])
        out[~ok] = flat.reshape((miss.size,) + c.shape[1:])
    return out


PASSES = 3
"""Further following passes at most, each started from the last pass's path."""

PATH_REACH_PX = 1.5
"""How far one pass can carry the path from where it started, px (the following's own
largest correction, ``max_px``): the frames' windows reach this much further per pass."""

SETTLE_PX = 0.5
"""No further pass once the path is within this of where the last pass started, px: the
box centroids then start within their reach of the spots (a 1.5 px step per pass is the
following's own limit)."""

CHANGE_PX = 0.05
"""The luminance is measured again where the chosen centres moved by more than this from
where the last pass measured it, px (a Gaussian window of sigma >= 0.6 px moved 0.05 px
changes a spot's weight by < 0.4 %)."""

FINAL_LIT_SHARE = 0.1
"""A frame keeps its own refined centres when its light is at least this share of the
block's brightest frames' and the following refined it (it judged the LEDs lit); the
others take the path (a dark frame's centroid is the background's, not the spot's)."""


@dataclass
class PathResult:
    """What :func:`follow_path` found for one block (per camera lists)."""

    centres: list[np.ndarray]
    """(F, N, 2) where each frame's luminance was measured, px."""
    luminance: list[np.ndarray]
    """(F, N) luminance, DN."""
    path_end: list[np.ndarray]
    """(N, 2) the path at the block's last frame: the next block's anchor, px."""
    passes: int
    """following passes run after the first (0: the path was settled at once)."""
    floors: list[np.ndarray]
    """(N,) per camera the dark LED's luminance held with this block's, DN (:func:`held_floor`)."""
    info: dict = field(default_factory=dict)
    """the first pass's ``info`` (``"light"``: the lit judgement's reference stays the one
    pass's, as without a path; a later pass's patches, placed on the path, measured up to
    5x the light where a bloom column or glare came into them, and a held reference that
    high then judged the LED dark for seconds); ``"spot_area"`` from the last pass."""


def _refined(centres: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(F,) frames the following moved from their starts (it judged an LED lit there)."""
    return np.abs(centres - starts).max(axis=(1, 2)) > 0


def path_step(centres: np.ndarray, lum: np.ndarray, starts: np.ndarray, floor: np.ndarray,
              anchor: np.ndarray | None, use: np.ndarray | None, *, lit_share: float = LIT_SHARE,
              sigma_frames: float = SIGMA_FRAMES, reach_sigmas: float = REACH_SIGMAS
              ) -> tuple[np.ndarray, float]:
    """One following pass's path: its refined, lit frames' centres smoothed in time.

    Parameters
    ----------
    centres : ndarray
        (F, N, 2) the pass's centres, px.
    lum : ndarray
        (F, N) the pass's luminance, DN.
    starts : ndarray
        (F, N, 2) or (N, 2) where the pass started, px (a frame whose centres equal its
        starts was not refined: nothing lit there).
    floor : ndarray
        (N,) a dark LED's luminance, DN.
    anchor : ndarray or None
        (N, 2) the last block's path end, px.
    use : ndarray or None
        The LEDs that steer.
    lit_share, sigma_frames, reach_sigmas
        :func:`frame_weights`'s and :func:`smooth_path`'s.

    Returns
    -------
    path : ndarray
        (F, N, 2) px.
    moved : float
        Largest distance of the path from the starts, px.
    """
    c = np.asarray(centres, dtype=np.float64)
    cur = np.broadcast_to(np.asarray(starts, dtype=np.float64), c.shape)
    w = frame_weights(lum, floor, use, lit_share=lit_share) * _refined(c, cur)
    p = smooth_path(c, w, anchor, sigma_frames=sigma_frames)
    return p, float(np.abs(p - cur).max()) if p.size else 0.0


def final_select(centres: np.ndarray, lum: np.ndarray, starts: np.ndarray, path: np.ndarray,
                 floor: np.ndarray, use: np.ndarray | None, *, lit_share: float = FINAL_LIT_SHARE
                 ) -> tuple[np.ndarray, float]:
    """Where each frame's luminance is taken: its own refined centres where it is lit enough
    (``lit_share`` of the block's brightest, and refined), the path elsewhere.

    Parameters
    ----------
    centres, lum, starts, floor, use
        As :func:`path_step`.
    path : ndarray
        (F, N, 2) the path, px.
    lit_share : float
        :func:`frame_weights`'s.

    Returns
    -------
    centres : ndarray
        (F, N, 2) px.
    change : float
        Largest distance from ``centres`` as given, px (0: nothing to measure again).
    """
    c = np.asarray(centres, dtype=np.float64)
    cur = np.broadcast_to(np.asarray(starts, dtype=np.float64), c.shape)
    lit = (frame_weights(lum, floor, use, lit_share=lit_share) > 0) & _refined(c, cur)
    out = np.where(lit[:, None, None], c, np.asarray(path, dtype=np.float64))
    return out, float(np.abs(out - c).max()) if c.size else 0.0


def path_block(centres: list[np.ndarray], lums: list[np.ndarray], starts: list[np.ndarray],
               floors: list[np.ndarray], anchors: list[np.ndarray | None], use: np.ndarray | None,
               *, lit_share: float = LIT_SHARE, final_share: float = FINAL_LIT_SHARE,
               sigma_frames: float = SIGMA_FRAMES, reach_sigmas: float = REACH_SIGMAS
               ) -> tuple[list[np.ndarray], float, list[np.ndarray], float]:
    """One pass's step for every camera: :func:`path_step` and :func:`final_select`.

    Parameters
    ----------
    centres, lums, starts, floors, anchors : list
        Per camera, as :func:`path_step` takes them.
    use : ndarray or None
        The LEDs that steer.
    lit_share, final_share : float
        :func:`path_step`'s and :func:`final_select`'s shares.
    sigma_frames, reach_sigmas : float
        The smoothing (:func:`smooth_path`).

    Returns
    -------
    paths : list of ndarray
        Per camera (F, N, 2), px.
    moved : float
        Largest distance of a path from its starts, px.
    final : list of ndarray
        Per camera where the luminance is taken, (F, N, 2) px.
    change : float
        Largest distance of those from ``centres``, px.
    """
    paths, finals, moved, change = [], [], 0.0, 0.0
    for c, lum, st, fl, an in zip(centres, lums, starts, floors, anchors):
        p, m = path_step(c, lum, st, fl, an, use, lit_share=lit_share, sigma_frames=sigma_frames,
                         reach_sigmas=reach_sigmas)
        f, ch = final_select(c, lum, st, p, fl, use, lit_share=final_share)
        paths.append(p)
        finals.append(f)
        moved, change = max(moved, m), max(change, ch)
    return paths, moved, finals, change


def follow_path(follow: Callable[..., tuple[list[np.ndarray], list[np.ndarray]]],
                frames: list[np.ndarray], starts: list[np.ndarray], size: int,
                sigmas: list[float], floors: list[np.ndarray | None],
                anchors: list[np.ndarray | None], *, use: np.ndarray | None = None,
                lit_light: np.ndarray | None = None, backgrounds: list | None = None,
                spot_radius_px: float | None = None, subtract: bool = True,
                passes: int = PASSES, settle_px: float = SETTLE_PX,
                sigma_frames: float = SIGMA_FRAMES, compiled: bool = True,
                offsets: list[np.ndarray] | None = None) -> PathResult:
    """Follow the LEDs through a block along their path, and measure their luminance on it.

    The first pass is ``follow`` from ``starts`` (the last block's end), as without a path.
    Its lit frames' centres give the path (:func:`smooth_path`); while the path has moved
    more than ``settle_px`` from where a pass started, another pass starts every frame
    from the path (a bump that carries the spots 3 px within a block is followed in two
    or three passes of the following's 1.5 px reach). Then each frame's luminance is
    taken at its own refined centres where it is lit enough to have them
    (:data:`FINAL_LIT_SHARE`), on the path elsewhere -- a partly lit or dark frame of a
    PWM symbol, whose luminance the demodulator reads too, is measured where the spot is,
    not where the block started.

    Parameters
    ----------
    follow : callable
        :func:`~iscd.decode.tracking.luminance.follow_and_measure` or its compiled twin.
    frames : list of ndarray
        Per camera (F, H, W) frames, DN.
    starts : list of ndarray
        Per camera (N, 2) or (F, N, 2) starting centres, px.
    size : int
        The following box, px.
    sigmas : list of float
        Per camera the Gaussian window sigma, px.
    floors : list of ndarray or None
        Per camera (N,) the luminance of a dark LED held from the last blocks, DN, or None
        (:func:`held_floor`; this block's first pass is folded in).
    anchors : list of ndarray or None
        Per camera (N, 2) the last block's path end, px, or None.
    use, lit_light, backgrounds, spot_radius_px, subtract
        As ``follow`` takes them; the backgrounds are folded in by the first pass only.
    passes : int
        Further passes at most.
    settle_px : float
        Path movement below which no further pass runs, px.
    sigma_frames : float
        Smoothing of the path in time, frames.
    compiled : bool
        The path steps of :mod:`iscd.decode.tracking.path_kernel` (else this module's
        numpy references; the same values).
    offsets : list of ndarray, optional
        Per camera (F, 2) px: the frames are stabilized (:mod:`iscd.decode.tracking.stabilize`)
        and a position in frame f is the image position less ``offsets[f]`` (its whole-pixel
        image shift). The path is then smoothed in image positions, where vibration moves
        the LED smoothly (in the stabilized frames its sub-pixel rest jumps by 1 px where
        the rounded shift steps), and ``anchors`` and the result's ``path_end`` are image
        positions; the centres stay positions in the frames given.

    Returns
    -------
    PathResult
    """
    F = frames[0].shape[0]
    cur = list(starts)  # ((N, 2) starts: the path steps broadcast them over the frames)
    info: dict = {}
    cs, lums = follow(frames, starts, size, sigmas, use, lit_light=lit_light, info=info,
                      backgrounds=backgrounds, spot_radius_px=spot_radius_px, subtract=subtract)
    n = len(frames)
    floors = [held_floor(floors[k], lums[k]) for k in range(n)]
    anchors = [a if a is not None and np.shape(a) == cs[k].shape[1:] else None for k, a in enumerate(anchors)]
    if compiled:
        from iscd.decode.tracking.path_kernel import path_block_compiled as block
    else:
        block = path_block
    off = None if offsets is None else [np.asarray(o, np.float64).reshape(F, 1, 2) for o in offsets]
    ran = 0
    while True:
        if off is None:
            paths, moved, final, change = block(cs, lums, cur, floors, anchors, use, lit_share=LIT_SHARE,
                                                final_share=FINAL_LIT_SHARE, sigma_frames=sigma_frames,
                                                reach_sigmas=REACH_SIGMAS)
        else:  # the path in image positions, the passes in the frames' (distances are the same)
            paths, moved, final, change = block([c + o for c, o in zip(cs, off)], lums,
                                                [c + o for c, o in zip(cur, off)], floors, anchors, use,
                                                lit_share=LIT_SHARE, final_share=FINAL_LIT_SHARE,
                                                sigma_frames=sigma_frames, reach_sigmas=REACH_SIGMAS)
            path_end = [p[-1].copy() for p in paths]
            paths = [p - o for p, o in zip(paths, off)]
            final = [f - o for f, o in zip(final, off)]
        if ran >= passes or moved < settle_px:
            break
        again: dict = {}
        cs, lums = follow(frames, paths, size, sigmas, use, lit_light=lit_light, info=again,
                          backgrounds=backgrounds, spot_radius_px=spot_radius_px,
                          subtract=subtract, new_block=False)
        cur = paths
        ran += 1
        if "spot_area" in again:  # the spots' size where they now are
            info["spot_area"] = again["spot_area"]
    if change > CHANGE_PX:  # the luminance where it is now taken (no refinement: iterations=0)
        cs, lums = follow(frames, final, size, sigmas, use, iterations=0, lit_light=lit_light,
                          info={}, backgrounds=backgrounds, spot_radius_px=None,
                          subtract=subtract, new_block=False)
        cs = final
    return PathResult(centres=list(cs), luminance=list(lums),
                      path_end=[p[-1].copy() for p in paths] if off is None else path_end,
                      passes=ran, floors=floors, info=info)


def held_floor(old: np.ndarray | None, lum: np.ndarray, rise_dn: float = 1.0) -> np.ndarray:
    """The luminance of a dark LED, held across blocks: the least of this block's and the
    last floor raised by ``rise_dn`` (so a background that brightens is followed).

    Parameters
    ----------
    old : ndarray or None
        (N,) the last floor, DN.
    lum : ndarray
        (F, N) this block's luminance, DN.
    rise_dn : float
        DN per block.

    Returns
    -------
    ndarray
        (N,) DN.
    """
    # (fmin: nanmin's values, NaN only where a column is all NaN, without its overhead and warning)
    low = np.fmin.reduce(np.asarray(lum, np.float64), axis=0) if len(lum) else np.full(np.shape(lum)[1:], np.inf)
    return low if old is None else np.minimum(old + rise_dn, low)
