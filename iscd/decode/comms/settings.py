"""The ``[receiver]`` config section: demodulator choices and thresholds.

Every key has a default; ``receiver_config(cfg)`` validates the ``[receiver]`` table with
:func:`iscd.core.config.build_section`, so a bad value is a one-line ConfigError naming the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from iscd.core.config import Config, ConfigError, build_section, config_section


def _f(default: Any, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
       choices: tuple[Any, ...] | None = None, doc: str = "") -> Any:
    return field(default=default, metadata={"lo": lo, "hi": hi, "lo_open": lo_open,
                                            "choices": choices, "doc": doc})


@config_section("receiver")
@dataclass(frozen=True)
class ReceiverConfig:
    """How packets are found and decided (docs/receiver.md)."""

    rule: str = _f("iscd", choices=("iscd", "dissertation", "left", "right"),
                   doc="decision rule: iscd (per-LED ML, both cameras), dissertation (3.11/3.12, "
                       "pooled Euclidean), left/right (dissertation rule on one camera)")
    cameras: str = _f("both", choices=("both", "left", "right"),
                      doc="cameras used by the iscd rule (and by timing)")
    noise_model: str = _f("t", choices=("gauss", "t"),
                          doc="iscd rule: Gaussian or Student-t likelihood (robust tails)")
    t_nu: float = _f(8.0, lo=1.0, doc="degrees of freedom of the Student-t likelihood")
    straddle: bool = _f(True, doc="iscd rule: also use frames straddling two symbols")
    straddle_candidates: int = _f(4, lo=0, doc="levels (best by the clean frames) that compete "
                                  "once straddling frames are added; 0 = all M")
    ic_iterations: int = _f(2, lo=1, hi=6, doc="decision-feedback passes over a packet")
    decision_directed: bool = _f(True, doc="re-estimate the channel from the decided data")
    chunk_symbols: int = _f(96, lo=8, doc="symbols decided between clock updates (drift tracking)")
    channel_window_symbols: int = _f(96, lo=0,
                                     doc="iscd rule: the channel is re-estimated along the packet from "
                                         "the decided symbols of a window this long around each stretch "
                                         "(an approaching car's LEDs brighten within a packet); 0 = one "
                                         "channel per packet")
    drift_max_ppm: float = _f(300.0, lo=0, lo_open=True,
                              doc="prior RMS of the LED clock error before it is tracked, ppm")
    timing_sigma_frames: float = _f(0.02, lo=0, doc="assumed boundary uncertainty, frames")
    var_floor_dn: float = _f(0.3, lo=0, lo_open=True, doc="smallest noise RMS per level, DN")
    header_rho: float = _f(0.7, lo=0, hi=1, doc="header search: least normalized correlation")
    training_rho: float = _f(0.5, lo=-1, hi=1,
                             doc="least rank correlation of the training sequence (rejects false headers)")
    min_contrast: float = _f(6.0, lo=0,
                             doc="least header contrast (level M - level 1) in noise RMS units")
    header_phases: int = _f(8, lo=1, hi=64, doc="sub-frame phases of the coarse header search")
    air_v2: bool = _f(True, doc="read air interface v2's PHY header after each Barker-13 and decode "
                                "v2 packets as it describes them (v1 packets decode as before)")

    @property
    def camera_indices(self) -> tuple[int, ...]:
        """Which cameras (0 = left, 1 = right) the demodulator reads."""
        sel = {"left": "left", "right": "right"}.get(self.rule, self.cameras)
        return {"both": (0, 1), "left": (0,), "right": (1,)}[sel]

    @property
    def dissertation(self) -> bool:
        return self.rule in ("dissertation", "left", "right")


def receiver_config(cfg: Config | None = None, table: dict[str, Any] | None = None) -> ReceiverConfig:
    """The validated ``[receiver]`` section of ``cfg`` (or of a raw ``table``).

    Parameters
    ----------
    cfg : Config or None
        A loaded configuration; its ``[receiver]`` table is read.
        ``None`` (with no ``table``) gives every default.
    table : dict or None
        A raw ``[receiver]`` table, used instead of ``cfg`` when given.

    Returns
    -------
    ReceiverConfig
        The section with every key checked and every default filled in.

    Raises
    ------
    ConfigError
        When the table is not a table, or a key is unknown or of the wrong type (the message
        names the key).
    """
    if table is None:
        table = cfg.table("receiver") if cfg is not None else {}
    if not isinstance(table, dict):
        raise ConfigError(f"receiver: expected a table [receiver], got {table!r}")
    return build_section(ReceiverConfig, table, "receiver")
