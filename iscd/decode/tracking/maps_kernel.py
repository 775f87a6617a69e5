"""The detection's per-pixel maps of a block of frames, in one compiled pass.

A look for a transmitter (:func:`iscd.decode.tracking.detect.detect_auto`,
:func:`~iscd.decode.tracking.detect.detect_array`) needs four (H, W) maps of the same block
of whole frames: the activity (mean absolute difference of consecutive frames,
:func:`~iscd.decode.tracking.detect.activity_map`), the temporal mean, minimum and maximum.
numpy makes them in five passes over the block with a temporary per frame (~12 ms for 64
frames of 512 x 512 px here); :func:`look_maps` reads each pixel of the block once (~2 ms),
and releases the GIL meanwhile (a searcher's look runs in a thread beside the frame loop).

The values are **identical** to numpy's (tests/test_maps_kernel.py, on rendered frames):
the sums are exact integers (int32), and the two divisions are the same float32 divisions
numpy makes (its float32 accumulation of integers is exact below 2**24, which
:func:`look_maps` checks before it takes the compiled path). Units: DN, DN per frame.
"""

from __future__ import annotations

import numpy as np

from iscd.core.jit import njit, register_warm

TILE = 2048
"""Pixels a pass keeps its accumulators for (in L1/L2 cache while the frames stream by)."""
EXACT = 2 ** 24
"""float32 holds every integer below this exactly (numpy's float32 sums agree up to it)."""


@njit
def _maps(f: np.ndarray, act: np.ndarray, mean: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
    """f (n, P) frames, n >= 2; writes act, mean (P,) float32, lo, hi (P,) f's dtype.
    Integer sums (int32: n * 65535 < 2**31 for the n :func:`look_maps` sends here)."""
    n, P = f.shape
    s = np.empty(TILE, np.int32)
    d = np.empty(TILE, np.int32)
    prev = np.empty(TILE, np.int32)
    a = np.empty(TILE, f.dtype)
    b = np.empty(TILE, f.dtype)
    dn = np.float32(n)
    dn1 = np.float32(n - 1)
    for p0 in range(0, P, TILE):
        m = min(TILE, P - p0)
        row = f[0, p0:p0 + m]
        for j in range(m):
            v = row[j]
            s[j] = np.int32(v)
            prev[j] = np.int32(v)
            d[j] = 0
            a[j] = v
            b[j] = v
        for k in range(1, n):
            row = f[k, p0:p0 + m]
            for j in range(m):
                v = row[j]
                iv = np.int32(v)
                s[j] += iv
                d[j] += abs(iv - prev[j])
                prev[j] = iv
                a[j] = min(a[j], v)
                b[j] = max(b[j], v)
        for j in range(m):
            act[p0 + j] = np.float32(d[j]) / dn1
            mean[p0 + j] = np.float32(s[j]) / dn
            lo[p0 + j] = a[j]
            hi[p0 + j] = b[j]


for _dt in (np.uint8, np.uint16):
    register_warm(_maps, lambda _dt=_dt: (np.zeros((2, 4), _dt), np.empty(4, np.float32), np.empty(4, np.float32),
                                           np.empty(4, _dt), np.empty(4, _dt)))


def frames_block(frames: np.ndarray) -> np.ndarray:
    """``frames`` as an array, checked to be a block of frames.

    Parameters
    ----------
    frames : array_like
        (n >= 2, H, W) frames, DN.

    Returns
    -------
    ndarray
        The same frames (no copy when already an array).

    Raises
    ------
    ValueError
        If ``frames`` is not (n >= 2, H, W).
    """
    f = np.asarray(frames)
    if f.ndim != 3 or f.shape[0] < 2:
        raise ValueError(f"need a (n >= 2, H, W) block of frames, got shape {f.shape}")
    return f


def activity_map(frames: np.ndarray) -> np.ndarray:
    """Temporal gradient: mean absolute difference of consecutive frames, (H, W) float32.

    Parameters
    ----------
    frames : ndarray
        (n, H, W) uint8/uint16 frames, DN, n >= 2.

    Returns
    -------
    ndarray of float32
        (H, W) activity, DN per frame.

    Raises
    ------
    ValueError
        If ``frames`` is not (n >= 2, H, W).
    """
    f = frames_block(frames)
    acc = np.zeros(f.shape[1:], dtype=np.float32)
    wide = np.int16 if f.dtype.itemsize == 1 else np.int32  # 16-bit data overflows int16
    prev = f[0].astype(wide)
    for k in range(1, f.shape[0]):  # per frame, vectorized over pixels; n is small (~64)
        cur = f[k].astype(wide)
        acc += np.abs(cur - prev)
        prev = cur
    return acc / (f.shape[0] - 1)


def look_maps_reference(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`look_maps` with numpy: the reference.

    Parameters
    ----------
    frames : ndarray
        (n >= 2, H, W) frames, DN.

    Returns
    -------
    act, mean, lo, hi : ndarray
        As :func:`look_maps`: activity (float32, DN per frame), mean (float32, DN),
        minimum and maximum (the frames' dtype, DN), each (H, W).
    """
    f = np.asarray(frames)
    return activity_map(f), f.mean(axis=0, dtype=np.float32), f.min(axis=0), f.max(axis=0)


def look_maps(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Activity, mean, minimum and maximum of a block of frames, each (H, W).

    Parameters
    ----------
    frames : ndarray
        (n >= 2, H, W) frames, DN (uint8 or uint16 take the compiled pass; anything else,
        or a block long enough for float32 sums to round, the numpy reference).

    Returns
    -------
    act : ndarray of float32
        Mean absolute difference of consecutive frames, DN per frame
        (:func:`iscd.decode.tracking.detect.activity_map`).
    mean : ndarray of float32
        Temporal mean, DN.
    lo, hi : ndarray
        Temporal minimum and maximum, DN, the frames' dtype.

    Raises
    ------
    ValueError
        If ``frames`` is not (n >= 2, H, W).
    """
    f = frames_block(frames)
    n, H, W = f.shape
    if f.dtype not in (np.uint8, np.uint16) or n * np.iinfo(f.dtype).max >= EXACT:
        return look_maps_reference(f)
    flat = np.ascontiguousarray(f).reshape(n, H * W)
    act = np.empty(H * W, np.float32)
    mean = np.empty(H * W, np.float32)
    lo = np.empty(H * W, f.dtype)
    hi = np.empty(H * W, f.dtype)
    _maps(flat, act, mean, lo, hi)
    return act.reshape(H, W), mean.reshape(H, W), lo.reshape(H, W), hi.reshape(H, W)
