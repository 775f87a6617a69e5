"""Stereo ranging of LEDs: sub-pixel disparity of LED patches and Z = f b / d (docs/ranging.md).

The live pipeline's block ranger (running background, one call per block) is
:class:`iscd.decode.ranging.stereo.StereoRanger`; it uses the estimators and formulas here.

- :mod:`.bicubic`    Keys bicubic magnification (dissertation eqs. 3.1-3.3)
- :mod:`.poc`        phase-only correlation and sub-pixel peaks (3.5-3.9)
- :mod:`.estimators` all shift estimators behind ``estimate_shift`` / ``get_estimator``
- :mod:`.projected`  the fast 1-D project method ("iscd-fast", the live default)
- :mod:`.range`      patches, disparity, range and its sigma (2.2), :class:`LedRanger` (per LED)
- :mod:`.kalman`     optional constant-velocity filter on range and closing speed
- :mod:`.compare`    one harness to score methods on the same pairs
- :mod:`.synth`      synthetic spots with known positions (tests, comparisons)
- :mod:`.config`     the ``[ranging]`` config section
"""

from iscd.decode.ranging.estimators import METHODS, ShiftEstimate, estimate_shift, get_estimator
from iscd.decode.ranging.kalman import RangeKalman, TrackState
from iscd.decode.ranging.range import (LedRanger, RangeEstimate, cut_patches, range_from_disparity,
                                range_sigma)

__all__ = ["METHODS", "ShiftEstimate", "estimate_shift", "get_estimator", "RangeKalman", "TrackState",
           "RangeEstimate", "LedRanger", "cut_patches", "range_from_disparity", "range_sigma"]
