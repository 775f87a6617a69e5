"""A clipped spot's sub-pixel phase taken out of one LED's luminance.

A spot whose core clips gives a fixed window a light that depends on where the spot sits
within its pixel: clipping happens per pixel, so no smooth window removes it. As a car
closes in, vibration and the approach move the spot over the pixel grid and the top PWM
levels spread (docs/eval.md, "Session 32": on a 40 km/h approach under engine vibration,
level 8's noise rises from 0.23 % of the level range with nothing moving to 1.04-1.12 %
with everything on; a static spot keeps its levels 19.8 noise widths apart).

Given each frame's level (a packet's decisions, its header and training known) and the
followed centre in each frame, each level's light is regressed, in windows of frames, on a
quadratic trend plus the first harmonics of the centre's sub-pixel phase
(:func:`phase_features`), and the phase part is taken out (:func:`take_out_phase`). The
:class:`~iscd.decode.comms.packets.PacketAssembler` does this for a one-LED packet that every
other attempt failed and demodulates it again (:func:`phase_corrected`); only a CRC pass
counts. Offline, on the receiver's own luminance and followed centres, this delivered 10 of
18 packets the receiver lost in 15 motion runs (``python -m iscd.eval.phaselight``).

Pure functions; units px, DN, frames.
"""

from __future__ import annotations

import numpy as np

from iscd.decode.comms.timing import SymbolClock, frame_map_range

PHASE_RETRY = True
"""A one-LED packet that every attempt failed is demodulated once more with the sub-pixel
phase taken out (:class:`~iscd.decode.comms.packets.PacketAssembler`)."""

ROUNDS = 2
"""Rounds of the phase attempt: each after the first takes its labels from the last round's
decisions (fewer of them wrong), the correction always made on the luminance as measured."""

WINDOW_FRAMES = 400
"""Frames per window of the regression (:func:`take_out_phase`): the trend and the phase's
effect change as the spot grows and the vibration moves it."""

MIN_FRAMES = 12
"""Least frames of a level in a window to fit it (more than the 7 unknowns)."""

OUTLIER_SIGMAS = 3.5
"""With ``robust``: frames further than this many robust standard deviations (1.4826 x the
median absolute deviation) from a level's first fit are left out of its second: a frame
labelled with a wrong decision sits a level step (many noise widths) off."""


def phase_features(x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
    """The first harmonics of the sub-pixel phase of positions on the pixel grid (pixel
    centres at integers).

    Parameters
    ----------
    x_px, y_px : numpy.ndarray
        (n,) positions, px.

    Returns
    -------
    numpy.ndarray
        (n, 4): cos and sin of 2 pi x, cos and sin of 2 pi y.
    """
    x = 2.0 * np.pi * np.asarray(x_px, dtype=np.float64)
    y = 2.0 * np.pi * np.asarray(y_px, dtype=np.float64)
    return np.stack([np.cos(x), np.sin(x), np.cos(y), np.sin(y)], axis=1)


def take_out_phase(light: np.ndarray, labels: np.ndarray, use: np.ndarray, features: np.ndarray, *,
                   window: int = WINDOW_FRAMES, min_frames: int = MIN_FRAMES, robust: bool = False) -> np.ndarray:
    """Each label's light less its fitted dependence on ``features``, window by window.

    In each window of ``window`` frames and for each label, the light of the frames in
    ``use`` is fitted (least squares) by a quadratic in time plus a linear combination of
    the features; the features' part is subtracted from those frames. Frames outside ``use``,
    and labels with fewer than ``min_frames`` frames in a window, are left as they are.

    Parameters
    ----------
    light : numpy.ndarray
        (n,) light per frame, DN (NaN: not measured, left out).
    labels : numpy.ndarray
        (n,) int label per frame (a level).
    use : numpy.ndarray
        (n,) bool, the frames to fit and correct (e.g. those inside one symbol).
    features : numpy.ndarray
        (n, k) regressors, e.g. :func:`phase_features`.
    window : int
        Frames per window.
    min_frames : int
        Least frames of a label in a window to fit it (> k + 3).
    robust : bool
        Fit each label twice, the second time without the frames more than
        :data:`OUTLIER_SIGMAS` robust standard deviations off the first fit.

    Returns
    -------
    numpy.ndarray
        (n,) the corrected light, DN.

    Raises
    ------
    ValueError
        Inputs of different lengths, or ``window`` < 1 or ``min_frames`` <= k + 3.
    """
    x = np.asarray(light, dtype=np.float64)
    n, k = features.shape
    if x.shape != (n,) or labels.shape != (n,) or use.shape != (n,):
        raise ValueError("light, labels, use and features must have n rows alike")
    if window < 1 or min_frames <= k + 3:
        raise ValueError(f"need window >= 1 and min_frames > {k + 3}")
    out = x.copy()
    ok = use & np.isfinite(x) & np.isfinite(features).all(axis=1)
    t = np.arange(n, dtype=np.float64)
    for s in range(0, n, window):
        sl = slice(s, min(n, s + window))
        for lab in np.unique(labels[sl][ok[sl]]):
            idx = np.flatnonzero(ok[sl] & (labels[sl] == lab)) + s
            if idx.size < min_frames:
                continue
            dt = t[idx] - s
            A = np.concatenate([np.stack([np.ones(idx.size), dt, dt * dt], 1), features[idx]], axis=1)
            coef, *_ = np.linalg.lstsq(A, x[idx], rcond=None)
            if robust:  # refit without the frames far off the fit (a wrong label's)
                r = x[idx] - A @ coef
                sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
                keep = np.abs(r) <= OUTLIER_SIGMAS * sigma
                if min_frames <= keep.sum() < idx.size:
                    coef, *_ = np.linalg.lstsq(A[keep], x[idx][keep], rcond=None)
            out[idx] = x[idx] - features[idx] @ coef[3:]
    return out


def phase_corrected(L: np.ndarray, centres: np.ndarray, levels: np.ndarray, clock: SymbolClock,
                    e: float, *, window: int | None = None) -> np.ndarray | None:
    """One LED's luminance with the sub-pixel phase taken out over a packet's frames.

    Parameters
    ----------
    L : numpy.ndarray
        (C, n, 1) luminance of the buffer's frames, DN (NaN: missing).
    centres : numpy.ndarray
        (C, n, 1, 2) the LED's followed centre (x, y) in each camera and frame, px (NaN:
        not known).
    levels : numpy.ndarray
        (S,) 0-based level of packet symbols 0 .. S-1 (header, training, the decided data
        and whatever is known after them).
    clock : SymbolClock
        The packet's symbol clock in buffer frames.
    e : float
        Exposure window length, frames (exposure_s * fps).
    window : int, optional
        Frames per window of :func:`take_out_phase` (default :data:`WINDOW_FRAMES`).

    Returns
    -------
    numpy.ndarray or None
        A corrected (C, n, 1) copy: the clean frames (exposure within one symbol) of the S
        symbols changed, every other frame as it was; None when no camera had enough clean
        frames with a known centre to fit.

    Raises
    ------
    ValueError
        ``L`` not one LED's, or ``centres`` of another shape.
    """
    C, n, N = L.shape
    if N != 1 or centres.shape != (C, n, 1, 2):
        raise ValueError(f"phase_corrected: one LED's (C, n, 1) luminance and (C, n, 1, 2) centres, "
                         f"got {L.shape} and {centres.shape}")
    window = WINDOW_FRAMES if window is None else int(window)
    lev = np.asarray(levels, dtype=np.int64).reshape(-1)
    lo = int(max(0.0, np.floor(clock.u0)))
    hi = int(min(float(n), np.ceil(clock.boundary(lev.size)) + 1))
    if hi - lo < window // 4:
        return None
    k, alpha = frame_map_range(lo, hi, clock, e)
    clean = (alpha >= 1.0) & (k >= 0) & (k < lev.size)
    labels = np.where(clean, lev[np.clip(k, 0, lev.size - 1)], -1)
    out = np.array(L, dtype=np.float64, copy=True)
    changed = False
    for c in range(C):
        xy = centres[c, lo:hi, 0, :]
        use = clean & np.isfinite(xy).all(axis=1)
        if use.sum() < MIN_FRAMES:
            continue
        xy = np.where(np.isfinite(xy), xy, 0.0)
        fixed = take_out_phase(out[c, lo:hi, 0], labels, use, phase_features(xy[:, 0], xy[:, 1]), window=window,
                               robust=True)
        changed = changed or bool((fixed != out[c, lo:hi, 0]).any())
        out[c, lo:hi, 0] = fixed
    return out if changed else None
