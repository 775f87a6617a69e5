"""The evaluation suites: which simulated points ``iscd eval`` runs, and running them.

- ``comms`` (dissertation chapter 3, fig. 3.8): one LED, OOK and PWM-8, b = 0.6 m, f/4 + f/4,
  100 ppm LED clock drift, 20-60 m every 5 m; single camera and diversity reception.
- ``hdr`` (chapter 4, figs. 4.6-4.9, table 4.2): 8x8 array, 6 cm pitch, b = 0.25 m, PWM-8 and
  PWM-16, left f/4, right f/4, f/8 or f/16, 10-50 m every 10 m; single camera, diversity
  (f/4 + f/4) and HDR (f/4 + f/8, f/4 + f/16) reception; plus a car approaching at 40 km/h
  from 50 m with 0.3 px rig vibration (HDR f/4 + f/8, PWM-8).
- ``ranging`` (chapter 3, fig. 3.7): one LED, PWM-8, b = 0.6 m, f/4, right camera slightly
  defocused (0.3 px), independent air jitter 0.05 px RMS per camera, textured background,
  20-60 m every 5 m, every shift estimator on the same frames.
- ``motion`` (issue 12; not part of ``all``): a moving car, :data:`MOTION_CASES` (one LED
  approaching at 40 km/h from 50 m and at 100 km/h from 100 m, both down to 25 m, 0.3 and
  0.5 px vibration, one LED still with vibration only, the 8x8 array with HDR f/4 + f/8 at
  40 km/h, and the one-LED approaches again with the HDR pair f/4 + f/8), several seeds a case, each decoded by the receiver and by the oracle stages of
  :mod:`iscd.eval.oracle` (where the errors come from, and where along the packet).

Each reception mode runs with the project's decision rule and (``rules``) the
dissertation's. Every point has its own fixed seed, derived from ``seed`` and the point's
parameters (so a point's result does not depend on which other points run); the LED's
clock phase is random per point (seeded).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from iscd.core.airinterface_v2 import from_config as air_from_config
from iscd.core.config import Config
from iscd.eval.sweeps import CommsResult, RangingResult, ReceiverMode, run_comms, run_ranging
from iscd.decode.ranging.estimators import METHODS
from iscd.sim.presets import override, single_led

SUITES = ("comms", "hdr", "ranging")
"""The suites of ``--suite all`` (``motion`` runs only when asked for)."""
ALL_SUITES = SUITES + ("motion", "fec")
FEC_DISTANCES_M = (20.0, 29.0, 40.0, 50.0, 60.0)
"""Distances of the ``fec`` suite (v1 against v2 goodput, 8x8 PWM-16)."""
FEC_AIRS = (("v1", "rs255_223"), ("v2", "rs255_223"), ("v2", "rs255_191"))
"""(air_interface, fec) of the ``fec`` suite's transmitters (v1 ignores fec)."""
COMMS_DISTANCES_M = (20.0, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0, 55.0, 60.0)
HDR_DISTANCES_M = (10.0, 20.0, 30.0, 40.0, 50.0)
RANGING_DISTANCES_M = COMMS_DISTANCES_M
RIGHT_DEFOCUS_PX = 0.3
"""'right camera slightly defocused': extra blur sigma of the right camera, px."""
JITTER_PX = 0.05
"""independent air jitter per camera, RMS px."""
APPROACH_SPEED_MPS = 40.0 / 3.6
APPROACH_VIBRATION_PX = 0.3
APPROACH_PACKETS = 2
"""Packets of the approach point: 50 -> 21 m at 40 km/h (a third would end at 7 m; the
receiver decodes to ~17 m, docs/receiver.md)."""


MOTION_SEEDS = 3
"""Seeds per motion case (the quick form: 1)."""
MOTION_QUICK_DATA_SYMBOLS = 120
"""Data symbols per packet in the quick motion form (short packets, same physics)."""


@dataclass(frozen=True)
class MotionCase:
    """One case of the motion suite: ``leds`` 1 (chapter 3: b = 0.6 m, f/4 + f/4, both
    cameras) or 64 (the 8x8 array, chapter 4: b = 0.25 m, HDR f/4 + f/8), PWM-8; closing at
    ``speed_kmh`` from ``start_m`` until ``end_m`` (the approach stops there), rig
    vibration ``vibration_px`` RMS; ``packets`` whole packets. ``scene``: further
    ``[scene]`` keys (e.g. ``(("vibration_model", "bumps"),)``); ``randomize``: pass the
    config through ``iscd.sim.randomize.randomized(cfg, seed)`` when that exists."""

    key: str
    leds: int
    speed_kmh: float
    start_m: float
    end_m: float
    vibration_px: float
    packets: int = 2
    scene: tuple[tuple[str, Any], ...] = ()
    randomize: bool = False
    title: str = ""
    """the label, when not made from the fields (a recording's)"""
    f_number_right: float = 0.0
    """the right camera's f-number; 0 = the chapter's (f/4 for one LED, f/8 for the array).
    One LED with f/8: the HDR pair, whose f/8 camera keeps the top levels apart where the
    f/4 spot's core clips as the car closes in."""

    @property
    def cameras(self) -> str:
        """``f/4+f/4`` or ``HDR f/4+f/N``."""
        fr = self.f_number_right or (4.0 if self.leds == 1 else 8.0)
        return "f/4+f/4" if fr == 4.0 else f"HDR f/4+f/{fr:g}"

    @property
    def label(self) -> str:
        if self.title:
            return self.title
        who = ("1 LED" + ("" if self.cameras == "f/4+f/4" else " " + self.cameras) if self.leds == 1
               else "8x8 " + self.cameras)
        if self.speed_kmh:
            how = f"{self.speed_kmh:g} km/h {self.start_m:g}->{self.end_m:g} m"
        else:
            how = f"still at {self.start_m:g} m"
        extra = "".join(f", {k}={v}" for k, v in self.scene)
        return f"{who} PWM-8, {how}, {self.vibration_px:g} px{extra}"


MOTION_CASES = (
    MotionCase("1led-40kmh-0.3px", 1, 40.0, 50.0, 25.0, 0.3),
    MotionCase("1led-40kmh-0.5px", 1, 40.0, 50.0, 25.0, 0.5),
    MotionCase("1led-100kmh-0.3px", 1, 100.0, 100.0, 25.0, 0.3),
    MotionCase("1led-100kmh-0.5px", 1, 100.0, 100.0, 25.0, 0.5),
    MotionCase("1led-still-0.5px", 1, 0.0, 50.0, 50.0, 0.5),
    MotionCase("8x8-40kmh-0.3px", 64, 40.0, 50.0, 25.0, 0.3),
    MotionCase("1led-hdr-40kmh-0.3px", 1, 40.0, 50.0, 25.0, 0.3, f_number_right=8.0),
    MotionCase("1led-hdr-40kmh-0.5px", 1, 40.0, 50.0, 25.0, 0.5, f_number_right=8.0),
    MotionCase("1led-hdr-100kmh-0.3px", 1, 100.0, 100.0, 25.0, 0.3, f_number_right=8.0),
    MotionCase("1led-hdr-100kmh-0.5px", 1, 100.0, 100.0, 25.0, 0.5, f_number_right=8.0),
)
"""The motion suite. Two packets (1.3 s each) a case: 40 km/h covers 50 -> 25 m (reached
after 2.25 s; the rest at 25 m), 100 km/h 100 -> 27.4 m."""


def motion_cfg(base: Config, case: MotionCase, seed: int, *, quick: bool = False,
               scene: dict[str, Any] | None = None, randomize: bool = False) -> tuple[Config, str]:
    """The config of a motion case.

    Parameters
    ----------
    base : Config
        Sensor, optics, background, [receiver], [tracking] come from it.
    case : MotionCase
        Transmitter, motion (km/h, m) and vibration (px RMS).
    seed : int
        Scene seed (noise, LED phase, payloads, vibration; the randomizer's draw).
    quick : bool
        Packets of :data:`MOTION_QUICK_DATA_SYMBOLS` data symbols.
    scene : dict, optional
        ``[scene]`` keys over the case's own (e.g. a vibration model).
    randomize : bool
        (Or the case's own flag.) Through ``iscd.sim.randomize.randomized(cfg, seed,
        motion=...)`` with the case's [scene] keys (speed, distances, vibration amplitude,
        ``scene``) fixed and the rest of the physics drawn; imported here -- when that
        module is not there the case runs without it.

    Returns
    -------
    cfg : Config
    note : str
        What was done about the randomizer ("" when not asked for).
    """
    keys = {"speed_mps": case.speed_kmh / 3.6, "vibration_px": case.vibration_px,
            "min_distance_m": min(case.end_m, case.start_m), **dict(case.scene), **(scene or {})}
    if case.leds == 1:
        cfg = chapter3_cfg(base, case.start_m, 8, seed, **keys)
    else:
        side = int(round(math.sqrt(case.leds)))
        if side * side != case.leds:
            raise ValueError(f"motion case {case.key}: {case.leds} LEDs is not a square array")
        cfg = chapter4_cfg(base, case.start_m, 8, 8.0, seed, **keys)
        if side != 8:
            cfg = override(cfg, transmitter={"rows": side, "cols": side})
    if case.f_number_right:
        cfg = override(cfg, camera={"f_number_right": case.f_number_right})
    if quick:
        cfg = override(cfg, transmitter={"data_symbols": MOTION_QUICK_DATA_SYMBOLS})
    note = ""
    if randomize or case.randomize:
        try:
            from iscd.sim.randomize import randomized  # lazily: another part of the simulator
        except ImportError:
            note = "iscd.sim.randomize is not available: run without randomized physics"
        else:
            import inspect

            if "motion" in inspect.signature(randomized).parameters:  # the case's motion stays fixed
                cfg = randomized(cfg, seed, motion=keys)
            else:
                cfg = randomized(cfg, seed)
            note = "randomized physics (iscd.sim.randomize)"
    return cfg, note


def point_seed(seed: int, *keys: Any) -> int:
    """A fixed per-point seed from the run's ``seed`` and the point's parameters."""
    text = "|".join([str(int(seed))] + [repr(k) for k in keys])
    return zlib.crc32(text.encode()) & 0x7FFFFFFF


def _still(**scene: Any) -> dict[str, Any]:
    base = {"speed_mps": 0.0, "vibration_px": 0.0, "jitter_px": 0.0, "led_drift_ppm": 100.0,
            "led_phase_s": -1.0}
    base.update(scene)
    return base


def chapter3_cfg(base: Config, distance_m: float, levels: int, seed: int, **scene: Any) -> Config:
    """One LED sending M-level PWM (2 = OOK) at ``distance_m``, b = 0.6 m, f/4 + f/4, 100 ppm
    drift, random LED phase (from ``seed``); ``scene`` overrides further scene keys."""
    cfg = single_led(base, distance_m, **_still(seed=seed, **scene))
    return override(cfg, transmitter={"levels": levels})


def chapter4_cfg(base: Config, distance_m: float, levels: int, f_right: float, seed: int,
                 **scene: Any) -> Config:
    """The 8x8 array (6 cm pitch) at ``distance_m``, b = 0.25 m, left f/4, right ``f_right``."""
    return override(base, transmitter={"rows": 8, "cols": 8, "pitch_m": 0.06, "levels": levels},
                    camera={"baseline_m": 0.25, "f_number_left": 4.0, "f_number_right": f_right},
                    scene={"distance_m": distance_m, **_still(seed=seed, **scene)})


def ranging_cfg(base: Config, distance_m: float, seed: int) -> Config:
    """Chapter 3 ranging: one LED, PWM-8, b = 0.6 m, f/4 + f/4, right camera defocused by
    :data:`RIGHT_DEFOCUS_PX`, air jitter :data:`JITTER_PX` per camera, textured background."""
    cfg = chapter3_cfg(base, distance_m, 8, seed, jitter_px=JITTER_PX, background="texture")
    return override(cfg, optics={"right_defocus_px": RIGHT_DEFOCUS_PX})


def with_rules(modes: Sequence[ReceiverMode], rules: Sequence[str]) -> list[ReceiverMode]:
    """Every mode once per decision rule (``iscd``, ``dissertation``)."""
    return [ReceiverMode(m.name, m.cameras, r) for r in rules for m in modes]


CH3_MODES = (ReceiverMode("single camera (left)", "left"), ReceiverMode("diversity", "both"))


def ch4_modes(f_right: float, quick: bool = False) -> list[ReceiverMode]:
    """Reception modes of a chapter 4 scene with the right camera at ``f_right``."""
    fr = f"f/{f_right:g}"
    both = ReceiverMode("diversity f/4+f/4" if f_right == 4.0 else f"HDR f/4+{fr}", "both")
    right = ReceiverMode(f"single camera {fr} (right)", "right")
    left = ReceiverMode("single camera f/4 (left)", "left")
    if f_right == 4.0 or quick:
        return [left, right, both]
    return [right, both]


@dataclass
class CommsRow:
    """One reception mode at one point of the comms, hdr or approach table."""

    suite: str
    distance_m: float
    levels: int
    f_left: float
    f_right: float
    seed: int
    result: CommsResult
    note: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {"suite": self.suite, "distance_m": self.distance_m, "levels": self.levels,
                "f_left": self.f_left, "f_right": self.f_right, "seed": self.seed, "note": self.note,
                **self.result.as_dict()}


@dataclass
class RangingRow:
    """One ranging point; ``jitter_floor_mae_m`` is the mean absolute range error that the
    air jitter alone causes (:func:`jitter_floor_mae`), a floor for every method."""

    distance_m: float
    seed: int
    result: RangingResult
    jitter_floor_mae_m: float = float("nan")

    def as_dict(self) -> dict[str, Any]:
        return {"seed": self.seed, "jitter_floor_mae_m": self.jitter_floor_mae_m, **self.result.as_dict()}


def jitter_floor_mae(cfg: Config) -> float:
    """Mean absolute range error (m) from the air jitter alone: independent Gaussian shifts
    of ``scene.jitter_px`` RMS per camera make the disparity err by sqrt(2) jitter_px RMS,
    i.e. Z^2 / (f b) times that in range (dZ/dd of eq. 2.2), and E|e| = sqrt(2/pi) RMS."""
    z, j = cfg.scene.distance_m, cfg.scene.jitter_px
    return math.sqrt(2.0 / math.pi) * math.sqrt(2.0) * j * z * z / (cfg.camera.focal_px * cfg.camera.baseline_m)


@dataclass
class EvalResults:
    """Everything one ``iscd eval`` run measured."""

    settings: dict[str, Any]
    comms: list[CommsRow] = field(default_factory=list)
    hdr: list[CommsRow] = field(default_factory=list)
    approach: list[CommsRow] = field(default_factory=list)
    ranging: list[RangingRow] = field(default_factory=list)
    motion: list["MotionRow"] = field(default_factory=list)
    fec: list[CommsRow] = field(default_factory=list)
    """v1 against v2 (``note``: the air interface and code) at the same points"""
    seconds: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        out = {"settings": self.settings, "seconds": round(self.seconds, 1),
               "comms": [r.as_dict() for r in self.comms], "hdr": [r.as_dict() for r in self.hdr],
               "approach": [r.as_dict() for r in self.approach],
               "ranging": [r.as_dict() for r in self.ranging]}
        if self.motion:
            out["motion"] = [r.as_dict() for r in self.motion]
        if self.fec:
            out["fec"] = [r.as_dict() for r in self.fec]
        return out


@dataclass
class MotionRow:
    """One seed of one motion case: the receiver's scores and the oracle stages
    (:class:`iscd.eval.oracle.OracleResult`)."""

    case: MotionCase
    seed: int
    result: Any  # iscd.eval.oracle.OracleResult (imported lazily: it imports the pipeline)
    note: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {"case": self.case.key, "label": self.case.label, "seed": self.seed, "note": self.note,
                **self.result.as_dict()}


@dataclass
class Job:
    """One simulated point: its config, what to run and how many frames it renders."""

    suite: str
    label: str
    cfg: Config
    frames: int
    run: Callable[[Callable[[int], None] | None], list[Any]]


@dataclass(frozen=True)
class EvalPlan:
    """What to run. ``packets`` per comms point, ``frames`` per ranging point; ``None``
    distances = the suite's standard ones."""

    suites: tuple[str, ...] = SUITES
    quick: bool = False
    seed: int = 1
    packets: int | None = None
    frames: int | None = None
    rules: tuple[str, ...] | None = None
    methods: tuple[str, ...] = tuple(METHODS)
    comms_distances: tuple[float, ...] | None = None
    hdr_distances: tuple[float, ...] | None = None
    ranging_distances: tuple[float, ...] | None = None
    fec_distances: tuple[float, ...] | None = None
    block: int = 32
    motion_block: int = 16
    """pairs per decode step of the motion suite: the daemon's ``[daemon] block_max`` (a
    moving car is where the block matters: the following judges and clamps per block)"""
    motion_seeds: int | None = None
    """seeds per motion case (default :data:`MOTION_SEEDS`, 1 with ``quick``)"""
    motion_cases: tuple[str, ...] | None = None
    """keys of :data:`MOTION_CASES` to run (default all)"""
    motion_scene: tuple[tuple[str, Any], ...] = ()
    """``[scene]`` keys over every motion case's (e.g. a vibration model)"""
    motion_randomize: bool = False
    """pass every motion case through ``iscd.sim.randomize.randomized`` when it exists"""
    motion_traces: str | None = None
    """a directory: every motion scene's luminance trace is written there
    (:mod:`iscd.eval.lumtrace`, ``<case>-<seed>[-<key>=<value>...].npz``)"""

    def resolved(self) -> "EvalPlan":
        """Fill the defaults (full or ``quick``)."""
        import dataclasses

        q = self.quick
        return dataclasses.replace(
            self,
            packets=self.packets or (2 if q else 4),
            frames=self.frames or (300 if q else 5000),
            rules=self.rules or (("iscd",) if q else ("iscd", "dissertation")),
            comms_distances=self.comms_distances or ((20.0, 60.0) if q else COMMS_DISTANCES_M),
            hdr_distances=self.hdr_distances or ((50.0,) if q else HDR_DISTANCES_M),
            ranging_distances=self.ranging_distances or ((30.0, 60.0) if q else RANGING_DISTANCES_M),
            fec_distances=self.fec_distances or ((50.0,) if q else FEC_DISTANCES_M),
            motion_seeds=self.motion_seeds or (1 if q else MOTION_SEEDS),
            motion_cases=self.motion_cases or tuple(c.key for c in MOTION_CASES))

    def settings(self) -> dict[str, Any]:
        p = self.resolved()
        return {"suites": list(p.suites), "quick": p.quick, "seed": p.seed, "packets": p.packets,
                "frames": p.frames, "rules": list(p.rules or ()), "methods": list(p.methods),
                "comms_distances_m": list(p.comms_distances or ()),
                "hdr_distances_m": list(p.hdr_distances or ()),
                "ranging_distances_m": list(p.ranging_distances or ()),
                **({"fec_distances_m": list(p.fec_distances or ())} if "fec" in p.suites else {}),
                **({"motion_seeds": p.motion_seeds, "motion_cases": list(p.motion_cases or ()),
                    "motion_scene": {k: v for k, v in p.motion_scene},
                    "motion_randomize": p.motion_randomize, "motion_block": p.motion_block}
                   if "motion" in p.suites else {})}


def _packet_frames(cfg: Config, packets: int) -> int:
    """About the frames :func:`iscd.eval.sweeps.run_comms` renders (for the progress total)."""
    t = cfg.transmitter
    period = air_from_config(t).period_symbols
    return int(period * packets * cfg.camera.fps / t.symbol_rate_hz) + 10


def jobs(base: Config, plan: EvalPlan, results: EvalResults) -> list[Job]:
    """The points of ``plan``; running a job appends its rows to ``results``."""
    p = plan.resolved()
    assert p.packets and p.frames and p.rules is not None
    out: list[Job] = []

    def comms_job(suite: str, label: str, cfg: Config, modes: list[ReceiverMode], d: float, m: int,
                  fl: float, fr: float, seed: int, table: list[CommsRow], note: str = "",
                  packets: int | None = None) -> Job:
        n = packets or p.packets or 2

        def run(progress: Callable[[int], None] | None) -> list[Any]:
            res = run_comms(cfg, modes, n, block=p.block, progress=progress)
            rows = [CommsRow(suite, d, m, fl, fr, seed, r, note) for r in res]
            table.extend(rows)
            return rows
        return Job(suite, label, cfg, _packet_frames(cfg, n), run)

    if "comms" in p.suites:
        levels = (8, 2)
        for d in p.comms_distances or ():
            for m in levels:
                s = point_seed(p.seed, "comms", d, m)
                cfg = chapter3_cfg(base, d, m, s)
                name = "OOK" if m == 2 else f"PWM-{m}"
                out.append(comms_job("comms", f"comms {name} {d:g} m", cfg, with_rules(CH3_MODES, p.rules),
                                     d, m, 4.0, 4.0, s, results.comms))
    if "hdr" in p.suites:
        rights = (8.0,) if p.quick else (4.0, 8.0, 16.0)
        for d in p.hdr_distances or ():
            for m in (8, 16):
                for fr in rights:
                    s = point_seed(p.seed, "hdr", d, m, fr)
                    cfg = chapter4_cfg(base, d, m, fr, s)
                    out.append(comms_job("hdr", f"hdr PWM-{m} f/4+f/{fr:g} {d:g} m", cfg,
                                         with_rules(ch4_modes(fr, p.quick), p.rules), d, m, 4.0, fr, s,
                                         results.hdr))
        s = point_seed(p.seed, "approach")
        cfg = chapter4_cfg(base, 50.0, 8, 8.0, s, speed_mps=APPROACH_SPEED_MPS,
                           vibration_px=APPROACH_VIBRATION_PX)
        out.append(comms_job("approach", "approach 40 km/h from 50 m", cfg,
                             with_rules([ReceiverMode("HDR f/4+f/8", "both")], p.rules), 50.0, 8, 4.0, 8.0,
                             s, results.approach,
                             note=f"{APPROACH_SPEED_MPS * 3.6:.0f} km/h, {APPROACH_VIBRATION_PX} px vibration",
                             packets=APPROACH_PACKETS))
    if "fec" in p.suites:
        pairs = ((4.0, 8.0),) if p.quick else ((4.0, 8.0), (4.0, 4.0))
        for d in p.fec_distances or ():
            for fl, fr in pairs:
                s = point_seed(p.seed, "fec", d, fr)  # one scene (seed) for every air interface
                mode = ReceiverMode("HDR f/4+f/8" if fr != fl else "diversity f/4+f/4", "both")
                for air, fec in FEC_AIRS:
                    cfg = override(chapter4_cfg(base, d, 16, fr, s),
                                   transmitter={"air_interface": air, "fec": fec})
                    label = air if air == "v1" else f"v2 {fec}"
                    out.append(comms_job("fec", f"fec {label} PWM-16 f/{fl:g}+f/{fr:g} {d:g} m", cfg,
                                         [mode], d, 16, fl, fr, s, results.fec, note=label))
    if "motion" in p.suites:
        cases = {c.key: c for c in MOTION_CASES}
        unknown = [k for k in p.motion_cases or () if k not in cases]
        if unknown:
            raise ValueError(f"unknown motion case(s) {', '.join(unknown)} (known: {', '.join(cases)})")
        for key in p.motion_cases or ():
            case = cases[key]
            for i in range(p.motion_seeds or 1):
                s = point_seed(p.seed, "motion", case.key, i)
                cfg, note = motion_cfg(base, case, s, quick=p.quick, scene=dict(p.motion_scene),
                                       randomize=p.motion_randomize)

                def run(progress: Callable[[int], None] | None, cfg: Config = cfg, case: MotionCase = case,
                        s: int = s, note: str = note) -> list[Any]:
                    from iscd.eval.oracle import run_oracle

                    label = "-".join([case.key, str(s)] + [f"{k}={v}" for k, v in p.motion_scene])
                    trace = None if p.motion_traces is None else Path(p.motion_traces) / f"{label}.npz"
                    row = MotionRow(case, s, run_oracle(cfg, case.packets, mode=ReceiverMode(
                        "HDR f/4+f/8" if case.leds > 1 else "diversity", "both"), block=p.motion_block,
                        progress=progress, trace_to=trace, trace_label=label), note)
                    results.motion.append(row)
                    return [row]
                out.append(Job("motion", f"motion {case.key} seed {i + 1}", cfg,
                               _packet_frames(cfg, case.packets), run))
    if "ranging" in p.suites:
        for d in p.ranging_distances or ():
            s = point_seed(p.seed, "ranging", d)
            cfg = ranging_cfg(base, d, s)

            def run(progress: Callable[[int], None] | None, cfg: Config = cfg, d: float = d,
                    s: int = s) -> list[Any]:
                res = run_ranging(cfg, p.frames or 1, p.methods, block=p.block, progress=progress)
                row = RangingRow(d, s, res, jitter_floor_mae(cfg))
                results.ranging.append(row)
                return [row]
            out.append(Job("ranging", f"ranging {d:g} m", cfg, p.frames, run))
    return out


def run_plan(base: Config, plan: EvalPlan, progress: Callable[[int, str], None] | None = None) -> EvalResults:
    """Run every point of ``plan`` on top of the ``base`` config (sensor, optics, background,
    distractors, [receiver], [tracking] and [ranging] come from it). ``progress(frames,
    label)`` is called as frames are processed."""
    import time

    results = EvalResults(settings=plan.settings())
    t0 = time.perf_counter()
    for job in jobs(base, plan, results):
        cb = None if progress is None else (lambda n, lab=job.label: progress(n, lab))
        job.run(cb)
    results.seconds = time.perf_counter() - t0
    return results


def total_frames(base: Config, plan: EvalPlan) -> int:
    """Frames all jobs of ``plan`` render (for a progress bar's total)."""
    return sum(j.frames for j in jobs(base, plan, EvalResults(settings={})))
