"""The ``[ranging]`` config section (validated with :func:`iscd.config.build_section`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from iscd.config import Config, build_section
from iscd.ranging.estimators import METHODS


def _f(default: Any, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
       choices: tuple[Any, ...] | None = None, doc: str = "") -> Any:
    return field(default=default, metadata={"lo": lo, "hi": hi, "lo_open": lo_open, "choices": choices, "doc": doc})


@dataclass(frozen=True)
class RangingConfig:
    """Stereo ranging (docs/ranging.md)."""

    method: str = _f("iscd", choices=tuple(METHODS), doc="sub-pixel shift estimator")
    patch_px: int = _f(16, lo=4, hi=256, doc="side of a single-LED patch, px")
    min_quality: float = _f(-1.0, lo=-1, hi=1,
                            doc="estimates with a lower match quality are not reported; -1 = the "
                                "method's default (iscd 0.75, others 0)")
    per_led: bool = _f(True, doc="a range record per LED of an array (led = i)")
    whole_array: bool = _f(True, doc="a range record for the whole array (one estimate)")
    beta: float = _f(0.5, lo=0, hi=1, doc="iscd: spectral whitening (1 = phase only, 0 = cross-correlation)")
    band_cutoff: float = _f(0.12, lo=0, doc="iscd: Gaussian band limit, cycles/px (0 = none)")
    saturation_mode: str = _f("declip", choices=("declip", "clip", "none"), doc="iscd: saturated cores")
    kalman: bool = _f(False, doc="also report Kalman-filtered range and closing speed")
    accel_psd: float = _f(1.0, lo=0, lo_open=True, doc="Kalman process noise, (m/s^2)^2/Hz")
    kalman_gate: float = _f(5.0, lo=0, lo_open=True, doc="Kalman outlier gate, standard deviations")

    def quality_threshold(self) -> float | None:
        """``min_quality`` for :class:`iscd.ranging.range.StereoRanger` (None = method default)."""
        return None if self.min_quality < 0 else self.min_quality

    def estimator_options(self) -> dict[str, Any]:
        """Keyword options for :func:`iscd.ranging.estimators.get_estimator`."""
        if self.method != "iscd":
            return {}
        return {"beta": self.beta, "band_cutoff": self.band_cutoff or None,
                "saturation_mode": self.saturation_mode}


def ranging_config(cfg: Config) -> RangingConfig:
    """The validated ``[ranging]`` section of a loaded config (defaults if absent)."""
    return build_section(RangingConfig, dict(cfg.extra.get("ranging", {})), "ranging")
