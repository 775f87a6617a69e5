"""The scene: renders synchronized left/right 8-bit frames of an LED transmitter, with truth.

Camera frame n exposes [t_n, t_n + exposure_s], t_n = n / fps (camera clock). Per frame only
the windows around the LEDs (and flickering distractors) are rendered with fresh noise and
pasted into a copy of a pre-rendered noisy background frame (a bank of ``bank_size``
frames per camera, drawn at random per frame). See docs/simulator.md for the model and its
approximations. Pure numerics, no threads; random access (frame n renders the same
whatever was rendered before). The per-pixel work runs in the compiled kernels of
:mod:`iscd.sim.kernels` (``Scene(cfg, compiled=False)``: their numpy references, the same
frames); ``scene.warm_up()`` compiles or loads them (0.4 s cached, ~4 s cold).

The motion and spot models of the config (``scene.vibration_model``, ``lateral_speed_mps``,
``optics.psf_model``, ``diffuser_falloff``, ``glare_model``, ``sensor.blooming``) all render
through the same kernels: a spot model is a table (:class:`~iscd.sim.optics.SpotProfile`),
a power-law glare adds glare-only source sets to a window, and blooming adds one kernel
(:func:`~iscd.sim.kernels.bloom_columns`) before the read-out of each window.

    scene = Scene(cfg)
    left, right = scene.render_pair(n)            # uint8 (H, W) each
    scene.render_pair_into(n, out_l, out_r)        # no allocation
    truth = scene.truth(np.arange(0, 2000))        # per-frame and per-symbol ground truth
    truths = scene.truths(np.arange(0, 2000))      # one Truth per transmitter (0 = main)

Several transmitters (``[[scene.transmitters]]`` beside the main ``[transmitter]``): each
has its own geometry, LED clock and packets; their LEDs are further source sets of the same
render windows (sources whose windows overlap share one window, so background and noise are
counted once), with the vibration and jitter of the whole image. A transmitter with
``start_s``/``stop_s`` contributes nothing (no window) to frames whose exposure lies outside
that interval, and only the light inside it to the frames that straddle an end.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from iscd.core.airinterface import AirInterface, duty
from iscd.core.airinterface_v2 import AirInterfaceV2, from_config
from iscd.core.config import (Config, ConfigError, OpticsConfig, PayloadConfig, SceneConfig,
                              TransmitterConfig, to_dict)
from iscd.sim import kernels
from iscd.sim.background import background_pair, flicker_gain
from iscd.sim.exposure import LedClock, on_time, on_time_window
from iscd.sim.geometry import (Jitter, StereoGeometry, distance, lateral, led_offsets,
                                make_vibration, project_rig, vibration_margin)
from iscd.sim.optics import (PIXEL_VAR, ZERO_TABLE, Canvas, Footprint, SpotProfile, SpotTable,
                             TableCache, diffuser_disks, footprint, gaussian_profile,
                             glare_components, moffat_components, render, source_box)
from iscd.sim.sensor import SensorModel, bloom_coefficients
from iscd.sim.transmitter import LevelSource, PacketSource, fixed_payload
from iscd.sim.truth import Truth

if TYPE_CHECKING:  # pragma: no cover
    from iscd.calibration.io import StereoCalibration

REF_F_NUMBER = 4.0
"""radiance_dn, background_dn and brightness_dn are grey levels at f/4 ..."""
REF_EXPOSURE_S = 1e-3
"""... and 1 ms exposure; the signal scales as (4/N)^2 * exposure_s / 1 ms."""


@dataclass
class _Tx:
    """One transmitter of the scene: index 0 is the main one (``[transmitter]`` +
    ``[scene]``), 1.. the ``[[scene.transmitters]]`` in order."""

    index: int
    tx: TransmitterConfig  # its effective transmitter config (rows, cols, levels, ...)
    scene: SceneConfig  # its position, motion and LED clock keys (the rest: the main scene's)
    source: LevelSource  # what its LEDs send
    clock: LedClock  # its LED clock
    offsets: np.ndarray  # (N, 2) LED offsets from the array centre, m
    start_s: float = 0.0  # in view from this camera time on, s
    stop_s: float = math.inf  # ... until this one, s
    payload_seed: int = 0  # seed of its random payloads

    @property
    def grid(self) -> tuple[int, int]:
        """(rows, cols) of its LED array."""
        return (self.tx.rows, self.tx.cols)

    @property
    def windowed(self) -> bool:
        """True when it is in view only part of the time (start_s > 0 or a stop_s)."""
        return self.start_s > 0 or math.isfinite(self.stop_s)

    @property
    def suffix(self) -> str:
        """Suffix of its per-frame state keys: '' for the main one, '@k' for extra k."""
        return "" if self.index == 0 else f"@{self.index}"

    def duty_of(self, k0: int, k1: int) -> np.ndarray:
        """(k1 - k0, N) PWM duties (0..1) of its symbols k0..k1-1."""
        n, m = self.tx.n_leds, self.tx.levels
        lv = np.asarray(self.source.levels(k0, k1))
        if lv.shape != (k1 - k0, n):
            raise ValueError(f"level source returned shape {lv.shape} for symbols {k0}..{k1}, "
                             f"expected ({k1 - k0}, {n})")
        return duty(np.clip(lv, 1, m), m)


@dataclass
class _Source:
    """Sources of one camera and frame that share a spot table."""

    u: np.ndarray
    v: np.ndarray
    amp: np.ndarray  # core peak scale, DN
    tab: SpotTable
    glare_flux: np.ndarray  # DN px^2
    glare_sigma: float
    glare_half: int
    grid: tuple[int, int] | None = None  # (rows, cols) for an LED array
    slot: tuple[int, int] = (0, 0)  # footprint cache slot: (source 0 = LEDs / i + 1, part)


@dataclass
class _Shape:
    """How a source of radius R px looks in one camera (amplitude-free part of _Source).
    A source is one or more parts: the first holds the core and the (first) glare
    Gaussian, further parts (power-law glare) only a glare Gaussian (``tab`` of no light)."""

    tab: SpotTable
    core_scale: float  # core peak scale per DN of light: (1 - g) (R / R_table)^2
    flux_scale: float  # glare flux per DN of light: g pi R^2, px^2
    glare_sigma: float  # px
    glare_half: int  # px, 0: no glare


@dataclass
class _SetPlan:
    """One source set of a render window, ready for :func:`kernels.add_sources`: its
    cached footprint and where its per-frame light comes from (``st[key][i, cols] * c_amp``)."""

    kern: np.ndarray  # (n, k, k) float32
    ix: np.ndarray  # (n,) int64 window origins, canvas px
    iy: np.ndarray
    key: str  # "on_fraction" (the LEDs) or "flicker"
    cols: slice
    c_amp: float  # DN of a fully-on source
    c_core: float
    c_flux: float
    gy: np.ndarray  # (h, m) float64, m = 0: no glare
    gxt: np.ndarray  # (q, w) float64
    grid_q: int


@dataclass
class _GroupPlan:
    """A render window (canvas ``box``, clipped to the image: ``clip``) with its buffers."""

    box: tuple[int, int, int, int]
    clip: tuple[int, int, int, int]  # X0, Y0, X1, Y1; empty when X0 >= X1 or Y0 >= Y1
    sets: list[_SetPlan] = field(default_factory=list)
    empty: bool = False  # the window lies outside the image
    head: tuple[_SetPlan, ...] = ()  # all sets but the last (added before the read-out)
    X0: int = 0  # image px of the read-out window (= clip[:2])
    Y0: int = 0
    ax: int = 0  # canvas px of the read-out window
    ay: int = 0
    bg_at: tuple | None = None  # (oy, ox, residual shift) that bg and prnu were copied at
    # the read-out window's background (DN) and PRNU, contiguous (cache-friendly)
    bg: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    prnu: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    acc: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (h, w) float64 DN
    z: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))  # N(0,1) draws


class _Camera:
    """Per-camera static state: aperture, blur, background, PRNU, noise bank, RNG."""

    def __init__(self, idx: int, name: str, f_number: float, sigma_core: float,
                 profile: SpotProfile | None = None) -> None:
        self.idx = idx
        self.name = name
        self.f_number = f_number
        self.sigma_core = sigma_core
        self.profile = profile if profile is not None else gaussian_profile(sigma_core)
        self.bg: np.ndarray  # (Hp, Wp) float32 clean photo-signal incl. steady distractors
        self.prnu: np.ndarray  # (Hp, Wp) float32
        self.bank: np.ndarray  # (B, Hp, Wp) uint8
        self.jitter: Jitter
        self.fp_cache: dict[tuple[int, int], tuple[tuple, Footprint]] = {}
        self.plan_key: tuple | None = None  # (radius, u, v) of the cached render plan
        self.plan_run = -1  # its pose run (first frame of a run of frames with that key)
        self.plan: list[_GroupPlan] = []

    def footprint(self, s: _Source, box: tuple[int, int, int, int]) -> Footprint:
        """The (cached) footprint of source ``s`` in the canvas ``box``."""
        key = (id(s.tab), box, s.u.tobytes(), s.v.tobytes(), s.glare_sigma)
        hit = self.fp_cache.get(s.slot)
        if hit is not None and hit[0] == key:
            return hit[1]
        x0, y0, x1, y1 = box
        fp = footprint(x0, y0, (y1 - y0, x1 - x0), s.u, s.v, s.tab,
                       s.glare_sigma if s.glare_half else 0.0, s.grid)
        self.fp_cache[s.slot] = (key, fp)
        return fp


class Scene:
    """A simulated stereo recording of the configured transmitter (see module docstring).

    cfg: the configuration (transmitter, camera, sensor, optics, scene, payload).
    level_source: what the LEDs send (default: back-to-back packets per [payload]).
    noise: False renders noise-free frames (PRNU, shot and read noise off), for tests.
    bank_size: noisy background frames per camera.
    rig: a non-ideal stereo rig (e.g. :func:`iscd.calibration.synthetic.nonideal_rig`): the LED
    spots are placed where its cameras image them (:func:`iscd.sim.geometry.project_rig`:
    lens distortion, principal points, focal lengths, rotation R and translation T); spot
    shapes, distractors and the background stay those of the ideal rig (docs/calibration.md).
    None (default): the ideal pinhole rig of ``cfg.camera``.
    compiled: render with the compiled kernels of :mod:`iscd.sim.kernels` (default; call
    :meth:`warm_up` before a real-time clock starts); False: with their numpy references
    (the same frames, see :mod:`iscd.sim.kernels` for the tolerance).

    Frames are always 8-bit (``camera.bit_depth`` is ignored). ``truth()`` holds (F, N)
    float64 arrays: query long runs in chunks. ``truths()`` gives one :class:`Truth` per
    transmitter (0 = the main one, then ``[[scene.transmitters]]`` in order; ``level_source``
    replaces the main one's levels only).
    """

    CHUNK = 512

    def __init__(self, cfg: Config, level_source: LevelSource | None = None, *,
                 noise: bool = True, bank_size: int = 16,
                 rig: StereoCalibration | None = None, compiled: bool = True) -> None:
        self.cfg = cfg
        tx, cam, sc, op = cfg.transmitter, cfg.camera, cfg.scene, cfg.optics
        self.geometry = StereoGeometry.from_config(cam)
        if rig is not None and (rig.image_width, rig.image_height) != (cam.width, cam.height):
            raise ValueError(f"rig is {rig.image_width}x{rig.image_height} px, the camera "
                             f"{cam.width}x{cam.height} px")
        self.rig = rig
        self.width, self.height = cam.width, cam.height
        self.fps = cam.fps
        self.exposure_s = cam.exposure_s
        self.n_leds = tx.n_leds
        self.levels_m = tx.levels
        self.noise = noise
        self.compiled = compiled
        self.seed = sc.seed & 0xFFFFFFFF
        self.source: LevelSource = (level_source if level_source is not None
                                    else PacketSource.from_config(cfg))
        if self.source.n_leds != self.n_leds:
            raise ValueError(f"level source has {self.source.n_leds} LEDs, the transmitter "
                             f"{self.n_leds}")
        rng = np.random.default_rng([self.seed, 0x5CE])
        T = 1.0 / tx.symbol_rate_hz
        phase = sc.led_phase_s if sc.led_phase_s >= 0 else float(rng.uniform(0.0, T))
        self.clock = LedClock(T, tx.pwm_hz, phase, sc.led_drift_ppm)
        self.offsets = led_offsets(tx)
        self.grid = (tx.rows, tx.cols)
        self.txs: list[_Tx] = [_Tx(0, tx, sc, self.source, self.clock, self.offsets,
                                   payload_seed=sc.seed)]
        self.txs += [self._extra_tx(i) for i in range(len(sc.transmitters))]
        self.sensor = SensorModel.from_config(cfg.sensor, 8, noise=noise)
        sm = self.sensor
        self._sensor32 = kernels.sensor_constants(sm.gain_dn_per_e, sm.read_dn, sm.dark_dn,
                                                  sm.max_dn)
        self.vibration = make_vibration(sc, self.seed)
        self.margin = vibration_margin(sc)
        self.subpixel_background = sc.background_motion == "subpixel"
        self.tables = TableCache()
        self.led_radius_fn = lambda z: self.geometry.focal_px * tx.led_diameter_m / (2.0 * z)
        scale = self.exposure_s / REF_EXPOSURE_S
        extra = (PIXEL_VAR, op.right_defocus_px ** 2 + PIXEL_VAR)
        self.cams = [
            _Camera(0, "left", cam.f_number_left, math.sqrt(op.psf_sigma_px ** 2 + PIXEL_VAR),
                    spot_profile(op, extra[0])),
            _Camera(1, "right", cam.f_number_right,
                    math.sqrt(op.psf_sigma_px ** 2 + op.right_defocus_px ** 2 + PIXEL_VAR),
                    spot_profile(op, extra[1])),
        ]
        self.glare = ((1.0, op.glare_sigma_px),) if op.glare_model == "gaussian" else \
            glare_components(op.glare_sigma_px, op.glare_power)
        self.bloom_coef = bloom_coefficients(cfg.sensor.blooming, cfg.sensor.bloom_length_px)
        self.bloom_spill = float(cfg.sensor.blooming)
        self.bloom_cap = float(self.sensor.max_dn)  # full well = the top grey level
        self.bloom_reach = int(self.bloom_coef.size)
        for c in self.cams:
            c.gain = (REF_F_NUMBER / c.f_number) ** 2 * scale  # type: ignore[attr-defined]
            c.jitter = Jitter(sc.jitter_px, self.seed, c.idx)
        self._noise_base = _mix64(self.seed ^ 0x401)
        self.flicker = [d for d in sc.distractors if d.flicker_hz > 0]
        self.flicker_phase = rng.uniform(0, 2 * np.pi, size=len(self.flicker))
        self._build_backgrounds(rng, max(1, bank_size if noise else 1))
        self._chunks: dict[int, dict[str, np.ndarray]] = {}

    def _extra_tx(self, i: int) -> _Tx:
        """Transmitter ``scene.transmitters[i]`` (index i + 1): its config, packets, clock
        (a random phase drawn from its own stream, seeded by (scene.seed, i + 1))."""
        main, sc = self.cfg.transmitter, self.cfg.scene
        ex = sc.transmitters[i]
        txc = ex.transmitter(main, i)
        air = from_config(txc)
        try:
            payload = fixed_payload(PayloadConfig(ex.payload_source, ex.payload_value),
                                    air.payload_bytes)
        except ConfigError as e:
            raise ConfigError(str(e).replace("payload.value",
                                             f"scene.transmitters[{i}].payload_value")) from None
        seed = ex.payload_seed(sc.seed, i)
        T = 1.0 / txc.symbol_rate_hz
        rng = np.random.default_rng([self.seed, 0x5CE, i + 1])
        phase = ex.led_phase_s if ex.led_phase_s >= 0 else float(rng.uniform(0.0, T))
        tsc = dataclasses.replace(sc, distance_m=ex.distance_m, lateral_m=ex.lateral_m,
                                  vertical_m=ex.vertical_m, speed_mps=ex.speed_mps,
                                  lateral_speed_mps=ex.lateral_speed_mps,
                                  led_drift_ppm=ex.led_drift_ppm, led_phase_s=phase,
                                  distractors=[], transmitters=[])
        return _Tx(i + 1, txc, tsc, PacketSource(air, payload, seed=seed),
                   LedClock(T, txc.pwm_hz, phase, ex.led_drift_ppm), led_offsets(txc),
                   ex.start_s, math.inf if ex.stop_s is None else ex.stop_s, seed)

    @property
    def n_transmitters(self) -> int:
        """Transmitters in the scene: 1 (the main one) + len(scene.transmitters)."""
        return len(self.txs)

    # ------------------------------------------------------------------ static parts
    def _distractor_sources(self, c: _Camera, ds: list, gains: np.ndarray | None = None
                            ) -> list[list[_Source]]:
        """Per distractor its source parts (slots (i + 1, part))."""
        out = []
        for i, d in enumerate(ds):
            ul, ur, v = self.geometry.project(d.x_m, d.y_m, d.z_m)
            u = ul if c.idx == 0 else ur
            R = self.geometry.focal_px * d.diameter_m / (2 * d.z_m)
            amp = d.brightness_dn * c.gain * (1.0 if gains is None else gains[i])  # type: ignore[attr-defined]
            parts = self._make_sources(c, np.array([float(u)]), np.array([float(v)]),
                                       np.array([amp]), R)
            for j, src in enumerate(parts):
                src.slot = (i + 1, j)
            out.append(parts)
        return out

    def _shapes(self, c: _Camera, radius_px: float) -> list[_Shape]:
        """Spot table, core and glare scales of a disk of ``radius_px`` in camera ``c``: one
        shape for the Gaussian glare; for the power-law glare, further glare-only parts."""
        op = self.cfg.optics
        g = op.glare_fraction
        tab = self.tables.get(radius_px, c.sigma_core, c.profile)
        shapes = []
        for j, (wj, sj) in enumerate(self.glare):
            gs = math.sqrt(sj ** 2 + radius_px ** 2 / 4.0 + PIXEL_VAR)
            flux = g * math.pi * radius_px ** 2
            shapes.append(_Shape(tab if j == 0 else ZERO_TABLE,
                                 (1.0 - g) * (radius_px / tab.radius_px) ** 2 if j == 0 else 0.0,
                                 flux if wj == 1.0 else wj * flux, gs,
                                 int(math.ceil(3.5 * gs)) if g > 0 else 0))
            if g <= 0:
                break
        return shapes

    def _make_sources(self, c: _Camera, u: np.ndarray, v: np.ndarray, amp: np.ndarray,
                      radius_px: float) -> list[_Source]:
        """The source parts at (u, v) px with light ``amp`` (DN of the resolved disk)."""
        out = []
        for j, sh in enumerate(self._shapes(c, radius_px)):
            out.append(_Source(u, v, np.asarray(amp * sh.core_scale, np.float64), sh.tab,
                               np.asarray(amp * sh.flux_scale, np.float64), sh.glare_sigma,
                               sh.glare_half, slot=(0, j)))
        return out

    def _build_backgrounds(self, rng: np.random.Generator, bank_size: int) -> None:
        sc = self.cfg.scene
        H, W, m = self.height, self.width, self.margin
        Hp, Wp = H + 2 * m, W + 2 * m
        d_bg = float(self.geometry.disparity(sc.background_distance_m))
        bl, br = background_pair(sc.background, (Hp, Wp), sc.background_dn, d_bg, rng,
                                 sc.background_contrast)
        steady = [d for d in sc.distractors if d.flicker_hz <= 0]
        for c, bg in zip(self.cams, (bl, br)):
            bg *= c.gain  # type: ignore[attr-defined]
            canvas_all = Canvas(-m, -m, bg)
            for parts in self._distractor_sources(c, steady):
                _render_into(canvas_all, parts)
            c.bg = bg
            prng = np.random.default_rng([self.seed, 0x9A1, c.idx])
            c.prnu = (self.sensor.prnu_map((Hp, Wp), prng) if self.noise
                      else np.ones((Hp, Wp), np.float32))
            c.bank = np.empty((bank_size, Hp, Wp), np.uint8)
            base = _mix64(self.seed ^ 0xBA4)
            for b in range(bank_size):
                self.sensor.expose(bg.copy(), c.prnu, base + 2 * b + c.idx, c.bank[b])

    # ------------------------------------------------------------------ per-frame state
    def frame_state(self, frames: np.ndarray) -> dict[str, np.ndarray]:
        """Per-frame geometry and on-times (the per-frame part of :meth:`truth`).

        Parameters
        ----------
        frames : ndarray
            (F,) frame indices, >= 0.

        Returns
        -------
        dict of str to ndarray
            ``frames`` (F,); ``t_s`` (F,) exposure starts, s; ``z_m`` (F,) distance at
            mid-exposure, m; ``vib`` (F, 2) rig vibration, px; ``shift_left``, ``shift_right``
            (F, 2) image shifts (vibration + jitter), px; ``u_left``, ``v_left``, ``u_right``,
            ``v_right`` (F, N) LED centres, px; ``on_fraction`` (F, N) on-time / exposure, 0..1.
        """
        f = np.asarray(frames, dtype=np.int64).reshape(-1)
        if f.size and f.min() < 0:
            raise ValueError("frame indices must be >= 0")
        t0 = f / self.fps
        tm = t0 + self.exposure_s / 2
        vib = self.vibration(tm)
        sl = vib + self.cams[0].jitter(f)
        sr = vib + self.cams[1].jitter(f)
        return {"frames": f, "t_s": t0, "vib": vib, "shift_left": sl, "shift_right": sr,
                **self._tx_state(self.txs[0], t0, tm, sl, sr)}

    def _tx_state(self, t: _Tx, t0: np.ndarray, tm: np.ndarray, sl: np.ndarray,
                  sr: np.ndarray) -> dict[str, np.ndarray]:
        """Per-frame state of transmitter ``t`` for exposure starts ``t0`` (F,) s,
        mid-exposures ``tm`` (F,) s and image shifts ``sl``, ``sr`` (F, 2) px: ``z_m`` (F,) m,
        ``u_left``, ``v_left``, ``u_right``, ``v_right`` (F, N) px, ``on_fraction`` (F, N)
        0..1 (the light inside its ``start_s``..``stop_s`` only) and ``present`` (F,) bool
        (the exposure overlaps that interval)."""
        sc = t.scene
        z = distance(tm, sc)
        X = lateral(tm, sc)[:, None] + t.offsets[None, :, 0]
        Y = sc.vertical_m + t.offsets[:, 1]
        if self.rig is None:
            ul, ur, v = self.geometry.project(X, Y[None, :], z[:, None])
            vl = vr = v
        else:
            ul, vl, ur, vr = project_rig(self.rig, X, Y[None, :], z[:, None])
        if t.windowed:
            a = np.clip(t0, t.start_s, t.stop_s)
            b = np.clip(t0 + self.exposure_s, t.start_s, t.stop_s)
            on = on_time_window(a, b, t.clock, t.duty_of) / self.exposure_s
            present = b > a
        else:
            on = on_time(t0, self.exposure_s, t.clock, t.duty_of) / self.exposure_s
            present = np.ones(t0.shape, bool)
        return {"z_m": z, "u_left": ul + sl[:, :1], "v_left": vl + sl[:, 1:],
                "u_right": ur + sr[:, :1], "v_right": vr + sr[:, 1:],
                "on_fraction": np.clip(on, 0.0, 1.0), "present": present}

    def _duty_of(self, k0: int, k1: int) -> np.ndarray:
        """(k1 - k0, N) PWM duties of the main transmitter's symbols k0..k1-1."""
        return self.txs[0].duty_of(k0, k1)

    def distractor_gains(self, frames: np.ndarray | range) -> np.ndarray:
        """(F, D) gain of every distractor (``scene.distractors`` order) on its
        ``brightness_dn`` in each frame's exposure: 1 for a steady one, the exposure mean of
        its sine (0-2) or its square wave's on-fraction (0-1) for a flickering one.

        Parameters
        ----------
        frames : array_like of int or range
            Frame indices, >= 0.

        Returns
        -------
        ndarray of float64
            (F, D) gains.
        """
        f = np.asarray(frames, dtype=np.int64).reshape(-1)
        t0 = f / self.fps
        ds = self.cfg.scene.distractors
        out = np.ones((f.size, len(ds)))
        j = 0
        for i, d in enumerate(ds):
            if d.flicker_hz > 0:
                out[:, i] = flicker_gain(d, t0, self.exposure_s, self.flicker_phase[j])
                j += 1
        return out

    def _chunk(self, n: int) -> tuple[dict[str, np.ndarray], int]:
        c, i = divmod(n, self.CHUNK)
        st = self._chunks.get(c)
        if st is None:
            if len(self._chunks) >= 2:
                self._chunks.pop(next(iter(self._chunks)))
            st = self.frame_state(np.arange(c * self.CHUNK, (c + 1) * self.CHUNK))
            st["radius"] = self.led_radius_fn(st["z_m"])
            tm = st["t_s"] + self.exposure_s / 2
            for t in self.txs[1:]:
                k = t.suffix
                for name, val in self._tx_state(t, st["t_s"], tm, st["shift_left"],
                                                st["shift_right"]).items():
                    st[name + k] = val
                st["radius" + k] = self.geometry.focal_px * t.tx.led_diameter_m / (
                    2.0 * st["z_m" + k])
            for side in ("left", "right"):
                u, v = st["u_" + side], st["v_" + side]
                if len(self.txs) > 1:  # a new pose when any transmitter moves or comes/goes
                    ex = [t.suffix for t in self.txs[1:]]
                    u = np.hstack([u, *[st["u_" + side + k] for k in ex],
                                   *[st["radius" + k][:, None] for k in ex],
                                   *[st["present" + k][:, None].astype(float) for k in ex]])
                    v = np.hstack([v, *[st["v_" + side + k] for k in ex]])
                st["pose_" + side] = _pose_runs(u, v, st["radius"], c * self.CHUNK)
            st["bank"] = _bank_sequence(self.seed, c, self.CHUNK, self.cams[0].bank.shape[0])
            if self.flicker:
                st["flicker"] = np.stack([flicker_gain(d, st["t_s"], self.exposure_s, ph)
                                          for d, ph in zip(self.flicker, self.flicker_phase)], 1)
            self._chunks[c] = st
        return st, i

    # ------------------------------------------------------------------ rendering
    def warm_up(self) -> float:
        """Compile (or load from the cache) the render kernels; returns the seconds taken.
        Call it before a real-time clock starts (the first frame would compile them)."""
        t0 = time.perf_counter()
        if self.compiled:
            kernels.warm()
            if self.bloom_reach:
                kernels.bloom_columns(*kernels.warm_bloom_args())
        return time.perf_counter() - t0

    def render_pair(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``n`` of both cameras as new (H, W) uint8 arrays.

        Parameters
        ----------
        n : int
            Frame index, >= 0.

        Returns
        -------
        left, right : ndarray of uint8
            Each (H, W), DN.
        """
        out_l = np.empty((self.height, self.width), np.uint8)
        out_r = np.empty((self.height, self.width), np.uint8)
        self.render_pair_into(n, out_l, out_r)
        return out_l, out_r

    def render_pair_into(self, n: int, out_l: np.ndarray, out_r: np.ndarray) -> None:
        """Render frame ``n`` (>= 0) of both cameras into ``out_l``/``out_r`` ((H, W) uint8).

        Parameters
        ----------
        n : int
            Frame index, >= 0.
        out_l, out_r : ndarray of uint8
            (H, W) left and right frames, overwritten.
        """
        n = int(n)
        if n < 0:
            raise ValueError(f"frame index must be >= 0, got {n}")
        st, i = self._chunk(n)
        self._render_camera(self.cams[0], n, st, i, out_l)
        self._render_camera(self.cams[1], n, st, i, out_r)

    def render(self, n: int, camera: int, out: np.ndarray) -> None:
        """Render frame ``n`` of one camera (0 = left, 1 = right) into ``out``.

        Parameters
        ----------
        n : int
            Frame index, >= 0.
        camera : int
            0 = left, 1 = right.
        out : ndarray of uint8
            (H, W) frame, overwritten.
        """
        st, i = self._chunk(int(n))
        self._render_camera(self.cams[camera], int(n), st, i, out)

    def _render_camera(self, c: _Camera, n: int, st: dict[str, np.ndarray], i: int,
                       out: np.ndarray) -> None:
        if self.compiled:
            self._render_camera_compiled(c, n, st, i, out)
        else:
            self._render_camera_ref(c, n, st, i, out)

    def _origin(self, st: dict[str, np.ndarray], i: int) -> tuple[int, int]:
        """(oy, ox): padded-array origin of image pixel (0, 0) (whole-pixel vibration).

        The rig's vibration (vx, vy) px moves the whole image, the background as the LEDs
        (whose centres are ``+ vib``): image pixel p shows the padded background at
        p + m - round(vib), so a background feature moves by +round(vib) with the spots.
        (Before 2026-12-04 the origin was m + round(vib): the background moved against
        the spots, twice the relative motion a real rig's pitch gives.)"""
        m = self.margin
        if not m:
            return 0, 0
        vx, vy = st["vib"][i]
        sx = min(max(int(round(vx)), -m), m)
        sy = min(max(int(round(vy)), -m), m)
        return m - sy, m - sx

    def _residual(self, st: dict[str, np.ndarray], i: int) -> tuple[float, float] | None:
        """(ry, rx) px: what :meth:`_origin`'s whole pixels leave of the rig's shift in frame
        row ``i`` (within [-1, 1]: a shift beyond the margin is clamped), when
        ``scene.background_motion`` is ``subpixel``; else None (the background moves by
        whole pixels)."""
        if not self.subpixel_background or not self.margin:
            return None
        oy, ox = self._origin(st, i)
        vx, vy = st["vib"][i]
        m = self.margin
        ry = min(max(float(vy) - (m - oy), -1.0), 1.0)
        rx = min(max(float(vx) - (m - ox), -1.0), 1.0)
        return ry, rx

    def _render_camera_compiled(self, c: _Camera, n: int, st: dict[str, np.ndarray], i: int,
                                out: np.ndarray) -> None:
        """Camera ``c``'s frame ``n`` (chunk state ``st``, row ``i``) into ``out``: the bank
        frame, then every render window through :mod:`iscd.sim.kernels`."""
        oy, ox = self._origin(st, i) if self.margin else (0, 0)
        kernels.copy_frame(out, c.bank[st["bank"][i, c.idx]], oy, ox)
        res = self._residual(st, i)
        if res is not None:
            kernels.add_residual_shift(out, c.bg, c.prnu, oy, ox, res[0], res[1], float(self.sensor.max_dn))
        seed = self._noise_base + (n * 2 + c.idx) * 8
        noise = self.noise
        for gi, g in enumerate(self._plan(c, st, i)):
            if g.empty:
                continue
            if self.bloom_reach:
                self._window_bloom(c, g, st, i, oy, ox, _window_seed(seed, gi), out)
                continue
            for sq in g.head:
                kernels.add_sources(g.acc, sq is g.sets[0], sq.kern, sq.ix, sq.iy,
                                    st[sq.key][i, sq.cols], sq.c_amp, sq.c_core, sq.c_flux,
                                    sq.gy, sq.gxt, sq.grid_q)
            if noise:  # the draws of SensorModel.expose (same seed, same stream)
                cv2.setRNGSeed(_window_seed(seed, gi) & 0x7FFFFFFF)
                cv2.randn(g.z, 0.0, 1.0)
            if g.bg_at != (oy, ox, res):  # contiguous copies of the window's background and PRNU
                h, w = g.z.shape
                g.bg = self._window_background(c, oy + g.Y0, ox + g.X0, h, w, res)
                g.prnu = np.ascontiguousarray(c.prnu[oy + g.Y0:oy + g.Y0 + h,
                                                     ox + g.X0:ox + g.X0 + w])
                g.bg_at = (oy, ox, res)
            sp = g.sets[-1]
            kernels.render_window(out, g.Y0, g.X0, g.acc, g.ay, g.ax, not g.head, sp.kern,
                                  sp.ix, sp.iy, st[sp.key][i, sp.cols], sp.c_amp, sp.c_core,
                                  sp.c_flux, sp.gy, sp.gxt, sp.grid_q, g.bg, g.prnu, 0, 0, g.z,
                                  noise, self._sensor32)

    @staticmethod
    def _window_background(c: _Camera, y: int, x: int, h: int, w: int,
                           res: tuple[float, float] | None) -> np.ndarray:
        """The (h, w) float32 noise-free background of a render window from padded (y, x),
        moved on by the residual shift ``res`` (None: as it is)."""
        if res is None:
            return np.ascontiguousarray(c.bg[y:y + h, x:x + w])
        return kernels.shifted_window(c.bg, y, x, h, w, res[0], res[1])

    def _window_bloom(self, c: _Camera, g: _GroupPlan, st: dict[str, np.ndarray], i: int,
                      oy: int, ox: int, seed: int, out: np.ndarray) -> None:
        """A render window with blooming (not fused: every set into the whole canvas, then
        :func:`kernels.bloom_columns`, then :func:`kernels.expose_window`)."""
        for sq in g.sets:
            kernels.add_sources(g.acc, sq is g.sets[0], sq.kern, sq.ix, sq.iy,
                                st[sq.key][i, sq.cols], sq.c_amp, sq.c_core, sq.c_flux,
                                sq.gy, sq.gxt, sq.grid_q)
        kernels.bloom_columns(g.acc, self.bloom_cap, self.bloom_spill, self.bloom_coef)
        if self.noise:
            cv2.setRNGSeed(seed & 0x7FFFFFFF)
            cv2.randn(g.z, 0.0, 1.0)
        h, w = g.z.shape
        bg = self._window_background(c, oy + g.Y0, ox + g.X0, h, w, self._residual(st, i))
        prnu = np.ascontiguousarray(c.prnu[oy + g.Y0:oy + g.Y0 + h, ox + g.X0:ox + g.X0 + w])
        kernels.expose_window(out, g.Y0, g.X0, g.acc, g.ay, g.ax, bg, prnu, 0, 0, g.z,
                              self.noise, self._sensor32)

    def _plan(self, c: _Camera, st: dict[str, np.ndarray], i: int) -> list[_GroupPlan]:
        """The render windows of camera ``c`` in frame row ``i`` (cached while the LEDs keep
        their positions and size: within a chunk by the pose runs, across chunks by value)."""
        pre = "left" if c.idx == 0 else "right"
        run = int(st["pose_" + pre][i])
        if run == c.plan_run:
            return c.plan
        poses = self._poses(c, st, i)
        key = tuple((t.index, r, u.tobytes(), v.tobytes()) for t, u, v, r in poses)
        if c.plan_key != key:
            c.plan = self._build_plan(c, poses)
            c.plan_key = key
        c.plan_run = run
        return c.plan

    def _poses(self, c: _Camera, st: dict[str, np.ndarray], i: int
               ) -> list[tuple[_Tx, np.ndarray, np.ndarray, float]]:
        """(transmitter, u, v, radius) in camera ``c`` at frame row ``i`` of every
        transmitter in view (u, v: (N,) px; radius px), the main one first."""
        pre = "left" if c.idx == 0 else "right"
        out = []
        for t in self.txs:
            k = t.suffix
            if t.index and not st["present" + k][i]:
                continue
            out.append((t, st["u_" + pre + k][i], st["v_" + pre + k][i],
                        float(st["radius" + k][i])))
        return out

    def _build_plan(self, c: _Camera, poses: list[tuple[_Tx, np.ndarray, np.ndarray, float]]
                    ) -> list[_GroupPlan]:
        """Group the sources (LED arrays, flickering distractors) into windows as
        :meth:`_render_camera_ref` does and precompute their footprints."""
        info = {}
        sources = []
        for t, u, v, radius in poses:
            one = np.ones(u.size)
            for j, sh in enumerate(self._shapes(c, radius)):
                led = _Source(u, v, one, sh.tab, one, sh.glare_sigma, sh.glare_half, t.grid,
                              slot=(-t.index, j))
                info[id(led)] = ("on_fraction" + t.suffix, slice(None),
                                 t.tx.radiance_dn * c.gain, sh)  # type: ignore[attr-defined]
                sources.append(led)
        for j, (d, parts) in enumerate(zip(self.flicker, self._distractor_sources(
                c, self.flicker, np.ones(len(self.flicker))))):
            R = self.geometry.focal_px * d.diameter_m / (2 * d.z_m)
            for s, ssh in zip(parts, self._shapes(c, R)):
                info[id(s)] = ("flicker", slice(j, j + 1), d.brightness_dn * c.gain,  # type: ignore[attr-defined]
                               ssh)
                sources.append(s)
        plans = []
        for group in _merge_groups(sources, self.bloom_reach):
            box = _group_box(group, self.bloom_reach)
            x0, y0, x1, y1 = box
            clip = (max(x0, 0), max(y0, 0), min(x1, self.width), min(y1, self.height))
            g = _GroupPlan(box, clip, empty=clip[0] >= clip[2] or clip[1] >= clip[3],
                           acc=np.zeros((y1 - y0, x1 - x0)),
                           z=np.zeros((max(clip[3] - clip[1], 0), max(clip[2] - clip[0], 0)),
                                      np.float32))
            for s in group:
                key, cols, c_amp, ssh = info[id(s)]
                g.sets.append(_set_plan(c.footprint(s, box), key, cols, c_amp, ssh))
            g.head = tuple(g.sets[:-1])
            g.X0, g.Y0 = clip[0], clip[1]
            g.ay, g.ax = clip[1] - y0, clip[0] - x0
            plans.append(g)
        return plans

    def _render_camera_ref(self, c: _Camera, n: int, st: dict[str, np.ndarray], i: int,
                           out: np.ndarray) -> None:
        """The numpy reference of :meth:`_render_camera_compiled`."""
        H, W, m = self.height, self.width, self.margin
        oy, ox = self._origin(st, i)
        bank = c.bank
        k = st["bank"][i, c.idx]
        if m:
            np.copyto(out, bank[k, oy:oy + H, ox:ox + W])
        else:
            np.copyto(out, bank[k])
        res = self._residual(st, i)
        if res is not None:
            kernels.add_residual_shift_ref(out, c.bg, c.prnu, oy, ox, res[0], res[1], float(self.sensor.max_dn))
        sources: list[_Source] = []
        for t, u, v, radius in self._poses(c, st, i):
            amp = st["on_fraction" + t.suffix][i] * (t.tx.radiance_dn * c.gain)  # type: ignore[attr-defined]
            parts = self._make_sources(c, u, v, amp, radius)
            for j, led in enumerate(parts):
                led.grid = t.grid
                led.slot = (-t.index, j)
            sources += parts
        if self.flicker:
            for parts in self._distractor_sources(c, self.flicker, st["flicker"][i]):
                sources += parts
        seed = self._noise_base + (n * 2 + c.idx) * 8
        for gi, group in enumerate(_merge_groups(sources, self.bloom_reach)):
            box = _group_box(group, self.bloom_reach)
            x0, y0, x1, y1 = box
            X0, Y0, X1, Y1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
            if X0 >= X1 or Y0 >= Y1:
                continue
            acc = None
            for s in group:
                acc = render(c.footprint(s, box), s.amp, s.glare_flux if s.glare_half else None,
                             out=acc)
            if self.bloom_reach:
                kernels.bloom_columns_ref(acc, self.bloom_cap, self.bloom_spill,
                                          self.bloom_coef)
            sig = np.add(acc[Y0 - y0:Y1 - y0, X0 - x0:X1 - x0],
                         self._window_background(c, oy + Y0, ox + X0, Y1 - Y0, X1 - X0, res), dtype=np.float32)
            self.sensor.expose(sig, c.prnu[oy + Y0:oy + Y1, ox + X0:ox + X1],
                               _window_seed(seed, gi) if self.noise else None,
                               out[Y0:Y1, X0:X1])

    # ------------------------------------------------------------------ truth
    def truth(self, frames: np.ndarray | range) -> Truth:
        """Ground truth of the main transmitter for ``frames`` (ascending frame indices),
        see :class:`Truth` (:meth:`truths` for every transmitter).

        Parameters
        ----------
        frames : array_like of int or range
            Frame indices, >= 0 (sorted and deduplicated; at least one).

        Returns
        -------
        Truth
        """
        f = _frames(frames)
        return self._truth(self.txs[0], f, self.frame_state(f))

    def truths(self, frames: np.ndarray | range) -> list[Truth]:
        """Ground truth of every transmitter for ``frames``: index 0 the main one (equal to
        :meth:`truth`), then ``scene.transmitters`` in config order. Each has its own
        ``levels``, packets and ``payloads``, LED centres (px, per camera), ``z_m`` (m),
        ``on_fraction`` and ``present`` (F,) (the exposure overlaps its ``start_s``..
        ``stop_s``; all True for the main one); ``meta["tx_index"]`` is the index.

        Parameters
        ----------
        frames : array_like of int or range
            Frame indices, >= 0 (sorted and deduplicated; at least one).

        Returns
        -------
        list of Truth
            ``n_transmitters`` truths.
        """
        f = _frames(frames)
        st = self.frame_state(f)
        out = [self._truth(self.txs[0], f, st)]
        tm = st["t_s"] + self.exposure_s / 2
        for t in self.txs[1:]:
            s2 = self._tx_state(t, st["t_s"], tm, st["shift_left"], st["shift_right"])
            s2.update({k: st[k] for k in ("t_s", "shift_left", "shift_right")})
            out.append(self._truth(t, f, s2))
        return out

    def _truth(self, t: _Tx, f: np.ndarray, st: dict[str, np.ndarray]) -> Truth:
        """The :class:`Truth` of transmitter ``t`` from its per-frame state ``st``."""
        clk = t.clock
        T = clk.symbol_period_s
        ua = clk.led_time(st["t_s"])
        ub = clk.led_time(st["t_s"] + self.exposure_s)
        ka, kb = np.floor(ua / T).astype(np.int64), np.floor(ub / T).astype(np.int64)
        # a window ending exactly on a boundary lies inside the earlier symbol
        kb = np.where(ub == kb * T, kb - 1, kb)
        kmid = np.floor(clk.led_time(st["t_s"] + self.exposure_s / 2) / T).astype(np.int64)
        k0, k1 = int(ka.min()), int(kb.max()) + 1
        sym = np.arange(k0, k1)
        src = t.source
        levels = src.levels(k0, k1)
        p_idx = np.zeros(0, np.int64)
        payloads: list[bytes] = []
        if isinstance(src, PacketSource):
            P = src.period
            lo, hi = max(k0, 0) // P, max(k1 - 1, 0) // P
            if k1 > 0:
                p_idx = np.arange(lo, hi + 1, dtype=np.int64)
                payloads = [src.payload(int(p)) for p in p_idx]
            p_start = p_idx * P
        else:
            p_start = np.zeros(0, np.int64)
        return Truth(
            frames=f, t_s=st["t_s"], z_m=st["z_m"], disparity_px=self.geometry.disparity(st["z_m"]),
            u_left=st["u_left"], v_left=st["v_left"], u_right=st["u_right"], v_right=st["v_right"],
            shift_left=st["shift_left"], shift_right=st["shift_right"],
            on_fraction=st["on_fraction"], symbol_mid=kmid, clean=ka == kb,
            symbol_index=sym, symbol_t_s=clk.symbol_start_cam(sym), levels=levels,
            packet_index=p_idx, packet_start_symbol=p_start,
            packet_t_s=clk.symbol_start_cam(p_start) if p_start.size else np.zeros(0),
            payloads=payloads, meta=self.meta() if t.index == 0 else self.tx_meta(t.index),
            present=st["present"])

    def meta(self) -> dict:
        """Scalars of the scene and its main transmitter (JSON-ready), as stored in
        truth.json."""
        tx, cam = self.cfg.transmitter, self.cfg.camera
        ds = []
        for d in self.cfg.scene.distractors:
            ul, ur, v = self.geometry.project(d.x_m, d.y_m, d.z_m)
            ds.append({"u_left": float(ul), "u_right": float(ur), "v": float(v),
                       "diameter_px": self.geometry.focal_px * d.diameter_m / d.z_m,
                       "flicker_hz": d.flicker_hz, "waveform": d.waveform, "duty": d.duty})
        return {
            "focal_px": self.geometry.focal_px, "baseline_m": cam.baseline_m,
            "cx": self.geometry.cx, "cy": self.geometry.cy, "width": self.width,
            "height": self.height, "fps": self.fps, "exposure_s": self.exposure_s,
            "levels": tx.levels, "n_leds": tx.n_leds, "rows": tx.rows, "cols": tx.cols,
            "symbol_rate_hz": tx.symbol_rate_hz, "pwm_hz": tx.pwm_hz,
            "led_phase_s": self.clock.phase_s, "led_drift_ppm": self.clock.drift_ppm,
            "seed": self.cfg.scene.seed, "noise": self.noise,
            **_air_meta(self.source),
            "tx_index": 0, "n_transmitters": len(self.txs),
            "distractors": ds, "config": to_dict(self.cfg),
        }

    def tx_meta(self, index: int) -> dict:
        """Scalars of transmitter ``index`` (0 = the main one, :meth:`meta`; k >= 1:
        ``scene.transmitters[k - 1]``), JSON-ready: the scene's :meth:`meta` with the
        transmitter's own keys (levels, n_leds, rows, cols, pitch_m, led_diameter_m,
        radiance_dn, led_phase_s (s), led_drift_ppm, packet_symbols, payload_bytes,
        air_interface, payload_seed, distance_m, lateral_m, vertical_m (m), speed_mps,
        start_s, stop_s (s; None = never leaves), tx_index).

        Parameters
        ----------
        index : int
            Transmitter index, 0 .. n_transmitters - 1.

        Returns
        -------
        dict
        """
        out = self.meta()
        if index == 0:
            return out
        t = self.txs[index]
        tx = t.tx
        out.pop("fec", None)
        out.update({
            "tx_index": index, "levels": tx.levels, "n_leds": tx.n_leds, "rows": tx.rows,
            "cols": tx.cols, "pitch_m": tx.pitch_m, "led_diameter_m": tx.led_diameter_m,
            "radiance_dn": tx.radiance_dn, "led_phase_s": t.clock.phase_s,
            "led_drift_ppm": t.clock.drift_ppm, "payload_seed": t.payload_seed,
            "distance_m": t.scene.distance_m, "lateral_m": t.scene.lateral_m,
            "vertical_m": t.scene.vertical_m, "speed_mps": t.scene.speed_mps,
            "start_s": t.start_s, "stop_s": t.stop_s if math.isfinite(t.stop_s) else None,
            **_air_meta(t.source)})
        return out


def spot_profile(op: OpticsConfig, extra_var_px2: float) -> SpotProfile:
    """The spot model of ``optics`` in a camera whose PSF gets ``extra_var_px2`` px^2 of
    Gaussian blur on top (pixel area 1/12, right-camera defocus): the Gaussian or Moffat
    PSF of width ``psf_sigma_px`` and the diffuser's nested disks.

    Parameters
    ----------
    op : OpticsConfig
        ``psf_model``, ``psf_sigma_px`` (px), ``psf_beta`` and ``diffuser_falloff``.
    extra_var_px2 : float
        Extra Gaussian variance, px^2.

    Returns
    -------
    SpotProfile
    """
    disks = diffuser_disks(op.diffuser_falloff)
    if op.psf_model == "moffat":
        psf = moffat_components(op.psf_sigma_px, op.psf_beta, extra_var_px2)
    else:
        psf = ((1.0, math.sqrt(op.psf_sigma_px ** 2 + extra_var_px2)),)
    return SpotProfile(psf, disks)


def _frames(frames: np.ndarray | range) -> np.ndarray:
    """Sorted unique int64 frame indices (at least one)."""
    f = np.asarray(frames, dtype=np.int64).reshape(-1)
    if f.size == 0:
        raise ValueError("truth of no frames")
    return np.unique(f)


def _air_meta(source: object) -> dict:
    """packet_symbols, payload_bytes, air_interface (and fec for v2) of a level source."""
    air = getattr(source, "air", None)
    known = isinstance(air, (AirInterface, AirInterfaceV2))
    return {
        "packet_symbols": air.period_symbols if known else None,  # type: ignore[union-attr]
        "payload_bytes": air.payload_bytes if known else None,  # type: ignore[union-attr]
        "air_interface": "v2" if isinstance(air, AirInterfaceV2) else "v1" if known else None,
        **({"fec": air.fec} if isinstance(air, AirInterfaceV2) else {}),
    }


def _window_seed(frame_seed: int, gi: int) -> int:
    """Noise seed of render window ``gi`` of a camera frame whose seeds start at
    ``frame_seed`` (which steps by 8 per frame and camera): ``frame_seed + gi`` for the first
    8 windows (the seeds of before), a mixed one from the 9th on (so that it does not reuse
    the next camera's or frame's first windows' noise)."""
    return frame_seed + gi if gi < 8 else _mix64(frame_seed ^ (gi << 48))


def _mix64(x: int) -> int:
    """splitmix64 finalizer: a well-mixed 64-bit value of ``x``."""
    x = (x + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return x ^ (x >> 31)


def _bank_sequence(seed: int, chunk: int, n: int, bank_size: int) -> np.ndarray:
    """(n, 2) bank frame per frame and camera: random, never the same twice in a row."""
    if bank_size == 1:
        return np.zeros((n, 2), np.int64)
    rng = np.random.default_rng([seed, 0xBA5, chunk])
    steps = rng.integers(1, bank_size, size=(n, 2))
    return np.cumsum(steps, axis=0) % bank_size


def _pose_runs(u: np.ndarray, v: np.ndarray, radius: np.ndarray, first: int) -> np.ndarray:
    """(F,) per frame the first frame (``first`` + row) of its run of consecutive frames with
    the same LED positions ``u``, ``v`` (F, N) px and radius (F,) px."""
    same = np.r_[False, (np.all(u[1:] == u[:-1], axis=1) & np.all(v[1:] == v[:-1], axis=1)
                         & (radius[1:] == radius[:-1]))]
    rows = np.arange(u.shape[0])
    return np.maximum.accumulate(np.where(same, 0, rows)) + first


def _set_plan(fp: Footprint, key: str, cols: slice, c_amp: float, sh: _Shape) -> _SetPlan:
    """A :class:`_SetPlan` of footprint ``fp`` (its kernel, window origins and glare)."""
    n = fp.kern.shape[0]
    k = int(round(math.sqrt(fp.kern.shape[1])))
    H, W = fp.shape
    base = fp.flat[::k * k]
    gy = fp.gy if fp.gy is not None else np.zeros((H, 0))
    gxt = (np.ascontiguousarray(fp.gx.T) if fp.gx is not None else np.zeros((0, W)))
    grid_q = fp.grid[1] if (fp.grid is not None and fp.gy is not None) else 0
    return _SetPlan(np.ascontiguousarray(fp.kern.reshape(n, k, k)), base % W, base // W,
                    key, cols, float(c_amp), float(sh.core_scale), float(sh.flux_scale),
                    np.ascontiguousarray(gy), gxt, int(grid_q))


def _group_box(group: list[_Source], pad: int = 0) -> tuple[int, int, int, int]:
    """The canvas box of a source group; ``pad`` px (the blooming reach) at least."""
    boxes = [source_box(s.u, s.v, max(s.tab.half, s.glare_half, pad)) for s in group]
    return (min(b[0] for b in boxes), min(b[1] for b in boxes),
            max(b[2] for b in boxes), max(b[3] for b in boxes))


def _merge_groups(sources: list[_Source], pad: int = 0) -> list[list[_Source]]:
    """Group sources whose boxes overlap, so that each group is rendered in one canvas."""
    groups = [[s] for s in sources]
    if len(groups) == 1:
        return groups
    merged = True
    while merged:
        merged = False
        for a in range(len(groups)):
            for b in range(a + 1, len(groups)):
                A, B = _group_box(groups[a], pad), _group_box(groups[b], pad)
                if A[0] < B[2] and B[0] < A[2] and A[1] < B[3] and B[1] < A[3]:
                    groups[a] += groups.pop(b)
                    merged = True
                    break
            if merged:
                break
    return groups


def _render_into(canvas: Canvas, group: list[_Source]) -> None:
    """Add sources into an existing canvas, clipping at its border."""
    x0, y0, x1, y1 = _group_box(group)
    acc = None
    for s in group:
        fp = footprint(x0, y0, (y1 - y0, x1 - x0), s.u, s.v, s.tab,
                       s.glare_sigma if s.glare_half else 0.0, s.grid)
        acc = render(fp, s.amp, s.glare_flux if s.glare_half else None, out=acc)
    assert acc is not None
    H, W = canvas.data.shape
    X0, Y0 = max(x0, canvas.x0), max(y0, canvas.y0)
    X1, Y1 = min(x1, canvas.x0 + W), min(y1, canvas.y0 + H)
    if X0 < X1 and Y0 < Y1:
        canvas.data[Y0 - canvas.y0:Y1 - canvas.y0, X0 - canvas.x0:X1 - canvas.x0] += \
            acc[Y0 - y0:Y1 - y0, X0 - x0:X1 - x0]
