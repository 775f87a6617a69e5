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

Each reception mode runs with the project's decision rule and (``rules``) the
dissertation's. Every point has its own fixed seed, derived from ``seed`` and the point's
parameters (so a point's result does not depend on which other points run); the LED's
clock phase is random per point (seeded).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from iscd.airinterface import AirInterface
from iscd.config import Config
from iscd.eval.sweeps import CommsResult, RangingResult, ReceiverMode, run_comms, run_ranging
from iscd.ranging.estimators import METHODS
from iscd.sim.presets import override, single_led

SUITES = ("comms", "hdr", "ranging")
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
    seconds: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {"settings": self.settings, "seconds": round(self.seconds, 1),
                "comms": [r.as_dict() for r in self.comms], "hdr": [r.as_dict() for r in self.hdr],
                "approach": [r.as_dict() for r in self.approach],
                "ranging": [r.as_dict() for r in self.ranging]}


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
    block: int = 32

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
            ranging_distances=self.ranging_distances or ((30.0, 60.0) if q else RANGING_DISTANCES_M))

    def settings(self) -> dict[str, Any]:
        p = self.resolved()
        return {"suites": list(p.suites), "quick": p.quick, "seed": p.seed, "packets": p.packets,
                "frames": p.frames, "rules": list(p.rules or ()), "methods": list(p.methods),
                "comms_distances_m": list(p.comms_distances or ()),
                "hdr_distances_m": list(p.hdr_distances or ()),
                "ranging_distances_m": list(p.ranging_distances or ())}


def _packet_frames(cfg: Config, packets: int) -> int:
    """About the frames :func:`iscd.eval.sweeps.run_comms` renders (for the progress total)."""
    t = cfg.transmitter
    period = AirInterface.from_config(t).period_symbols
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
