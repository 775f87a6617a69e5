"""Frames held still: one LED followed in the background's own frame.

The contract, once: frame f shows scene point q at image pixel ``p = q + s_f``, where ``s_f``
(px, whole pixels, (x, y)) is the image shift that
:class:`~iscd.decode.tracking.registered_background.RegisteredBackground` measures on a ring
of background pixels. The *stabilized* frame is ``S_f(q) = frame_f(q + s_f)``: the
background's texture stands still in it, and an LED at image position ``p`` sits at
``p - s_f``. Following (centroids, the path through a block, the per-pixel background under
the centroids) runs on stabilized frames; its centres are turned back into image positions by
adding ``s_f``.

Why: the following's centroids are of the light above a per-pixel background
(:class:`~iscd.decode.tracking.luminance.PixelBackground`), each pixel's least value. Indexed
by the image, that map holds at a texture edge the darker side that vibration has brought
there; when the image moves back, the bright side stands above it as "light" -- at 100 m as
much as a dim PWM level's spot. The centroids of the dim frames were pulled onto such edges,
and the following passes along the path carried the spot there (randomized engine-vibration
scene 957526840: both cameras 3.8 px off for 10 frames next to an 18 DN edge 3 px above the
LED, the first packet lost). In the background's own frame the edge does not move, its least
value is itself, and nothing of it is left above the map.

Only the pixels the following reads are copied (``box``); the rest of ``out`` is left as it
was. Where ``q + s_f`` falls outside the frame, the nearest edge pixel is taken.

:func:`stabilize_into` is the compiled kernel, :func:`stabilize_reference` its numpy
reference (the same values).

Pure functions of arrays; units px.
"""

from __future__ import annotations

import numpy as np

from iscd.core.jit import njit


def _check(frames: np.ndarray, shifts: np.ndarray, box: tuple[int, int, int, int], out: np.ndarray) -> None:
    if frames.ndim != 3 or out.ndim != 3 or out.shape[1:] != frames.shape[1:] or out.shape[0] < frames.shape[0]:
        raise ValueError(f"out: expected at least {frames.shape} for frames of {frames.shape}, got {out.shape}")
    if out.dtype != frames.dtype:
        raise ValueError(f"out: expected dtype {frames.dtype}, got {out.dtype}")
    if np.shape(shifts) != (frames.shape[0], 2):
        raise ValueError(f"shifts: expected ({frames.shape[0]}, 2), got {np.shape(shifts)}")
    if len(box) != 4:
        raise ValueError(f"box: expected (x0, y0, x1, y1), got {box}")


def stabilize_reference(frames: np.ndarray, shifts: np.ndarray, box: tuple[int, int, int, int],
                        out: np.ndarray) -> None:
    """Pure-numpy reference of :func:`stabilize_into`.

    Parameters
    ----------
    frames : ndarray
        (F, H, W) one camera's frames, DN.
    shifts : ndarray
        (F, 2) int image shift (x, y) of each frame, px.
    box : tuple of int
        (x0, y0, x1, y1) the stabilized pixels to fill, px (clipped to the frame).
    out : ndarray
        (>= F, H, W) of the frames' dtype: ``out[f, y, x] = frames[f, y + sy, x + sx]`` inside
        ``box`` (edge pixels where that falls outside); untouched elsewhere.
    """
    _check(frames, shifts, box, out)
    F, H, W = frames.shape
    x0, y0, x1, y1 = max(int(box[0]), 0), max(int(box[1]), 0), min(int(box[2]), W), min(int(box[3]), H)
    if x1 <= x0 or y1 <= y0:
        return
    for f in range(F):
        sx, sy = int(shifts[f][0]), int(shifts[f][1])
        ys = np.clip(np.arange(y0, y1) + sy, 0, H - 1)
        xs = np.clip(np.arange(x0, x1) + sx, 0, W - 1)
        out[f, y0:y1, x0:x1] = frames[f][np.ix_(ys, xs)]


def _warm_args() -> tuple:
    return (np.zeros((2, 8, 8), np.uint8), np.zeros((2, 2), np.int64), 1, 1, 7, 7, np.zeros((2, 8, 8), np.uint8))


def _warm_args16() -> tuple:
    return (np.zeros((2, 8, 8), np.uint16), np.zeros((2, 2), np.int64), 1, 1, 7, 7, np.zeros((2, 8, 8), np.uint16))


@njit(warm=_warm_args)
def _stabilize_kernel(frames: np.ndarray, shifts: np.ndarray, x0: int, y0: int, x1: int, y1: int,
                      out: np.ndarray) -> None:
    """:func:`stabilize_into`'s loops (box already clipped to the frame)."""
    F, H, W = frames.shape
    for f in range(F):
        sx, sy = shifts[f, 0], shifts[f, 1]
        for y in range(y0, y1):
            yy = min(max(y + sy, 0), H - 1)
            for x in range(x0, x1):
                xx = min(max(x + sx, 0), W - 1)
                out[f, y, x] = frames[f, yy, xx]


from iscd.core.jit import register_warm  # noqa: E402

register_warm(_stabilize_kernel, _warm_args16)


def stabilize_into(frames: np.ndarray, shifts: np.ndarray, box: tuple[int, int, int, int],
                   out: np.ndarray, *, compiled: bool = True) -> np.ndarray:
    """Fill ``box`` of the stabilized frames: ``out[f, y, x] = frames[f, y + sy, x + sx]``.

    Parameters
    ----------
    frames : ndarray
        (F, H, W) one camera's frames (uint8 or uint16), DN.
    shifts : ndarray
        (F, 2) int image shift (x, y) of each frame, px (module docstring).
    box : tuple of int
        (x0, y0, x1, y1) the stabilized pixels the caller will read, px (clipped to the
        frame; x1, y1 exclusive).
    out : ndarray
        (>= F, H, W) buffer of the frames' dtype; only ``box`` of its first F frames is
        written.
    compiled : bool
        The compiled kernel (else :func:`stabilize_reference`).

    Returns
    -------
    ndarray
        ``out[:F]``.

    Raises
    ------
    ValueError
        If the shapes or dtypes do not match.
    """
    _check(frames, shifts, box, out)
    F, H, W = frames.shape
    if not compiled:
        stabilize_reference(frames, shifts, box, out)
        return out[:F]
    x0, y0, x1, y1 = max(int(box[0]), 0), max(int(box[1]), 0), min(int(box[2]), W), min(int(box[3]), H)
    if x1 > x0 and y1 > y0:
        # writable C-contiguous (a read-only array is another type to Numba)
        _stabilize_kernel(np.require(frames, requirements=["C", "W"]),
                          np.require(shifts, dtype=np.int64, requirements=["C", "W"]), x0, y0, x1, y1, out)
    return out[:F]
