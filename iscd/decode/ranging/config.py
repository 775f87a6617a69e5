"""The ``[ranging]`` config section (validated with :func:`iscd.core.config.build_section`).

One dataclass for the whole section: the live ranger (:class:`iscd.decode.ranging.stereo.StereoRanger`,
which re-exports it as ``RangingSettings``), the per-LED ranger
(:class:`iscd.decode.ranging.range.LedRanger`) and the Kalman filter read their keys from it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from iscd.core.config import Config, config_section, section
from iscd.decode.ranging.estimators import METHODS

PROJECT_METHODS = ("iscd-fast", "iscd")
"""The project's methods: they take the running-minimum background themselves (they
detect saturation on the raw patches)."""


def _f(default: Any, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
       choices: tuple[Any, ...] | None = None, doc: str = "") -> Any:
    return field(default=default, metadata={"lo": lo, "hi": hi, "lo_open": lo_open, "choices": choices, "doc": doc})


@config_section("ranging")
@dataclass(frozen=True)
class RangingSettings:
    """Stereo ranging (docs/ranging.md)."""

    method: str = _f("iscd-fast", choices=tuple(METHODS),
                     doc="sub-pixel shift estimator (iscd-fast: 1-D, live default; iscd: 2-D, slower)")
    margin_px: int = _f(5, lo=1, hi=64, doc="patch margin around the transmitter's spots, px")
    max_patch_px: int = _f(96, lo=8, hi=512, doc="largest patch side, px")
    background: str = _f("project", choices=("project", "all", "none"),
                         doc="running per-pixel minimum background: subtracted for the project's "
                             "methods (project), for every method (all: compares the estimators alone) "
                             "or not at all (none: each patch's border median)")
    background_frames: int = _f(64, lo=2, hi=4096,
                                doc="frames in the running minimum (it must hold a dark symbol of every LED)")
    min_snr: float = _f(8.0, lo=0, doc="a frame is ranged only when the weaker camera's spot has this "
                                       "signal-to-noise ratio after background removal (0 = every frame)")
    min_quality: float = _f(-1.0, lo=-1, hi=1,
                            doc="estimates with a lower match quality are not reported; -1 = the "
                                "method's default (iscd 0.75, others 0)")
    beta: float = _f(0.5, lo=0, hi=1, doc="iscd, iscd-fast: spectral whitening (1 = phase only, 0 = cross-correlation)")
    band_cutoff: float = _f(0.12, lo=0, doc="iscd, iscd-fast: Gaussian band limit, cycles/px (0 = none)")
    saturation_mode: str = _f("auto", choices=("auto", "declip", "clip", "none"),
                              doc="saturated LED cores: refill them (declip), clip both cameras at a common "
                                  "level (clip, iscd only) or nothing; auto = declip, except iscd-fast on "
                                  "an array (none: 5x cheaper, 0.016 instead of 0.007 px)")
    saturation_dn: int = _f(0, lo=0, hi=65535, doc="grey level at which the sensor clips (0 = the frames' "
                                                    "type maximum: 255 for 8-bit; set 4095 for 12-bit data in 16 bits)")
    patch_px: int = _f(16, lo=4, hi=256, doc="per-LED ranging (LedRanger): side of a single-LED patch, px")
    per_led: bool = _f(False, doc="also emit range_leds records: one range per LED of the array "
                                  "(LedRanger, at the LEDs' followed positions) every per_led_every_frames")
    per_led_every_frames: int = _f(10, lo=1, hi=100000,
                                   doc="per-LED ranges on one frame in this many (a 64-LED array costs "
                                       "~1.2 ms a frame: 10 = 100 per-LED ranges/s per LED)")
    kalman: bool = _f(False, doc="also emit range_filtered records: Kalman-filtered range and closing speed")
    accel_psd: float = _f(1.0, lo=0, lo_open=True, doc="Kalman process noise, (m/s^2)^2/Hz")
    kalman_gate: float = _f(5.0, lo=0, lo_open=True, doc="Kalman outlier gate, standard deviations")

    def __post_init__(self) -> None:
        if self.method == "iscd-fast" and self.saturation_mode == "clip":
            raise ValueError("saturation_mode 'clip' is only available for method iscd "
                             "(iscd-fast: auto, declip or none)")

    def quality_threshold(self) -> float | None:
        """``min_quality`` (None = the method's default, see :data:`iscd.decode.ranging.range.DEFAULT_MIN_QUALITY`)."""
        return None if self.min_quality < 0 else self.min_quality

    def estimator_options(self) -> dict[str, Any]:
        """Keyword options for :func:`iscd.decode.ranging.estimators.get_estimator`."""
        if self.method == "iscd":
            return {"beta": self.beta, "band_cutoff": self.band_cutoff or None,
                    "saturation_mode": "declip" if self.saturation_mode == "auto" else self.saturation_mode}
        if self.method == "iscd-fast":
            return {"beta": self.beta, "band_cutoff": self.band_cutoff or None,
                    "declip": {"auto": None, "declip": True, "none": False}[self.saturation_mode]}
        return {}

    def subtracts_background(self) -> bool:
        """Whether the running-minimum background is removed for this method."""
        return self.background == "all" or (self.background == "project" and self.method in PROJECT_METHODS)


def ranging_config(cfg: Config) -> RangingSettings:
    """The validated ``[ranging]`` section of a loaded config (defaults if absent).

    Parameters
    ----------
    cfg : Config
        A loaded config.

    Returns
    -------
    RangingSettings
    """
    return section(cfg, RangingSettings)
