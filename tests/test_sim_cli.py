"""`iscd simulate`: a recording with truth, config echo and calibration, reproducible."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.cli.main import main
from iscd.core.config import load
from iscd.recording import open_recording
from iscd.sim import Scene, Truth

CONFIG = """
[transmitter]
rows = 2
cols = 2
[camera]
width = 96
height = 64
baseline_m = 0.6
[scene]
distance_m = 25
seed = 11
jitter_px = 0.05
[[scene.distractors]]
x_m = 0.8
y_m = 0.2
z_m = 40
diameter_m = 0.1
flicker_hz = 100
"""


@pytest.fixture()
def config_file(tmp_path):
    p = tmp_path / "sim.toml"
    p.write_text(CONFIG)
    return p


def test_simulate_writes_a_reproducible_recording(tmp_path, config_file, capsys):
    out = tmp_path / "rec"
    assert main(["simulate", "--config", str(config_file), "--out", str(out), "--frames", "37"]) == 0
    for name in ("left.iscr", "right.iscr", "truth.npz", "truth.json", "config.toml"):
        assert (out / name).is_file()
    cfg = load(config_file)
    assert load(out / "config.toml") == cfg  # the echo reproduces the config exactly
    scene = Scene(cfg)
    with open_recording(out / "left.iscr") as left, open_recording(out / "right.iscr") as right:
        assert len(left) == len(right) == 37
        assert (left.width, left.height, left.fps) == (96, 64, 1000.0)
        np.testing.assert_array_equal(left.frame_ids, np.arange(37))
        np.testing.assert_array_equal(right.timestamps_ns, np.arange(37) * 1_000_000)
        el, er = scene.render_pair(30)
        assert np.array_equal(left[30], el) and np.array_equal(right[30], er)
    truth = Truth.load(out)
    assert len(truth) == 37 and truth.meta["seed"] == 11
    np.testing.assert_allclose(truth.disparity_px, 3500 * 0.6 / 25)
    # the config echo renders the same frames (bit for bit)
    out2 = tmp_path / "rec2"
    assert main(["simulate", "--config", str(out / "config.toml"), "--out", str(out2),
                 "--frames", "37"]) == 0
    with open_recording(out / "right.iscr") as a, open_recording(out2 / "right.iscr") as b:
        assert np.array_equal(a.read(), b.read())
    try:
        import iscd.calibration.io as cio  # noqa: F401
    except ImportError:
        return
    if hasattr(cio.StereoCalibration, "ideal"):
        cal = cio.load_calibration(out / "calibration.yml")
        assert cal.M1[0, 0] == pytest.approx(3500.0)
        assert abs(float(np.ravel(cal.T)[0])) == pytest.approx(0.6)


def test_simulate_seed_and_duration(tmp_path, config_file):
    out = tmp_path / "s"
    assert main(["simulate", "--config", str(config_file), "--out", str(out),
                 "--duration", "0.012", "--seed", "5", "--no-noise"]) == 0
    truth = Truth.load(out)
    assert len(truth) == 12 and truth.meta["seed"] == 5 and truth.meta["noise"] is False


def test_simulate_user_errors(tmp_path, config_file, capsys):
    out = tmp_path / "e"
    assert main(["simulate", "--config", str(config_file), "--out", str(out), "--frames", "2"]) == 0
    capsys.readouterr()
    assert main(["simulate", "--config", str(config_file), "--out", str(out), "--frames", "2"]) == 2
    err = capsys.readouterr().err
    assert "--overwrite" in err and err.count("\n") == 1
    assert main(["simulate", "--config", str(config_file), "--out", str(out), "--frames", "2",
                 "--overwrite"]) == 0
    assert main(["simulate", "--out", str(out), "--frames", "0", "--overwrite"]) == 2
    bad = tmp_path / "bad.toml"
    bad.write_text("[scene]\ndistance_m = -3\n")
    assert main(["simulate", "--config", str(bad), "--out", str(out), "--overwrite"]) == 2
    assert "scene.distance_m" in capsys.readouterr().err
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["simulate", "--out", str(f), "--frames", "1"]) == 2


def test_default_length_is_two_packets(tmp_path, monkeypatch):
    from iscd.cli.commands import simulate as sim_cmd
    from iscd.core.config import default_config

    cfg = default_config()
    scene = Scene(cfg)
    n = sim_cmd.default_frames(cfg, scene)
    t = scene.truth(np.arange(n))
    assert list(t.packet_index) == [0, 1] or list(t.packet_index) == [0, 1, 2]
    # the second packet's last symbol ends before the last frame's exposure does
    last = scene.clock.symbol_start_cam(2 * 653)
    assert t.t_s[-1] + cfg.camera.exposure_s >= last
