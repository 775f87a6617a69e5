"""Randomized simulator physics for tests: draw a concrete config per seed.

    cfg = randomized(default_config(), seed=7)                       # a concrete Config
    cfg = randomized(base, 7, motion={"distance_m": 40, "speed_mps": 11.1})

:func:`randomized` is a pure function of (cfg, seed, motion): it draws the vibration model
and its parameters, the PSF model and width, glare kind and fraction, the diffuser profile,
blooming, the right camera's defocus, the noise levels, the background and how vibration
moves it (whole pixels or the exact shift, :data:`P_SUBPIXEL_BACKGROUND`), the exposure and
LED brightness, the LED clock phase and drift, the LED size and a small lateral offset and
speed, and returns an explicit :class:`~iscd.core.config.Config` with those values (and
``scene.randomized_seed = seed``), so the truth's meta (its ``config``) records what was
drawn, and a receiver given the recording never sees the draw. ``motion``: [scene] keys
that are fixed instead of drawn (applied before the lateral bounds are computed, which
depend on the distance and speed). Everything else of ``cfg`` (the transmitter array,
apertures, baseline, distance, speed, scene seed, distractors) is kept.

The ranges (:data:`RANGES`) stay within what a real camera and LED of the SPEC's rig could
produce, and keep the scene decodable in principle: the effective LED brightness
radiance_dn * exposure / 1 ms lies in 350-900 DN at f/4 (the default is 600), so level 2 is
never saturated in a resolved spot at f/4 (<= 129 DN) and level M never in the f/8 camera
(<= 225 DN); the PSF stays about 1-2 px wide and the LED array stays inside the image for
:data:`RUN_S` s of the run.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from iscd.core.config import Config
from iscd.sim.presets import override

RANGES: dict[str, tuple[float, float]] = {
    "scene.vibration_px": (0.05, 0.4),
    "scene.jitter_px": (0.0, 0.08),
    "scene.bump_rate_hz": (1.0, 5.0),
    "scene.bump_freq_hz": (6.0, 15.0),
    "scene.bump_damping": (0.08, 0.3),
    "scene.engine_hz": (22.0, 38.0),
    "scene.engine_wander_hz": (0.3, 4.0),  # and the fundamental stays in 20-40 Hz
    "scene.engine_harmonic": (0.1, 0.6),
    "scene.led_drift_ppm": (-200.0, 200.0),
    "scene.led_phase_s": (0.0, 1.0),  # x the symbol period
    "scene.lateral_m": (-0.5, 0.5),  # and the array in view of both cameras
    "scene.lateral_speed_mps": (-0.5, 0.5),  # and the array stays in view for RUN_S
    "scene.background_dn": (15.0, 80.0),
    "scene.background_contrast": (0.15, 0.6),
    "optics.psf_sigma_px": (0.45, 0.85),
    "optics.psf_beta": (2.0, 4.5),
    "optics.right_defocus_px": (0.0, 1.0),
    "optics.glare_fraction": (0.01, 0.10),
    "optics.glare_sigma_px": (1.5, 4.0),
    "optics.glare_power": (1.6, 3.0),
    "optics.diffuser_falloff": (0.2, 0.7),  # or 0 (uniform), probability 0.4
    "sensor.full_well_e": (12_000.0, 35_000.0),
    "sensor.read_noise_e": (8.0, 40.0),
    "sensor.prnu": (0.003, 0.02),
    "sensor.dark_dn": (0.0, 6.0),
    "sensor.blooming": (0.1, 0.5),  # or 0 (off), probability 0.4
    "sensor.bloom_length_px": (1.0, 4.0),
    "camera.exposure_s": (0.6, 1.0),  # x the frame period 1/fps
    "transmitter.led_diameter_m": (0.022, 0.038),
    "effective_radiance_dn": (350.0, 900.0),  # radiance_dn * exposure_s / 1 ms
}
"""Uniform ranges drawn by :func:`randomized` (``section.key``: (lo, hi))."""

CHOICES: dict[str, tuple[tuple[str, ...], tuple[float, ...]]] = {
    "scene.vibration_model": (("smooth", "bumps", "engine"), (1 / 3, 1 / 3, 1 / 3)),
    "scene.background": (("texture", "flat"), (0.8, 0.2)),
    "optics.psf_model": (("gaussian", "moffat"), (0.5, 0.5)),
    "optics.glare_model": (("gaussian", "power"), (0.5, 0.5)),
}
"""Discrete draws: (choices, probabilities)."""

P_SUBPIXEL_BACKGROUND = 0.5
"""Probability that vibration moves the background by the exact shift
(``scene.background_motion = "subpixel"``, as a real rig's image moves) rather than by whole
pixels (the renderer's cheaper approximation, the only one before session 36). Drawn from
its own stream (:data:`BACKGROUND_STREAM`), so every other draw of a seed is what it was."""
BACKGROUND_STREAM = 0xB6C3
"""The second key of the background motion's generator ``default_rng([seed, key])``."""

P_UNIFORM_DIFFUSER = 0.4
"""Probability of a uniform disk (diffuser_falloff = 0)."""
P_NO_BLOOMING = 0.4
"""Probability of no blooming (sensor.blooming = 0)."""
RUN_S = 3.0
"""s: the lateral draws keep the LED array in view this long (about two packets)."""
VIEW_MARGIN_PX = 40
"""px kept free between the LED array and the image border."""


def randomized(cfg: Config, seed: int, *, motion: dict[str, Any] | None = None) -> Config:
    """``cfg`` with the simulator's physics drawn for ``seed`` (see module docstring);
    deterministic in (cfg, seed, motion). ``motion``: [scene] keys fixed instead of drawn.

    Parameters
    ----------
    cfg : Config
        The base config (transmitter array, apertures, baseline, distance, speed, scene seed
        and distractors are kept).
    seed : int
        Seed of the draw (recorded as ``scene.randomized_seed``).
    motion : dict, optional
        ``[scene]`` keys (e.g. ``distance_m``, m; ``speed_mps``, m/s) fixed instead of drawn.

    Returns
    -------
    Config
    """
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 0x7A4D])
    motion = dict(motion or {})
    base = override(cfg, scene=motion) if motion else cfg
    scene = _draw_scene(rng, base)
    optics = _draw_optics(rng)
    sensor = _draw_sensor(rng)
    camera, transmitter = _draw_exposure(rng, base)
    scene.update(_draw_lateral(rng, base, transmitter["led_diameter_m"]))
    sub = np.random.default_rng([seed & 0xFFFFFFFF, BACKGROUND_STREAM]).uniform() < P_SUBPIXEL_BACKGROUND
    scene["background_motion"] = "subpixel" if sub else "whole"
    scene = {k: v for k, v in scene.items() if k not in motion}
    scene.update(motion)
    scene["randomized_seed"] = int(seed)
    return override(cfg, scene=scene, optics=optics, sensor=sensor, camera=camera,
                    transmitter=transmitter)


def drawn(cfg: Config) -> dict[str, Any]:
    """The values :func:`randomized` draws, read back from a config (``section.key``: value),
    JSON-ready: what ``iscd simulate --randomize`` records in the truth's meta.

    Parameters
    ----------
    cfg : Config
        A (randomized) config.

    Returns
    -------
    dict
        ``section.key`` -> value, in the config's units; also ``transmitter.radiance_dn``,
        ``effective_radiance_dn`` (radiance_dn exposure_s / 1 ms, DN) and
        ``scene.randomized_seed``.
    """
    keys = [*RANGES, *CHOICES]
    out: dict[str, Any] = {}
    for k in keys:
        if "." not in k:
            continue
        sec, key = k.split(".", 1)
        out[k] = getattr(getattr(cfg, sec), key)
    out["scene.led_phase_s"] = cfg.scene.led_phase_s
    out["scene.background_motion"] = cfg.scene.background_motion
    out["transmitter.radiance_dn"] = cfg.transmitter.radiance_dn
    out["effective_radiance_dn"] = cfg.transmitter.radiance_dn * cfg.camera.exposure_s / 1e-3
    out["scene.randomized_seed"] = cfg.scene.randomized_seed
    return out


def _u(rng: np.random.Generator, key: str) -> float:
    lo, hi = RANGES[key]
    return float(rng.uniform(lo, hi))


def _choice(rng: np.random.Generator, key: str) -> str:
    options, p = CHOICES[key]
    return str(options[int(rng.choice(len(options), p=p))])


def _draw_scene(rng: np.random.Generator, cfg: Config) -> dict[str, Any]:
    """Vibration (model and parameters), jitter, LED clock, background."""
    T = 1.0 / cfg.transmitter.symbol_rate_hz
    d: dict[str, Any] = {
        "vibration_model": _choice(rng, "scene.vibration_model"),
        "vibration_px": _u(rng, "scene.vibration_px"),
        "jitter_px": _u(rng, "scene.jitter_px"),
        "bump_rate_hz": _u(rng, "scene.bump_rate_hz"),
        "bump_freq_hz": _u(rng, "scene.bump_freq_hz"),
        "bump_damping": _u(rng, "scene.bump_damping"),
        "engine_hz": _u(rng, "scene.engine_hz"),
        "engine_harmonic": _u(rng, "scene.engine_harmonic"),
        "led_drift_ppm": _u(rng, "scene.led_drift_ppm"),
        "led_phase_s": float(rng.uniform(0.0, 1.0)) * T * (1 - 1e-9),
        "background": _choice(rng, "scene.background"),
        "background_dn": _u(rng, "scene.background_dn"),
        "background_contrast": _u(rng, "scene.background_contrast"),
    }
    lo, hi = RANGES["scene.engine_wander_hz"]
    hi = min(hi, d["engine_hz"] - 20.0, 40.0 - d["engine_hz"])  # f0 stays in 20-40 Hz
    d["engine_wander_hz"] = float(rng.uniform(lo, max(hi, lo)))
    return d


def _draw_optics(rng: np.random.Generator) -> dict[str, Any]:
    """PSF model and width, defocus of the right camera, glare, diffuser profile."""
    d: dict[str, Any] = {
        "psf_model": _choice(rng, "optics.psf_model"),
        "psf_sigma_px": _u(rng, "optics.psf_sigma_px"),
        "psf_beta": _u(rng, "optics.psf_beta"),
        "right_defocus_px": _u(rng, "optics.right_defocus_px"),
        "glare_model": _choice(rng, "optics.glare_model"),
        "glare_fraction": _u(rng, "optics.glare_fraction"),
        "glare_sigma_px": _u(rng, "optics.glare_sigma_px"),
        "glare_power": _u(rng, "optics.glare_power"),
    }
    k = _u(rng, "optics.diffuser_falloff")
    d["diffuser_falloff"] = 0.0 if rng.uniform() < P_UNIFORM_DIFFUSER else k
    return d


def _draw_sensor(rng: np.random.Generator) -> dict[str, Any]:
    """Full well, read noise, PRNU, black level, blooming."""
    d: dict[str, Any] = {k: _u(rng, "sensor." + k)
                         for k in ("full_well_e", "read_noise_e", "prnu", "dark_dn",
                                   "bloom_length_px")}
    b = _u(rng, "sensor.blooming")
    d["blooming"] = 0.0 if rng.uniform() < P_NO_BLOOMING else b
    return d


def _draw_exposure(rng: np.random.Generator, cfg: Config
                   ) -> tuple[dict[str, Any], dict[str, Any]]:
    """Exposure (a share of the frame period), LED size and brightness (the effective
    brightness radiance_dn * exposure / 1 ms is drawn, so a short exposure does not make
    the scene undecodably dark)."""
    exposure = _u(rng, "camera.exposure_s") / cfg.camera.fps
    eff = _u(rng, "effective_radiance_dn")
    diameter = _u(rng, "transmitter.led_diameter_m")
    return ({"exposure_s": exposure},
            {"radiance_dn": eff / (exposure / 1e-3), "led_diameter_m": diameter})


def lateral_interval_m(cfg: Config, led_diameter_m: float | None = None
                       ) -> tuple[float, float]:
    """(lo, hi) m: where the array centre X may be so that the whole array stays
    :data:`VIEW_MARGIN_PX` inside both images (left at f X/Z, right at f (X - b)/Z from the
    centre) at every distance of :data:`RUN_S` s of the approach, intersected with
    :data:`RANGES`; lo > hi when it never fits.

    Parameters
    ----------
    cfg : Config
        Camera, transmitter array and scene motion.
    led_diameter_m : float, optional
        LED diameter, m (default ``transmitter.led_diameter_m``).

    Returns
    -------
    lo, hi : float
        Bounds on X, m.
    """
    sc, cam, tx = cfg.scene, cfg.camera, cfg.transmitter
    z = min(sc.distance_m, max(sc.distance_m - sc.speed_mps * RUN_S, sc.min_distance_m))
    half_w = (tx.cols - 1) / 2 * tx.pitch_m + (led_diameter_m or tx.led_diameter_m) / 2
    room = (cam.width / 2 - VIEW_MARGIN_PX) * z / cam.focal_px - half_w
    lo, hi = RANGES["scene.lateral_m"]
    return max(cam.baseline_m - room, lo), min(room, hi)


def _draw_lateral(rng: np.random.Generator, cfg: Config, led_diameter_m: float
                  ) -> dict[str, float]:
    """A small lateral offset X0 (in the middle half of :func:`lateral_interval_m`) and
    speed v (X0 + v RUN_S stays in the interval), both within :data:`RANGES`; the config's
    lateral_m and no lateral speed when the array does not fit."""
    lo, hi = lateral_interval_m(cfg, led_diameter_m)
    if hi <= lo:
        return {"lateral_m": cfg.scene.lateral_m, "lateral_speed_mps": 0.0}
    c, h = (lo + hi) / 2, (hi - lo) / 4
    x0 = float(rng.uniform(c - h, c + h))
    vlo, vhi = RANGES["scene.lateral_speed_mps"]
    vlo = max(vlo, (lo - x0) / RUN_S)
    vhi = min(vhi, (hi - x0) / RUN_S)
    v = float(rng.uniform(vlo, vhi)) if vhi > vlo else 0.0
    return {"lateral_m": x0, "lateral_speed_mps": v}


__all__ = ["CHOICES", "RANGES", "RUN_S", "drawn", "lateral_interval_m", "randomized"]
