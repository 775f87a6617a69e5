"""Configuration: TOML file -> typed, validated dataclasses.

Every section is a frozen dataclass; every key has a default (the dissertation's
chapter 4 setup, SPEC section 2, unless noted), so an empty file is a valid config.
Errors name the key and the problem, e.g.
``scene.distance_m: expected a number > 0, got -3``; unknown keys are errors too (a typo
must not silently fall back to a default).

Units are in the key names: ``_m`` metres, ``_s`` seconds, ``_hz`` hertz, ``_px`` pixels,
``_dn`` digital numbers (8-bit grey levels), ``_e`` electrons.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, TypeVar, get_args, get_origin


class ConfigError(ValueError):
    """A config file or value is invalid. ``str(err)`` is one line naming key and problem."""


def _check(lo: float | None = None, hi: float | None = None, lo_open: bool = False,
           choices: tuple[Any, ...] | None = None, doc: str = "", auto: bool = False) -> dict[str, Any]:
    return {"lo": lo, "hi": hi, "lo_open": lo_open, "choices": choices, "doc": doc, "auto": auto}


AUTO = 0
"""An integer key that takes ``"auto"`` (``[transmitter] rows``, ``cols``) holds this for it."""


def _f(default: Any, **kw: Any) -> Any:
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda d=default: type(d)(d), metadata=_check(**kw))
    return field(default=default, metadata=_check(**kw))


FEC_NAMES = ("none", "rs255_239", "rs255_223", "rs255_191")
"""v2's code modes (:data:`iscd.core.airinterface_v2.FEC_MODES`; a test keeps them equal)."""


@dataclass(frozen=True)
class TransmitterConfig:
    """The LED transmitter and its air interface (SPEC section 3, table 4.1)."""

    rows: int = _f(8, lo=0, hi=64, auto=True,
                   doc='LED array rows; "auto" (or 0, with cols): the receiver infers the array\'s shape '
                       "from the lit spots (docs/air-interface.md); the simulator and the board need numbers")
    cols: int = _f(8, lo=0, hi=64, auto=True, doc='LED array columns; "auto" (or 0) as rows')
    pitch_m: float = _f(0.06, lo=0, lo_open=True, doc="centre-to-centre LED spacing, m")
    levels: int = _f(8, choices=(2, 4, 8, 16, 32), doc="M, PWM levels (2 = OOK)")
    symbol_rate_hz: float = _f(500.0, lo=1, doc="f_sym, symbols per second")
    pwm_hz: float = _f(50_000.0, lo=1, doc="f_pwm, PWM carrier frequency, Hz")
    training_symbols: int = _f(40, lo=0, doc="K, training symbol times per packet")
    data_symbols: int = _f(600, lo=1, doc="F, data symbol times per packet")
    idle_symbols: int = _f(0, lo=0, doc="G, idle (level 1) symbol times between packets")
    led_diameter_m: float = _f(0.03, lo=0, lo_open=True,
                               doc="apparent emitting diameter of one LED (with its glow), m")
    radiance_dn: float = _f(600.0, lo=0, lo_open=True,
                            doc="grey level of a fully-on, resolved LED at f/4 and 1 ms")
    air_interface: str = _f("v1", choices=("v1", "v2"),
                            doc="v1 (SPEC section 3) or v2: PHY header + Reed-Solomon FEC "
                                "(docs/air-interface.md)")
    fec: str = _f("rs255_223", choices=FEC_NAMES,
                  doc="v2 only: code mode (none; rs255_239 high rate, t=8; rs255_223, t=16; "
                      "rs255_191 strong, t=32)")
    payload_len: int = _f(0, lo=0, hi=0xFFFFFF,
                          doc="v2 only: payload bytes per packet; 0 = as many as data_symbols hold "
                              "(else F is the fewest symbol times that hold it)")

    def __post_init__(self) -> None:
        if (self.rows == AUTO) != (self.cols == AUTO):
            raise ConfigError('transmitter.rows, transmitter.cols: "auto" (0) for both or for neither, '
                              f"got {self.rows} x {self.cols}")
        if self.air_interface != "v2" or self.shape_auto:
            return
        for key in ("training_symbols", "data_symbols", "idle_symbols"):
            if getattr(self, key) > 0xFFFF:
                raise ConfigError(f"transmitter.{key}: v2's PHY header holds at most 65535, "
                                  f"got {getattr(self, key)}")
        from iscd.core.airinterface_v2 import from_config  # (numba: only for v2)
        from iscd.core.airinterface import AirInterfaceError

        try:
            from_config(self)
        except AirInterfaceError as e:
            key = "payload_len" if self.payload_len else "data_symbols"
            raise ConfigError(f"transmitter.{key}: {e}") from None

    @property
    def shape_auto(self) -> bool:
        """rows = cols = "auto": the receiver infers the array's shape (n_leds is then 0)."""
        return self.rows == AUTO

    @property
    def n_leds(self) -> int:
        return self.rows * self.cols

    @property
    def bits_per_symbol(self) -> int:
        return int(math.log2(self.levels))


@dataclass(frozen=True)
class CameraConfig:
    """The stereo camera pair (Photron IDP-Express R2000-F in the dissertation)."""

    fps: float = _f(1000.0, lo=0, lo_open=True, doc="frames per second")
    exposure_s: float = _f(1e-3, lo=0, lo_open=True, doc="exposure time, s")
    width: int = _f(512, lo=16, hi=8192, doc="image width, px")
    height: int = _f(512, lo=16, hi=8192, doc="image height, px")
    focal_length_m: float = _f(0.035, lo=0, lo_open=True, doc="f, m")
    pixel_pitch_m: float = _f(10e-6, lo=0, lo_open=True, doc="rho, m")
    baseline_m: float = _f(0.25, lo=0, lo_open=True, doc="b, m (0.6 in chapter 3)")
    f_number_left: float = _f(4.0, lo=0.5, doc="left aperture N")
    f_number_right: float = _f(8.0, lo=0.5, doc="right aperture N (4, 8 or 16 in chapter 4)")
    bit_depth: int = _f(8, choices=(8, 10, 12, 16), doc="bits per pixel")

    @property
    def focal_px(self) -> float:
        """f/rho in px (3500 for the reference rig)."""
        return self.focal_length_m / self.pixel_pitch_m

    def __post_init__(self) -> None:
        if self.exposure_s > 1.0 / self.fps + 1e-12:
            raise ConfigError(
                f"camera.exposure_s: {self.exposure_s} s is longer than the frame period "
                f"1/fps = {1.0 / self.fps:g} s")


@dataclass(frozen=True)
class SensorConfig:
    """Sensor noise model (see docs/simulator.md)."""

    full_well_e: float = _f(20_000.0, lo=1, doc="electrons at the top grey level")
    read_noise_e: float = _f(20.0, lo=0, doc="read noise RMS, electrons")
    prnu: float = _f(0.01, lo=0, hi=0.5, doc="pixel response non-uniformity, relative RMS")
    dark_dn: float = _f(2.0, lo=0, doc="black level, grey levels")
    blooming: float = _f(0.0, lo=0, hi=1, doc="share of the charge above full well (255 DN) "
                         "of a saturated pixel that spills along its column (0 = off)")
    bloom_length_px: float = _f(2.0, lo=0, lo_open=True, hi=16,
                                doc="decay length of the blooming spill along the column, px")


@dataclass(frozen=True)
class OpticsConfig:
    """Lens blur and glare (see docs/simulator.md)."""

    psf_sigma_px: float = _f(0.6, lo=0, doc="Gaussian PSF sigma, px")
    right_defocus_px: float = _f(0.0, lo=0, doc="extra blur sigma of the right camera, px")
    glare_fraction: float = _f(0.04, lo=0, hi=1, doc="share of a spot's light in the glare halo")
    glare_sigma_px: float = _f(2.5, lo=0, lo_open=True,
                               doc="glare halo sigma (gaussian) or core radius r0 (power), px")
    psf_model: str = _f("gaussian", choices=("gaussian", "moffat"),
                        doc="lens PSF shape: gaussian, or moffat (same FWHM, heavier wings)")
    psf_beta: float = _f(2.5, lo=1.2, hi=20, doc="moffat PSF exponent beta (smaller = heavier wings)")
    glare_model: str = _f("gaussian", choices=("gaussian", "power"),
                          doc="glare halo shape: gaussian, or power law (1 + r^2/r0^2)^-gamma")
    glare_power: float = _f(2.0, lo=1.2, hi=10, doc="power-law glare exponent gamma")
    diffuser_falloff: float = _f(0.0, lo=0, hi=0.9, doc="LED disk brightness drop centre to "
                                 "edge, b = 1 - k (rho/R)^2 (0 = uniform disk)")


@dataclass(frozen=True)
class DistractorConfig:
    """A light that is not a transmitter (street lamp, reflection, PWM-dimmed tail light):
    steady, flickering (sine) or blinking (square wave); it never carries data."""

    x_m: float = _f(2.0, doc="lateral position, m (right positive)")
    y_m: float = _f(-1.0, doc="vertical position, m (down positive)")
    z_m: float = _f(40.0, lo=0, lo_open=True, doc="distance, m")
    diameter_m: float = _f(0.2, lo=0, lo_open=True, doc="diameter, m")
    brightness_dn: float = _f(200.0, lo=0, doc="grey level at f/4 (sine: the mean; square: "
                              "while on)")
    flicker_hz: float = _f(0.0, lo=0, doc="0 = steady; 100 = mains-driven lamp; 100-2000 = a "
                           "PWM-dimmed LED lamp (waveform = square), Hz")
    waveform: str = _f("sine", choices=("sine", "square"),
                       doc="flicker_hz > 0: sine, 1 - cos(2 pi f t + phi) (mean brightness_dn), "
                           "or square, on for the first duty of each period 1/f (PWM dimming)")
    duty: float = _f(0.5, lo=0, hi=1, doc="square only: on-fraction of each period, 0..1")


@dataclass(frozen=True)
class ExtraTransmitterConfig:
    """A further transmitter of the simulated scene (``[[scene.transmitters]]``), beside the
    main one (``[transmitter]`` + ``[scene]``). Keys left out (None) take the main
    transmitter's value (``[transmitter]``); it runs on its own LED clock and sends its own
    packets (docs/simulator.md, "Several transmitters and blinkers")."""

    rows: int = _f(1, lo=1, hi=64, doc="LED array rows")
    cols: int = _f(1, lo=1, hi=64, doc="LED array columns")
    levels: int | None = _f(None, choices=(2, 4, 8, 16, 32),
                            doc="M, PWM levels (2 = OOK); default: the main transmitter's")
    training_symbols: int | None = _f(None, lo=0, doc="K; default: the main transmitter's")
    data_symbols: int | None = _f(None, lo=1, doc="F; default: the main transmitter's")
    idle_symbols: int | None = _f(None, lo=0, doc="G; default: the main transmitter's")
    air_interface: str | None = _f(None, choices=("v1", "v2"),
                                   doc="v1 or v2; default: the main transmitter's")
    fec: str | None = _f(None, choices=FEC_NAMES, doc="v2 only: code mode; default: the main "
                         "transmitter's")
    payload_len: int | None = _f(None, lo=0, hi=0xFFFFFF,
                                 doc="v2 only: payload bytes; default: the main transmitter's")
    pitch_m: float | None = _f(None, lo=0, lo_open=True,
                               doc="LED spacing, m; default: the main transmitter's")
    led_diameter_m: float | None = _f(None, lo=0, lo_open=True,
                                      doc="LED diameter, m; default: the main transmitter's")
    radiance_dn: float | None = _f(None, lo=0, lo_open=True,
                                   doc="grey level of a fully-on LED at f/4 and 1 ms; default: "
                                       "the main transmitter's")
    lateral_m: float = _f(0.0, doc="array centre, lateral offset from the left camera axis, m "
                          "(right positive)")
    vertical_m: float = _f(0.0, doc="array centre, vertical offset, m (down positive)")
    distance_m: float = _f(30.0, lo=0, lo_open=True, doc="initial distance Z, m")
    speed_mps: float = _f(0.0, doc="closing speed, m/s (stops at scene.min_distance_m)")
    lateral_speed_mps: float = _f(0.0, doc="lateral speed relative to the rig, m/s")
    led_drift_ppm: float = _f(0.0, doc="its LED clock's rate error against the cameras, ppm")
    led_phase_s: float = _f(-1.0, doc="its LED symbol clock offset at t = 0, s; < 0 = random "
                            "(seeded by scene.seed and the entry's index)")
    seed: int | None = _f(None, doc="seed of its random payloads; default: scene.seed + "
                          "4096 (index + 1), index = 0 for the first entry")
    payload_source: str = _f("random", choices=("random", "text", "hex", "file"),
                             doc="random payloads per packet (seeded by seed), or a fixed one")
    payload_value: str = _f("", doc="the text, hex string or file path of a fixed payload")
    start_s: float = _f(0.0, lo=0, doc="it is in view (lit) from this camera time on, s")
    stop_s: float | None = _f(None, lo=0, lo_open=True,
                              doc="... until this camera time, s; default: never leaves")

    @property
    def n_leds(self) -> int:
        return self.rows * self.cols

    def payload_seed(self, scene_seed: int, index: int) -> int:
        """The seed of its random payloads: ``seed``, or ``scene_seed + 4096 (index + 1)``.

        Parameters
        ----------
        scene_seed : int
            ``scene.seed``.
        index : int
            Its index in ``scene.transmitters`` (0-based).

        Returns
        -------
        int
        """
        return int(self.seed) if self.seed is not None else int(scene_seed) + 4096 * (index + 1)

    def transmitter(self, main: "TransmitterConfig", index: int) -> "TransmitterConfig":
        """Its effective :class:`TransmitterConfig`: the main transmitter's with this entry's
        keys (symbol rate and PWM carrier are the main transmitter's).

        Parameters
        ----------
        main : TransmitterConfig
            ``[transmitter]``.
        index : int
            Its index in ``scene.transmitters`` (for error messages).

        Raises
        ------
        ConfigError
            Naming the key, e.g. ``scene.transmitters[1].data_symbols: ...``.
        """
        keys = {k: getattr(self, k) for k in (
            "levels", "training_symbols", "data_symbols", "idle_symbols", "air_interface", "fec",
            "payload_len", "pitch_m", "led_diameter_m", "radiance_dn")}
        keys = {k: v for k, v in keys.items() if v is not None}
        try:
            return dataclasses.replace(main, rows=self.rows, cols=self.cols, **keys)
        except ConfigError as e:
            msg = str(e)
            pre = f"scene.transmitters[{index}]."
            raise ConfigError(msg.replace("transmitter.", pre) if msg.startswith("transmitter.")
                              else pre.rstrip(".") + ": " + msg) from None


@dataclass(frozen=True)
class SceneConfig:
    """Where the transmitter is and how the rig moves."""

    distance_m: float = _f(30.0, lo=0, lo_open=True, doc="initial distance Z, m")
    lateral_m: float = _f(0.0, doc="transmitter centre, lateral offset from the left camera axis, m")
    vertical_m: float = _f(0.0, doc="transmitter centre, vertical offset (down positive), m")
    speed_mps: float = _f(0.0, doc="closing speed, m/s (11.1 = 40 km/h)")
    lateral_speed_mps: float = _f(0.0, doc="lateral speed of the transmitter relative to the rig "
                                  "(right positive), m/s")
    min_distance_m: float = _f(2.0, lo=0, lo_open=True, doc="the approach stops here, m")
    vibration_px: float = _f(0.0, lo=0, doc="rig vibration, RMS image shift common to both cameras, px")
    vibration_model: str = _f("smooth", choices=("smooth", "bumps", "engine"),
                              doc="rig vibration: smooth random (1-40 Hz), road bumps (damped "
                              "pitch ringing), engine (20-40 Hz tone + harmonic)")
    bump_rate_hz: float = _f(2.5, lo=0, lo_open=True, hi=50, doc="bumps: mean bumps per second")
    bump_freq_hz: float = _f(10.0, lo=0.5, hi=100, doc="bumps: mean ringing frequency after a bump, Hz")
    bump_damping: float = _f(0.15, lo=0.02, hi=0.9, doc="bumps: damping ratio of the ringing")
    engine_hz: float = _f(30.0, lo=1, hi=200, doc="engine: mean fundamental frequency, Hz")
    engine_wander_hz: float = _f(3.0, lo=0, doc="engine: peak slow wander of the fundamental, Hz")
    engine_harmonic: float = _f(0.4, lo=0, hi=2, doc="engine: 2nd harmonic amplitude / fundamental")
    background_motion: str = _f("whole", choices=("whole", "subpixel"),
                                doc="how vibration moves the background: by the rounded shift "
                                "(whole pixels, as before) or by the exact one (the residual "
                                "bilinear, as a real rig's image moves)")
    jitter_px: float = _f(0.0, lo=0, doc="air jitter, independent RMS shift per camera, px")
    led_drift_ppm: float = _f(100.0, doc="LED clock rate error against the cameras, ppm")
    led_phase_s: float = _f(-1.0, doc="LED symbol clock offset at t = 0, s; < 0 = random")
    background: str = _f("texture", choices=("texture", "flat", "none"), doc="daylight background")
    background_dn: float = _f(40.0, lo=0, doc="mean background grey level at f/4")
    background_contrast: float = _f(0.35, lo=0, hi=2, doc="texture: relative RMS contrast")
    background_distance_m: float = _f(150.0, lo=0, lo_open=True, doc="background distance, m")
    distractors: list[DistractorConfig] = _f([], doc="lights that are not transmitters: steady, "
                                             "flickering (sine) or blinking (square)")
    transmitters: list[ExtraTransmitterConfig] = _f(
        [], doc="further transmitters beside the main one ([[scene.transmitters]])")
    seed: int = _f(1, doc="random seed of the scene (noise, texture, phases, payloads)")
    randomized_seed: int = _f(-1, doc="informational: the iscd.sim.randomize seed that drew "
                              "this config (-1 = not randomized)")

    def __post_init__(self) -> None:
        if self.engine_wander_hz >= self.engine_hz:
            raise ConfigError(
                f"scene.engine_wander_hz: {self.engine_wander_hz:g} Hz must be below "
                f"scene.engine_hz = {self.engine_hz:g} Hz (the frequency must stay > 0)")
        for i, t in enumerate(self.transmitters):
            if t.stop_s is not None and t.stop_s <= t.start_s:
                raise ConfigError(f"scene.transmitters[{i}].stop_s: {t.stop_s:g} s must be after "
                                  f"start_s = {t.start_s:g} s")


@dataclass(frozen=True)
class PayloadConfig:
    """What the (simulated) transmitter sends."""

    source: str = _f("random", choices=("random", "text", "hex", "file"),
                     doc="random bytes per packet (seeded), or a fixed payload")
    value: str = _f("", doc="the text, hex string or file path for the fixed sources")


@dataclass(frozen=True)
class FaultConfig:
    """An injected fault of the mock rig."""

    kind: str = _f("drop", choices=("drop", "duplicate", "stall", "id_offset", "vanish"),
                   doc="what goes wrong")
    camera: str = _f("left", choices=("left", "right"), doc="which camera")
    frame: int = _f(0, lo=0, doc="trigger index where it happens")
    duration_ms: float = _f(0.0, lo=0, doc="stall/vanish duration, ms")
    offset: int = _f(1, doc="id_offset: added to frame ids from then on")


@dataclass(frozen=True)
class RigConfig:
    """Which cameras feed the daemon: camera URLs (docs/cameras.md; 'iscd devices' lists them)."""

    backend: str = _f("", doc="old form: the backend whose cameras left/right name by serial number, user "
                      "id or device path (a camera URL scheme); '' = the scheme of the URLs (the mock "
                      "rig without any); filled in from the URLs")
    url: str = _f("", doc="a stereo rig that is one device: mock://default (the simulated rig showing this "
                  "config's scene; ?seed=N, ?noise=false); '' = the cameras of left and right")
    left: str = _f("", doc="left camera (trigger master) URL: genicam://SERIAL?cti=PATH or "
                   "v4l2:///dev/videoN; old form: serial number / user id (genicam) or device path (v4l2)")
    right: str = _f("", doc="right camera (trigger slave), as left")
    producer: str = _f("", doc="GenTL producer .cti path of genicam cameras whose URL has no ?cti= "
                       "(default: GENICAM_GENTL64_PATH)")
    pace: bool = _f(True, doc="mock: deliver frames at fps in real time (False: as fast as the decoder takes them; the daemon then drops nothing for want of time, however busy the machine; injected faults still lose their frames)")
    buffer_frames: int = _f(256, lo=1, hi=4096, doc="mock: frames a camera queues for a late reader "
                            "(genicam, v4l2: the ?buffers=N of their URL)")
    faults: list[FaultConfig] = _f([], doc="mock: injected faults")

    def _resolved(self) -> "RigURLs":
        """The URLs of this table resolved by the camera registry's resolver (once; the
        table is frozen)."""
        got = self.__dict__.get("_urls")
        if got is None:
            got = resolve_rig(self)
            object.__setattr__(self, "_urls", got)
        return got

    def __post_init__(self) -> None:
        if _RIG_RESOLVER:  # checked at load when the camera registry is there (the CLI, the daemon)
            self._resolved()

    @property
    def scheme(self) -> str:
        """The camera backend of the rig, from its URLs (or ``backend``; ``mock`` without any)."""
        return self._resolved().scheme

    @property
    def stereo_url(self) -> str:
        """The URL of the rig when it is one device (``mock://default``), else ''."""
        return self._resolved().stereo_url

    @property
    def camera_urls(self) -> tuple[str, str]:
        """The (left, right) camera URLs ('' where unset) when the rig is two cameras, with
        the old form mapped (``left = "0"`` of backend genicam -> ``genicam://0``) and
        ``producer`` as the ``cti`` of genicam URLs that lack it; ('', '') for a stereo URL."""
        return self._resolved().camera_urls


@dataclass(frozen=True)
class RigURLs:
    """``[rig]`` resolved against the camera registry: ``stereo_url`` (a rig that is one
    device, else ''), ``camera_urls`` (left, right; ('', '') for a stereo URL) and
    ``scheme`` (the backend)."""

    stereo_url: str
    camera_urls: tuple[str, str]
    scheme: str


_RIG_RESOLVER: list[Callable[[RigConfig], RigURLs]] = []
"""The resolver of ``[rig]`` camera URLs, set by the layer that knows the camera backends
(:mod:`iscd.drivers.urls` registers one when it is imported); this module knows none."""


def set_rig_resolver(fn: Callable[[RigConfig], RigURLs]) -> None:
    """Install the function that resolves (and checks: ConfigError naming the ``rig.`` key)
    a ``[rig]`` table's camera URLs. :mod:`iscd.drivers.urls` calls it when imported."""
    _RIG_RESOLVER[:] = [fn]


def resolve_rig(rig: RigConfig) -> RigURLs:
    """``[rig]`` resolved by the installed resolver (:func:`set_rig_resolver`).

    Raises
    ------
    ConfigError
        A bad camera URL or key, naming it (``rig.left: ...``).
    RuntimeError
        No resolver installed (nothing imported :mod:`iscd.drivers.urls`): a programming error.
    """
    if not _RIG_RESOLVER:
        raise RuntimeError("[rig] camera URLs: no resolver installed (import iscd.drivers.urls)")
    return _RIG_RESOLVER[0](rig)


@dataclass(frozen=True)
class Config:
    """The whole configuration file."""

    transmitter: TransmitterConfig = field(default_factory=TransmitterConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    optics: OpticsConfig = field(default_factory=OpticsConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    payload: PayloadConfig = field(default_factory=PayloadConfig)
    rig: RigConfig = field(default_factory=RigConfig)
    owned: dict[str, Any] = field(default_factory=dict)
    """The raw tables of the sections this module does not define (each owned by the module
    that uses it, e.g. ``[daemon]``); read them with :func:`section` (or :meth:`table`)."""

    def replace(self, **sections: Any) -> "Config":
        return _sourced(dataclasses.replace(self, **sections), self.source)

    @property
    def source(self) -> str:
        """The file this config was loaded from ('' if none): the owned tables' errors
        (:func:`section`, :func:`check_sections`) name it, as :func:`load` names it for
        the tables defined here. Not a field: not in :func:`to_dict` nor compared."""
        return str(self.__dict__.get("_source", ""))

    def table(self, name: str) -> dict[str, Any]:
        """A copy of the raw table ``[name]`` (one of :data:`SECTION_NAMES`; empty if the
        file leaves it out). Read validated settings with :func:`section` instead."""
        if name not in SECTION_NAMES:
            raise KeyError(f"[{name}] is not an owned config section")
        return dict(self.owned.get(name, {}))

    def with_keys(self, name: str, **keys: Any) -> "Config":
        """A copy with ``keys`` set in table ``[name]`` over what it holds (validated when
        its owner reads it with :func:`section`)."""
        return _sourced(dataclasses.replace(self, owned={**self.owned, name: {**self.table(name), **keys}}),
                        self.source)


def _sourced(cfg: Config, source: str) -> Config:
    """``cfg`` marked as loaded from ``source`` (see :attr:`Config.source`)."""
    if source:
        object.__setattr__(cfg, "_source", source)
    return cfg


def named_error(cfg: Config, e: ConfigError) -> ConfigError:
    """``e`` with the file ``cfg`` was loaded from in front (once), as :func:`load` says it."""
    msg, src = str(e), cfg.source
    return ConfigError(msg if not src or msg.startswith(src) else f"{src}: {msg}")


SECTION_NAMES: tuple[str, ...] = ("daemon", "acquisition", "tracking", "receiver", "ranging", "output",
                                   "rerun", "board", "record")
"""The tables a config file may hold beside the ones defined here. Each is owned (its keys,
defaults, documentation and validation) by the module that uses it, which declares its
dataclass with :func:`config_section`; this module knows their names only, never their
modules (it sits below all of them). Until its owner is imported a table is kept raw in
:attr:`Config.owned`."""

_OWNERS: dict[str, type] = {}
_S = TypeVar("_S")


def config_section(name: str) -> Callable[[type], type]:
    """Class decorator: the dataclass owns table ``[name]`` of the config file.

    The owner module declares it where the settings are used, e.g.::

        @config_section("daemon")
        @dataclass(frozen=True)
        class DaemonSettings: ...

    and reads it with :func:`section` (``section(cfg, DaemonSettings)``).

    Raises
    ------
    ValueError
        When ``name`` is not in :data:`SECTION_NAMES`, or another class owns it already
        (a programming error, not a user's).
    """
    if name not in SECTION_NAMES:
        raise ValueError(f"[{name}] is not a config section (SECTION_NAMES: {', '.join(SECTION_NAMES)})")

    def register(cls: type) -> type:
        if not dataclasses.is_dataclass(cls):
            raise ValueError(f"{cls.__qualname__}: a config section must be a dataclass")
        old = _OWNERS.get(name)
        if old is not None and (old.__module__, old.__qualname__) != (cls.__module__, cls.__qualname__):
            raise ValueError(f"[{name}] is owned by {old.__module__}.{old.__qualname__} already")
        _OWNERS[name] = cls
        cls.__config_section__ = name  # type: ignore[attr-defined]
        return cls

    return register


def section_owners() -> dict[str, type]:
    """The sections whose owner modules are imported: ``name -> dataclass``, in
    :data:`SECTION_NAMES` order (``iscd.cli.sections`` imports every owner)."""
    return {n: _OWNERS[n] for n in SECTION_NAMES if n in _OWNERS}


def section(cfg: "Config", cls: type[_S]) -> _S:
    """The validated table that ``cls`` owns (see :func:`config_section`), every default
    filled in where the file leaves a key (or the whole table) out.

    Raises
    ------
    ConfigError
        A key unknown or of the wrong type; the message names it (``daemon.ring_ms: ...``).
    """
    name = getattr(cls, "__config_section__", None)
    if name is None or _OWNERS.get(name) is not cls:
        raise TypeError(f"{cls.__qualname__} is not declared with @config_section")
    try:
        return build_section(cls, cfg.table(name), name)
    except ConfigError as e:
        raise named_error(cfg, e) from None


def check_sections(cfg: "Config") -> None:
    """Validate every owned table of ``cfg`` with its owner, and ``[rig]`` with the camera
    registry's resolver (ConfigError naming the key).

    The owners must be imported (``import iscd.cli.sections`` does it); a table whose owner
    is not is a programming error here (RuntimeError), never silently passed."""
    try:
        resolve_rig(cfg.rig)
        for name, table in cfg.owned.items():
            cls = _OWNERS.get(name)
            if cls is None:
                raise RuntimeError(f"[{name}]: its owner module is not imported (import iscd.cli.sections)")
            build_section(cls, dict(table), name)
    except ConfigError as e:
        raise named_error(cfg, e) from None


def _type_name(tp: Any) -> str:
    return {int: "an integer", float: "a number", str: "a string", bool: "true or false"}.get(
        tp, getattr(tp, "__name__", str(tp)))


def _convert(key: str, tp: Any, value: Any, meta: dict[str, Any]) -> Any:
    origin = get_origin(tp)
    if origin in (list,):
        (item_tp,) = get_args(tp)
        if not isinstance(value, list):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        return [_convert(f"{key}[{i}]", item_tp, v, {}) for i, v in enumerate(value)]
    if origin in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _convert(key, args[0], value, meta)
    if origin is Literal:
        if value not in get_args(tp):
            raise ConfigError(f"{key}: expected one of {list(get_args(tp))}, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a table, got {value!r}")
        return build_section(tp, value, key)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        out: Any = value
    elif tp is int and meta.get("auto") and value == "auto":
        return AUTO
    elif tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        out = value
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        out = float(value)
        if not math.isfinite(out):
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
    elif tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        out = value
    else:  # pragma: no cover - programming error
        raise TypeError(f"{key}: unsupported config type {tp}")
    choices = meta.get("choices")
    if choices is not None and out not in choices:
        raise ConfigError(f"{key}: expected one of {list(choices)}, got {value!r}")
    lo, hi = meta.get("lo"), meta.get("hi")
    if lo is not None:
        bad = out <= lo if meta.get("lo_open") else out < lo
        if bad:
            op = ">" if meta.get("lo_open") else ">="
            raise ConfigError(f"{key}: expected {_type_name(tp)} {op} {lo:g}, got {value!r}")
    if hi is not None and out > hi:
        raise ConfigError(f"{key}: expected {_type_name(tp)} <= {hi:g}, got {value!r}")
    return out


def build_section(cls: type, table: dict[str, Any], prefix: str) -> Any:
    """Build dataclass ``cls`` from a TOML table, validating every key.

    ``prefix`` is the dotted path used in error messages (``"scene"``).
    """
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for k, v in table.items():
        key = f"{prefix}.{k}" if prefix else k
        if k not in fields or k == "owned":
            known = ", ".join(sorted(n for n in fields if n != "owned"))
            raise ConfigError(f"{key}: unknown key (known keys: {known})")
        kwargs[k] = _convert(key, hints[k], v, dict(fields[k].metadata))
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{prefix}: {e}") from None


def config_from_dict(data: dict[str, Any], *, receiver: bool = False) -> Config:
    """Build a :class:`Config` from parsed TOML (``tomllib.loads`` output).

    ``receiver``: the config of a receiver alone (``iscd replay``): without a
    ``[transmitter]`` table the array's shape is left to the receiver (rows = cols =
    "auto") and v1 packets are read with the SPEC's defaults (M = 8, K = 40, F = 600);
    otherwise (the simulator, the mock rig, the board also read the table) a missing table
    is the default 8x8 transmitter."""
    sections: dict[str, Any] = {}
    owned: dict[str, Any] = {}
    fields = {f.name: f for f in dataclasses.fields(Config) if f.name != "owned"}
    hints = typing.get_type_hints(Config)
    for name, table in data.items():
        if name in fields:
            if not isinstance(table, dict):
                raise ConfigError(f"{name}: expected a table [{name}], got {table!r}")
            sections[name] = build_section(hints[name], table, name)
        elif name in SECTION_NAMES:
            if not isinstance(table, dict):
                raise ConfigError(f"{name}: expected a table [{name}], got {table!r}")
            owned[name] = table
        else:
            known = ", ".join(sorted([*fields, *SECTION_NAMES]))
            raise ConfigError(f"{name}: unknown section (known sections: {known})")
    if receiver and "transmitter" not in sections:
        sections["transmitter"] = TransmitterConfig(rows=AUTO, cols=AUTO)
    cfg = Config(**sections, owned=owned)
    _cross_check(cfg)
    return cfg


def _cross_check(cfg: Config) -> None:
    t, c = cfg.transmitter, cfg.camera
    if t.pwm_hz < t.symbol_rate_hz:
        raise ConfigError(
            f"transmitter.pwm_hz: the PWM carrier ({t.pwm_hz:g} Hz) must be at least the "
            f"symbol rate ({t.symbol_rate_hz:g} Hz)")
    if c.fps < 2 * t.symbol_rate_hz * 0.999:
        raise ConfigError(
            f"camera.fps: {c.fps:g} frames/s is below 2 frames per symbol "
            f"(transmitter.symbol_rate_hz = {t.symbol_rate_hz:g}); symbols could not be decoded")
    if not t.shape_auto:
        for i, ex in enumerate(cfg.scene.transmitters):
            ex.transmitter(t, i)  # ConfigError naming scene.transmitters[i].key


def loads(text: str, source: str = "<string>", *, receiver: bool = False) -> Config:
    """Parse TOML text into a :class:`Config` (``receiver``: :func:`config_from_dict`)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{source}: not valid TOML: {e}") from None
    except RecursionError:  # arrays/tables nested thousands deep
        raise ConfigError(f"{source}: not valid TOML: nested too deeply") from None
    return config_from_dict(data, receiver=receiver)


def load(path: str | Path | None = None, *, receiver: bool = False) -> Config:
    """Load a config file; ``None`` gives the embedded default (the mock rig).
    ``receiver``: the config of a receiver alone (:func:`config_from_dict`)."""
    if path is None:
        return default_config()
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{p}: is a folder, not a config file") from None
    except OSError as e:
        raise ConfigError(f"{p}: cannot read config file: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{p}: cannot read config file: {e}") from None
    try:
        return _sourced(loads(text, str(p), receiver=receiver), str(p))
    except ConfigError as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith(str(p)) else f"{p}: {msg}") from None


def default_config() -> Config:
    """The embedded default: the mock rig with an 8x8 PWM-8 transmitter at 30 m."""
    from importlib.resources import files

    text = files("iscd").joinpath("data/default.toml").read_text(encoding="utf-8")
    return loads(text, "<embedded default config>")


def to_dict(obj: Any) -> Any:
    """A config (or section) as plain dicts/lists, e.g. for recording metadata."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, list):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


def describe() -> str:
    """Every section and key with default and documentation (for ``--help`` and docs)."""
    lines: list[str] = []
    hints = typing.get_type_hints(Config)
    classes = [(f.name, hints[f.name]) for f in dataclasses.fields(Config) if f.name != "owned"]
    classes += list(section_owners().items())
    for name, cls in classes:
        lines.append(f"[{name}]  {(cls.__doc__ or '').strip().splitlines()[0]}")
        for sf in dataclasses.fields(cls):
            if not sf.init:
                continue
            default = sf.default if sf.default is not dataclasses.MISSING else sf.default_factory()  # type: ignore[misc]
            lines.append(f"  {sf.name} = {default!r}  # {sf.metadata.get('doc', '')}")
    return "\n".join(lines)
