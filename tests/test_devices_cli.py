"""``iscd devices`` and iscd.drivers.registry (list_cameras, make_stereo, open_stereo).

GenICam cameras come from the simulated producer shipped with the genicam wheel; LED
boards from a stand-in for iscd.drivers.board.discovery.find_boards.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from iscd.drivers import registry
from iscd.drivers.base import Camera, CameraError
from iscd.cli import main as cli
from iscd.core.config import ConfigError, loads

gc = pytest.importorskip("iscd.drivers.genicam")
VIKY = gc.simulated_producer()
needs_viky = pytest.mark.skipif(VIKY is None, reason="the genicam wheel ships no simulated producer (*.cti)")


pytestmark = pytest.mark.usefixtures("release_harvesters")


@pytest.fixture
def no_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(gc.ENV_VAR, raising=False)


def run_cli(capsys: pytest.CaptureFixture, *argv: str) -> tuple[int, str, str]:
    code = cli.main(["-q", "devices", *argv])
    out, err = capsys.readouterr()
    return code, out, err


@needs_viky
def test_devices_lists_the_simulated_cameras_as_json(capsys, no_env):
    code, out, err = run_cli(capsys, "--producer", "simulated", "--json", "--no-boards")
    assert code == 0, err
    report = json.loads(out)
    g = report["genicam"]
    assert g["producers"] == [VIKY]
    assert sorted(c["serial"] for c in g["cameras"]) == ["0", "1", "2"]
    assert {c["model"] for c in g["cameras"]} == {"Viky"}
    assert isinstance(report["v4l2"]["cameras"], list)
    assert "boards" not in report


@needs_viky
def test_devices_text_output_and_environment_producer(capsys, monkeypatch):
    import os

    monkeypatch.setenv(gc.ENV_VAR, os.path.dirname(VIKY))
    code, out, _ = run_cli(capsys, "--backend", "genicam", "--no-boards")
    assert code == 0
    assert f"producer {VIKY}: 3 camera(s)" in out
    for sn, colour in (("0", "red"), ("1", "green"), ("2", "blue")):
        assert f"serial {sn} " in out and f"VikyTL_DEV_{colour}" in out


def test_devices_without_a_producer_explains_how_to_get_one(capsys, no_env):
    code, out, _ = run_cli(capsys, "--backend", "genicam", "--no-boards")
    assert code == 0
    assert "GenICam cameras (0)" in out
    assert "GENICAM_GENTL64_PATH" in out


def test_devices_bad_producer_is_a_one_line_error(capsys, tmp_path: Path):
    code, out, err = run_cli(capsys, "--producer", str(tmp_path / "vendor.cti"))
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and "vendor.cti" in err and "not found" in err
    assert "Traceback" not in err


def test_devices_lists_boards_with_the_configured_usb_id(capsys, monkeypatch, tmp_path: Path, no_env):
    discovery = pytest.importorskip("iscd.drivers.board.discovery")
    seen: list[tuple[int, int]] = []

    def find_boards(vid: int = discovery.DEFAULT_VID, pid: int = discovery.DEFAULT_PID, **kw):
        seen.append((vid, pid))
        return [discovery.FoundBoard(device="/dev/ttyACM3", serial_number="B0007", vid=vid, pid=pid,
                                     location="1-1.4", description="iscd LED board",
                                     seen_by=("usb", "serial"))]

    monkeypatch.setattr(discovery, "find_boards", find_boards)
    cfg = tmp_path / "rig.toml"
    cfg.write_text("[board]\nvid = 0x1234\npid = 0x5678\n")
    code, out, err = run_cli(capsys, "--backend", "v4l2", "--config", str(cfg))
    assert code == 0, err
    assert seen == [(0x1234, 0x5678)]
    assert "LED boards (1):" in out and "/dev/ttyACM3  serial B0007  usb 1234:5678 at 1-1.4" in out
    code, out, _ = run_cli(capsys, "--backend", "v4l2", "--json")
    assert json.loads(out)["boards"][0]["serial_number"] == "B0007"


def test_devices_survives_a_failing_board_search(capsys, monkeypatch, no_env):
    discovery = pytest.importorskip("iscd.drivers.board.discovery")

    def broken(*a, **kw):
        raise OSError("libusb exploded")

    monkeypatch.setattr(discovery, "find_boards", broken)
    code, out, _ = run_cli(capsys, "--backend", "v4l2")
    assert code == 0 and "boards: search failed: OSError: libusb exploded" in out


# ------------------------------------------------------------------ registry

@needs_viky
def test_list_cameras_per_backend(no_env):
    cams = registry.list_cameras("genicam", producer="simulated")
    assert [c["backend"] for c in cams] == ["genicam"] * 3
    assert registry.list_cameras("genicam") == []  # no producer configured
    assert all(c["backend"] in ("genicam", "v4l2") for c in registry.list_cameras())
    with pytest.raises(CameraError, match="unknown camera backend"):
        registry.list_cameras("firewire")


def rig_config(backend: str, left: str, right: str, producer: str = "") -> object:
    return loads(f"""
[camera]
fps = 1000
exposure_s = 0.001
width = 256
height = 200
[rig]
backend = "{backend}"
left = "{left}"
right = "{right}"
producer = "{producer}"
""")


@needs_viky
def test_open_stereo_genicam_pair(caplog):
    cfg = rig_config("genicam", "0", "2", VIKY)
    left, right = registry.open_stereo(cfg)
    try:
        assert isinstance(left, gc.GenICamCamera) and isinstance(right, gc.GenICamCamera)
        assert (left.info["serial"], right.info["serial"]) == ("0", "2")
        for cam in (left, right):
            assert cam.settings.roi.width == 256 and cam.settings.roi.height == 200
            assert cam.settings.fps == pytest.approx(200.0)  # Viky's limit, read back
        # Viky has no trigger lines: the registry warns that the pair is not synchronized
        assert "not hardware-synchronized" in caplog.text
        right.start(), left.start()
        a, b = left.read(2.0), right.read(2.0)
        assert a.camera == "left" and b.camera == "right"
        assert a.image.shape == b.image.shape == (200, 256)
    finally:
        left.close(), right.close()


def test_stereo_config_errors():
    with pytest.raises(ConfigError, match="rig.left: set the left camera's serial number"):
        registry.make_stereo(rig_config("genicam", "", "1"))
    with pytest.raises(ConfigError, match="rig.right: the same camera"):
        registry.make_stereo(rig_config("v4l2", "/dev/video0", "/dev/video0"))
    left, right = registry.make_stereo(rig_config("v4l2", "/dev/video0", "/dev/video2"))
    assert (left.path, right.path, left.name, right.name) == ("/dev/video0", "/dev/video2", "left", "right")


@needs_viky
def test_open_stereo_closes_the_left_camera_when_the_right_one_fails():
    cfg = rig_config("genicam", "1", "42", VIKY)
    with pytest.raises(CameraError, match="right: no GenICam camera"):
        registry.open_stereo(cfg)
    # the left camera was released: it can be opened again at once
    cam = gc.GenICamCamera(serial="1", producer=VIKY, num_buffers=3)
    cam.open()
    cam.close()


def test_settings_from_config_makes_left_master_right_slave():
    cfg = rig_config("genicam", "a", "b")
    s_left, s_right = registry.settings_from_config(cfg, "left"), registry.settings_from_config(cfg, "right")
    assert (s_left.trigger, s_right.trigger) == ("master", "slave")
    assert s_left.roi.width == 256 and s_left.fps == 1000 and s_left.pixel_format == "Mono8"


def test_mock_backend_through_the_registry():
    pytest.importorskip("iscd.drivers.mock", reason="iscd.drivers.mock (the mock rig) is not written yet")
    from iscd.core.config import load

    left, right = registry.make_stereo(load(None))
    assert isinstance(left, Camera) and isinstance(right, Camera)
