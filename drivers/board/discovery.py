"""Find LED boards on USB by VID:PID: pyusb for the devices, pyserial for their tty.

The board is a USB CDC-ACM device (a virtual serial port) with a unique serial-number
string descriptor. :func:`find_boards` asks pyusb for every device with the board's
VID:PID (it sees them even when no serial driver is bound, and reads their serial
numbers), and pyserial's ``list_ports.comports()`` for the ``/dev/tty*`` ports with the
same VID:PID; it matches the two by serial number, else by USB location (bus-ports).

The default ID is pid.codes' test pair 1209:0001, free for prototypes and tests only; a
production board gets its own PID and the ``[board]`` config section's ``vid`` / ``pid``
name it.

Without libusb (pyusb raises NoBackendError) the pyserial list alone is used.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)

DEFAULT_VID = 0x1209
"""pid.codes (open-source hardware vendor ID)."""
DEFAULT_PID = 0x0001
"""pid.codes' test PID: for development and tests; never ship it."""


@dataclass(frozen=True)
class FoundBoard:
    """One board found on USB."""

    device: str | None
    """Serial port to open (``/dev/ttyACM0``), or None: on USB but without a tty (no
    CDC-ACM driver bound, or a bad cable/permissions)."""
    serial_number: str | None
    vid: int
    pid: int
    location: str | None
    """USB bus and port path, ``1-1.2``."""
    description: str = ""
    seen_by: tuple[str, ...] = ()
    """``"usb"`` (pyusb), ``"serial"`` (pyserial) or both."""

    def as_dict(self) -> dict[str, Any]:
        return {"device": self.device, "serial_number": self.serial_number,
                "usb_id": f"{self.vid:04x}:{self.pid:04x}", "location": self.location,
                "description": self.description, "seen_by": list(self.seen_by)}


@dataclass(frozen=True)
class _UsbDevice:
    serial_number: str | None
    location: str | None
    product: str | None


def _safe_str(get: Callable[[], Any]) -> str | None:
    """A string descriptor, or None if the device cannot be asked (permissions, no langid)."""
    try:
        v = get()
    except Exception as e:  # noqa: BLE001 - pyusb raises USBError, ValueError, NotImplementedError
        log.debug("USB string descriptor not readable: %s", e)
        return None
    return str(v) if v is not None else None


def _usb_location(dev: Any) -> str | None:
    bus = getattr(dev, "bus", None)
    ports = getattr(dev, "port_numbers", None)
    if bus is None or not ports:
        return None
    return f"{int(bus)}-{'.'.join(str(int(p)) for p in ports)}"


def usb_devices(vid: int, pid: int, backend: Any = None) -> list[_UsbDevice] | None:
    """pyusb's view: devices with ``vid:pid``; None when pyusb has no backend (no libusb)."""
    try:
        import usb.core
    except ImportError:  # pragma: no cover - pyusb is a dependency
        return None
    try:
        found = list(usb.core.find(find_all=True, idVendor=vid, idProduct=pid, backend=backend) or [])
    except usb.core.NoBackendError:
        log.debug("pyusb: no backend (libusb not installed); using the serial port list only")
        return None
    except (usb.core.USBError, OSError) as e:
        log.warning("pyusb could not enumerate USB devices: %s", e)
        return None
    out = []
    for dev in found:
        out.append(_UsbDevice(serial_number=_safe_str(lambda d=dev: d.serial_number),
                              location=_usb_location(dev),
                              product=_safe_str(lambda d=dev: d.product)))
        try:
            import usb.util
            usb.util.dispose_resources(dev)
        except Exception:  # noqa: BLE001
            pass
    return out


def find_boards(vid: int = DEFAULT_VID, pid: int = DEFAULT_PID, *, usb_backend: Any = None,
                comports: Callable[[], Iterable[Any]] | None = None, use_usb: bool = True) -> list[FoundBoard]:
    """Every board with USB ID ``vid:pid``, ports first, sorted by device path.

    ``usb_backend``: a pyusb backend (None: pyusb's default, libusb); ``comports``: the
    port lister (None: ``serial.tools.list_ports.comports``). Both are parameters so that
    tests can pass fakes.
    """
    if comports is None:
        from serial.tools import list_ports

        comports = list_ports.comports
    ports = [p for p in comports() if getattr(p, "vid", None) == vid and getattr(p, "pid", None) == pid]
    usb = usb_devices(vid, pid, usb_backend) if use_usb else None

    boards: list[FoundBoard] = []
    unmatched = list(usb or [])
    for p in ports:
        loc = (getattr(p, "location", None) or "").split(":")[0] or None
        sn = getattr(p, "serial_number", None)
        match = next((u for u in unmatched if sn and u.serial_number == sn), None)
        if match is None:
            match = next((u for u in unmatched if loc and u.location == loc), None)
        if match is not None:
            unmatched.remove(match)
        boards.append(FoundBoard(
            device=p.device, serial_number=sn or (match.serial_number if match else None), vid=vid, pid=pid,
            location=loc or (match.location if match else None),
            description=str(getattr(p, "description", "") or (match.product if match else "") or ""),
            seen_by=("usb", "serial") if match else ("serial",)))
    boards.sort(key=lambda b: b.device or "")
    for u in unmatched:
        boards.append(FoundBoard(device=None, serial_number=u.serial_number, vid=vid, pid=pid,
                                 location=u.location, description=u.product or "", seen_by=("usb",)))
    return boards
