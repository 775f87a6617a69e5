"""Air interface v2 at the receiver: the PHY header after the Barker-13, and erasures.

:func:`read_phy_header` reads the OOK header of a candidate packet from the clean frames of
its symbols 13 .. 13 + H - 1, normalized per LED and camera between the Barker's dark and
fully-on chips (so it needs neither M nor a channel model), averages the cameras and hands
the soft values to :func:`iscd.core.airinterface_v2.parse_header`, which soft-combines
every bit's copies and checks the header's CRC-32. A v1 packet (training after the Barker)
or a false header gives no header, and the packet is demodulated as v1.

:func:`erasure_masks` turns the decision stage's confidence into the candidate erasure sets
that :meth:`iscd.core.airinterface_v2.AirInterfaceV2.decode_data` tries per codeword.
"""

from __future__ import annotations

import warnings

import numpy as np

from iscd.core.airinterface import BARKER13, HEADER_SYMBOLS
from iscd.core.airinterface_v2 import HeaderError, PhyHeader, header_symbols, parse_header
from iscd.decode.comms.timing import SymbolClock, clean_frame

MIN_SWING_DN = 4.0
"""A camera whose Barker swing (fully on minus dark) on an LED is below this, DN, does not
vote for that LED's header bits (it does not see it)."""

ERASURE_MARGINS = (1.0, 2.5, 5.0)
"""Decision margins (twice the log-likelihood ratio, :mod:`iscd.decode.comms.decide`) below
which a data symbol is marked an erasure, tried in this order after no erasures at all:
about 38 %, 22 % and 8 % chance of a wrong decision at the threshold."""

INCOMPLETE = "incomplete"


def read_phy_header(L: np.ndarray, clock: SymbolClock, e: float) -> PhyHeader | str | None:
    """The v2 PHY header of the packet whose Barker-13 starts at ``clock.u0``.

    Parameters
    ----------
    L : ndarray
        (C, n, N) luminance of the selected cameras, DN (NaN = missing).
    clock : SymbolClock
        The packet's symbol clock (from the Barker), frames.
    e : float
        Exposure window length, frames.

    Returns
    -------
    PhyHeader, str or None
        The header (CRC-32 and fields checked), :data:`INCOMPLETE` when its frames are not
        all in ``L`` yet, or None when there is none (a v1 packet, a false header, too
        much noise).
    """
    C, n, N = L.shape
    H = header_symbols(N)
    frames = clean_frame(np.arange(HEADER_SYMBOLS + H), clock, e)
    if frames[-1] >= n:
        return INCOMPLETE
    if frames[0] < 0:
        return None
    y = L[:, frames, :]  # (C, 13 + H, N)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices: that LED unseen
        hi = np.nanmean(y[:, :HEADER_SYMBOLS][:, BARKER13 > 0], axis=1)  # (C, N)
        lo = np.nanmean(y[:, :HEADER_SYMBOLS][:, BARKER13 < 0], axis=1)
        swing = hi - lo
        soft = (y[:, HEADER_SYMBOLS:] - lo[:, None, :]) / swing[:, None, :]
        soft = np.where((swing > MIN_SWING_DN)[:, None, :], soft, np.nan)
        soft = np.nanmean(soft, axis=0)  # (H, N)
    try:
        return parse_header(soft, N)
    except HeaderError:
        return None


def erasure_masks(margins: np.ndarray, unobserved: np.ndarray) -> np.ndarray:
    """Candidate erasure sets of a packet's data symbols, mildest first.

    Parameters
    ----------
    margins : ndarray
        (F, N) decision margins (cost gap to the runner-up; twice the log-likelihood
        ratio for the Gaussian model).
    unobserved : ndarray
        (F, N) bool, symbols no frame observed.

    Returns
    -------
    ndarray of bool
        (1 + len(ERASURE_MARGINS), F, N): no erasures but the unobserved symbols, then
        every symbol whose margin is below each of :data:`ERASURE_MARGINS`.
    """
    m = np.asarray(margins, np.float64)
    un = np.asarray(unobserved, bool)
    out = [un] + [un | ~(m >= t) for t in ERASURE_MARGINS]
    return np.stack(out)
