"""The one reader interface that every recording format implements.

A :class:`Recording` is a sequence of grey frames from ONE camera, each with a
``frame_id`` (trigger counter; a left and a right frame with the same id were exposed
together) and a ``timestamp_ns`` (start of exposure, ns). Pixels come back in the
format's native dtype (uint8 or uint16, values ``0 .. 2**bit_depth - 1``), shaped
``(n, height, width)`` for blocks and ``(height, width)`` for single frames.

Subclasses set the attributes in ``__init__`` and implement :meth:`Recording._read`;
everything else (indexing, iteration, blocks, ``info()``, context manager) lives here.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np


class RecordingError(Exception):
    """A recording cannot be opened or read. ``str(err)`` is ONE line: ``<file>: <problem>``."""

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = str(path)
        self.problem = " ".join(str(problem).split())  # force one line
        super().__init__(f"{self.path}: {self.problem}")


class RecordingWarning(UserWarning):
    """A recording was readable but not quite whole (e.g. a partial trailing record)."""


def header_number(value: object, key: str, *, integer: bool = False, lo: float | None = None,
                  hi: float | None = None) -> float | int:
    """A number from a recording's header or sidecar, checked: a real int/float (not a
    bool), finite, within ``[lo, hi]``; ``integer`` also requires an integral value (an int,
    or a float such as 512.0). Raises ValueError naming ``key`` (readers turn it into
    RecordingError)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{key} must be a number, got {value!r:.40}")
    if integer:
        if isinstance(value, float):
            if not math.isfinite(value) or value != int(value):
                raise ValueError(f"{key} must be an integer, got {value!r}")
        out: float | int = int(value)
    else:
        try:
            out = float(value)
        except OverflowError:
            raise ValueError(f"{key} is out of range: {str(value)[:20]}...") from None
        if not math.isfinite(out):
            raise ValueError(f"{key} must be finite, got {value!r}")
    if (lo is not None and out < lo) or (hi is not None and out > hi):
        shown = str(out) if len(str(out)) <= 24 else str(out)[:20] + "..."
        raise ValueError(f"{key} must be in {lo:g}..{hi:g}, got {shown}" if hi is not None
                         else f"{key} must be >= {lo:g}, got {shown}")
    return out


class Recording(abc.ABC):
    """A recorded frame sequence of one camera.

    Attributes (set by every subclass):
      path: the file or folder it was opened from.
      format: short format name (``"iscr"``, ``"photron"``, ``"images"``).
      width, height: frame size, px.
      dtype: ``np.dtype(np.uint8)`` or ``np.dtype(np.uint16)``.
      bit_depth: significant bits per pixel (8, 10, 12, 16...); values are < 2**bit_depth.
      fps: frame rate, frames/s, or ``None`` when the source does not say.
      exposure_s: exposure time, s, or ``None``.
      camera: the camera's name (``"left"``/``"right"``) or model, or ``None``.
      frame_ids: int64 array (n,), trigger counter of every frame.
      timestamps_ns: int64 array (n,), start of exposure of every frame, ns.
    """

    format: str = "?"

    path: Path
    width: int
    height: int
    dtype: np.dtype
    bit_depth: int
    fps: float | None
    exposure_s: float | None
    camera: str | None
    frame_ids: np.ndarray
    timestamps_ns: np.ndarray

    # ---- to implement -------------------------------------------------------------
    @abc.abstractmethod
    def _read(self, start: int, stop: int) -> np.ndarray:
        """Frames ``start <= i < stop`` (already clipped, ``start < stop``) as a new
        C-contiguous array (stop - start, height, width) of :attr:`dtype`."""

    def _extra_info(self) -> dict[str, Any]:
        """Format-specific entries for :meth:`info` (JSON-serializable)."""
        return {}

    def close(self) -> None:
        """Release file handles / memory maps (idempotent)."""

    # ---- shared -------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        """Number of complete frames."""
        return int(len(self.frame_ids))

    def __len__(self) -> int:
        return self.n_frames

    @property
    def duration_s(self) -> float | None:
        """n_frames / fps in s, or ``None`` without fps."""
        return self.n_frames / self.fps if self.fps else None

    def read(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Frames ``start <= i < stop`` (Python slice rules, negative indices allowed,
        clipped to the recording) as a new array (n, height, width) of :attr:`dtype`.
        An empty range gives an array with n = 0."""
        s, e, _ = slice(start, stop).indices(self.n_frames)
        if e <= s:
            return np.empty((0, self.height, self.width), dtype=self.dtype)
        return self._read(s, e)

    def __getitem__(self, index: int | slice) -> np.ndarray:
        """``rec[i]`` -> (height, width) frame; ``rec[a:b]`` -> like :meth:`read`
        (a step other than 1 is applied after reading the span)."""
        if isinstance(index, slice):
            s, e, step = index.indices(self.n_frames)
            if step == 1:
                return self.read(s, e)
            idx = np.arange(s, e, step)
            if idx.size == 0:
                return self.read(0, 0)
            lo, hi = int(idx.min()), int(idx.max()) + 1
            return np.ascontiguousarray(self.read(lo, hi)[idx - lo])
        try:
            i = int(index)  # accepts numpy integers
        except TypeError:
            raise TypeError(f"recording indices must be int or slice, not {type(index).__name__}") from None
        n = self.n_frames
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame index {index} out of range for {n} frames")
        return self._read(i, i + 1)[0]

    def __iter__(self) -> Iterator[np.ndarray]:
        """Every frame (height, width) in order, read in blocks of 64 frames."""
        for block in self.iter_blocks(64):
            yield from block

    def iter_blocks(self, size: int, start: int = 0, stop: int | None = None) -> Iterator[np.ndarray]:
        """Consecutive blocks (n, height, width), n = ``size`` except for the last one.
        Block k covers frames ``start + k*size ...``; their ids are
        ``frame_ids[start + k*size : start + (k+1)*size]``."""
        if int(size) < 1:
            raise ValueError(f"block size must be >= 1, got {size}")
        s, e, _ = slice(start, stop).indices(self.n_frames)
        for b in range(s, e, int(size)):
            yield self._read(b, min(b + int(size), e))

    def info(self) -> dict[str, Any]:
        """A JSON-serializable summary: frames, width, height, fps, bit_depth, dtype,
        format, path, camera, duration_s, exposure_s, first/last frame id and
        format-specific entries under ``"extra"``."""
        n = self.n_frames
        return {
            "format": self.format,
            "path": str(self.path),
            "camera": self.camera,
            "frames": n,
            "width": int(self.width),
            "height": int(self.height),
            "fps": None if self.fps is None else float(self.fps),
            "bit_depth": int(self.bit_depth),
            "dtype": np.dtype(self.dtype).name,
            "duration_s": self.duration_s,
            "exposure_s": None if self.exposure_s is None else float(self.exposure_s),
            "first_frame_id": int(self.frame_ids[0]) if n else None,
            "last_frame_id": int(self.frame_ids[-1]) if n else None,
            "missing_frame_ids": missing_ids(self.frame_ids),
            "extra": self._extra_info(),
        }

    def __enter__(self) -> "Recording":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        fps = "?" if self.fps is None else f"{self.fps:g}"
        return (f"<{type(self).__name__} {str(self.path)!r} {self.n_frames}x{self.height}x{self.width} "
                f"{np.dtype(self.dtype).name} {self.bit_depth}-bit {fps} fps>")


def missing_ids(frame_ids: np.ndarray) -> int | None:
    """How many ids are missing between the first and last frame (dropped frames);
    None if the ids do not strictly increase."""
    ids = np.asarray(frame_ids, dtype=np.int64)
    if ids.size and not np.all(np.diff(ids) > 0):
        return None
    return int(ids[-1] - ids[0] + 1 - ids.size) if ids.size else 0


def match_frames(left_ids: np.ndarray, right_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pair a stereo recording by frame id.

    Returns index arrays ``(li, ri)`` such that ``left_ids[li] == right_ids[ri]``, in
    increasing frame-id order; frames that only one camera has are left out (dropped
    frames). Ids must be unique within each camera.
    """
    left_ids = np.asarray(left_ids, dtype=np.int64)
    right_ids = np.asarray(right_ids, dtype=np.int64)
    _, li, ri = np.intersect1d(left_ids, right_ids, assume_unique=True, return_indices=True)
    return li.astype(np.intp), ri.astype(np.intp)
