"""USB discovery of LED boards: pyusb (with a fake backend) + pyserial's port list (faked),
and the ``[board]`` config section."""

from __future__ import annotations

import array
from dataclasses import dataclass, field

import pytest
import usb.backend
import usb.core
from serial.tools.list_ports_common import ListPortInfo

from iscd.drivers.board.discovery import DEFAULT_PID, DEFAULT_VID, FoundBoard, find_boards, usb_devices
from iscd.drivers.board.settings import BoardSettings, board_settings
from iscd.core.config import ConfigError, loads


@dataclass
class FakeUsbDevice:
    vid: int
    pid: int
    bus: int
    ports: tuple[int, ...]
    serial: str | None = None
    product: str = "iscd LED board"
    locked: bool = False  # string descriptors unreadable (no permission)
    address: int = field(default=0)


@dataclass
class _Descriptor:
    """A device descriptor with every field pyusb's Device copies."""

    idVendor: int
    idProduct: int
    iSerialNumber: int
    bus: int
    address: int
    port_number: int
    port_numbers: tuple[int, ...]
    bLength: int = 18
    bDescriptorType: int = 1
    bcdUSB: int = 0x0200
    bDeviceClass: int = 2  # CDC
    bDeviceSubClass: int = 0
    bDeviceProtocol: int = 0
    bMaxPacketSize0: int = 64
    bcdDevice: int = 0x0100
    iManufacturer: int = 1
    iProduct: int = 2
    bNumConfigurations: int = 1
    speed: int = 2


class FakeBackend(usb.backend.IBackend):
    """A pyusb backend that enumerates FakeUsbDevices and answers GET_DESCRIPTOR(string)."""

    def __init__(self, devices: list[FakeUsbDevice]) -> None:
        self.devices = devices
        self.opened: list[FakeUsbDevice] = []

    def enumerate_devices(self):
        return iter(self.devices)

    def get_device_descriptor(self, dev: FakeUsbDevice) -> _Descriptor:
        return _Descriptor(dev.vid, dev.pid, 3 if dev.serial else 0, dev.bus, dev.address,
                           dev.ports[-1], dev.ports)

    def open_device(self, dev: FakeUsbDevice) -> FakeUsbDevice:
        self.opened.append(dev)
        return dev

    def close_device(self, dev_handle: FakeUsbDevice) -> None:
        pass

    def ctrl_transfer(self, dev_handle: FakeUsbDevice, bmRequestType: int, bRequest: int, wValue: int,
                      wIndex: int, data: array.array, timeout: int) -> int:
        if dev_handle.locked:
            raise usb.core.USBError("Access denied (insufficient permissions)", errno=13)
        assert bmRequestType == 0x80 and bRequest == 0x06 and wValue >> 8 == 3  # GET_DESCRIPTOR(STRING)
        index = wValue & 0xFF
        if index == 0:
            desc = bytes([4, 3, 0x09, 0x04])  # LANGID en-US
        else:
            assert wIndex == 0x0409
            text = {1: "iscd", 2: dev_handle.product, 3: dev_handle.serial}[index] or ""
            raw = text.encode("utf-16-le")
            desc = bytes([2 + len(raw), 3]) + raw
        n = min(len(data), len(desc))
        data[:n] = array.array("B", desc[:n])
        return n


def port(device: str, vid: int | None, pid: int | None, serial: str | None = None,
         location: str | None = None) -> ListPortInfo:
    p = ListPortInfo(device, skip_link_detection=True)
    p.vid, p.pid, p.serial_number, p.location = vid, pid, serial, location
    p.product, p.interface = "iscd LED board", None
    p.apply_usb_info()
    return p


def test_pyusb_fake_backend_enumerates_with_serial_numbers() -> None:
    backend = FakeBackend([FakeUsbDevice(DEFAULT_VID, DEFAULT_PID, 1, (1, 4), "A1"),
                           FakeUsbDevice(0x046D, 0xC52B, 1, (2,), "mouse")])
    # pyusb itself, with our backend: only the board matches
    devs = list(usb.core.find(find_all=True, idVendor=DEFAULT_VID, backend=backend))
    assert [d.serial_number for d in devs] == ["A1"]
    got = usb_devices(DEFAULT_VID, DEFAULT_PID, backend)
    assert got is not None and [(u.serial_number, u.location, u.product) for u in got] == \
        [("A1", "1-1.4", "iscd LED board")]


def test_find_boards_maps_usb_devices_to_their_ttys() -> None:
    backend = FakeBackend([
        FakeUsbDevice(DEFAULT_VID, DEFAULT_PID, 1, (1, 2), "B0002"),
        FakeUsbDevice(DEFAULT_VID, DEFAULT_PID, 3, (1,), "B0001"),
        FakeUsbDevice(DEFAULT_VID, DEFAULT_PID, 2, (4,), "B0003"),  # no tty: no CDC driver bound
        FakeUsbDevice(0x0403, 0x6001, 1, (3,), "FTDI"),  # another device
    ])
    ports = [
        port("/dev/ttyACM1", DEFAULT_VID, DEFAULT_PID, "B0002", "1-1.2:1.0"),
        port("/dev/ttyUSB0", 0x0403, 0x6001, "FTDI", "1-3"),
        port("/dev/ttyACM0", DEFAULT_VID, DEFAULT_PID, "B0001", "3-1:1.0"),
        port("/dev/ttyS0", None, None),
    ]
    boards = find_boards(usb_backend=backend, comports=lambda: ports)
    assert [(b.device, b.serial_number, b.location, b.seen_by) for b in boards] == [
        ("/dev/ttyACM0", "B0001", "3-1", ("usb", "serial")),
        ("/dev/ttyACM1", "B0002", "1-1.2", ("usb", "serial")),
        (None, "B0003", "2-4", ("usb",)),
    ]
    assert boards[0].as_dict()["usb_id"] == "1209:0001"


def test_match_by_location_when_serials_are_unknown() -> None:
    # the USB device refuses its string descriptors; the port list has no serial number
    backend = FakeBackend([FakeUsbDevice(DEFAULT_VID, DEFAULT_PID, 1, (1, 3), "X", locked=True)])
    ports = [port("/dev/ttyACM7", DEFAULT_VID, DEFAULT_PID, None, "1-1.3:1.0")]
    (b,) = find_boards(usb_backend=backend, comports=lambda: ports)
    assert (b.device, b.serial_number, b.location, b.seen_by) == ("/dev/ttyACM7", None, "1-1.3", ("usb", "serial"))


def test_custom_vid_pid() -> None:
    backend = FakeBackend([FakeUsbDevice(0x16C0, 0x05DC, 1, (1,), "P1"),
                           FakeUsbDevice(DEFAULT_VID, DEFAULT_PID, 1, (2,), "T1")])
    ports = [port("/dev/ttyACM0", 0x16C0, 0x05DC, "P1", "1-1:1.0"),
             port("/dev/ttyACM1", DEFAULT_VID, DEFAULT_PID, "T1", "1-2:1.0")]
    boards = find_boards(0x16C0, 0x05DC, usb_backend=backend, comports=lambda: ports)
    assert [b.device for b in boards] == ["/dev/ttyACM0"]


def test_without_libusb_the_port_list_alone_is_used(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_backend(*a, **k):
        raise usb.core.NoBackendError("No backend available")

    monkeypatch.setattr(usb.core, "find", no_backend)
    ports = [port("/dev/ttyACM0", DEFAULT_VID, DEFAULT_PID, "S1", "1-1:1.0")]
    assert usb_devices(DEFAULT_VID, DEFAULT_PID) is None
    assert find_boards(comports=lambda: ports) == [
        FoundBoard("/dev/ttyACM0", "S1", DEFAULT_VID, DEFAULT_PID, "1-1", "iscd LED board", ("serial",))]


def test_board_config_section() -> None:
    cfg = loads('[board]\nport = "/dev/ttyACM3"\nvid = 0x16c0\npid = 0x05dc\ntimeout_s = 0.5\nretries = 1\n')
    s = board_settings(cfg)
    assert s == BoardSettings(port="/dev/ttyACM3", vid=0x16C0, pid=0x05DC, timeout_s=0.5, retries=1)
    assert board_settings(loads("")) == BoardSettings()
    for text, msg in [("vid = 70000", "board.vid: expected an integer <= 65535, got 70000"),
                      ("timeout_s = 0", "board.timeout_s: expected a number > 0, got 0"),
                      ("retries = -1", "board.retries: expected an integer >= 0, got -1"),
                      ("speed = 3", "board.speed: unknown key")]:
        with pytest.raises(ConfigError) as e:
            board_settings(loads("[board]\n" + text))
        assert str(e.value).startswith(msg)
