"""One LED followed in two cameras, held to its stereo disparity where one camera walks off.

The two cameras of the rig are rigid: vibration moves both images together, and the
disparity (right minus left position) changes only as the car closes in, smoothly (at
100 km/h and 25 m by ~0.1 px a frame), and stops changing when the car stops. A camera's
following that walks off the LED -- onto a texture edge whose light stands above a
background map that a misregistered frame lowered; 195152883 at 97 m: the right camera
4.8 px off in one frame, and there for the whole next block -- makes the disparity *jump*
by pixels from one frame to the next. Such a frame, and the frames after it while the
disparity stays away, have the walked-off camera's centre put back where the other camera's
centre and the disparity before the jump (carried on at its recent rate) say the LED is.

Only a jump starts a hold: a disparity that drifts from a trend (a car that brakes) is
followed frame by frame, never held against. Which camera walked off: the one whose centre
stepped further at the jump, in the background's own frame (the image shifts of both
cameras, vibration, taken out), where the other camera's LED has not moved. A hold ends
when the camera's own following comes back within the tolerance, or after
:data:`MAX_HOLD_FRAMES` (then the new disparity is taken as it is).

Pure functions on a small state (:class:`StereoTrend`) that the decoder
(:class:`iscd.decode.stream.StreamDecoder`) carries from block to block. Positions px
(image x right, y down), frames as frame indices.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

TOLERANCE_PX = 1.0
"""A frame whose disparity (x) or vertical offset (y) is further than this from the median
of the last kept frames' (:data:`REF_FRAMES`, carried on at the recent rate) is a jump (or
still away after one), px. The
cameras' independent air jitter is ~0.05 px and the following's own scatter on lit frames
0.01-0.3 px (docs/receiver.md); a walk onto a texture feature is pixels."""

MAX_HOLD_FRAMES = 64
"""Longest hold, frames: a disparity still away after it is taken as it is (the hold never
runs away from a disparity the two cameras agree on)."""

RATE_BLOCKS = 4
"""Blocks whose median disparity the rate is fitted on."""

REF_FRAMES = 8
"""Kept frames whose disparity, carried on at the rate, the reference is the median of: one
noisy frame (a dim one, its centre 1 px off) neither moves it nor, frame after frame, walks
it away from the LED's."""


@dataclass(frozen=True)
class StereoTrend:
    """What the hold carries from block to block (all None / empty before the first block).

    ``kept`` the last :data:`REF_FRAMES` kept frames' (frame, right - left x, y) px; ``rate``
    px/frame of x from the last blocks' medians ``blocks`` ((frame, x) of their kept frames);
    ``last`` per camera the last kept frame's centre in the background's frame (2, 2) px;
    ``run`` frames held in a row so far and ``side`` the camera held (-1 none)."""

    kept: tuple[tuple[float, float, float], ...] = ()
    rate: float = 0.0
    blocks: tuple[tuple[float, float], ...] = ()
    last: np.ndarray | None = field(default=None, compare=False)
    run: int = 0
    side: int = -1


def _median(values: list[float]) -> float:
    """The median of a short list (pure Python: a few microseconds where numpy's takes ~20)."""
    v = sorted(values)
    n = len(v)
    return float(v[n // 2]) if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


def block_rate(blocks: tuple[tuple[float, float], ...]) -> float:
    """The disparity's rate from the last blocks' medians: the least-squares slope.

    Parameters
    ----------
    blocks : tuple of (frame, x)
        Per block the mean frame of its kept frames and their median right minus left x,
        px, oldest first; the last :data:`RATE_BLOCKS` are used.

    Returns
    -------
    float
        px/frame (0 with fewer than two blocks).
    """
    h = blocks[-RATE_BLOCKS:]
    n = len(h)
    if n < 2:
        return 0.0
    mf = sum(f for f, _ in h) / n
    mx = sum(x for _, x in h) / n
    sff = sum((f - mf) ** 2 for f, _ in h)
    return sum((f - mf) * (x - mx) for f, x in h) / sff if sff > 0 else 0.0  # least squares


def hold_block(trend: StereoTrend, frames: np.ndarray, c_l: np.ndarray, c_r: np.ndarray,
               still_l: np.ndarray, still_r: np.ndarray, *, tolerance_px: float = TOLERANCE_PX,
               max_hold: int = MAX_HOLD_FRAMES, shortcut: bool = True
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, StereoTrend]:
    """Hold one LED's centres where one camera's following jumped off the disparity.

    Parameters
    ----------
    trend : StereoTrend
        The state after the last block (``StereoTrend()`` after an acquisition).
    frames : ndarray
        (F,) the block's frame indices.
    c_l, c_r : ndarray
        (F, 1, 2) the block's followed centres in the left and right camera, image px.
    still_l, still_r : ndarray
        (F, 2) the same centres in the background's own frame (less the frame's image
        shift), px; the image positions where the shifts are not known.
    tolerance_px : float
        Largest jump kept, px (:data:`TOLERANCE_PX`).
    max_hold : int
        Longest hold, frames (:data:`MAX_HOLD_FRAMES`).
    shortcut : bool
        Check the usual block (nothing departs) in one vectorized step; False = frame by
        frame throughout (the reference the tests hold the shortcut to; the same results).

    Returns
    -------
    c_l, c_r : ndarray
        The centres, the walked-off camera's held frames replaced (copies where changed).
    held : ndarray
        (F,) bool, the frames replaced.
    trend : StereoTrend
        The state for the next block.
    """
    F = int(np.asarray(frames).size)
    held = np.zeros(F, dtype=bool)
    dx = c_r[:, 0, 0] - c_l[:, 0, 0]
    dy = c_r[:, 0, 1] - c_l[:, 0, 1]
    ok = np.isfinite(dx) & np.isfinite(dy)
    ids = np.asarray(frames, dtype=np.float64)
    still = (np.asarray(still_l, dtype=np.float64), np.asarray(still_r, dtype=np.float64))
    kept, run, side, rate = list(trend.kept), trend.run, trend.side, trend.rate
    last = None if trend.last is None else trend.last.copy()
    if shortcut and kept and last is not None and run == 0 and F and ok.all():
        # the usual block, in one step: every kept and new disparity within half the
        # tolerance of the reference line at the block's start, so every frame's median
        # reference is too and no frame departs from it by more than the tolerance (the
        # frame-by-frame loop below would hold none)
        f0 = float(ids[0])
        lx = [x + rate * (f0 - f) for f, x, _ in kept]
        ly = [y for _, _, y in kept]
        x0, y0 = _median(lx), _median(ly)
        half = 0.5 * tolerance_px
        if max(abs(v - x0) for v in lx) <= half and max(abs(v - y0) for v in ly) <= half \
                and float(np.abs(dx - (x0 + rate * (ids - f0))).max()) <= half \
                and float(np.abs(dy - y0).max()) <= half:
            dxl = dx.tolist()
            new_kept = (kept + list(zip(ids.tolist(), dxl, dy.tolist())))[-REF_FRAMES:]
            blocks = (trend.blocks + ((float(ids.mean()), _median(dxl)),))[-RATE_BLOCKS:]
            return c_l, c_r, held, replace(trend, kept=tuple(new_kept), rate=block_rate(blocks), blocks=blocks,
                                           last=np.stack([still[0][-1], still[1][-1]]), run=0, side=-1)
    out = [c_l, c_r]
    copied = [False, False]
    for f in range(F):
        if not ok[f]:
            continue
        if kept and last is not None and run < max_hold:
            px = _median([x + rate * (ids[f] - g) for g, x, _ in kept])
            py = _median([y for _, _, y in kept])
            if max(abs(dx[f] - px), abs(dy[f] - py)) > tolerance_px:
                if run == 0:  # a jump: the camera that stepped further walked off
                    steps = [float(np.hypot(*(still[c][f] - last[c]))) for c in (0, 1)]
                    side = 1 if steps[1] >= steps[0] else 0
                run += 1
                held[f] = True
                if not copied[side]:
                    out[side] = out[side].copy()
                    copied[side] = True
                d = np.array([px, py])
                out[side][f, 0] = out[0][f, 0] + d if side == 1 else out[1][f, 0] - d
                continue
        # kept (the first frames after an acquisition, or a hold given up): the reference
        # moves on with this frame
        if run >= max_hold:
            kept = []
        run, side = 0, -1
        kept = (kept + [(float(ids[f]), float(dx[f]), float(dy[f]))])[-REF_FRAMES:]
        last = np.stack([still[0][f], still[1][f]])
    keep = ok & ~held
    blocks = trend.blocks
    if keep.sum() >= max(1, F // 2):
        blocks = (blocks + ((float(ids[keep].mean()), _median(dx[keep].tolist())),))[-RATE_BLOCKS:]
    new = replace(trend, kept=tuple(kept), rate=block_rate(blocks), blocks=blocks, last=last, run=run, side=side)
    return out[0], out[1], held, new
