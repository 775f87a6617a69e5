"""GenICam cameras through harvesters and a GenTL producer (``.cti``).

Any GenTL-compliant camera (GigE Vision, USB3 Vision, CoaXPress, Camera Link HS)
works through its vendor's GenTL producer; the camera is picked by serial number or
user id (``DeviceUserID``), and its SFNC features are set from
:class:`~iscd.drivers.base.CameraSettings`:

======================  =====================================================
setting                 SFNC nodes (skipped, and logged, when absent)
======================  =====================================================
``pixel_format``        ``PixelFormat``
``roi``                 ``OffsetX``/``OffsetY`` (zeroed first), ``Width``,
                        ``Height``, then the offsets
``exposure_s``          ``ExposureAuto=Off``, ``ExposureTime`` (µs)
``gain_db``             ``GainAuto=Off``, ``Gain`` (dB on most cameras)
``fps``                 ``AcquisitionFrameRateEnable=True``,
                        ``AcquisitionFrameRate`` (frames/s)
``trigger="free"``      ``TriggerSelector=FrameStart``, ``TriggerMode=Off``
``trigger="master"``    free running, plus ``LineSelector=<output_line>``,
                        ``LineMode=Output``, ``LineSource=<output_source>``
                        (``ExposureActive``: one pulse per exposure)
``trigger="slave"``     ``TriggerSelector=FrameStart``, ``TriggerMode=On``,
                        ``TriggerSource=<trigger_source>`` (``Line1``),
                        ``TriggerActivation=RisingEdge``; no frame-rate limit
``trigger="software"``  ``TriggerMode=On``, ``TriggerSource=Software``;
                        :meth:`GenICamCamera.trigger` runs ``TriggerSoftware``
======================  =====================================================

Numbers are clamped to the node's range and increment; :meth:`GenICamCamera.configure`
returns what the device reports back. Settings whose nodes are missing keep the
requested value in the returned settings and are listed in
:attr:`GenICamCamera.skipped` (a slave without trigger nodes is reported as
``trigger="free"``: it is not synchronized).

Producers: an explicit ``.cti`` path, else every ``*.cti`` in the directories of
``GENICAM_GENTL64_PATH``; ``"simulated"`` names the simulated producer shipped in the
``genicam`` wheel (``viky.cti``: three cameras, serial numbers ``0``–``2``, ≤ 200 fps,
Mono8, no exposure/gain/trigger nodes, no timestamps). One :class:`harvesters.core.
Harvester` is shared per producer file (GenTL producers are loaded once per process).

harvesters and genicam are imported only when a camera is opened or listed, so the
daemon starts without them.
"""

from __future__ import annotations

import glob
import logging
import math
import os
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from iscd.drivers import urls
from iscd.drivers.base import (Camera, CameraError, CameraLost, CameraSettings, CameraTimeout, Frame,
                          Roi, TriggerMode)

log = logging.getLogger(__name__)

ENV_VAR = "GENICAM_GENTL64_PATH"
SIMULATED = "simulated"

_harvesters: dict[str, Any] = {}
_lock = threading.RLock()


# --------------------------------------------------------------------------- producers

def _import_harvesters() -> Any:
    try:
        from harvesters import core
    except ImportError as e:  # pragma: no cover - depends on the install
        raise CameraError(f"the genicam backend needs harvesters and genicam "
                          f"(pip install harvesters genicam): {e}") from None
    return core


def simulated_producer() -> str | None:
    """Path of the simulated GenTL producer in the installed ``genicam`` wheel
    (``viky.cti`` in genicam 1.6), or None."""
    try:
        import genicam
    except ImportError:
        return None
    found = sorted(glob.glob(os.path.join(os.path.dirname(genicam.__file__), "*.cti")))
    return found[0] if found else None


_LIBRARY_MAGIC = (b"\x7fELF", b"MZ", b"\xcf\xfa\xed\xfe", b"\xce\xfa\xed\xfe", b"\xca\xfe\xba\xbe")
"""First bytes of a shared library: ELF (Linux), PE (Windows), Mach-O (macOS)."""


def check_producer(path: str) -> None:
    """Raise :class:`CameraError` unless ``path`` is a GenTL producer: a shared library
    (by its first bytes) that loads and exports ``GCInitLib``. harvesters itself accepts
    any file silently and then lists no camera."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as e:
        raise CameraError(f"GenTL producer {path!r}: cannot read: {e.strerror or e}") from None
    if not head.startswith(_LIBRARY_MAGIC):
        raise CameraError(f"{path}: not a GenTL producer (.cti): not a shared library")
    import ctypes

    try:
        lib = ctypes.CDLL(os.path.abspath(path))
    except OSError as e:
        raise CameraError(f"{path}: not a GenTL producer (.cti): cannot load it: "
                          f"{' '.join(str(e).split())}") from None
    if not hasattr(lib, "GCInitLib"):
        raise CameraError(f"{path}: not a GenTL producer (.cti): it does not export GCInitLib")


def find_producers(producer: str | None = None) -> list[str]:
    """The GenTL producer files to use.

    ``producer``: a ``.cti`` path, ``"simulated"``, or None for every ``*.cti`` in the
    ``GENICAM_GENTL64_PATH`` directories (``os.pathsep``-separated; a ``.cti`` file
    there is used as is). Raises :class:`CameraError` for a path that does not exist.
    """
    if producer:
        if producer == SIMULATED:
            sim = simulated_producer()
            if sim is None:
                raise CameraError("no simulated GenTL producer: the genicam wheel is not installed")
            return [sim]
        if not os.path.isfile(producer):
            raise CameraError(f"GenTL producer {producer!r} not found")
        check_producer(producer)
        return [os.path.abspath(producer)]
    out: list[str] = []
    for entry in os.environ.get(ENV_VAR, "").split(os.pathsep):
        if not entry:
            continue
        if entry.endswith(".cti") and os.path.isfile(entry):
            out.append(os.path.abspath(entry))
        elif os.path.isdir(entry):
            out.extend(sorted(os.path.abspath(p) for p in glob.glob(os.path.join(entry, "*.cti"))))
    good: list[str] = []
    for cti in dict.fromkeys(out):
        try:
            check_producer(cti)  # harvesters crashes (SIGSEGV) on a library that is not GenTL
        except CameraError as e:
            log.warning("%s: skipped: %s", ENV_VAR, e)
            continue
        good.append(cti)
    return good


def harvester(producer: str) -> Any:
    """The process-wide :class:`harvesters.core.Harvester` of ``producer`` (a .cti path),
    created and enumerated on first use, or re-populated after a ``reset()``."""
    core = _import_harvesters()
    with _lock:
        h = _harvesters.get(producer)
        if h is None:
            h = core.Harvester()
            _harvesters[producer] = h
        if producer not in h.files:
            h.add_file(producer)
            h.update()
            log.info("GenTL producer %s: %d device(s)", producer, len(h.device_info_list))
        return h


def refresh_producer(producer: str) -> Any:
    """Re-enumerate the producer's devices (after a camera was unplugged/replugged).

    GenTL invalidates every open image acquirer of the producer on re-enumeration:
    other cameras on it report :class:`CameraLost` on their next read and reconnect.
    """
    with _lock:
        h = harvester(producer)
        live = [ia for ia in h.image_acquirers if ia.is_valid()]
        if live:
            log.warning("re-enumerating %s invalidates %d open camera(s) on it", producer, len(live))
        h.update()
        return h


def release_all() -> None:
    """Reset every cached Harvester: closes all GenICam cameras and unloads the producers.

    The Harvester objects stay cached and reload their producer on next use: while one
    Harvester object exists, a second one on the same producer sees no devices (the
    producer's system module is a per-process singleton).
    """
    with _lock:
        for h in _harvesters.values():
            try:
                # Harvester.reset() works only once (a weakref.finalize); this is repeatable:
                h.remove_files()
                h.update()  # destroys the image acquirers, closes the producer, opens none
                h.image_acquirers.clear()
            except Exception as e:  # noqa: BLE001 - best effort at teardown
                log.debug("reset failed: %s", e)


def _info_value(info: Any, attr: str) -> Any:
    try:
        v = getattr(info, attr)
    except Exception:  # noqa: BLE001 - GenTL raises for absent info
        return None
    return v if v not in ("",) else None


def _describe(info: Any, producer: str) -> dict[str, Any]:
    access = _info_value(info, "access_status")
    return {
        "backend": "genicam",
        "producer": producer,
        "serial": _info_value(info, "serial_number"),
        "user_id": _info_value(info, "user_defined_name"),
        "vendor": _info_value(info, "vendor"),
        "model": _info_value(info, "model"),
        "id": _info_value(info, "id_"),
        "tl_type": _info_value(info, "tl_type"),
        # GenTL DEVICE_ACCESS_STATUS: 1 readwrite (free), 2 readonly, 3 no access, 4 busy, 5/6 open
        "available": access in (None, 1),
    }


def list_devices(producer: str | None = None) -> list[dict[str, Any]]:
    """Every GenICam camera of the producer(s) (see :func:`find_producers`) as dicts
    with ``serial``, ``user_id``, ``vendor``, ``model``, ``id``, ``producer``,
    ``available``. Does not re-enumerate a producer that has cameras open."""
    out: list[dict[str, Any]] = []
    for cti in find_producers(producer):
        with _lock:
            h = harvester(cti)
            if not any(ia.is_valid() for ia in h.image_acquirers):
                h.update()
            out.extend(_describe(info, cti) for info in h.device_info_list)
    return out


# --------------------------------------------------------------------------- node access

def _has(nm: Any, name: str) -> bool:
    try:
        getattr(nm, name)
    except AttributeError:
        return False
    return True


def _node(nm: Any, name: str) -> Any | None:
    try:
        return getattr(nm, name)
    except AttributeError:
        return None


def _symbolics(node: Any) -> tuple[str, ...]:
    try:
        return tuple(node.symbolics)
    except Exception:  # noqa: BLE001
        return ()


class _NodeWriter:
    """Writes SFNC nodes tolerantly, clamping numbers; records what was skipped."""

    def __init__(self, nm: Any, camera: str) -> None:
        self.nm = nm
        self.camera = camera
        self.skipped: list[str] = []

    def _skip(self, name: str, why: str) -> None:
        self.skipped.append(name)
        log.info("%s: %s skipped: %s", self.camera, name, why)

    def enum(self, name: str, value: str, required: bool = False) -> bool:
        node = _node(self.nm, name)
        if node is None:
            self._skip(name, "no such node")
            return False
        syms = _symbolics(node)
        if syms and value not in syms:
            msg = f"{value!r} not offered (offered: {', '.join(syms)})"
            if required:
                raise CameraError(f"{self.camera}: {name} {msg}")
            self._skip(name, msg)
            return False
        if self.read(name) == value:  # already so (and maybe read-only, like Viky's AcquisitionMode)
            return True
        return self._set(name, node, value)

    def number(self, name: str, value: float) -> bool:
        node = _node(self.nm, name)
        if node is None:
            self._skip(name, "no such node")
            return False
        try:
            lo, hi = node.min, node.max
        except Exception:  # noqa: BLE001
            lo, hi = -math.inf, math.inf
        is_int = isinstance(node.value, int) and not isinstance(node.value, bool)
        v = min(max(value, lo), hi)
        if is_int:
            try:
                inc = max(int(node.inc), 1)
            except Exception:  # noqa: BLE001
                inc = 1
            # round down onto the increment grid (never above the request or the maximum)
            v = int(lo + math.floor((v - lo) / inc) * inc) if math.isfinite(lo) else int(v)
        if v != value:
            # rounding onto the increment grid is routine; a device that cannot come within 1 %
            # of the request (e.g. AcquisitionFrameRate 1000 on a 200 fps camera) is said loudly
            far = abs(v - value) > 0.01 * max(abs(value), 1e-12)
            log.log(logging.WARNING if far else logging.INFO, "%s: %s %g clamped to %g (range %g..%g)%s",
                    self.camera, name, value, v, lo, hi,
                    ": the device cannot do what the config asks" if far else "")
        return self._set(name, node, v)

    def boolean(self, name: str, value: bool) -> bool:
        node = _node(self.nm, name)
        if node is None:
            self._skip(name, "no such node")
            return False
        return self._set(name, node, value)

    def _set(self, name: str, node: Any, value: Any) -> bool:
        try:
            node.value = value
        except Exception as e:  # noqa: BLE001 - GenApi access/range/logic errors
            self._skip(name, f"write of {value!r} refused: {str(e).splitlines()[0] if str(e) else type(e).__name__}")
            return False
        return True

    def read(self, name: str, default: Any = None) -> Any:
        node = _node(self.nm, name)
        if node is None:
            return default
        try:
            return node.value
        except Exception:  # noqa: BLE001
            return default


@dataclass(frozen=True)
class TriggerWiring:
    """Which GPIO lines carry the stereo trigger (camera-model specific)."""

    trigger_source: str = "Line1"
    """Slave: the input line the master's pulse arrives on [TriggerSource]."""
    trigger_activation: str = "RisingEdge"
    """Slave: which edge starts an exposure [TriggerActivation]."""
    output_line: str = "Line1"
    """Master: the output line [LineSelector]."""
    output_source: str = "ExposureActive"
    """Master: the signal put on the line [LineSource]; ExposureActive is high during
    each exposure, so its rising edge is the start of exposure."""


def apply_settings(nm: Any, settings: CameraSettings, wiring: TriggerWiring = TriggerWiring(),
                   camera: str = "camera") -> tuple[CameraSettings, list[str]]:
    """Write ``settings`` to the node map ``nm`` (SFNC names; see the module docstring).

    Returns (settings read back from the device, names of nodes that were missing or
    refused). Raises :class:`CameraError` if the device offers the PixelFormat node but
    not the requested format. Pure of any camera state: works on any object whose
    attributes are GenApi-like nodes (``value``, ``min``/``max``/``inc``, ``symbolics``).
    """
    w = _NodeWriter(nm, camera)
    s = settings
    trig = s.trigger

    # Trigger first: on many cameras it gates which other nodes are writable.
    triggered = False
    output = False
    if _has(nm, "TriggerSelector"):
        w.enum("TriggerSelector", "FrameStart")
    if trig in ("slave", "software"):
        source = wiring.trigger_source if trig == "slave" else "Software"
        ok = w.enum("TriggerMode", "On")
        ok = w.enum("TriggerSource", source) and ok
        if trig == "slave":
            ok = w.enum("TriggerActivation", wiring.trigger_activation) and ok
        triggered = ok
        if not ok:
            if _has(nm, "TriggerMode"):  # half set up would wait for pulses that never come
                w.enum("TriggerMode", "Off")
            log.warning("%s: %s trigger could not be set up (missing/refused nodes); the camera "
                        "free-runs and is NOT synchronized", camera, trig)
    else:
        if _has(nm, "TriggerMode"):
            w.enum("TriggerMode", "Off")
        if trig == "master":
            ok = w.enum("LineSelector", wiring.output_line)
            if ok and _has(nm, "LineMode"):
                w.enum("LineMode", "Output")
            ok = ok and w.enum("LineSource", wiring.output_source)
            output = ok
            if not ok:
                log.warning("%s: master trigger output could not be set up; the slave gets no "
                            "pulses", camera)
    if _has(nm, "AcquisitionMode"):
        w.enum("AcquisitionMode", "Continuous")

    # Pixel format and ROI (before frame rate: the ROI bounds the maximum rate).
    if _has(nm, "PixelFormat"):
        w.enum("PixelFormat", s.pixel_format, required=True)
    else:
        w._skip("PixelFormat", "no such node")
    roi = s.roi
    for name in ("OffsetX", "OffsetY"):
        if _has(nm, name):
            w.number(name, 0)
    w.number("Width", roi.width)
    w.number("Height", roi.height)
    w.number("OffsetX", roi.x)
    w.number("OffsetY", roi.y)

    # Exposure and gain, then the frame rate, then exposure again (its maximum depends
    # on the frame period on many cameras).
    if _has(nm, "ExposureAuto"):
        w.enum("ExposureAuto", "Off")
    if _has(nm, "ExposureMode"):
        w.enum("ExposureMode", "Timed")
    w.number("ExposureTime", s.exposure_s * 1e6)
    if _has(nm, "GainAuto"):
        w.enum("GainAuto", "Off")
    w.number("Gain", s.gain_db)
    if triggered:
        if _has(nm, "AcquisitionFrameRateEnable"):
            w.boolean("AcquisitionFrameRateEnable", False)
    else:
        if _has(nm, "AcquisitionFrameRateEnable"):
            w.boolean("AcquisitionFrameRateEnable", True)
        w.number("AcquisitionFrameRate", s.fps)
    if _has(nm, "ExposureTime"):
        w.number("ExposureTime", s.exposure_s * 1e6)

    # Read back.
    fps = s.fps if triggered else float(w.read("AcquisitionFrameRate", s.fps))
    exposure = w.read("ExposureTime")
    exposure_s = s.exposure_s if exposure is None else float(exposure) * 1e-6
    if exposure_s > 1.0 / fps:
        exposure_s = 1.0 / fps
    pixel_format = str(w.read("PixelFormat", s.pixel_format))
    accepted_roi = Roi(int(w.read("OffsetX", roi.x if _has(nm, "OffsetX") else 0)),
                       int(w.read("OffsetY", roi.y if _has(nm, "OffsetY") else 0)),
                       int(w.read("Width", roi.width)), int(w.read("Height", roi.height)))
    if trig in ("slave", "software"):
        accepted_trigger: TriggerMode = trig if triggered else "free"
    elif trig == "master":
        accepted_trigger = "master" if output else "free"
    else:
        accepted_trigger = "free"
    accepted = CameraSettings(fps=fps, exposure_s=exposure_s,
                              gain_db=float(w.read("Gain", s.gain_db)), roi=accepted_roi,
                              trigger=accepted_trigger, pixel_format=pixel_format)
    return accepted, list(dict.fromkeys(w.skipped))


# --------------------------------------------------------------------------- timestamps

def buffer_timestamp_ns(raw: Any, tick_hz: int | None, host_ns: int) -> tuple[int, str]:
    """Timestamp of a GenTL buffer in ns, and where it came from.

    1. ``BUFFER_INFO_TIMESTAMP_NS`` (GenTL ≥ 1.5): device clock, ns → ``"device"``.
    2. ``BUFFER_INFO_TIMESTAMP`` in device ticks, converted with the device's
       ``DEVICE_INFO_TIMESTAMP_FREQUENCY`` (Hz): ns = ticks · 10⁹ / tick_hz → ``"device"``.
    3. Otherwise (or when the device reports 0) ``host_ns``, the host's monotonic
       clock when the buffer was fetched → ``"host"``. That is later than the start of
       exposure by exposure + readout + transfer time, and jitters with scheduling.

    GenTL leaves open whether the device latches the timestamp at the start or end of
    exposure; GigE Vision/USB3 Vision cameras latch at the start.
    """
    try:
        ns = int(raw.timestamp_ns)
        if ns > 0:
            return ns, "device"
    except Exception:  # noqa: BLE001 - GenTL NotAvailable
        pass
    if tick_hz:
        try:
            ticks = int(raw.timestamp)
            if ticks > 0:
                return ticks * 1_000_000_000 // int(tick_hz), "device"
        except Exception:  # noqa: BLE001
            pass
    return host_ns, "host"


def _to_image(component: Any, bit_depth: int) -> np.ndarray:
    """Copy a 2-D image component into a (height, width) array (uint8 or uint16)."""
    h, w = int(component.height), int(component.width)
    data = np.asarray(component.data)
    if data.size < h * w:
        raise CameraError(f"buffer holds {data.size} pixels, expected {h}x{w}")
    if data.ndim != 2:
        data = data.reshape(-1)
        stride = data.size // h if data.size % h == 0 else w  # rows may carry padding
        data = data[: h * stride].reshape(h, stride)
    img = np.array(data[:, :w], copy=True)
    if bit_depth > 8 and img.dtype != np.uint16:
        img = img.astype(np.uint16)
    return img


# --------------------------------------------------------------------------- camera

class GenICamCamera(Camera):
    """A GenICam camera through harvesters.

    serial: ``DeviceSerialNumber``; user_id: ``DeviceUserID``; device: either (the
    rig config's ``left``/``right``); none of them: the producer's only camera.
    producer: ``.cti`` path, ``"simulated"``, or None for ``GENICAM_GENTL64_PATH``.
    num_buffers: GenTL buffers announced (at 1000 fps, 16 buffers absorb 16 ms stalls).
    wiring: the GPIO lines of the stereo trigger.

    :attr:`stats` counts ``frames``, ``dropped`` (frame-id gaps), ``incomplete``
    (buffers the producer delivered incomplete; harvesters re-queues them),
    ``timeouts`` and ``reconnects``.
    """

    def __init__(self, serial: str | None = None, user_id: str | None = None,
                 producer: str | None = None, name: str = "left", *, device: str | None = None,
                 num_buffers: int = 16, wiring: TriggerWiring = TriggerWiring(),
                 first: bool = False) -> None:
        self.serial = serial or None
        self.first = bool(first)  # no selector: the first camera found (else exactly one)
        self.user_id = user_id or None
        self.device = device or None
        self.producer_arg = producer or None
        self.name = name
        self.num_buffers = int(num_buffers)
        self.wiring = wiring
        self.producer: str | None = None
        self.info: dict[str, Any] = {}
        self.skipped: list[str] = []
        self.stats: dict[str, int] = {"frames": 0, "dropped": 0, "incomplete": 0,
                                      "timeouts": 0, "reconnects": 0}
        self.timestamp_source: str | None = None
        self._ia: Any = None
        self._requested: CameraSettings | None = None
        self._settings: CameraSettings | None = None
        self._started = False
        self._last_id: int | None = None
        self._counter = 0
        self._tick_hz: int | None = None

    # ---------------------------------------------------------------- selection
    def _wanted(self) -> str:
        parts = [f"serial {self.serial!r}" if self.serial else "",
                 f"user id {self.user_id!r}" if self.user_id else "",
                 f"serial or user id {self.device!r}" if self.device else ""]
        return " and ".join(p for p in parts if p) or "any camera"

    def _matches(self, info: Any) -> bool:
        sn = _info_value(info, "serial_number")
        uid = _info_value(info, "user_defined_name")
        if self.serial and sn != self.serial:
            return False
        if self.user_id and uid != self.user_id:
            return False
        if self.device and self.device not in (sn, uid):
            return False
        return True

    def _find(self, h: Any) -> int | None:
        idx = [i for i, info in enumerate(h.device_info_list) if self._matches(info)]
        if len(idx) > 1 and not (self.serial or self.user_id or self.device or self.first):
            found = ", ".join(str(_info_value(h.device_info_list[i], "serial_number")) for i in idx)
            raise CameraError(f"{self.name}: {len(idx)} GenICam cameras (serials {found}); "
                              f"choose one by serial number or user id")
        return idx[0] if idx else None

    # ---------------------------------------------------------------- lifecycle
    def open(self) -> None:
        if self._ia is not None and self._ia.is_valid():
            return
        self._open(refresh="if_idle")

    def _open(self, refresh: str) -> None:
        """Find and open the camera. ``refresh``: when the device is not in the
        producer's list, re-enumerate ``"never"``, ``"if_idle"`` (no other camera open
        on the producer, since re-enumeration invalidates them) or ``"always"``."""
        core = _import_harvesters()
        producers = find_producers(self.producer_arg)
        if not producers:
            raise CameraError(f"{self.name}: no GenTL producer: set rig.producer or "
                              f"{ENV_VAR} (a directory holding the vendor's .cti)")
        for cti in producers:
            with _lock:
                h = harvester(cti)
                index = self._find(h)
                idle = not any(ia.is_valid() for ia in h.image_acquirers)
                if index is None and (refresh == "always" or (refresh == "if_idle" and idle)):
                    h = refresh_producer(cti)
                    index = self._find(h)
                if index is None:
                    continue
                info = h.device_info_list[index]
                try:
                    ia = h.create(index)
                except Exception as e:  # noqa: BLE001 - GenTL access denied/busy/...
                    raise CameraError(f"{self.name}: cannot open GenICam camera {self._wanted()} "
                                      f"on {os.path.basename(cti)}: {e}") from None
            self.producer = cti
            self.info = _describe(info, cti)
            self._ia = ia
            try:
                ia.num_buffers = max(self.num_buffers, 1)
            except Exception as e:  # noqa: BLE001
                log.debug("%s: num_buffers not set: %s", self.name, e)
            ia.add_callback(core.ImageAcquirer.Events.INCOMPLETE_BUFFER,
                            _incomplete_counter(core, self.stats))
            self._tick_hz = self._read_tick_hz(ia)
            self._last_id = None
            log.info("%s: opened GenICam camera %s %s serial %s (%s)", self.name,
                     self.info.get("vendor"), self.info.get("model"), self.info.get("serial"),
                     os.path.basename(cti))
            return
        raise CameraError(f"{self.name}: no GenICam camera with {self._wanted()} on "
                          f"{', '.join(os.path.basename(p) for p in producers)}")

    @staticmethod
    def _read_tick_hz(ia: Any) -> int | None:
        try:
            return int(ia.device.module.timestamp_frequency) or None
        except Exception:  # noqa: BLE001
            pass
        try:
            return int(ia.remote_device.node_map.GevTimestampTickFrequency.value) or None
        except Exception:  # noqa: BLE001
            return None

    def _require_ia(self) -> Any:
        if self._ia is None:
            raise CameraError(f"{self.name}: camera is not open")
        if not self._ia.is_valid():
            raise CameraLost(f"{self.name}: GenICam camera {self._wanted()} was lost")
        return self._ia

    def configure(self, settings: CameraSettings) -> CameraSettings:
        ia = self._require_ia()
        if self._started:
            raise CameraError(f"{self.name}: configure() while acquiring; stop() first")
        try:
            accepted, skipped = apply_settings(ia.remote_device.node_map, settings, self.wiring,
                                               self.name)
        except CameraError:
            raise
        except Exception as e:  # noqa: BLE001 - device gone mid-configuration
            if not ia.is_valid():
                raise CameraLost(f"{self.name}: lost while configuring: {e}") from None
            raise CameraError(f"{self.name}: configuration failed: {e}") from None
        if skipped:
            log.info("%s: features not set (absent or refused): %s", self.name, ", ".join(skipped))
        self.skipped = skipped
        self._requested = settings
        self._settings = accepted
        return accepted

    def start(self) -> None:
        ia = self._require_ia()
        if self._started:
            return
        try:
            ia.start()
        except Exception as e:  # noqa: BLE001
            if not ia.is_valid():
                raise CameraLost(f"{self.name}: lost while starting: {e}") from None
            raise CameraError(f"{self.name}: cannot start acquisition: {e}") from None
        self._started = True
        self._last_id = None

    def read(self, timeout_s: float = 1.0) -> Frame:
        ia = self._require_ia()
        if not self._started:
            raise CameraError(f"{self.name}: read() before start()")
        from genicam import gentl

        deadline = time.monotonic() + max(timeout_s, 0.0)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.stats["timeouts"] += 1
                raise CameraTimeout(f"{self.name}: no frame within {timeout_s:g} s")
            try:
                # try_fetch returns None on timeout *and* on an incomplete buffer (which
                # harvesters re-queues and reports to _CountIncomplete); loop to the deadline.
                buf = ia.try_fetch(timeout=remaining)
            except gentl.TimeoutException:
                continue
            except Exception as e:  # noqa: BLE001 - IoException, InvalidHandle, destroyed acquirer...
                raise CameraLost(f"{self.name}: GenICam camera lost: {type(e).__name__}: {e}") from None
            if buf is None:
                if not ia.is_valid():
                    raise CameraLost(f"{self.name}: GenICam camera {self._wanted()} was lost")
                continue
            try:
                return self._to_frame(buf)
            finally:
                try:
                    buf.queue()
                except Exception as e:  # noqa: BLE001
                    log.debug("%s: re-queue failed: %s", self.name, e)

    def _to_frame(self, buf: Any) -> Frame:
        host_ns = time.monotonic_ns()
        raw = buf.module
        try:
            fid = int(raw.frame_id)
        except Exception:  # noqa: BLE001 - producer without BUFFER_INFO_FRAMEID
            fid = self._counter
        self._counter = fid + 1
        if self._last_id is not None:
            gap = fid - self._last_id - 1
            if gap > 0:
                self.stats["dropped"] += gap
                log.warning("%s: %d frame(s) lost before frame id %d", self.name, gap, fid)
            elif gap < -1:
                log.warning("%s: frame id went back from %d to %d", self.name, self._last_id, fid)
        self._last_id = fid
        ts, self.timestamp_source = buffer_timestamp_ns(raw, self._tick_hz, host_ns)
        bit_depth = self._settings.bit_depth if self._settings else 8
        image = _to_image(buf.payload.components[0], bit_depth)
        self.stats["frames"] += 1
        return Frame(self.name, fid, ts, image)

    def trigger(self) -> None:
        ia = self._require_ia()
        if not self._settings or self._settings.trigger != "software":
            raise CameraError(f"{self.name}: trigger() needs trigger='software'")
        try:
            ia.remote_device.node_map.TriggerSoftware.execute()
        except Exception as e:  # noqa: BLE001
            raise CameraError(f"{self.name}: TriggerSoftware failed: {e}") from None

    def stop(self) -> None:
        self._started = False
        if self._ia is not None and self._ia.is_valid():
            try:
                self._ia.stop()
            except Exception as e:  # noqa: BLE001 - stopping a vanished device
                log.debug("%s: stop failed: %s", self.name, e)

    def close(self) -> None:
        self._started = False
        ia, self._ia = self._ia, None
        if ia is None:
            return
        try:
            ia.destroy()
        except Exception as e:  # noqa: BLE001
            log.debug("%s: destroy failed: %s", self.name, e)
        with _lock:
            for h in _harvesters.values():
                if ia in h.image_acquirers:
                    h.image_acquirers.remove(ia)

    def reconnect(self, max_tries: int = 5, backoff_s: float = 0.5, max_backoff_s: float = 8.0) -> None:
        """Close and reopen the camera after :class:`CameraLost`, re-applying the last
        requested settings and restarting acquisition if it was running.

        Tries ``max_tries`` times, sleeping ``backoff_s``·2ⁱ s (at most ``max_backoff_s``)
        between tries; the first try reuses the producer's device list, later ones
        re-enumerate it. Raises :class:`CameraLost` when the camera does not come back.
        """
        was_started = self._started
        self.close()
        last: Exception | None = None
        for attempt in range(max(1, max_tries)):
            if attempt:
                time.sleep(min(backoff_s * 2 ** (attempt - 1), max_backoff_s))
            try:
                self._open(refresh="always" if attempt else "never")
                if self._requested is not None:
                    self.configure(self._requested)
                if was_started:
                    self.start()
            except CameraError as e:
                last = e
                log.warning("%s: reconnect %d/%d failed: %s", self.name, attempt + 1, max_tries, e)
                self.close()
                continue
            self.stats["reconnects"] += 1
            log.info("%s: reconnected after %d tr%s", self.name, attempt + 1,
                     "y" if attempt == 0 else "ies")
            return
        raise CameraLost(f"{self.name}: camera {self._wanted()} did not come back after "
                         f"{max_tries} tries: {last}")


def _incomplete_counter(core: Any, stats: dict[str, int]) -> Any:
    """A harvesters ``Callback`` that counts incomplete buffers into ``stats``."""

    class _CountIncomplete(core.Callback):  # type: ignore[misc, name-defined]
        def emit(self, context: object = None) -> None:
            stats["incomplete"] += 1

    return _CountIncomplete()


# --------------------------------------------------------------------------- genicam:// URLs
def device_url(entry: dict[str, Any]) -> str:
    """The URL of a camera :func:`list_devices` found: ``genicam://SERIAL?cti=PRODUCER``."""
    return urls.make_url("genicam", entry.get("serial") or entry.get("user_id") or "*",
                         cti=entry.get("producer") or "")


def _check_url(u: urls.CameraURL) -> None:
    urls.int_option(u, "buffers", lo=1)
    if u.option("cti") == "":
        raise urls.fail(u, "option cti: give the GenTL producer's .cti path (or 'simulated')")


def _open_url(u: urls.CameraURL, *, name: str = "camera", producer: str | None = None,
              num_buffers: int | None = None, wiring: TriggerWiring | None = None) -> GenICamCamera:
    """``genicam://SERIAL?cti=PATH&buffers=N``: SERIAL is a serial number or user id, ''
    or ``*`` the first camera found; ``cti`` the producer (default ``producer``, else
    GENICAM_GENTL64_PATH)."""
    any_camera = u.target in ("", "*")
    return GenICamCamera(device=None if any_camera else u.target, producer=u.option("cti") or producer,
                         name=name, num_buffers=urls.int_option(u, "buffers") or num_buffers or 16,
                         wiring=wiring or TriggerWiring(), first=any_camera)


def _discover(producer: str | None = None, **_: Any) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    for cti in find_producers(producer):  # raises for a missing .cti
        try:
            out.extend({**d, "url": device_url(d)} for d in list_devices(cti))
        except CameraError as e:
            log.warning("genicam: %s: %s", cti, e)
    return out


urls.register(urls.Backend(
    "genicam", _open_url, target="host", what="serial number or user id",
    form="genicam://SERIAL?cti=PATH", options={"cti": "GenTL producer .cti path, or 'simulated'",
                                                 "buffers": "GenTL buffers announced (16)"},
    check=_check_url, rig_defaults={"cti": "producer"}, discover=_discover,
    summary="GenICam camera through harvesters and a GenTL producer"))
