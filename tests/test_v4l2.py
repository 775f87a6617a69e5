"""The V4L2 backend, driven through linuxpy's real streaming code.

There is no /dev/video here, so a fake capture device answers the ioctls: linuxpy's
module-level ``ioctl`` (the one ``linuxpy.video.device`` calls) is replaced by
:class:`FakeV4L2Device.ioctl` for file descriptors of the fake's memfd; everything else
(Device open, controls, REQBUFS/QUERYBUF/mmap of the memfd, QBUF/DQBUF, select,
STREAMON/OFF) is linuxpy's own code. The fake writes each frame's pixels into the mmap'ed
buffer region of the memfd, as a driver's DMA would, so pixel content, sequence numbers
and timestamps are checked end to end.
"""

from __future__ import annotations

import ctypes
import errno
import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("linuxpy")
from linuxpy import util as lp_util  # noqa: E402
from linuxpy.video import device as vd  # noqa: E402
from linuxpy.video import raw  # noqa: E402

from iscd.drivers import v4l2  # noqa: E402
from iscd.drivers.base import CameraError, CameraLost, CameraSettings, CameraTimeout, Roi  # noqa: E402

IOC = raw.IOC
PAGE = 4096
SENSOR_W, SENSOR_H = 320, 240
MAX_FPS = 500.0
T0_NS = 1_000_000_000_000  # the fake's CLOCK_MONOTONIC at sequence 0


def _err(code: int) -> OSError:
    return OSError(code, os.strerror(code))


class FakeV4L2Device:
    """A monochrome V4L2 capture device (GREY and Y16) over a memfd.

    Frame with sequence n has pixel (x, y) of the sensor = (3x + 5y + n) mod 256 (GREY)
    or (7x + 11y + 13n) mod 4096 (Y16), and timestamp T0 + n/fps (µs resolution, as a
    timeval). Rows are padded to a multiple of 64 bytes. Knobs: ``frames_left`` (DQBUF
    says EAGAIN when it reaches 0), ``gaps`` {sequence: n} (n frames skipped after that
    sequence, as a driver does when it had no free buffer), ``error_seqs`` (buffers
    flagged V4L2_BUF_FLAG_ERROR), ``lost`` (every ioctl fails with ENODEV), ``soe``
    (start-of-exposure timestamps, else end-of-frame).
    """

    def __init__(self) -> None:
        self.memfd = os.memfd_create("fake-video", 0)
        self.path = f"/proc/self/fd/{self.memfd}"
        self.ino = os.fstat(self.memfd).st_ino
        self.width, self.height, self.fourcc = 640, 480, "GREY"
        self.crop = (0, 0)
        self.fps = 30.0
        self.controls = {
            int(raw.ControlID.CAMERA_CLASS): dict(type=raw.CtrlType.CTRL_CLASS, name=b"Camera Controls",
                                                  min=0, max=0, step=0, value=0, flags=0x0044),
            int(raw.ControlID.EXPOSURE_AUTO): dict(type=raw.CtrlType.MENU, name=b"Auto Exposure",
                                                   min=0, max=3, step=1, value=3, flags=0),
            int(raw.ControlID.EXPOSURE_ABSOLUTE): dict(type=raw.CtrlType.INTEGER,
                                                       name=b"Exposure Time, Absolute",
                                                       min=1, max=5000, step=1, value=333, flags=0),
        }
        self.menus = {int(raw.ControlID.EXPOSURE_AUTO): [b"Auto Mode", b"Manual Mode",
                                                         b"Shutter Priority Mode",
                                                         b"Aperture Priority Mode"]}
        self.nbuf = 0
        self.buf_stride = 0
        self.queued: list[int] = []
        self.streaming = False
        self.seq = 0
        self.frames_left: int | None = None
        self.gaps: dict[int, int] = {}
        self.error_seqs: set[int] = set()
        self.lost = False
        self.soe = True
        self.calls: list[str] = []

    # ------------------------------------------------------------------ geometry
    @property
    def bpp(self) -> int:
        return 2 if self.fourcc == "Y16" else 1

    @property
    def bytesperline(self) -> int:
        return -(-self.width * self.bpp // 64) * 64

    @property
    def sizeimage(self) -> int:
        return self.bytesperline * self.height

    def expected(self, seq: int) -> np.ndarray:
        """The image (height, width) this fake delivers for sequence ``seq``."""
        x0, y0 = self.crop
        y, x = np.mgrid[y0:y0 + self.height, x0:x0 + self.width]
        if self.fourcc == "Y16":
            return ((7 * x + 11 * y + 13 * seq) % 4096).astype(np.uint16)
        return ((3 * x + 5 * y + seq) % 256).astype(np.uint8)

    def timestamp_ns(self, seq: int) -> int:
        return T0_NS + seq * int(round(1e6 / self.fps)) * 1000  # whole µs per frame

    # ------------------------------------------------------------------ dispatch
    def owns(self, fd: int) -> bool:
        try:
            return os.fstat(fd).st_ino == self.ino
        except OSError:
            return False

    def ioctl(self, fd: int, request: int, *args: object) -> object:
        name = IOC(request).name
        self.calls.append(name)
        if self.lost:
            raise _err(errno.ENODEV)
        handler = getattr(self, f"_{name.lower()}", None)
        if handler is None:
            raise _err(errno.ENOTTY)
        arg = args[0] if args else None
        handler(arg)
        return arg

    def _querycap(self, caps: raw.v4l2_capability) -> None:
        caps.driver = b"fakecam"
        caps.card = b"Fake mono camera"
        caps.bus_info = b"platform:fake"
        caps.version = (6 << 16) | (1 << 8)
        dc = raw.Capability.VIDEO_CAPTURE | raw.Capability.STREAMING | raw.Capability.EXT_PIX_FORMAT
        caps.device_caps = dc
        caps.capabilities = dc | raw.Capability.DEVICE_CAPS

    def _enum_fmt(self, f: raw.v4l2_fmtdesc) -> None:
        fmts = [("GREY", b"8-bit Greyscale"), ("Y16", b"16-bit Greyscale")]
        if f.type != raw.BufType.VIDEO_CAPTURE or f.index >= len(fmts):
            raise _err(errno.EINVAL)
        fourcc, desc = fmts[f.index]
        f.pixelformat = raw.v4l2_fourcc(*fourcc.ljust(4))
        f.description = desc
        f.flags = 0

    def _fill_fmt(self, f: raw.v4l2_format) -> None:
        p = f.fmt.pix
        p.width, p.height = self.width, self.height
        p.pixelformat = raw.v4l2_fourcc(*self.fourcc.ljust(4))
        p.field = raw.Field.NONE
        p.bytesperline = self.bytesperline
        p.sizeimage = self.sizeimage

    def _s_fmt(self, f: raw.v4l2_format) -> None:
        if self.nbuf:
            raise _err(errno.EBUSY)
        p = f.fmt.pix
        self.width = int(min(max(p.width, 16), SENSOR_W)) // 2 * 2
        self.height = int(min(max(p.height, 16), SENSOR_H)) // 2 * 2
        self.fourcc = "Y16" if p.pixelformat == raw.v4l2_fourcc(*"Y16 ") else "GREY"
        self.crop = (min(self.crop[0], SENSOR_W - self.width), min(self.crop[1], SENSOR_H - self.height))
        self._fill_fmt(f)

    def _g_fmt(self, f: raw.v4l2_format) -> None:
        self._fill_fmt(f)

    def _s_selection(self, sel: raw.v4l2_selection) -> None:
        if sel.target != raw.SelectionTarget.CROP:
            raise _err(errno.EINVAL)
        self.crop = (int(min(sel.r.left, SENSOR_W - self.width)) // 2 * 2,
                     int(min(sel.r.top, SENSOR_H - self.height)) // 2 * 2)

    def _g_selection(self, sel: raw.v4l2_selection) -> None:
        sel.r.left, sel.r.top = self.crop
        sel.r.width, sel.r.height = self.width, self.height

    def _s_parm(self, p: raw.v4l2_streamparm) -> None:
        tpf = p.parm.capture.timeperframe
        self.fps = min(MAX_FPS, tpf.denominator / tpf.numerator)
        self._g_parm(p)

    def _g_parm(self, p: raw.v4l2_streamparm) -> None:
        p.parm.capture.capability = raw.Capability.TIMEPERFRAME
        p.parm.capture.timeperframe.numerator = 1000
        p.parm.capture.timeperframe.denominator = int(round(self.fps * 1000))

    def _query_ext_ctrl(self, q: raw.v4l2_query_ext_ctrl) -> None:
        flags = int(raw.ControlFlag.NEXT_CTRL | raw.ControlFlag.NEXT_COMPOUND)
        cid = q.id & ~flags
        if q.id & flags:
            ids = sorted(i for i in self.controls if i > cid)
            if not ids:
                raise _err(errno.EINVAL)
            cid = ids[0]
        elif cid not in self.controls:
            raise _err(errno.EINVAL)
        c = self.controls[cid]
        q.id, q.type, q.name = cid, c["type"], c["name"]
        q.minimum, q.maximum, q.step, q.default_value = c["min"], c["max"], c["step"], c["value"]
        q.flags, q.elem_size, q.elems, q.nr_of_dims = c["flags"], 4, 1, 0

    def _querymenu(self, m: raw.v4l2_querymenu) -> None:
        names = self.menus.get(m.id, [])
        if m.index >= len(names):
            raise _err(errno.EINVAL)
        m.name = names[m.index]

    def _g_ext_ctrls(self, ctrls: raw.v4l2_ext_controls) -> None:
        for i in range(ctrls.count):
            c = ctrls.controls[i]
            if c.id not in self.controls:
                raise _err(errno.EINVAL)
            c.value = self.controls[c.id]["value"]

    def _s_ext_ctrls(self, ctrls: raw.v4l2_ext_controls) -> None:
        for i in range(ctrls.count):
            c = ctrls.controls[i]
            spec = self.controls.get(c.id)
            if spec is None:
                raise _err(errno.EINVAL)
            if not spec["min"] <= c.value <= spec["max"]:
                raise _err(errno.ERANGE)
            spec["value"] = int(c.value)

    def _reqbufs(self, req: raw.v4l2_requestbuffers) -> None:
        if req.memory != raw.Memory.MMAP:
            raise _err(errno.EINVAL)
        if self.streaming:
            raise _err(errno.EBUSY)
        self.nbuf = min(int(req.count), 32)
        self.queued.clear()
        self.buf_stride = -(-self.sizeimage // PAGE) * PAGE
        os.ftruncate(self.memfd, self.nbuf * self.buf_stride)
        req.count = self.nbuf

    def _querybuf(self, b: raw.v4l2_buffer) -> None:
        if b.index >= self.nbuf:
            raise _err(errno.EINVAL)
        b.length = self.sizeimage
        b.m.offset = b.index * self.buf_stride
        b.flags = raw.BufferFlag.MAPPED

    def _qbuf(self, b: raw.v4l2_buffer) -> None:
        if b.index >= self.nbuf or b.index in self.queued:
            raise _err(errno.EINVAL)
        self.queued.append(int(b.index))

    def _streamon(self, btype: ctypes.c_uint) -> None:
        if not self.nbuf:
            raise _err(errno.EINVAL)
        self.streaming = True

    def _streamoff(self, btype: ctypes.c_uint) -> None:
        self.streaming = False
        self.queued.clear()

    def _dqbuf(self, b: raw.v4l2_buffer) -> None:
        if not self.streaming:
            raise _err(errno.EINVAL)
        if not self.queued or self.frames_left == 0:
            raise BlockingIOError(errno.EAGAIN, "Resource temporarily unavailable")
        if self.frames_left is not None:
            self.frames_left -= 1
        index = self.queued.pop(0)
        seq = self.seq
        img = self.expected(seq)
        rows = np.full((self.height, self.bytesperline), 0xAB, np.uint8)  # row padding: junk
        rows[:, : self.width * self.bpp] = img.astype("<u2").view(np.uint8) if self.bpp == 2 else img
        os.pwrite(self.memfd, rows.tobytes(), index * self.buf_stride)
        ts = self.timestamp_ns(seq)
        b.index = index
        b.bytesused = self.sizeimage
        b.field = raw.Field.NONE
        b.sequence = seq
        b.timestamp.secs, b.timestamp.usecs = ts // 1_000_000_000, ts % 1_000_000_000 // 1000
        b.flags = (raw.BufferFlag.MAPPED | raw.BufferFlag.DONE | raw.BufferFlag.TIMESTAMP_MONOTONIC
                   | (raw.BufferFlag.TSTAMP_SRC_SOE if self.soe else 0)
                   | (raw.BufferFlag.ERROR if seq in self.error_seqs else 0))
        self.seq = seq + 1 + self.gaps.get(seq, 0)

    def close(self) -> None:
        os.close(self.memfd)


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch):
    dev = FakeV4L2Device()
    real_ioctl = vd.ioctl

    def ioctl(fd, request, *args):
        n = lp_util.to_fd(fd)
        if dev.owns(n):
            return dev.ioctl(n, request, *args)
        return real_ioctl(fd, request, *args)  # pragma: no cover - no real devices here

    monkeypatch.setattr(vd, "ioctl", ioctl)
    yield dev
    dev.close()


@pytest.fixture
def cam(fake: FakeV4L2Device):
    c = v4l2.V4L2Camera(fake.path, name="left", num_buffers=4)
    c.open()
    yield c
    c.close()


def test_configure_maps_format_roi_fps_and_exposure(cam: v4l2.V4L2Camera, fake: FakeV4L2Device):
    acc = cam.configure(CameraSettings(fps=1000, exposure_s=1e-3, roi=Roi(32, 16, 200, 120)))
    # format and crop reached the device, fps was clamped by the driver and read back
    assert (fake.width, fake.height, fake.fourcc, fake.crop) == (200, 120, "GREY", (32, 16))
    assert acc.roi == Roi(32, 16, 200, 120)
    assert acc.fps == pytest.approx(MAX_FPS)
    assert acc.pixel_format == "Mono8"
    # 1 ms = 10 units of 100 µs; auto exposure switched to manual (menu index 1)
    assert fake.controls[int(raw.ControlID.EXPOSURE_ABSOLUTE)]["value"] == 10
    assert fake.controls[int(raw.ControlID.EXPOSURE_AUTO)]["value"] == 1
    assert acc.exposure_s == pytest.approx(1e-3)
    assert "S_FMT" in fake.calls and "S_PARM" in fake.calls and "S_SELECTION" in fake.calls
    # an exposure beyond the control's range is clamped by linuxpy and read back
    acc = cam.configure(CameraSettings(fps=1.0, exposure_s=0.9))
    assert fake.controls[int(raw.ControlID.EXPOSURE_ABSOLUTE)]["value"] == 5000
    assert acc.exposure_s == pytest.approx(0.5)
    assert acc.fps == pytest.approx(1.0)


def test_unsupported_settings_are_reported(cam: v4l2.V4L2Camera, fake: FakeV4L2Device):
    with pytest.raises(CameraError, match="does not offer Mono12"):
        cam.configure(CameraSettings(pixel_format="Mono12"))
    acc = cam.configure(CameraSettings(fps=100, exposure_s=1e-3, gain_db=6.0, trigger="slave",
                                       roi=Roi(0, 0, 64, 48)))
    assert acc.trigger == "free"
    assert "trigger" in cam.skipped and "gain" in cam.skipped


def test_stream_pixels_sequence_and_timestamps(cam: v4l2.V4L2Camera, fake: FakeV4L2Device):
    acc = cam.configure(CameraSettings(fps=200, exposure_s=1e-3, roi=Roi(10, 6, 100, 50)))
    assert acc.roi == Roi(10, 6, 100, 50)
    cam.start()
    assert fake.streaming and "REQBUFS" in fake.calls and "QUERYBUF" in fake.calls
    frames = [cam.read(timeout_s=1.0) for _ in range(40)]
    assert [f.frame_id for f in frames] == list(range(40))
    for f in frames:
        assert f.image.shape == (50, 100) and f.image.dtype == np.uint8
        np.testing.assert_array_equal(f.image, fake.expected(f.frame_id))
        assert f.timestamp_ns == fake.timestamp_ns(f.frame_id)
    assert np.diff([f.timestamp_ns for f in frames]).tolist() == [5_000_000] * 39
    assert cam.timestamp_source == "device"
    assert cam.stats["frames"] == 40 and cam.stats["dropped"] == 0
    # 4 buffers cycle: every buffer was handed back (QBUF) after being read
    assert fake.calls.count("DQBUF") == 40 and fake.calls.count("QBUF") == 44
    cam.stop()
    assert not fake.streaming and fake.nbuf == 0


def test_sequence_gap_is_counted_as_dropped(cam: v4l2.V4L2Camera, fake: FakeV4L2Device):
    cam.configure(CameraSettings(fps=100, exposure_s=1e-3, roi=Roi(0, 0, 64, 32)))
    fake.gaps = {4: 3, 9: 1}  # after sequence 4 three frames are lost, after 9 one
    cam.start()
    frames = [cam.read(1.0) for _ in range(10)]
    ids = [f.frame_id for f in frames]
    assert ids == [0, 1, 2, 3, 4, 8, 9, 11, 12, 13]
    assert cam.stats["dropped"] == 4
    for f in frames:  # content still matches each frame's own sequence number
        np.testing.assert_array_equal(f.image, fake.expected(f.frame_id))


def test_error_flagged_buffer_is_dropped(cam: v4l2.V4L2Camera, fake: FakeV4L2Device):
    cam.configure(CameraSettings(fps=100, exposure_s=1e-3, roi=Roi(0, 0, 64, 32)))
    fake.error_seqs = {2}
    cam.start()
    ids = [cam.read(1.0).frame_id for _ in range(4)]
    assert ids == [0, 1, 3, 4]
    assert cam.stats["errors"] == 1


def test_mono16_and_end_of_frame_timestamps(cam: v4l2.V4L2Camera, fake: FakeV4L2Device):
    acc = cam.configure(CameraSettings(fps=100, exposure_s=2e-3, roi=Roi(0, 0, 48, 20),
                                       pixel_format="Mono16"))
    assert acc.pixel_format == "Mono16" and fake.fourcc == "Y16"
    fake.soe = False  # end-of-frame stamps: the driver subtracts the exposure time
    cam.start()
    f = cam.read(1.0)
    assert f.image.dtype == np.uint16 and f.image.shape == (20, 48)
    np.testing.assert_array_equal(f.image, fake.expected(f.frame_id))
    assert f.image.max() > 255
    assert f.timestamp_ns == fake.timestamp_ns(f.frame_id) - 2_000_000


def test_timeout_when_no_frame_arrives(cam: v4l2.V4L2Camera, fake: FakeV4L2Device):
    cam.configure(CameraSettings(fps=100, exposure_s=1e-3, roi=Roi(0, 0, 32, 32)))
    fake.frames_left = 2
    cam.start()
    cam.read(0.5), cam.read(0.5)
    with pytest.raises(CameraTimeout):
        cam.read(timeout_s=0.05)
    assert cam.stats["timeouts"] == 1
    fake.frames_left = None  # the stream resumes
    assert cam.read(0.5).frame_id == 2


def test_device_loss_raises_camera_lost(cam: v4l2.V4L2Camera, fake: FakeV4L2Device):
    cam.configure(CameraSettings(fps=100, exposure_s=1e-3, roi=Roi(0, 0, 32, 32)))
    cam.start()
    cam.read(0.5)
    fake.lost = True
    with pytest.raises(CameraLost):
        cam.read(0.5)
    cam.stop()  # stopping a vanished device does not raise
    cam.close()


def test_open_errors_are_one_line(tmp_path: Path):
    with pytest.raises(CameraError, match="not found"):
        v4l2.V4L2Camera(str(tmp_path / "video9")).open()
    cam = v4l2.V4L2Camera(str(tmp_path / "video9"))
    with pytest.raises(CameraError, match="not open"):
        cam.configure(CameraSettings())
    with pytest.raises(CameraError, match="before start"):
        cam.read(0.01)


def test_list_devices_queries_capabilities(fake: FakeV4L2Device, tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch):
    (tmp_path / "video0").symlink_to(fake.path)
    monkeypatch.setattr(v4l2, "V4L2_GLOB", str(tmp_path / "video*"))
    (entry,) = v4l2.list_devices()
    assert entry["device"] == str(tmp_path / "video0")
    assert entry["card"] == "Fake mono camera" and entry["driver"] == "fakecam"
    assert entry["formats"] == ["GREY", "Y16"] and entry["mono"] is True
    assert v4l2.list_devices(str(tmp_path / "nothing*")) == []


def test_pure_helpers():
    data = bytes(range(12)) * 2  # 2 rows of 12 bytes, 5 px used
    img = v4l2.to_image(data, 5, 2, 12, 1)
    np.testing.assert_array_equal(img, [[0, 1, 2, 3, 4], [0, 1, 2, 3, 4]])
    img16 = v4l2.to_image(np.array([1, 256, 0, 0x0FFF], "<u2").tobytes(), 2, 2, 4, 2)
    np.testing.assert_array_equal(img16, [[1, 256], [0, 4095]])
    with pytest.raises(CameraError):
        v4l2.to_image(b"\0" * 5, 4, 2, 4, 1)
    mono = v4l2.BUF_FLAG_TIMESTAMP_MONOTONIC
    assert v4l2.v4l2_timestamp_ns(2, 500, mono | v4l2.BUF_FLAG_TSTAMP_SRC_SOE, 10, 7) == (2_000_500_000, "device")
    assert v4l2.v4l2_timestamp_ns(2, 500, mono, 1000, 7) == (2_000_499_000, "device")
    assert v4l2.v4l2_timestamp_ns(0, 0, mono, 0, 7) == (7, "host")
    assert v4l2.v4l2_timestamp_ns(2, 0, 0x4000, 0, 7) == (7, "host")  # TIMESTAMP_COPY
