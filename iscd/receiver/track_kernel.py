"""The tracking's light map accumulated block by block (compiled), instead of keeping the
frames of a tracking interval and reducing them at its end.

:func:`iscd.receiver.detect.light_map` of a block of frames is the temporal mean minus the
temporal minimum of each pixel (grey levels). Both are running reductions, so
:class:`LightAccumulator` folds each block's window into a sum and a minimum as it
arrives (one pass over the window's pixels, no copies) and gives the same map at the end
of the interval (float tolerance: the mean is summed in float64 where the reference sums
in float32; ``tests/test_rx_kernels_follow.py``).
"""

from __future__ import annotations

import numpy as np

from iscd.jit import njit, register_warm


@njit
def _fold(frames, x0: int, y0: int, acc_sum: np.ndarray, acc_min: np.ndarray) -> None:
    """acc_sum += frames' window, acc_min = min(acc_min, window); window (h, w) at x0, y0."""
    h, w = acc_sum.shape
    for f in range(frames.shape[0]):
        for a in range(h):
            row = frames[f, y0 + a, x0:x0 + w]
            sa = acc_sum[a]
            ma = acc_min[a]
            for b in range(w):
                v = np.int64(row[b])
                sa[b] += v
                ma[b] = min(ma[b], v)


def _warm(dtype: type) -> tuple:
    return (np.zeros((2, 4, 4), dtype), 0, 0, np.zeros((2, 2), np.int64), np.zeros((2, 2), np.int64))


register_warm(_fold, lambda: _warm(np.uint8))
register_warm(_fold, lambda: _warm(np.uint16))


class LightAccumulator:
    """Running sum and minimum of a fixed window (x0, y0, x1, y1) px over blocks of frames."""

    def __init__(self, window: tuple[int, int, int, int]) -> None:
        self.window = window
        x0, y0, x1, y1 = window
        h, w = max(0, y1 - y0), max(0, x1 - x0)
        self._sum = np.zeros((h, w), np.int64)
        self._min = np.full((h, w), np.iinfo(np.int64).max, np.int64)
        self.frames = 0

    def add(self, frames: np.ndarray) -> None:
        """Fold a block (F, H, W) of integer frames in (its window's pixels only)."""
        fr = np.asarray(frames)
        if fr.dtype.kind not in "ui":
            raise ValueError(f"LightAccumulator takes integer frames, got {fr.dtype}")
        if self._sum.size and fr.shape[0]:
            x0, y0, x1, y1 = self.window
            if x1 > fr.shape[2] or y1 > fr.shape[1]:
                raise ValueError(f"window {self.window} outside frames of {fr.shape[2]}x{fr.shape[1]}")
            _fold(fr if fr.flags.c_contiguous else np.ascontiguousarray(fr), x0, y0, self._sum, self._min)
        self.frames += fr.shape[0]

    def light_map(self) -> np.ndarray:
        """(h, w) float32: temporal mean minus temporal minimum over the frames added."""
        if self.frames == 0:
            raise ValueError("no frames added")
        return (self._sum / self.frames - self._min).astype(np.float32)
