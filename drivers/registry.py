"""Pick a camera backend by name: list its cameras, build the stereo pair of a config.

Backends (``[rig] backend``): ``mock`` (simulated rig, :mod:`drivers.mock`), ``genicam``
(:mod:`drivers.genicam`, harvesters + a GenTL producer) and ``v4l2``
(:mod:`drivers.v4l2`, linuxpy). Each is imported only when used.
"""

from __future__ import annotations

import logging
from typing import Any

from drivers.base import Camera, CameraError, CameraSettings, Roi

log = logging.getLogger(__name__)

BACKENDS = ("mock", "genicam", "v4l2")
HARDWARE_BACKENDS = ("genicam", "v4l2")
_PIXEL_FORMATS = {8: "Mono8", 10: "Mono10", 12: "Mono12", 16: "Mono16"}


def list_cameras(backend: str | None = None, producer: str | None = None) -> list[dict[str, Any]]:
    """The cameras attached, as dicts with at least ``backend``; ``backend`` None = the
    hardware backends (genicam and v4l2). ``producer``: GenTL producer for genicam
    (``.cti`` path or ``"simulated"``; None = ``GENICAM_GENTL64_PATH``).

    Raises :class:`CameraError` for an unknown backend or a producer path that does
    not exist; a backend whose library is missing contributes no cameras (logged).
    """
    if backend is not None and backend not in BACKENDS:
        raise CameraError(f"unknown camera backend {backend!r} (known: {', '.join(BACKENDS)})")
    out: list[dict[str, Any]] = []
    for name in ([backend] if backend else HARDWARE_BACKENDS):
        if name == "genicam":
            from drivers import genicam

            for cti in genicam.find_producers(producer):  # raises for a missing .cti
                try:
                    out.extend(genicam.list_devices(cti))
                except CameraError as e:
                    log.warning("genicam: %s: %s", cti, e)
        elif name == "v4l2":
            from drivers import v4l2

            try:
                out.extend(v4l2.list_devices())
            except CameraError as e:
                log.warning("v4l2: %s", e)
        elif name == "mock":
            out.extend({"backend": "mock", "name": side} for side in ("left", "right"))
    return out


def settings_from_config(cfg: Any, side: str) -> CameraSettings:
    """CameraSettings of one side of the rig from ``[camera]``: the left camera is the
    trigger master, the right one its slave (hardware backends)."""
    c = cfg.camera
    return CameraSettings(fps=c.fps, exposure_s=c.exposure_s, gain_db=0.0,
                          roi=Roi(0, 0, c.width, c.height),
                          trigger="master" if side == "left" else "slave",
                          pixel_format=_PIXEL_FORMATS.get(c.bit_depth, "Mono8"))


def make_stereo(cfg: Any) -> tuple[Camera, Camera]:
    """The (left, right) cameras of ``cfg.rig``, constructed but not opened."""
    from iscd.config import ConfigError

    rig = cfg.rig
    if rig.backend == "mock":
        from drivers.mock import MockRig  # written alongside; imported only when used

        made = MockRig.from_config(cfg)
        if isinstance(made, tuple):
            return made  # type: ignore[return-value]
        return made.left, made.right
    for side in ("left", "right"):
        if not getattr(rig, side):
            what = "serial number or user id" if rig.backend == "genicam" else "device path (/dev/videoN)"
            raise ConfigError(f"rig.{side}: set the {side} camera's {what} for backend {rig.backend!r}")
    if rig.left == rig.right:
        raise ConfigError(f"rig.right: the same camera as rig.left ({rig.left!r})")
    if rig.backend == "genicam":
        from drivers.genicam import GenICamCamera

        producer = rig.producer or None
        return (GenICamCamera(device=rig.left, producer=producer, name="left"),
                GenICamCamera(device=rig.right, producer=producer, name="right"))
    if rig.backend == "v4l2":
        from drivers.v4l2 import V4L2Camera

        return V4L2Camera(rig.left, name="left"), V4L2Camera(rig.right, name="right")
    raise ConfigError(f"rig.backend: unknown camera backend {rig.backend!r}")


def open_stereo(cfg: Any) -> tuple[Camera, Camera]:
    """The (left, right) cameras of ``cfg.rig``, opened and configured from ``[camera]``
    (left = trigger master, right = slave), not started: start the slave first.

    On failure, whatever was opened is closed again and :class:`CameraError` (or
    :class:`iscd.config.ConfigError` for a bad ``[rig]``) propagates.
    """
    left, right = make_stereo(cfg)
    opened: list[Camera] = []
    try:
        for cam, side in ((left, "left"), (right, "right")):
            cam.open()
            opened.append(cam)
            accepted = cam.configure(settings_from_config(cfg, side))
            if cfg.rig.backend in HARDWARE_BACKENDS:
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
