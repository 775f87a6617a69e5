"""What every shift estimator returns, and the protocol it follows.

Conventions (stated once for :mod:`iscd.decode.ranging`): shifts are left position - right
position, px (the disparity d of eq. 3.1 for rectified cameras, positive for a target in
front of the rig); patches are (n, h, w) batches of background-removed grey levels.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class ShiftEstimate:
    """Shifts of a batch of patch pairs (left position - right position), px; all (n,)."""

    dx: NDArray[np.float64]
    dy: NDArray[np.float64]
    quality: NDArray[np.float64]
    sigma_px: NDArray[np.float64]
    """standard deviation of ``dx``, px (NaN where it could not be computed)."""
    sigma_y_px: NDArray[np.float64] = field(default_factory=lambda: np.array([]))


class Estimator(Protocol):
    """A shift estimator: ``estimate(left, right)`` on (n, h, w) batches."""

    name: str

    def estimate(self, left: ArrayLike, right: ArrayLike, **kw: Any) -> ShiftEstimate:
        """Shifts of each pair of patches (left position - right position).

        Parameters
        ----------
        left, right : array_like
            (n, h, w) batches of patches, DN (a single (h, w) pair is n = 1).
        **kw
            Method-specific options (e.g. ``background``); others ignore them.

        Returns
        -------
        ShiftEstimate
            dx, dy, px; quality; standard deviations, px; all (n,).
        """
        ...
