"""The stereo pair of a config, by camera URL: list the cameras, build and open the rig.

The cameras of ``[rig]`` are camera URLs (:mod:`iscd.drivers.urls`, as pyserial's
``serial_for_url``): ``url = "mock://default"`` for a rig that is one device (the
simulated rig, :mod:`iscd.drivers.mock`), or ``left`` / ``right`` =
``genicam://SERIAL?cti=PATH`` (:mod:`iscd.drivers.genicam`, harvesters + a GenTL producer) or
``v4l2:///dev/videoN`` (:mod:`iscd.drivers.v4l2`, linuxpy). The old form (``backend`` with
serial numbers or device paths) is mapped to those URLs by :mod:`iscd.core.config`. Each
backend registers itself under its scheme; hardware libraries are imported only when a
camera is opened or listed.

With ``[board] emulate = true`` the mock rig's transmitter is an emulated LED board
(:class:`iscd.drivers.board.emulator.PtyEmulator`, served on a pty linked at ``[board] port``
for as long as the cameras exist): ``iscd tx`` loads it, and the simulated LEDs show what
it sends (:class:`BoardOnSceneClock`). The cameras are built inside the daemon's
acquisition process, so the board lives there too.
"""

from __future__ import annotations

import logging
import math
import threading
import weakref
from typing import Any

import numpy as np

from iscd.drivers import urls
from iscd.drivers.base import Camera, CameraError, CameraSettings, Roi

log = logging.getLogger(__name__)

_PIXEL_FORMATS = {8: "Mono8", 10: "Mono10", 12: "Mono12", 16: "Mono16"}


def list_cameras(backend: str | None = None, producer: str | None = None) -> list[dict[str, Any]]:
    """The cameras attached, as dicts with at least ``backend`` and ``url`` (the camera URL
    to put in ``[rig]``); ``backend`` None = every hardware backend (genicam and v4l2).
    ``producer``: GenTL producer for genicam (``.cti`` path or ``"simulated"``; None =
    ``GENICAM_GENTL64_PATH``).

    Raises :class:`CameraError` for an unknown backend or a producer path that does not
    exist; a backend whose library is missing contributes no cameras (logged).
    """
    if backend is not None and backend not in urls.schemes():
        raise CameraError(f"unknown camera backend {backend!r} (known: {', '.join(urls.schemes())})")
    return urls.discover(backend, producer=producer)


def settings_from_config(cfg: Any, side: str) -> CameraSettings:
    """CameraSettings of one side of the rig from ``[camera]``: the left camera is the
    trigger master, the right one its slave (hardware backends)."""
    c = cfg.camera
    return CameraSettings(fps=c.fps, exposure_s=c.exposure_s, gain_db=0.0,
                          roi=Roi(0, 0, c.width, c.height),
                          trigger="master" if side == "left" else "slave",
                          pixel_format=_PIXEL_FORMATS.get(c.bit_depth, "Mono8"))


def check_stereo_config(cfg: Any) -> str | None:
    """Check what :func:`make_stereo` needs from ``cfg`` without building anything (so a
    parent process can refuse a bad config before spawning the acquisition): raises
    :class:`iscd.core.config.ConfigError` (one line, naming the key). Returns the emulated
    board's link path (``[board] emulate``), else None."""
    from iscd.drivers.board.settings import emulated_board_link
    from iscd.core.config import ConfigError

    rig = cfg.rig
    link = emulated_board_link(cfg)  # ConfigError for a board that cannot be emulated
    if rig.stereo_url:
        if rig.scheme == "mock" and getattr(cfg.transmitter, "shape_auto", False):
            raise ConfigError('transmitter.rows, transmitter.cols: "auto" is for a receiver of real cameras '
                              "or a replay; the mock rig renders the transmitter and needs its numbers")
        return link
    b = urls.backend(rig.scheme)
    left, right = rig.camera_urls
    for side, url in (("left", left), ("right", right)):
        if not url:
            raise ConfigError(f"rig.{side}: set the {side} camera's {b.what} for backend {rig.scheme!r} "
                              f"(or its URL, {b.form}; 'iscd devices' lists them)")
    if left == right:
        raise ConfigError(f"rig.right: the same camera as rig.left ({rig.left!r})")
    return link


def make_stereo(cfg: Any) -> tuple[Camera, Camera]:
    """The (left, right) cameras of ``cfg.rig``, constructed but not opened, by the backend
    of their URL (:func:`iscd.drivers.urls.rig_for_url`); with ``[board] emulate``, the mock
    rig's emulated board is served from now on."""
    rig = cfg.rig
    link = check_stereo_config(cfg)
    if rig.stereo_url:
        if link is not None:
            return _mock_rig_with_board(cfg, link)
        return urls.rig_for_url(rig.stereo_url, cfg=cfg, buffer_frames=rig.buffer_frames)
    return urls.rig_for_url(*rig.camera_urls)


def open_stereo(cfg: Any) -> tuple[Camera, Camera]:
    """The (left, right) cameras of ``cfg.rig``, opened and configured from ``[camera]``
    (left = trigger master, right = slave), not started: start the slave first.

    On failure, whatever was opened is closed again and :class:`CameraError` (or
    :class:`iscd.core.config.ConfigError` for a bad ``[rig]``) propagates.
    """
    left, right = make_stereo(cfg)
    hardware = urls.backend(cfg.rig.scheme).hardware
    opened: list[Camera] = []
    try:
        for cam, side in ((left, "left"), (right, "right")):
            cam.open()
            opened.append(cam)
            accepted = cam.configure(settings_from_config(cfg, side))
            if hardware:
                wanted = settings_from_config(cfg, side)
                if accepted.trigger != wanted.trigger:
                    log.warning("%s camera: trigger %r requested, %r accepted: the pair is not "
                                "hardware-synchronized", side, wanted.trigger, accepted.trigger)
                if abs(accepted.fps - wanted.fps) > 1e-6 * wanted.fps:
                    log.warning("%s camera: %g fps requested, %g accepted", side, wanted.fps,
                                accepted.fps)
    except BaseException:
        for cam in opened:
            try:
                cam.close()
            except Exception as e:  # noqa: BLE001
                log.debug("close after failed open: %s", e)
        raise
    return left, right


# ---------------------------------------------------------------------- emulated LED board
class BoardOnSceneClock:
    """An emulated board's LEDs as the mock rig's level source (``iscd.sim.LevelSource``).

    The board counts symbols from its START on wall-clock time (``time.monotonic``, the
    clock of the mock rig's triggers); the scene counts symbols on its LED clock (phase
    and drift of ``[scene]``). Board symbol 0 is put on the first scene symbol that
    starts at or after START, so scene symbol k shows board symbol ``k - k_start``:

        t_cam(START) = START - t0,   k_start = ceil(t_led(t_cam(START)) / T)     [s]

    with t0 the rig's trigger 0 and t_led the scene's LED clock (exposure.LedClock).
    Before START, while stopped and while the board holds nothing, every LED is level 1.

    The board must drive the scene's transmitter: rows, cols, M and the symbol rate of
    its SET_CONFIG must equal ``[transmitter]``; otherwise the LEDs stay dark and a
    warning is logged (load it with ``iscd tx --config`` of the daemon's config).
    The scene asks for the levels of half a second of frames at a time (``Scene.CHUNK``
    frames), so a START or STOP shows in the frames up to that much later.
    """

    def __init__(self, board: Any, tx: Any) -> None:
        from iscd.drivers.board.protocol import BoardConfig

        self.board = board
        self.n_leds = int(tx.rows * tx.cols)
        self.expected = BoardConfig.from_transmitter(tx)
        self.rig: Any = None  # set by attach(): the MockRig whose scene shows the LEDs
        self.emulator: Any = None  # the PtyEmulator serving the board, if any
        self._lock = threading.Lock()
        self._warned: object = None

    def attach(self, rig: Any) -> None:
        self.rig = rig

    def start_symbol(self, start_s: float) -> int:
        """Scene symbol index of board symbol 0 for a START at ``start_s`` (monotonic s)."""
        clock = self.rig.scene.clock
        t_cam = start_s - self.rig.trigger_time_ns(0) * 1e-9
        return math.ceil(float(clock.led_time(t_cam)) / clock.symbol_period_s - 1e-9)

    def _mismatch(self, cfg: Any) -> str | None:
        e = self.expected
        got = (cfg.rows, cfg.cols, cfg.levels, cfg.symbol_rate_mhz)
        want = (e.rows, e.cols, e.levels, e.symbol_rate_mhz)
        if got == want:
            return None
        return (f"the emulated board is configured for {cfg.rows}x{cfg.cols} LEDs, M = {cfg.levels}, "
                f"{cfg.symbol_rate_hz:g} symbols/s but the simulated transmitter is "
                f"{e.rows}x{e.cols}, M = {e.levels}, {e.symbol_rate_hz:g} symbols/s: LEDs dark "
                f"(load the board with 'iscd tx --config' of the daemon's config)")

    def levels(self, k0: int, k1: int) -> np.ndarray:
        """(k1 - k0, N) uint8 levels of scene symbols k0 .. k1-1."""
        n = max(0, int(k1) - int(k0))
        dark = np.ones((n, self.n_leds), dtype=np.uint8)
        if self.rig is None:
            return dark
        for _ in range(3):  # a STOP/START between the reads: read again
            start = self.board.start_time
            cfg = self.board.config
            if start is None or cfg is None:
                return dark
            why = self._mismatch(cfg)
            if why is not None:
                with self._lock:
                    if self._warned is not cfg:
                        self._warned = cfg
                        log.warning("%s", why)
                return dark
            try:
                lv = self.board.levels(int(k0) - self.start_symbol(start), n, self.n_leds)
            except ValueError:  # reconfigured between the reads
                continue
            if self.board.start_time == start:
                return lv
        return dark


def _mock_rig_with_board(cfg: Any, link: str) -> tuple[Camera, Camera]:
    """The mock rig's (left, right) cameras whose transmitter is an emulated board served
    on a pty at ``link``; the board is closed (link removed) when the rig is collected or
    at interpreter exit."""
    from iscd.drivers.board.emulator import PtyEmulator

    emu = PtyEmulator(link=link)
    source = BoardOnSceneClock(emu.board, cfg.transmitter)
    source.emulator = emu
    left, right = urls.rig_for_url(cfg.rig.stereo_url, cfg=cfg, level_source=source,
                                   buffer_frames=cfg.rig.buffer_frames)
    rig = left.rig  # type: ignore[attr-defined]
    source.attach(rig)
    try:
        emu.start()
    except OSError as e:
        emu.close()
        raise CameraError(f"cannot serve the emulated LED board at {link}: {e.strerror or e}") from None
    weakref.finalize(rig, emu.close)
    log.info("emulated LED board on %s (%s): load it with 'iscd tx --port %s'", link, emu.path, link)
    return left, right
