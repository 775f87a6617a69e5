"""The camera interface that every backend (mock, GenICam, V4L2) implements.

A camera is opened, configured, started, read frame by frame and stopped::

    cam = SomeCamera(...)
    cam.open()
    cam.configure(CameraSettings(fps=1000, exposure_s=1e-3))
    cam.start()
    frame = cam.read(timeout_s=0.1)   # -> Frame, or raises CameraTimeout
    cam.stop(); cam.close()

Cameras are context managers (``with cam: ...`` opens and closes). A stereo rig is
two cameras on one shared hardware trigger: ``frame_id`` counts trigger pulses, so a
left and a right frame with the same ``frame_id`` were exposed together.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

TriggerMode = Literal["free", "master", "slave", "software"]
"""``free``: the camera runs on its own clock; ``master``: it runs on its own clock and
outputs a trigger pulse per frame on a line; ``slave``: it exposes on each pulse from the
master's line; ``software``: one frame per :meth:`Camera.trigger` call."""


class CameraError(RuntimeError):
    """A camera could not be opened, configured or read."""


class CameraTimeout(CameraError):
    """No frame arrived within the read timeout."""


class CameraLost(CameraError):
    """The device vanished (unplugged, producer error); reopen to recover."""


@dataclass(frozen=True)
class Roi:
    """Region of interest on the sensor, in px: offset (x, y) and size (width, height)."""

    x: int = 0
    y: int = 0
    width: int = 512
    height: int = 512

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or self.x < 0 or self.y < 0:
            raise ValueError(f"invalid ROI {self}")


@dataclass(frozen=True)
class CameraSettings:
    """What :meth:`Camera.configure` applies (SFNC names in brackets).

    fps: frame rate in frames/s [AcquisitionFrameRate].
    exposure_s: exposure time in s [ExposureTime, which is in µs].
    gain_db: analogue gain in dB [Gain].
    roi: sensor window in px [Width, Height, OffsetX, OffsetY].
    trigger: see :data:`TriggerMode` [TriggerSelector/Mode/Source/Activation, LineSource].
    pixel_format: ``Mono8`` (8-bit) or ``Mono12``/``Mono16`` (delivered as uint16).
    """

    fps: float = 1000.0
    exposure_s: float = 1e-3
    gain_db: float = 0.0
    roi: Roi = field(default_factory=Roi)
    trigger: TriggerMode = "free"
    pixel_format: str = "Mono8"

    def __post_init__(self) -> None:
        if not self.fps > 0:
            raise ValueError(f"fps must be > 0, got {self.fps}")
        if not 0 < self.exposure_s <= 1.0 / self.fps + 1e-12:
            raise ValueError(
                f"exposure_s must be in (0, 1/fps = {1.0 / self.fps:g}] s, got {self.exposure_s}")

    def with_(self, **kw: object) -> "CameraSettings":
        return replace(self, **kw)  # type: ignore[arg-type]

    @property
    def bit_depth(self) -> int:
        return {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono16": 16}.get(self.pixel_format, 8)


@dataclass(frozen=True)
class Frame:
    """One image from one camera.

    camera: the camera's name in the rig (``"left"``/``"right"``) or its serial number.
    frame_id: trigger/sequence counter from the device (increments by 1 per exposure;
      a gap means frames were lost).
    timestamp_ns: start of exposure in ns on the device clock (or host monotonic clock
      where the device has none).
    image: (height, width) array, uint8 for Mono8, uint16 otherwise. Treat as read-only:
      backends may hand out views of reused buffers only until the next :meth:`read`.
    """

    camera: str
    frame_id: int
    timestamp_ns: int
    image: np.ndarray


class Camera(abc.ABC):
    """Abstract camera. Subclasses implement the ``_``-free methods below."""

    name: str = "camera"

    @abc.abstractmethod
    def open(self) -> None:
        """Connect to the device. Raises :class:`CameraError` if it cannot be found."""

    @abc.abstractmethod
    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply settings (only while stopped); return what the device actually accepted."""

    @abc.abstractmethod
    def start(self) -> None:
        """Start acquisition."""

    @abc.abstractmethod
    def read(self, timeout_s: float = 1.0) -> Frame:
        """Next frame, in acquisition order. Raises :class:`CameraTimeout` after
        ``timeout_s`` s without one and :class:`CameraLost` if the device vanished."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop acquisition (idempotent)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device (idempotent)."""

    def trigger(self) -> None:
        """Fire one software trigger (only with ``trigger="software"``)."""
        raise CameraError(f"{type(self).__name__} has no software trigger")

    def skip_to(self, until_ns: int, timeout_s: float = 1.0,
                max_frames: int = 1 << 16) -> tuple[int, Frame | None]:
        """Discard the frames this camera has waiting whose ``timestamp_ns`` (ns, device
        clock) is below ``until_ns``: a reader that has fallen behind catches up with its
        partner camera. Returns (frames discarded, the first frame not older, or None when
        none came within ``timeout_s`` s of a read or ``max_frames`` were discarded).
        The default reads and drops; backends that can skip without delivering images
        override it. Raises what :meth:`read` raises, except :class:`CameraTimeout`."""
        n = 0
        while n < max_frames:
            try:
                frame = self.read(timeout_s=timeout_s)
            except CameraTimeout:
                return n, None
            if frame.timestamp_ns >= until_ns:
                return n, frame
            n += 1
        return n, None

    waits_for_consumer: bool = False
    """True for a camera without a clock of its own (the mock rig with ``rig.pace =
    false``): it makes its next frame when read, so nothing is lost by waiting. The
    acquisition then reads it in step with its partner (by timestamp) and waits for room in
    the ring instead of dropping the oldest pair, injected faults included."""

    reuses_buffers: bool = True
    """False for a driver whose every read returns a new image array that it never touches
    again (the mock rig): the acquisition then keeps a frame that waits for its partner
    without copying it (``[acquisition] copy_frames``)."""

    makes_images_on_read: bool = False
    """True for a camera whose :meth:`read` makes its image on the CPU, much of it holding
    the GIL (the mock rig's renderer), rather than waiting for a device. The acquisition
    then runs the two cameras' reader threads on one CPU (``[acquisition] one_cpu_readers``):
    two CPU-bound CPython threads handing the GIL to each other across two cores cost about
    half as much again as on one (0.81 against 0.56 cores, the mock rig with faults at
    1000 fps, 2026-12-07)."""

    @property
    def settings(self) -> CameraSettings | None:
        return getattr(self, "_settings", None)

    def pair_source(self) -> "StereoPairSource | None":
        """A :class:`StereoPairSource` that delivers this camera's frames together with its
        partner's into caller buffers, or None (the default: frames one by one)."""
        return None

    def __enter__(self) -> "Camera":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.stop()
        finally:
            self.close()


@dataclass(frozen=True)
class PairMeta:
    """What :meth:`StereoPairSource.read_pair_into` delivered: both frames' ids and
    exposure-start timestamps (ns, device clock)."""

    left_id: int
    right_id: int
    ts_left_ns: int
    ts_right_ns: int


class StereoPairSource(abc.ABC):
    """A rig that delivers both frames of one trigger at once, straight into buffers the
    caller owns (a hardware-synchronized stereo grabber; the mock rig). The acquisition
    then writes each pair into its ring slot without pairing or copying
    (:class:`iscd.rig.acquisition.Acquisition`); cameras offer one through
    ``Camera.pair_source()``, which returns None where they cannot."""

    waits_for_consumer: bool = False
    """True for a source without a clock of its own (the mock rig with ``rig.pace = false``):
    it makes the next pair when asked, so nothing is lost by waiting. The acquisition then
    waits for room in the ring instead of dropping the oldest pair (a run that is as fast
    as the decoder and loses nothing however busy the machine: tests, replays)."""

    @abc.abstractmethod
    def read_pair_into(self, left: np.ndarray, right: np.ndarray, timeout_s: float = 1.0) -> PairMeta:
        """Fill ``left`` and ``right`` ((H, W), the cameras' dtype) with the next pair.
        Raises :class:`CameraTimeout` if none came within ``timeout_s``, or
        :class:`CameraError` / :class:`CameraLost` as :meth:`Camera.read` does."""
