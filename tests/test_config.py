"""Config loading: defaults, the embedded default, and errors that name the key."""

from __future__ import annotations

import pytest

from iscd.core import config as C
from iscd.cli.main import main


def test_empty_config_is_chapter_4_defaults() -> None:
    cfg = C.loads("")
    assert (cfg.transmitter.rows, cfg.transmitter.cols, cfg.transmitter.levels) == (8, 8, 8)
    assert cfg.transmitter.training_symbols == 40 and cfg.transmitter.data_symbols == 600
    assert cfg.camera.focal_px == pytest.approx(3500.0)
    assert cfg.camera.baseline_m == 0.25


def test_embedded_default_is_the_mock_rig() -> None:
    import iscd.drivers.urls  # noqa: F401  (installs the [rig] resolver, as the command line does)

    cfg = C.default_config()
    assert cfg.rig.scheme == "mock" and cfg.rig.stereo_url == "mock://default"
    assert cfg.scene.distance_m == 30
    assert cfg.transmitter.n_leds == 64


@pytest.mark.parametrize("text, key, problem", [
    ("[scene]\ndistance_m = -3", "scene.distance_m", "> 0"),
    ("[scene]\ndistanse_m = 3", "scene.distanse_m", "unknown key"),
    ("[transmitter]\nlevels = 6", "transmitter.levels", "one of"),
    ("[camera]\nfps = 'fast'", "camera.fps", "expected a number"),
    ("[camera]\nwidth = 1.5", "camera.width", "integer"),
    ("[bogus]\nx = 1", "bogus", "unknown section"),
    ("[[scene.distractors]]\nz_m = 0", "scene.distractors[0].z_m", "> 0"),
    ("[camera]\nexposure_s = 0.01", "camera.exposure_s", "frame period"),
    ("[camera]\nfps = 600", "camera.fps", "2 frames per symbol"),
    ("[scene\n", "", "not valid TOML"),
])
def test_errors_name_key_and_problem(text: str, key: str, problem: str) -> None:
    with pytest.raises(C.ConfigError) as ei:
        C.loads(text)
    msg = str(ei.value)
    assert key in msg and problem in msg and "\n" not in msg


def test_missing_file(tmp_path) -> None:
    with pytest.raises(C.ConfigError, match="not found"):
        C.load(tmp_path / "nope.toml")


def test_owned_sections_are_kept_raw() -> None:
    cfg = C.loads("[daemon]\nring_ms = 200")
    assert cfg.owned["daemon"] == {"ring_ms": 200} == cfg.table("daemon")


def test_cli_config_describe_and_check(tmp_path, capsys) -> None:
    assert main(["config", "--describe"]) == 0
    assert "distance_m" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text("[scene]\ndistance_m = 'far'\n")
    assert main(["config", "--check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "scene.distance_m" in err and "Traceback" not in err
