"""V4L2 (Video4Linux2) cameras through linuxpy, with mmap streaming.

For monochrome machine-vision cameras with a Linux kernel driver (MIPI CSI-2 sensors
on embedded boards, UVC cameras with a GREY/Y16 mode). What
:meth:`V4L2Camera.configure` maps:

==================  ==========================================================
setting             V4L2 (skipped, and logged, when the driver lacks it)
==================  ==========================================================
``pixel_format``    ``VIDIOC_S_FMT`` fourcc: Mono8 ``GREY``, Mono10 ``Y10``,
                    Mono12 ``Y12``, Mono16 ``Y16`` (16-bit little-endian words)
``roi``             ``S_FMT`` width/height; offsets by ``VIDIOC_S_SELECTION``
                    (target CROP)
``fps``             ``VIDIOC_S_PARM`` timeperframe = 1/fps
``exposure_s``      ``auto_exposure`` = Manual, ``exposure_time_absolute``
                    (V4L2_CID_EXPOSURE_ABSOLUTE, in units of 100 µs)
``gain_db``         not mapped: V4L2 gain controls have driver-specific units
``trigger``         only ``"free"``: V4L2 has no standard trigger controls
==================  ==========================================================

Streaming uses linuxpy's :class:`~linuxpy.video.device.VideoCapture` with memory-mapped
buffers (REQBUFS/QUERYBUF/mmap/QBUF, STREAMON, DQBUF/QBUF per frame, STREAMOFF). Frame
ids are the driver's buffer ``sequence`` numbers; a jump means the driver dropped
frames (no free buffer), counted in ``stats["dropped"]``. Timestamps: see
:func:`v4l2_timestamp_ns`.

linuxpy is imported when a camera is opened or listed.
"""

from __future__ import annotations

import errno
import glob
import logging
import time
from typing import Any

import numpy as np

from iscd.drivers import urls
from iscd.drivers.base import (Camera, CameraError, CameraLost, CameraSettings, CameraTimeout, Frame,
                          Roi)

log = logging.getLogger(__name__)

V4L2_GLOB = "/dev/video*"
"""Where :func:`list_devices` looks for capture devices."""

FOURCC = {"Mono8": "GREY", "Mono10": "Y10 ", "Mono12": "Y12 ", "Mono16": "Y16 "}
_FROM_FOURCC = {v.strip(): k for k, v in FOURCC.items()}

EXPOSURE_UNIT_S = 100e-6
"""V4L2_CID_EXPOSURE_ABSOLUTE counts 100 µs units."""

_LOST_ERRNOS = {errno.ENODEV, errno.ENXIO, errno.EIO, errno.EBADF, errno.EPIPE}

# V4L2 buffer flags (videodev2.h), kept here so that the pure functions need no linuxpy.
BUF_FLAG_ERROR = 0x0040
BUF_FLAG_TIMESTAMP_MASK = 0xE000
BUF_FLAG_TIMESTAMP_MONOTONIC = 0x2000
BUF_FLAG_TSTAMP_SRC_SOE = 0x10000


def _import_linuxpy() -> Any:
    try:
        from linuxpy.video import device
    except ImportError as e:  # pragma: no cover - depends on the install
        raise CameraError(f"the v4l2 backend needs linuxpy (pip install linuxpy): {e}") from None
    return device


def v4l2_timestamp_ns(secs: int, usecs: int, flags: int, exposure_ns: int, host_ns: int) -> tuple[int, str]:
    """Start-of-exposure time in ns of a dequeued V4L2 buffer, and its source.

    V4L2 stamps buffers on CLOCK_MONOTONIC (flag TIMESTAMP_MONOTONIC), the clock of
    Python's ``time.monotonic_ns()``, as a timeval (s, µs: 1 µs resolution). With
    TSTAMP_SRC_SOE the stamp is the start of exposure; otherwise (TSTAMP_SRC_EOF, the
    default) it is the end of frame, and ``exposure_ns`` is subtracted (readout time,
    unknown to V4L2, is not). A zero stamp or a copied/unknown clock
    (TIMESTAMP_COPY/UNKNOWN) falls back to ``host_ns`` (the host monotonic clock at
    dequeue) → source ``"host"``.
    """
    ns = int(secs) * 1_000_000_000 + int(usecs) * 1_000
    if ns <= 0 or (flags & BUF_FLAG_TIMESTAMP_MASK) != BUF_FLAG_TIMESTAMP_MONOTONIC:
        return host_ns, "host"
    if not flags & BUF_FLAG_TSTAMP_SRC_SOE:
        ns -= int(exposure_ns)
    return ns, "device"


def to_image(data: bytes | memoryview, width: int, height: int, bytes_per_line: int,
             bytes_per_pixel: int) -> np.ndarray:
    """A (height, width) uint8/uint16 image from a V4L2 frame buffer whose rows are
    ``bytes_per_line`` bytes apart (rows may be padded). 16-bit formats are
    little-endian words. The result does not share memory with ``data``."""
    bpl = bytes_per_line or width * bytes_per_pixel
    need = bpl * (height - 1) + width * bytes_per_pixel
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size < need:
        raise CameraError(f"V4L2 frame has {buf.size} bytes, expected at least {need} "
                          f"for {width}x{height}")
    if buf.size < bpl * height:
        buf = np.concatenate([buf, np.zeros(bpl * height - buf.size, np.uint8)])
    rows = buf[: bpl * height].reshape(height, bpl)[:, : width * bytes_per_pixel]
    if bytes_per_pixel == 1:
        return rows.copy()
    return rows.copy().view("<u2").reshape(height, width).astype(np.uint16, copy=False)


def _oserror(name: str, what: str, e: OSError) -> CameraError:
    if e.errno in _LOST_ERRNOS:
        return CameraLost(f"{name}: V4L2 device lost during {what}: {e}")
    return CameraError(f"{name}: V4L2 {what} failed: {e}")


class V4L2Camera(Camera):
    """A V4L2 capture device, e.g. ``V4L2Camera("/dev/video0", name="left")``.

    num_buffers: mmap buffers requested (the driver may grant fewer/more).
    :attr:`stats` counts ``frames``, ``dropped`` (sequence gaps), ``errors`` (buffers
    flagged V4L2_BUF_FLAG_ERROR, dropped) and ``timeouts``.
    """

    def __init__(self, path: str, name: str = "left", num_buffers: int = 8) -> None:
        self.path = str(path)
        self.name = name
        self.num_buffers = int(num_buffers)
        self.skipped: list[str] = []
        self.info: dict[str, Any] = {}
        self.stats: dict[str, int] = {"frames": 0, "dropped": 0, "errors": 0, "timeouts": 0}
        self.timestamp_source: str | None = None
        self._dev: Any = None
        self._capture: Any = None
        self._reader: Any = None
        self._settings: CameraSettings | None = None
        self._format: Any = None
        self._last_seq: int | None = None

    # ---------------------------------------------------------------- lifecycle
    def open(self) -> None:
        if self._dev is not None:
            return
        vd = _import_linuxpy()
        dev = vd.Device(self.path)
        try:
            dev.open()
            caps = dev.info.device_capabilities
        except FileNotFoundError:
            raise CameraError(f"{self.name}: V4L2 device {self.path} not found") from None
        except OSError as e:
            dev.close()
            raise CameraError(f"{self.name}: cannot open V4L2 device {self.path}: {e}") from None
        if vd.Capability.VIDEO_CAPTURE not in caps or vd.Capability.STREAMING not in caps:
            dev.close()
            raise CameraError(f"{self.name}: {self.path} is not a streaming video capture device "
                              f"(capabilities: {caps!r})")
        self._dev = dev
        self.info = {"backend": "v4l2", "device": self.path, "driver": dev.info.driver,
                     "card": dev.info.card, "bus": dev.info.bus_info}
        log.info("%s: opened V4L2 %s (%s, %s)", self.name, self.path, self.info["card"],
                 self.info["driver"])

    def _require_dev(self) -> Any:
        if self._dev is None:
            raise CameraError(f"{self.name}: camera is not open")
        return self._dev

    def configure(self, settings: CameraSettings) -> CameraSettings:
        dev = self._require_dev()
        if self._capture is not None:
            raise CameraError(f"{self.name}: configure() while streaming; stop() first")
        vd = _import_linuxpy()
        s = settings
        skipped: list[str] = []
        bt = vd.BufferType.VIDEO_CAPTURE
        fourcc = FOURCC.get(s.pixel_format)
        if fourcc is None:
            raise CameraError(f"{self.name}: pixel format {s.pixel_format!r} has no V4L2 "
                              f"equivalent (use one of {', '.join(FOURCC)})")
        try:
            offered = {f.pixel_format.human_str().strip() for f in dev.info.formats
                       if f.type == bt}
            if fourcc.strip() not in offered:
                raise CameraError(f"{self.name}: {self.path} does not offer {s.pixel_format} "
                                  f"({fourcc.strip()}); it offers {', '.join(sorted(offered)) or 'nothing'}")
            dev.set_format(bt, s.roi.width, s.roi.height, fourcc)
            fmt = dev.get_format(bt)
        except OSError as e:
            raise _oserror(self.name, "format setup", e) from None
        got = fmt.pixel_format.human_str().strip()
        if got != fourcc.strip():
            raise CameraError(f"{self.name}: driver chose {got} instead of {fourcc.strip()}")
        x, y = 0, 0
        if s.roi.x or s.roi.y:
            try:
                dev.set_selection(bt, vd.SelectionTarget.CROP,
                                  vd.Rect(s.roi.x, s.roi.y, fmt.width, fmt.height))
                r = dev.get_selection(bt, vd.SelectionTarget.CROP)
                x, y = int(r.left), int(r.top)
            except OSError as e:
                if e.errno in _LOST_ERRNOS:
                    raise _oserror(self.name, "crop setup", e) from None
                skipped.append("roi offset")
                log.info("%s: ROI offset skipped: S_SELECTION unsupported (%s)", self.name, e)
        fps = s.fps
        try:
            dev.set_fps(bt, s.fps)
            fps = float(dev.get_fps(bt))
            if not fps > 0:
                raise ValueError("driver reports no frame interval")
        except (OSError, ValueError, ZeroDivisionError) as e:
            if isinstance(e, OSError) and e.errno in _LOST_ERRNOS:
                raise _oserror(self.name, "frame-rate setup", e) from None
            skipped.append("fps")
            fps = s.fps
            log.info("%s: frame rate skipped: %s", self.name, e)
        exposure_s = self._set_exposure(vd, dev, s.exposure_s, skipped)
        if s.gain_db:
            skipped.append("gain")
            log.info("%s: gain_db skipped: V4L2 gain has driver-specific units", self.name)
        if s.trigger != "free":
            skipped.append("trigger")
            log.warning("%s: trigger=%r skipped: V4L2 has no standard trigger; free-running",
                        self.name, s.trigger)
        exposure_s = min(exposure_s, 1.0 / fps)
        self._format = fmt
        self.skipped = skipped
        self._settings = CameraSettings(fps=fps, exposure_s=exposure_s, gain_db=s.gain_db,
                                        roi=Roi(x, y, int(fmt.width), int(fmt.height)),
                                        trigger="free", pixel_format=_FROM_FOURCC[got])
        return self._settings

    def _set_exposure(self, vd: Any, dev: Any, exposure_s: float, skipped: list[str]) -> float:
        ctrls = dev.controls
        try:
            try:
                auto = ctrls[vd.ControlID.EXPOSURE_AUTO]
            except KeyError:
                auto = None
            if auto is not None and auto.is_writeable:
                manual = int(vd.raw.ExposureAutoType.MANUAL)
                if manual in getattr(auto, "data", {manual: None}):
                    auto.value = manual
            try:
                exp = ctrls[vd.ControlID.EXPOSURE_ABSOLUTE]
            except KeyError:
                skipped.append("exposure")
                log.info("%s: exposure skipped: no exposure_time_absolute control", self.name)
                return exposure_s
            exp.value = max(1, round(exposure_s / EXPOSURE_UNIT_S))
            return float(exp.value) * EXPOSURE_UNIT_S
        except OSError as e:
            if e.errno in _LOST_ERRNOS:
                raise _oserror(self.name, "exposure setup", e) from None
            skipped.append("exposure")
            log.info("%s: exposure skipped: %s", self.name, e)
            return exposure_s
        except AttributeError as e:  # linuxpy: control not writeable (read-only/inactive)
            skipped.append("exposure")
            log.info("%s: exposure skipped: %s", self.name, e)
            return exposure_s

    def start(self) -> None:
        dev = self._require_dev()
        if self._capture is not None:
            return
        vd = _import_linuxpy()
        if self._settings is None:
            self._format = dev.get_format(vd.BufferType.VIDEO_CAPTURE)
        capture = vd.VideoCapture(dev, size=max(self.num_buffers, 1))
        try:
            capture.open()  # REQBUFS, QUERYBUF + mmap, QBUF, STREAMON
        except OSError as e:
            try:
                capture.close()
            except Exception:  # noqa: BLE001
                pass
            raise _oserror(self.name, "stream start", e) from None
        self._capture = capture
        self._format = capture.buffer.format or self._format
        self._reader = vd.FrameReader(dev, capture.buffer.raw_read)
        self._last_seq = None

    def read(self, timeout_s: float = 1.0) -> Frame:
        if self._reader is None:
            raise CameraError(f"{self.name}: read() before start()")
        deadline = time.monotonic() + max(timeout_s, 0.0)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.stats["timeouts"] += 1
                raise CameraTimeout(f"{self.name}: no frame within {timeout_s:g} s")
            try:
                frame = self._reader.read(timeout=remaining)  # select(), then DQBUF/QBUF
            except BlockingIOError:
                # Readable but no buffer done yet (EAGAIN on the non-blocking fd).
                time.sleep(min(0.001, max(remaining, 0.0)))
                continue
            except OSError as e:
                raise _oserror(self.name, "dequeue", e) from None
            except ValueError as e:  # select() on a closed fd
                raise CameraLost(f"{self.name}: V4L2 device closed: {e}") from None
            if frame is None:
                continue
            out = self._to_frame(frame)
            if out is not None:
                return out

    def _to_frame(self, frame: Any) -> Frame | None:
        host_ns = time.monotonic_ns()
        buff = frame.buff
        seq = int(buff.sequence)
        if self._last_seq is not None:
            gap = seq - self._last_seq - 1
            if gap > 0:
                self.stats["dropped"] += gap
                log.warning("%s: %d frame(s) lost before sequence %d", self.name, gap, seq)
        self._last_seq = seq
        if buff.flags & BUF_FLAG_ERROR:
            self.stats["errors"] += 1
            log.warning("%s: buffer %d (sequence %d) flagged as corrupted; dropped", self.name,
                        buff.index, seq)
            return None
        fmt = self._format
        bpp = 2 if fmt.pixel_format.human_str().strip() in ("Y10", "Y12", "Y16") else 1
        image = to_image(frame.data, int(fmt.width), int(fmt.height), int(fmt.bytes_per_line), bpp)
        exposure_ns = int(round((self._settings.exposure_s if self._settings else 0.0) * 1e9))
        ts, self.timestamp_source = v4l2_timestamp_ns(buff.timestamp.secs, buff.timestamp.usecs,
                                                      int(buff.flags), exposure_ns, host_ns)
        self.stats["frames"] += 1
        return Frame(self.name, seq, ts, image)

    def stop(self) -> None:
        capture, self._capture, self._reader = self._capture, None, None
        if capture is None:
            return
        try:
            capture.close()  # STREAMOFF, munmap, REQBUFS 0
        except Exception as e:  # noqa: BLE001 - stopping a vanished device
            log.debug("%s: stream stop failed: %s", self.name, e)

    def close(self) -> None:
        self.stop()
        dev, self._dev = self._dev, None
        if dev is not None:
            try:
                dev.close()
            except Exception as e:  # noqa: BLE001
                log.debug("%s: close failed: %s", self.name, e)


def list_devices(pattern: str | None = None) -> list[dict[str, Any]]:
    """Video capture devices matching ``pattern`` (default :data:`V4L2_GLOB`) as dicts
    with ``device``, ``driver``, ``card``, ``bus``, ``formats`` (fourccs), ``mono``
    (offers a Mono format). Nodes without capture streaming (UVC metadata nodes) are
    left out; a device that cannot be opened is listed with ``error``."""
    paths = sorted(glob.glob(pattern or V4L2_GLOB))
    if not paths:
        return []
    vd = _import_linuxpy()
    out: list[dict[str, Any]] = []
    for path in paths:
        entry: dict[str, Any] = {"backend": "v4l2", "device": path}
        try:
            with vd.Device(path) as dev:
                caps = dev.info.device_capabilities
                if vd.Capability.VIDEO_CAPTURE not in caps or vd.Capability.STREAMING not in caps:
                    continue
                formats = [f.pixel_format.human_str().strip() for f in dev.info.formats
                           if f.type == vd.BufferType.VIDEO_CAPTURE]
                entry.update(driver=dev.info.driver, card=dev.info.card, bus=dev.info.bus_info,
                             formats=formats, mono=any(f in _FROM_FOURCC for f in formats))
        except OSError as e:
            entry["error"] = f"{e.strerror or e}"
        out.append(entry)
    return out


# --------------------------------------------------------------------------- v4l2:// URLs
def device_url(entry: dict[str, Any]) -> str:
    """The URL of a device :func:`list_devices` found: ``v4l2:///dev/videoN``."""
    return urls.make_url("v4l2", entry["device"])


def _check_url(u: urls.CameraURL) -> None:
    urls.int_option(u, "buffers", lo=1)


def _open_url(u: urls.CameraURL, *, name: str = "camera", num_buffers: int | None = None) -> V4L2Camera:
    """``v4l2:///dev/videoN?buffers=N``."""
    return V4L2Camera(u.target, name=name, num_buffers=urls.int_option(u, "buffers") or num_buffers or 8)


def _discover(**_: Any) -> list[dict[str, Any]]:
    try:
        return [{**d, "url": device_url(d)} for d in list_devices()]
    except CameraError as e:
        log.warning("v4l2: %s", e)
        return []


urls.register(urls.Backend(
    "v4l2", _open_url, target="path", what="device path (/dev/videoN)", form="v4l2:///dev/videoN",
    options={"buffers": "mmap buffers (8)"}, check=_check_url,
    discover=_discover, summary="Linux kernel video device through linuxpy"))
