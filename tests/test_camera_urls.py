"""Cameras opened by URL (iscd.drivers.urls): parsing, dispatch by scheme to the registered
backends, the config's [rig] URLs and the old keys they replace, and `iscd devices`.

The backends run for real where the repo's tests can run them: the mock rig; GenICam through
harvesters on the simulated producer of the genicam wheel (viky.cti; skipped when absent);
V4L2 through linuxpy's own code over the fake capture device of tests/test_v4l2.py.
"""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from iscd.drivers import registry, urls
from iscd.drivers.base import CameraError
from fakes import FakeCamera
from iscd.cli import main as cli
from iscd.core.config import ConfigError, default_config, loads

SMALL_CAMERA = "[camera]\nwidth = 128\nheight = 128\n"


def one_line(e: BaseException) -> str:
    msg = str(e)
    assert "\n" not in msg and "Traceback" not in msg, msg
    return msg


# ------------------------------------------------------------------ parsing

@pytest.mark.parametrize("url, scheme, target, options", [
    ("mock://default", "mock", "default", {}),
    ("mock://default?seed=7&noise=false", "mock", "default", {"seed": "7", "noise": "false"}),
    ("MOCK://default", "mock", "default", {}),
    ("genicam://21345678?cti=/opt/vendor/lib/x.cti", "genicam", "21345678", {"cti": "/opt/vendor/lib/x.cti"}),
    ("genicam://*?cti=simulated", "genicam", "*", {"cti": "simulated"}),
    ("genicam://?cti=simulated&buffers=4", "genicam", "", {"cti": "simulated", "buffers": "4"}),
    ("genicam://left%20cam", "genicam", "left cam", {}),
    ("genicam://0/", "genicam", "0", {}),
    ("v4l2:///dev/video0", "v4l2", "/dev/video0", {}),
    ("v4l2:///dev/v4l/by-id/usb-Cam_1234-video-index0?buffers=4", "v4l2",
     "/dev/v4l/by-id/usb-Cam_1234-video-index0", {"buffers": "4"}),
])
def test_good_urls_parse_and_read_back(url, scheme, target, options):
    u = urls.parse_url(url)
    assert (u.scheme, u.target, dict(u.options)) == (scheme, target, options)
    assert urls.parse_url(u.url) == u  # the canonical form reads back equal
    assert u.backend is urls.backends()[scheme]


@pytest.mark.parametrize("url, problem", [
    ("", "empty"),
    ("mock", "not a URL"),
    ("/dev/video0", "not a URL"),
    ("usb3://cam0", "unknown scheme 'usb3://'"),
    (" mock://default", "spaces or control characters"),
    ("genicam://0\n", "spaces or control characters"),
    ("v4l2://dev/video0", "v4l2:///dev/video0 (three slashes)"),
    ("v4l2:///", "needs an absolute device path"),
    ("genicam://0/extra", "unexpected path"),
    ("genicam://0#x", "fragment"),
    ("genicam://[0", "malformed"),
    ("genicam://0?cti", "malformed query"),
    ("genicam://0?foo=1", "unknown option 'foo' for genicam:// (its options: buffers, cti)"),
    ("genicam://0?cti=a&cti=b", "option 'cti' given twice"),
    ("genicam://0?cti=", "option cti: give the GenTL producer's .cti path"),
    ("genicam://0?buffers=0", "option buffers: expected an integer >= 1"),
    ("v4l2:///dev/video0?buffers=many", "option buffers: expected an integer"),
    ("mock://elsewhere", "unknown mock scene 'elsewhere'"),
    ("mock://", "unknown mock scene ''"),
    ("mock://default?seed=x", "option seed: expected an integer"),
    ("mock://default?noise=maybe", "option noise: expected true or false"),
])
def test_bad_urls_are_one_line_naming_the_url_and_the_known_schemes(url, problem):
    with pytest.raises(urls.CameraURLError) as info:
        urls.parse_url(url)
    msg = one_line(info.value)
    assert problem in msg
    assert repr(url) in msg
    for form in ("mock://default", "genicam://SERIAL?cti=PATH", "v4l2:///dev/videoN"):
        assert form in msg
    assert isinstance(info.value, CameraError) and isinstance(info.value, ValueError)


def test_non_string_and_unknown_backend():
    with pytest.raises(urls.CameraURLError, match="expected a string"):
        urls.parse_url(None)  # type: ignore[arg-type]
    with pytest.raises(urls.CameraURLError, match=r"unknown camera backend 'usb3' \(known: genicam, mock, v4l2"):
        urls.backend("usb3")


def test_make_url_quotes_what_needs_it():
    assert urls.make_url("genicam", "a b/c", cti="/x y/p.cti") == "genicam://a%20b%2Fc?cti=/x+y/p.cti"
    assert urls.parse_url("genicam://a%20b%2Fc?cti=/x+y/p.cti").target == "a b/c"
    assert urls.make_url("v4l2", "/dev/video0", buffers="") == "v4l2:///dev/video0"
    assert urls.make_url("mock", "default", seed="3") == "mock://default?seed=3"


# ------------------------------------------------------------------ the registry

def test_backends_register_under_their_scheme_no_if_chain(monkeypatch: pytest.MonkeyPatch):
    assert urls.schemes() == ("genicam", "mock", "v4l2")
    assert urls.schemes(stereo=True) == ("mock",)
    assert urls.schemes(hardware=True) == ("genicam", "v4l2")
    opened: list[tuple[urls.CameraURL, dict]] = []

    def opener(u: urls.CameraURL, **options):
        opened.append((u, options))
        return FakeCamera(options.get("name", u.target), n=3)

    monkeypatch.setattr(urls, "BACKENDS", dict(urls.BACKENDS))  # undone after the test
    urls.register(urls.Backend("fake", opener, form="fake://NAME", options={"n": "frames"}))
    cam = urls.camera_for_url("fake://cam7?n=3", name="left")
    assert isinstance(cam, FakeCamera) and cam.name == "left"
    assert opened[0][0].target == "cam7" and opened[0][1] == {"name": "left"}
    left, right = urls.rig_for_url("fake://a", "fake://b")
    assert (left.name, right.name) == ("left", "right")
    with pytest.raises(urls.CameraURLError, match="fake://NAME"):
        urls.parse_url("nope://x")  # the new backend is among the known forms
    with pytest.raises(ValueError, match="already registered"):
        urls.register(urls.Backend("fake", lambda u: None))
    with pytest.raises(ValueError, match="lower case"):
        urls.register(urls.Backend("Bad_Scheme", opener))


def test_stereo_and_camera_urls_are_not_mixed_up():
    with pytest.raises(urls.CameraURLError, match="whole stereo rig.*rig_for_url"):
        urls.camera_for_url("mock://default")
    with pytest.raises(urls.CameraURLError, match="one camera, not a stereo rig"):
        urls.rig_for_url("v4l2:///dev/video0")
    with pytest.raises(urls.CameraURLError, match="whole stereo rig, not one camera of a pair"):
        urls.rig_for_url("mock://default", "v4l2:///dev/video0")
    with pytest.raises(urls.CameraURLError, match="the two cameras of a rig use one backend"):
        urls.rig_for_url("v4l2:///dev/video0", "genicam://1")
    with pytest.raises(urls.CameraURLError, match="the same camera"):
        urls.rig_for_url("v4l2:///dev/video0", "v4l2:///dev/video0")


# ------------------------------------------------------------------ mock://

def test_mock_default_is_the_embedded_default_scene_or_the_configs_own():
    from iscd.drivers.mock import MockCamera

    left, right = urls.rig_for_url("mock://default")
    assert isinstance(left, MockCamera) and left.rig is right.rig
    assert left.rig.cfg == default_config() and left.rig.buffer_frames == default_config().rig.buffer_frames
    cfg = loads(SMALL_CAMERA + "[scene]\nseed = 3\n[rig]\nbuffer_frames = 9\n")
    left, _ = urls.rig_for_url("mock://default", cfg=cfg)
    assert left.rig.cfg is cfg and left.rig.buffer_frames == 9 and left.rig.noise
    left, _ = urls.rig_for_url("mock://default?seed=7&noise=off", cfg=cfg, buffer_frames=4)
    assert left.rig.cfg.scene.seed == 7 and left.rig.cfg.camera == cfg.camera
    assert left.rig.noise is False and left.rig.buffer_frames == 4


def _first_pair(left, right):
    for cam in (left, right):
        cam.open()
    right.start(), left.start()
    try:
        return left.read(5.0), right.read(5.0)
    finally:
        for cam in (left, right):
            cam.stop(), cam.close()


def test_mock_url_and_old_backend_key_give_the_same_rig():
    old = loads(SMALL_CAMERA + '[rig]\nbackend = "mock"\npace = false\nbuffer_frames = 5\n')
    new = loads(SMALL_CAMERA + '[rig]\nurl = "mock://default"\npace = false\nbuffer_frames = 5\n')
    assert old.rig.stereo_url == new.rig.stereo_url == "mock://default"
    assert old.rig.scheme == new.rig.scheme == "mock"
    a, b = registry.make_stereo(old), registry.make_stereo(new)
    assert a[0].rig.buffer_frames == b[0].rig.buffer_frames == 5
    (al, ar), (bl, br) = _first_pair(*a), _first_pair(*b)
    assert (al.frame_id, ar.frame_id) == (bl.frame_id, br.frame_id) == (0, 0)
    assert np.array_equal(al.image, bl.image) and np.array_equal(ar.image, br.image)
    # the URL's seed reaches the scene: other noise, same geometry
    seeded = loads(SMALL_CAMERA + '[rig]\nurl = "mock://default?seed=99"\npace = false\n')
    sl, _ = _first_pair(*registry.make_stereo(seeded))
    assert sl.image.shape == al.image.shape and not np.array_equal(sl.image, al.image)


# ------------------------------------------------------------------ genicam://

gc = pytest.importorskip("iscd.drivers.genicam")
try:
    import harvesters  # noqa: F401

    VIKY = gc.simulated_producer()
except ImportError:  # pragma: no cover - depends on the install
    VIKY = None
needs_viky = pytest.mark.skipif(VIKY is None, reason="harvesters or the genicam wheel's simulated "
                                "producer (viky.cti) is not installed")


@pytest.fixture
def no_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(gc.ENV_VAR, raising=False)


def test_genicam_url_builds_the_camera_it_names():
    cam = urls.camera_for_url("genicam://21345678?cti=/opt/x.cti&buffers=4", name="left")
    assert isinstance(cam, gc.GenICamCamera)
    assert (cam.device, cam.producer_arg, cam.name, cam.num_buffers, cam.first) == (
        "21345678", "/opt/x.cti", "left", 4, False)
    anyone = urls.camera_for_url("genicam://*", producer="/opt/y.cti")
    assert (anyone.device, anyone.producer_arg, anyone.first, anyone.num_buffers) == (None, "/opt/y.cti", True, 16)
    assert urls.camera_for_url("genicam://?cti=simulated").first


@needs_viky
@pytest.mark.usefixtures("release_harvesters")
def test_genicam_urls_open_the_simulated_cameras(no_env):
    cam = urls.camera_for_url(f"genicam://2?cti={VIKY}&buffers=3", name="left")
    try:
        cam.open()
        assert cam.info["serial"] == "2" and cam.producer == VIKY
    finally:
        cam.close()
    first = urls.camera_for_url("genicam://*?cti=simulated&buffers=3")
    try:
        first.open()  # three cameras: the first found, no 'choose one by serial' error
        assert first.info["serial"] == "0"
    finally:
        first.close()


@needs_viky
@pytest.mark.usefixtures("release_harvesters")
def test_genicam_config_urls_and_old_keys_open_the_same_pair(no_env):
    cam = SMALL_CAMERA.replace("128", "160", 1) + "fps = 200\nexposure_s = 0.001\n[transmitter]\nsymbol_rate_hz = 100\n"
    old = loads(cam + f'[rig]\nbackend = "genicam"\nleft = "0"\nright = "2"\nproducer = "{VIKY}"\n')
    new = loads(cam + f'[rig]\nleft = "genicam://0?cti={VIKY}"\nright = "genicam://2?cti={VIKY}"\n')
    assert old.rig.camera_urls == new.rig.camera_urls == (f"genicam://0?cti={VIKY}", f"genicam://2?cti={VIKY}")
    assert new.rig.scheme == "genicam"
    for cfg in (old, new):
        left, right = registry.open_stereo(cfg)
        try:
            assert (left.name, right.name) == ("left", "right")
            assert (left.info["serial"], right.info["serial"]) == ("0", "2")
            assert left.settings.roi.width == 160
            right.start(), left.start()
            assert left.read(2.0).image.shape == (128, 160)
        finally:
            left.close(), right.close()


@needs_viky
@pytest.mark.usefixtures("release_harvesters")
def test_devices_lists_urls_that_open_the_cameras(capsys, no_env, tmp_path: Path):
    assert cli.main(["-q", "devices", "--producer", "simulated", "--backend", "genicam", "--no-boards",
                     "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    got = {c["serial"]: c["url"] for c in report["genicam"]["cameras"]}
    assert got == {sn: f"genicam://{sn}?cti={VIKY}" for sn in ("0", "1", "2")}
    assert registry.list_cameras("genicam", producer="simulated")[1]["url"] == got["1"]
    assert cli.main(["-q", "devices", "--producer", "simulated", "--no-boards"]) == 0
    text = capsys.readouterr().out
    assert f"    {got['0']}  serial 0  " in text
    assert 'Simulated rig: mock://default' in text
    # the suggested [rig] lines, pasted into a config, open those cameras
    rig_lines = text[text.index("[rig] of a config"):].splitlines()[1:3]
    assert rig_lines == [f'  left = "{got["0"]}"', f'  right = "{got["1"]}"']
    cfg_file = tmp_path / "rig.toml"
    cfg_file.write_text("[camera]\nfps = 200\n[transmitter]\nsymbol_rate_hz = 100\n[rig]\n"
                        + "\n".join(line.strip() for line in rig_lines) + "\n")
    from iscd.core.config import load

    cfg = load(cfg_file)
    left, right = registry.open_stereo(cfg)
    try:
        assert (left.info["serial"], right.info["serial"]) == ("0", "1")
    finally:
        left.close(), right.close()
    # --config: the cti of its genicam URLs is the producer to list
    assert cli.main(["-q", "devices", "--config", str(cfg_file), "--backend", "genicam", "--no-boards",
                     "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["genicam"]["producers"] == [VIKY]


# ------------------------------------------------------------------ v4l2://

try:
    pytest.importorskip("linuxpy")
    from test_v4l2 import FakeV4L2Device, fake  # noqa: F401 - the fake capture device and its fixture
    HAVE_LINUXPY = True
except (ImportError, pytest.skip.Exception):  # pragma: no cover - depends on the install
    HAVE_LINUXPY = False
needs_linuxpy = pytest.mark.skipif(not HAVE_LINUXPY, reason="linuxpy is not installed")


@needs_linuxpy
def test_v4l2_url_streams_from_the_fake_device(fake):
    from iscd.drivers import v4l2
    from iscd.drivers.base import CameraSettings, Roi

    cam = urls.camera_for_url(f"v4l2://{fake.path}?buffers=4", name="right")
    assert isinstance(cam, v4l2.V4L2Camera)
    assert (cam.path, cam.name, cam.num_buffers) == (fake.path, "right", 4)
    cam.open()
    try:
        cam.configure(CameraSettings(fps=100, exposure_s=1e-3, roi=Roi(0, 0, 64, 48)))
        cam.start()
        f = cam.read(1.0)
        assert f.camera == "right" and f.image.shape == (48, 64) and f.image.dtype == np.uint8
        assert f.image[0, 1] == (3 + f.frame_id) % 256  # the fake's pattern, through linuxpy's mmap
    finally:
        cam.close()


@needs_linuxpy
def test_v4l2_config_urls_and_old_keys_give_the_same_cameras(fake, tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch, capsys):
    from iscd.drivers import v4l2

    for n in (0, 1):
        (tmp_path / f"video{n}").symlink_to(fake.path)
    p0, p1 = tmp_path / "video0", tmp_path / "video1"
    old = loads(f'[rig]\nbackend = "v4l2"\nleft = "{p0}"\nright = "{p1}"\n')
    new = loads(f'[rig]\nleft = "v4l2://{p0}"\nright = "v4l2://{p1}"\n')
    assert old.rig.camera_urls == new.rig.camera_urls == (f"v4l2://{p0}", f"v4l2://{p1}")
    for cfg in (old, new):
        left, right = registry.make_stereo(cfg)
        assert (left.path, right.path, left.name, right.name) == (str(p0), str(p1), "left", "right")
    left.open()
    left.close()
    # iscd devices lists them by URL
    monkeypatch.setattr(v4l2, "V4L2_GLOB", str(tmp_path / "video*"))
    assert cli.main(["-q", "devices", "--backend", "v4l2", "--no-boards", "--json"]) == 0
    assert [c["url"] for c in json.loads(capsys.readouterr().out)["v4l2"]["cameras"]] == [
        f"v4l2://{p0}", f"v4l2://{p1}"]
    assert [c["url"] for c in registry.list_cameras("v4l2")] == [f"v4l2://{p0}", f"v4l2://{p1}"]


# ------------------------------------------------------------------ the config's [rig]

def test_old_keys_map_to_urls():
    cfg = loads('[rig]\nbackend = "genicam"\nleft = "0"\nright = "cam B"\nproducer = "/opt/p.cti"\n')
    assert cfg.rig.camera_urls == ("genicam://0?cti=/opt/p.cti", "genicam://cam%20B?cti=/opt/p.cti")
    assert (cfg.rig.left, cfg.rig.stereo_url) == ("0", "")  # the file's values stay as written
    # [rig] producer is the cti of a genicam URL that has none; a URL's own cti wins
    cfg = loads('[rig]\nleft = "genicam://0"\nright = "genicam://1?cti=/b.cti"\nproducer = "/a.cti"\n')
    assert cfg.rig.camera_urls == ("genicam://0?cti=/a.cti", "genicam://1?cti=/b.cti")
    assert cfg.rig.scheme == "genicam"
    cfg = loads('[rig]\nbackend = "v4l2"\nleft = "/dev/video0"\nright = "/dev/video2"\n')
    assert cfg.rig.camera_urls == ("v4l2:///dev/video0", "v4l2:///dev/video2")
    assert loads("").rig.stereo_url == "mock://default" and loads("").rig.scheme == "mock"
    assert default_config().rig.stereo_url == "mock://default"


def test_a_url_config_reads_back_and_pickles():
    from iscd.sim.tomlout import config_to_toml

    for text in ('[rig]\nurl = "mock://default?seed=4"\n',
                 '[rig]\nleft = "genicam://0?cti=/a.cti"\nright = "genicam://1"\n',
                 '[rig]\nbackend = "v4l2"\nleft = "/dev/video0"\nright = "/dev/video1"\n'):
        cfg = loads(text)
        again = loads(config_to_toml(cfg))
        assert again == cfg and again.rig.camera_urls == cfg.rig.camera_urls
        assert again.rig.stereo_url == cfg.rig.stereo_url
        clone = pickle.loads(pickle.dumps(cfg))  # as the acquisition process gets it
        assert clone.rig.camera_urls == cfg.rig.camera_urls and clone.rig.stereo_url == cfg.rig.stereo_url


@pytest.mark.parametrize("rig, key, problem", [
    ('backend = "usb3"', "rig.backend", "expected one of ['genicam', 'mock', 'v4l2']"),
    ('url = "genicam://0"', "rig.url", "is one camera, not a stereo rig"),
    ('url = "usb3://0"', "rig.url", "unknown scheme 'usb3://'"),
    ('url = "mock://default"\nleft = "genicam://0"', "rig.left", "not used with rig.url"),
    ('url = "mock://default"\nbackend = "genicam"', "rig.backend", "contradicts rig.url"),
    ('left = "mock://default"', "rig.left", "whole stereo rig (both cameras): set it as rig.url"),
    ('left = "v4l2://dev/video0"\nright = "v4l2:///dev/video1"', "rig.left", "three slashes"),
    ('left = "genicam://0"\nright = "genicam://1?colour=red"', "rig.right", "unknown option 'colour'"),
    ('left = "genicam://0"\nright = "v4l2:///dev/video0"', "rig.right", "use one backend"),
    ('left = "genicam://0"\nright = "1"', "rig.right", "give a camera URL like rig.left"),
    ('backend = "v4l2"\nleft = "genicam://0"\nright = "genicam://1"', "rig.backend", "contradicts rig.left"),
])
def test_rig_config_errors_name_the_key(rig, key, problem):
    with pytest.raises(ConfigError) as info:
        loads(f"[rig]\n{rig}\n")
    msg = one_line(info.value)
    assert msg.startswith(f"{key}: ") and problem in msg, msg


def test_stereo_checks_on_urls():
    with pytest.raises(ConfigError, match=r"rig.left: set the left camera's serial number or user id "
                                          r"for backend 'genicam' \(or its URL, genicam://SERIAL\?cti=PATH"):
        registry.make_stereo(loads('[rig]\nright = "genicam://1"\n'))
    with pytest.raises(ConfigError, match="rig.right: the same camera as rig.left"):
        registry.check_stereo_config(loads('[rig]\nleft = "genicam://1?cti=/a.cti"\nright = "genicam://1"\n'
                                           'producer = "/a.cti"\n'))
    left, right = registry.make_stereo(loads('[rig]\nleft = "v4l2:///dev/video0"\nright = "v4l2:///dev/video2"\n'))
    assert (left.path, right.path, left.name, right.name) == ("/dev/video0", "/dev/video2", "left", "right")


def test_cli_refuses_a_bad_url_in_one_line(tmp_path: Path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[rig]\nleft = "v4l2://dev/video0"\nright = "v4l2:///dev/video1"\n')
    for argv in (["config", "--check", str(bad)], ["run", "--config", str(bad), "--duration", "1"]):
        p = subprocess.run([sys.executable, "-m", "iscd", *argv], capture_output=True, text=True, timeout=120)
        assert p.returncode == 2, p.stderr
        assert p.stderr.count("\n") == 1 and "rig.left: camera URL 'v4l2://dev/video0'" in p.stderr
        assert "Traceback" not in p.stderr


def test_describe_lists_the_url_keys():
    from iscd.core.config import describe

    text = describe()
    assert "  url = ''  # a stereo rig that is one device: mock://default" in text
    assert "genicam://SERIAL?cti=PATH" in text and "v4l2:///dev/videoN" in text


def test_devices_backend_comes_from_the_registry(capsys):
    assert cli.main(["-q", "devices", "--backend", "firewire", "--no-boards"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown camera backend 'firewire' (known: genicam, mock, v4l2, all)" in err
    assert cli.main(["-q", "devices", "--backend", "mock", "--no-boards", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["mock"] == {"urls": ["mock://default"]}


def test_rig_urls_are_resolved_by_the_drivers_layer(monkeypatch):
    """The core knows no camera backend: [rig]'s URLs are resolved by the resolver that
    iscd.drivers.urls installs (checked at load once it is imported; else at first use)."""
    from iscd.core import config as C

    monkeypatch.setattr(C, "_RIG_RESOLVER", [])
    rig = C.RigConfig(left="genicam://0", right="genicam://1")  # nothing resolved yet
    with pytest.raises(RuntimeError, match="import iscd.drivers.urls"):
        rig.camera_urls
    monkeypatch.setattr(C, "_RIG_RESOLVER", [urls.resolve_rig])
    assert rig.camera_urls == ("genicam://0", "genicam://1") and rig.scheme == "genicam"
    assert rig == C.RigConfig(left="genicam://0", right="genicam://1")  # the cache is no field


def test_the_core_loads_a_config_without_the_drivers():
    code = ("import sys, iscd.core.config as C; cfg = C.default_config(); "
            "assert not [m for m in sys.modules if m.startswith('iscd.drivers')], 'drivers imported'; "
            "import iscd.drivers.urls; print(cfg.rig.stereo_url)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "mock://default"
