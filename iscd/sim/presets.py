"""Config helpers for simulations: override keys of a :class:`~iscd.core.config.Config`.

    cfg = override(default_config(), scene={"distance_m": 20, "background": "none"},
                   transmitter={"rows": 1, "cols": 1})
"""

from __future__ import annotations

import dataclasses
from typing import Any

from iscd.core.config import Config, ConfigError, DistractorConfig, FaultConfig, build_section, to_dict


def override(cfg: Config, **sections: dict[str, Any]) -> Config:
    """A copy of ``cfg`` with the given keys of each section replaced (validated like a
    config file: unknown keys and bad values raise ConfigError).

    Parameters
    ----------
    cfg : Config
        The base config (not modified).
    **sections : dict
        Section name (``scene``, ``camera``, ...) -> {key: new value}.

    Returns
    -------
    Config
    """
    new = {}
    for name, changes in sections.items():
        current = getattr(cfg, name, None)
        if current is None or not dataclasses.is_dataclass(current):
            raise ConfigError(f"{name}: unknown section")
        table = to_dict(current)
        table.update(changes)
        new[name] = build_section(type(current), table, name)
    return cfg.replace(**new)


def single_led(cfg: Config, distance_m: float, baseline_m: float = 0.6, **scene: Any) -> Config:
    """The chapter 3 setup: one LED at ``distance_m``, equal f/4 apertures, b = 0.6 m.

    Parameters
    ----------
    cfg : Config
        The base config.
    distance_m : float
        Initial distance Z, m.
    baseline_m : float
        Baseline b, m.
    **scene
        Further ``[scene]`` keys.

    Returns
    -------
    Config

    References
    ----------
    Dissertation, table 3.1 (SPEC section 2).
    """
    return override(cfg, transmitter={"rows": 1, "cols": 1},
                    camera={"baseline_m": baseline_m, "f_number_left": 4.0, "f_number_right": 4.0},
                    scene={"distance_m": distance_m, **scene})


__all__ = ["override", "single_led", "DistractorConfig", "FaultConfig"]
