"""Live guided capture against the Camera interface, with fake cameras that serve synthetic
chessboard frames: pairs are taken only when the board is steady in both views and the view
is new; the taken pairs calibrate the rig; Rerun logging and the ``--live`` command work."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import numpy as np
import pytest

from iscd.calibration.boards import BoardSpec
from iscd.calibration.live import CaptureLogic, LiveSettings, RerunView, read_pair, run_capture
from iscd.calibration.solve import calibrate_stereo
from iscd.calibration.synthetic import BoardRenderer, default_board, default_rig, random_poses
from iscd.drivers.base import CameraSettings, Frame
from fakes import FakeCamera
from iscd.cli.main import main

BOARD = default_board()


class Script:
    """Frames shared by the two fake cameras: (left, right) noiseless images; noise is added
    per read so consecutive frames of a still board differ like real ones."""

    def __init__(self, frames: list[tuple[np.ndarray, np.ndarray]], fps: float = 20.0,
                 noise_dn: float = 1.5) -> None:
        self.frames = frames
        self.fps = fps
        self.noise_dn = noise_dn
        self.rng = np.random.default_rng(0)
        self.served = 0
        self.starts: list[str] = []

    def image(self, i: int, k: int) -> np.ndarray:
        base = self.frames[i][k].astype(np.float32)
        noisy = base + self.rng.normal(0, self.noise_dn, base.shape).astype(np.float32)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


class ScriptCamera(FakeCamera):
    """One camera of the script's rig (side 0 left, 1 right), unpaced: frame i has the
    timestamp i / fps and comes at once; ``drop``: frames that never arrive."""

    def __init__(self, script: Script, side: int, drop: set[int] | None = None) -> None:
        super().__init__(("left", "right")[side], len(script.frames), 0, round(1e9 / script.fps),
                         skip=drop or (), image=lambda i, _name: script.image(i, side), paced=False)
        self.side = side
        self.script_of = script

    def start(self) -> None:
        super().start()
        self.script_of.starts.append(self.name)

    def read(self, timeout_s: float = 1.0) -> Frame:
        f = super().read(timeout_s)
        self.script_of.served = max(self.script_of.served, self.cursor)
        return f


@pytest.fixture(scope="module")
def scene():  # type: ignore[no-untyped-def]
    """Noiseless renders of 7 board poses and of a half-way pose between each."""
    cal = default_rig()
    r = BoardRenderer(cal, BOARD, supersample=2)
    poses = random_poses(r, 7, np.random.default_rng(21), pool_factor=6)
    still, moving = [], []
    for k, (rv, tv) in enumerate(poses):
        still.append((r.render(rv, tv, "left", noise_dn=0), r.render(rv, tv, "right", noise_dn=0)))
        prv, ptv = poses[k - 1]
        mv, mt = 0.5 * (rv + prv), 0.5 * (tv + ptv)
        moving.append((r.render(mv, mt, "left", noise_dn=0), r.render(mv, mt, "right", noise_dn=0)))
    return cal, still, moving


def sequence(scene, order: list[int], still_frames: int = 5):  # type: ignore[no-untyped-def]
    _, still, moving = scene
    frames = []
    for k in order:
        frames += [moving[k]] + [still[k]] * still_frames
    return frames


def test_takes_a_pair_only_when_steady_and_new(scene) -> None:  # type: ignore[no-untyped-def]
    _, still, moving = scene
    blank = (np.full((512, 512), 110, np.uint8),) * 2
    frames = ([moving[0]] + [still[0]] * 8 + [blank] * 2 + [moving[1]] + [still[1]] * 2
              + [moving[2]] + [still[2]] * 5 + [still[0]] * 5)
    script = Script(frames)
    logic = CaptureLogic(BOARD, LiveSettings(n_pairs=10, steady_frames=3))
    events = [logic.step(script.image(i, 0), script.image(i, 1)) for i in range(len(frames))]
    states = [e.state for e in events]
    # Pose 0: first frame of the still board moved from the previous view, then 3 steady.
    assert states[:6] == ["moving", "moving", "steady", "steady", "captured", "steady"]
    assert "duplicate" in states[6:9]  # still at pose 0 after the capture
    assert states[9:11] == ["no board", "no board"]
    # Pose 1 is shown for only 2 frames: never steady long enough.
    assert "captured" not in states[11:14]
    # Pose 2 is taken; the return to pose 0 is recognised as a view already taken.
    assert states[14:20].count("captured") == 1
    assert states[20:].count("captured") == 0 and "duplicate" in states[20:]
    assert len(logic.captures) == 2
    assert all(np.isfinite(e.motion_px) for e in events if e.state == "steady")
    cl, cr = logic.coverage_fraction()
    assert 0 < cl < 1 and 0 < cr < 1
    # Taken pairs are sub-pixel detections of the board.
    obs = logic.captures[0].observation
    assert obs.left_points.shape == (54, 2) and obs.right_points.shape == (54, 2)


def test_capture_from_cameras_calibrates_the_rig(scene) -> None:  # type: ignore[no-untyped-def]
    import rerun as rr

    cal, _, _ = scene
    frames = sequence(scene, list(range(7)), still_frames=5)
    script = Script(frames)
    left, right = ScriptCamera(script, 0), ScriptCamera(script, 1, drop={7})  # one lost frame
    right.start()  # run_capture takes started cameras
    left.start()
    rec = rr.RecordingStream("test-calibrate")
    mem = rec.memory_recording()
    logic = run_capture(left, right, BOARD, LiveSettings(n_pairs=6, steady_frames=3,
                                                         process_interval_s=0.04),
                        view=RerunView(rec))
    assert len(logic.captures) == 6
    assert script.served < len(frames)  # stopped as soon as 6 pairs were taken
    rec.flush()
    assert mem.num_msgs() > 10
    res = calibrate_stereo([c.observation for c in logic.captures], logic.image_size)
    assert abs(res.calibration.baseline_m - cal.baseline_m) / cal.baseline_m < 0.02
    assert abs(res.calibration.M1[0, 0] - cal.M1[0, 0]) / cal.M1[0, 0] < 0.02


def test_read_pair_realigns_frame_ids(scene) -> None:  # type: ignore[no-untyped-def]
    frames = sequence(scene, [0, 1], still_frames=2)
    script = Script(frames)
    left, right = ScriptCamera(script, 0, drop={1}), ScriptCamera(script, 1, drop={2})
    left.start()
    right.start()
    ids = []
    for _ in range(3):
        fl, fr = read_pair(left, right)
        assert fl.frame_id == fr.frame_id
        ids.append(fl.frame_id)
    assert ids == [0, 3, 4]


def test_live_command(scene, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,  # type: ignore[no-untyped-def]
                      capsys: pytest.CaptureFixture[str]) -> None:
    frames = sequence(scene, list(range(7)), still_frames=5)
    script = Script(frames, fps=20.0)
    cams: list[ScriptCamera] = []

    def open_stereo(cfg):  # type: ignore[no-untyped-def]
        """As iscd.drivers.registry.open_stereo: opened and configured, not started."""
        cams[:] = [ScriptCamera(script, 0), ScriptCamera(script, 1)]
        for c, trig in zip(cams, ("master", "slave")):
            c.open()
            c.configure(CameraSettings(fps=20.0, exposure_s=1e-3, trigger=trig))
        return cams[0], cams[1]

    fake = types.ModuleType("iscd.drivers.registry")
    fake.open_stereo = open_stereo  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "iscd.drivers.registry", fake)
    out = tmp_path / "live.yml"
    rrd = tmp_path / "capture.rrd"
    rc = main(["calibrate", "--live", "--board", "9x6", "--square", "0.08", "--out", str(out),
               "--pairs", "6", "--steady-frames", "3", "--save-pairs", str(tmp_path / "pairs"),
               "--rerun-save", str(rrd)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert cap.err.count("captured: took pair") == 6
    assert out.is_file() and (tmp_path / "live_report" / "preview.png").is_file()
    assert len(list((tmp_path / "pairs").glob("left_*.png"))) == 6
    assert len(list((tmp_path / "pairs").glob("right_*.png"))) == 6
    assert rrd.is_file() and rrd.stat().st_size > 1000
    assert script.starts == ["right", "left"]  # the trigger slave first
    assert not cams[0].opened and not cams[1].opened  # closed again
    assert not cams[0].started and not cams[1].started


def test_live_without_camera_backends_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "iscd.drivers.registry", None)  # import fails
    rc = main(["calibrate", "--live", "--board", "9x6", "--square", "0.08",
               "--out", str(tmp_path / "x.yml")])
    assert rc == 2
    assert "live capture needs iscd.drivers.registry" in capsys.readouterr().err
    assert not (tmp_path / "x.yml").exists()


def test_charuco_capture_logic() -> None:
    board = BoardSpec("charuco", 10, 7, 0.07, 0.052, "4X4_50")
    cal = default_rig()
    r = BoardRenderer(cal, board, supersample=2)
    (rv, tv), = random_poses(r, 1, np.random.default_rng(2), z_range_m=(1.2, 1.6), pool_factor=2)
    img = (r.render(rv, tv, "left", noise_dn=0), r.render(rv, tv, "right", noise_dn=0))
    script = Script([img] * 5)
    logic = CaptureLogic(board, LiveSettings(steady_frames=2))
    states = [logic.step(script.image(i, 0), script.image(i, 1)).state for i in range(5)]
    assert states[:3] == ["moving", "steady", "captured"] and "duplicate" in states[3:]
    assert logic.captures[0].observation.ids is not None
