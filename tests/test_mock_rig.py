"""The mock stereo rig: shared trigger, pacing, buffer drops and injected faults."""

from __future__ import annotations

import time

import numpy as np
import pytest

from iscd.drivers.base import CameraError, CameraLost, CameraSettings, CameraTimeout, Roi
from iscd.drivers import mock
from iscd.drivers.mock import MockCamera, MockRig
from iscd.core.config import default_config
from iscd.sim.presets import override

SMALL = {"width": 128, "height": 128}  # fast frames; the transmitter still fits


def _rig(pace: bool = False, faults: list | None = None, **kw) -> tuple[MockCamera, MockCamera]:
    cfg = override(default_config(), camera=SMALL,
                   rig={"pace": pace, "faults": faults or []})
    left, right = MockRig.from_config(cfg, **kw)
    for cam in (left, right):
        cam.open()
        cam.start()
    return left, right


def _ids(cam: MockCamera, n: int) -> list[int]:
    return [cam.read(timeout_s=1.0).frame_id for _ in range(n)]


def test_pairs_share_ids_timestamps_and_match_the_scene():
    left, right = _rig()
    scene = left.truth
    assert right.truth is scene
    for n in range(20):
        fl, fr = left.read(), right.read()
        assert (fl.frame_id, fl.timestamp_ns) == (fr.frame_id, fr.timestamp_ns) == (
            n, left.rig.trigger_time_ns(n))
        assert fl.camera == "left" and fr.camera == "right"
        assert fl.image.shape == (128, 128) and fl.image.dtype == np.uint8
        if n in (3, 17):
            el, er = scene.render_pair(n)
            assert np.array_equal(fl.image, el) and np.array_equal(fr.image, er)
    stamps = [left.read().timestamp_ns for _ in range(3)]
    assert np.diff(stamps).tolist() == [1_000_000, 1_000_000]


def test_pacing_follows_fps_in_real_time():
    left, right = _rig(pace=True)
    got = []
    t_start = time.monotonic_ns()
    for _ in range(60):
        f = left.read(timeout_s=1.0)
        right.read(timeout_s=1.0)
        got.append((f.frame_id, f.timestamp_ns, time.monotonic_ns()))
    elapsed = (time.monotonic_ns() - t_start) / 1e9
    last = got[-1][0]
    # never delivered before the exposure ended; the trigger advances at ~1000 fps
    assert all(now >= ts + 1_000_000 for _, ts, now in got)
    assert last >= 59
    assert elapsed == pytest.approx(last / 1000.0 + 0.011, abs=0.05)


def test_late_consumer_loses_frames_from_a_small_buffer(fake_clock):
    fake_clock.install(mock)  # the rig's trigger clock runs on virtual time
    left, right = _rig(pace=True, buffer_frames=4)
    right.stop()
    assert left.read().frame_id == 0
    fake_clock.sleep(0.05)  # ~50 frames arrive; only 4 fit
    ids = _ids(left, 6)
    assert ids[:4] == [1, 2, 3, 4]
    assert ids[4] > 30 and ids[5] > ids[4]
    assert left.stats.dropped_buffer >= 30


def test_timeout_before_the_first_trigger(fake_clock):
    fake_clock.install(mock)  # virtual time: no stall of a loaded machine reaches trigger 0
    left, _ = _rig(pace=True)  # the trigger starts 10 ms after start()
    t = fake_clock.now()
    with pytest.raises(CameraTimeout):
        left.read(timeout_s=0.003)
    assert fake_clock.now() - t >= 0.0025
    assert left.read(timeout_s=1.0).frame_id == 0


def test_drop_fault():
    left, right = _rig(faults=[{"kind": "drop", "camera": "left", "frame": 5}])
    assert _ids(left, 8) == [0, 1, 2, 3, 4, 6, 7, 8]
    assert _ids(right, 8) == list(range(8))
    assert left.stats.dropped_fault == 1


def test_duplicate_fault():
    left, right = _rig(faults=[{"kind": "duplicate", "camera": "right", "frame": 3}])
    frames = [right.read() for _ in range(6)]
    assert [f.frame_id for f in frames] == [0, 1, 2, 3, 3, 4]
    assert frames[3].timestamp_ns == frames[4].timestamp_ns
    assert np.array_equal(frames[3].image, frames[4].image)
    assert _ids(left, 6) == list(range(6))


def test_stall_fault_unpaced():
    left, right = _rig(faults=[{"kind": "stall", "camera": "left", "frame": 10,
                                "duration_ms": 5.0}])
    assert _ids(left, 12) == list(range(10)) + [15, 16]
    assert left.stats.dropped_fault == 5


def test_stall_fault_paced_delivers_nothing_for_its_duration():
    left, right = _rig(pace=True, faults=[{"kind": "stall", "camera": "left", "frame": 5,
                                           "duration_ms": 30.0}])
    right.stop()
    ids, arrived = [], []
    for _ in range(8):
        ids.append(left.read(timeout_s=1.0).frame_id)
        arrived.append(time.monotonic_ns())
    assert ids == [0, 1, 2, 3, 4, 35, 36, 37]
    # nothing between trigger 5 and the end of the 30 ms stall
    assert arrived[5] - left.rig.trigger_time_ns(5) >= 30_000_000


def test_id_offset_fault():
    left, right = _rig(faults=[{"kind": "id_offset", "camera": "right", "frame": 4, "offset": 3}])
    fr = [right.read() for _ in range(6)]
    assert [f.frame_id for f in fr] == [0, 1, 2, 3, 7, 8]
    assert fr[4].timestamp_ns == left.rig.trigger_time_ns(4)  # timestamps unaffected
    assert _ids(left, 6) == list(range(6))


def test_vanish_fault_unpaced_then_reopen():
    left, right = _rig(faults=[{"kind": "vanish", "camera": "left", "frame": 3,
                                "duration_ms": 4.0}])
    assert _ids(left, 3) == [0, 1, 2]
    with pytest.raises(CameraLost):
        left.read()
    with pytest.raises(CameraLost):
        left.read()  # stays lost until reopened
    left.close()
    left.open()
    left.start()
    assert _ids(left, 2) == [7, 8]  # triggers 3..6 happened while it was gone
    assert _ids(right, 9) == list(range(9))


def test_vanish_fault_paced_cannot_reopen_early(fake_clock):
    fake_clock.install(mock)
    left, right = _rig(pace=True, faults=[{"kind": "vanish", "camera": "left", "frame": 2,
                                           "duration_ms": 40.0}])
    right.stop()
    assert _ids(left, 2) == [0, 1]
    with pytest.raises(CameraLost):
        left.read(timeout_s=1.0)
    left.close()
    with pytest.raises(CameraError):
        left.open()  # still gone
    deadline = fake_clock.now() + 2.0
    while True:
        try:
            left.open()
            break
        except CameraError:
            assert fake_clock.now() < deadline
            fake_clock.sleep(0.005)
    left.start()
    first = left.read(timeout_s=1.0).frame_id
    assert first >= 42


def test_configure_roi_fps_and_errors():
    cfg = override(default_config(), camera=SMALL, rig={"pace": False})
    rig = MockRig(cfg)
    left, right = rig.left, rig.right
    with pytest.raises(CameraError):
        left.configure(CameraSettings())  # not open
    left.open()
    right.open()
    got = left.configure(CameraSettings(fps=2000, exposure_s=0.4e-3, roi=Roi(16, 32, 64, 48),
                                        gain_db=6.0))
    assert got.fps == 2000 and got.gain_db == 0.0 and got.roi == Roi(16, 32, 64, 48)
    assert rig.scene.fps == 2000 and rig.scene.exposure_s == 0.4e-3
    with pytest.raises(CameraError):
        left.configure(CameraSettings(roi=Roi(100, 0, 64, 64)))  # outside the sensor
    with pytest.raises(CameraError):
        left.configure(CameraSettings(trigger="software"))
    left.start()
    right.start()
    fl, fr = left.read(), right.read()
    assert fl.image.shape == (48, 64) and fr.image.shape == (128, 128)
    full = rig.scene.render_pair(fl.frame_id)[0]
    assert np.array_equal(fl.image, full[32:80, 16:80])
    assert right.read().timestamp_ns - fr.timestamp_ns == 500_000
    with pytest.raises(CameraError):
        left.configure(CameraSettings())  # while started
    with pytest.raises(CameraError):
        right.configure(CameraSettings(fps=1000))  # rig-wide while the left one runs


def test_context_manager_and_read_before_start():
    cfg = override(default_config(), camera=SMALL, rig={"pace": False})
    left, right = MockRig.from_config(cfg)
    with left:
        with pytest.raises(CameraError):
            left.read()
        left.start()
        assert left.read().frame_id == 0
    with pytest.raises(CameraError):
        left.read()


def test_benchmark_quick_runs_and_prints_ratios(capsys):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_mock_rig.py"
    spec = importlib.util.spec_from_file_location("bench_mock_rig", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--quick"]) == 0
    out = capsys.readouterr().out
    assert "pairs/s" in out
    line = next(x for x in out.splitlines() if x.startswith("ratio vs real time"))
    assert float(line.rsplit(":", 1)[1]) > 0
    assert "mock / memcpy" in out and "mock / naive" in out
    line = next(x for x in out.splitlines() if x.startswith("mock rig cost at 1000 fps:"))
    assert 0 < float(line.split(":", 1)[1].split()[0]) < 10


def test_two_reader_threads_paced():
    # like the acquisition worker: one thread per camera; ids rise, equal ids pair up
    import threading

    left, right = _rig(pace=True)
    got: dict[str, list] = {"left": [], "right": []}

    def reader(cam):
        for _ in range(150):
            f = cam.read(timeout_s=1.0)
            got[cam.name].append((f.frame_id, f.timestamp_ns, f.image))

    threads = [threading.Thread(target=reader, args=(c,)) for c in (left, right)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    for side in got:
        ids = [g[0] for g in got[side]]
        assert len(ids) == 150 and all(b > a for a, b in zip(ids, ids[1:]))
    by_id = {g[0]: g for g in got["right"]}
    common = [g for g in got["left"] if g[0] in by_id]
    assert len(common) > 100
    scene = left.truth
    for fid, ts, img in common[::50]:
        assert by_id[fid][1] == ts
        el, er = scene.render_pair(fid)
        assert np.array_equal(img, el) and np.array_equal(by_id[fid][2], er)


def test_render_kernels_are_warmed_before_the_trigger_clock_starts(monkeypatch):
    # a paced rig must not spend its first frames compiling: the scene (and its kernels)
    # is built in start(), before t0 is set
    from iscd.sim import Scene

    seen = []
    orig = Scene.warm_up

    def spy(self):
        seen.append(rig._t0_ns)
        return orig(self)

    monkeypatch.setattr(Scene, "warm_up", spy)
    cfg = override(default_config(), camera=SMALL, rig={"pace": True})
    rig = MockRig(cfg)
    rig.left.open()
    rig.left.start()
    assert seen == [None] and rig._t0_ns is not None
    assert rig.left.read(timeout_s=1.0).frame_id == 0  # trigger 0 caught


def test_faults_can_be_replaced_and_are_indexed_per_camera():
    left, right = _rig(faults=[{"kind": "drop", "camera": "left", "frame": 2}])
    rig = left.rig
    assert [f.kind for f in rig.faults] == ["drop"]
    assert rig._faults(rig._cams[0], "drop") and not rig._faults(rig._cams[1], "drop")
    rig.faults = []
    assert _ids(left, 4) == [0, 1, 2, 3]


@pytest.mark.parametrize("lag", [10, 200])
def test_a_reader_far_behind_does_not_make_the_rig_render_every_pair_twice(monkeypatch, lag):
    """One camera read ``lag`` frames ahead of the other (a reader behind on a loaded host,
    or back from a vanish): every camera image is rendered once at most -- the pair
    rendered together and the other image cached where the other camera will read it while
    it is still cached (lag < the cache), each image alone where it would be evicted first.
    Before, a lag beyond the cache had each camera render every pair itself (twice the
    rig's cost), and a reader that fell behind in the soak stayed behind."""
    left, right = _rig()
    scene = left.truth
    images = [0]
    pair, one = scene.render_pair_into, scene.render

    def count_pair(n, l, r):
        images[0] += 2
        return pair(n, l, r)

    def count_one(n, idx, out):
        images[0] += 1
        return one(n, idx, out)

    monkeypatch.setattr(scene, "render_pair_into", count_pair)
    monkeypatch.setattr(scene, "render", count_one)
    _ids(left, lag)
    n = 300
    for _ in range(n):  # both read at the same pace, left ``lag`` ahead
        fl, fr = left.read(), right.read()
        assert fl.frame_id == fr.frame_id + lag
        if fr.frame_id % 97 == 0:  # (rendered with the uncounted kernel)
            el, er = np.empty_like(fl.image), np.empty_like(fr.image)
            pair(fr.frame_id, el, er)
            assert np.array_equal(fr.image, er)
    read = 2 * n + lag
    print(f"lag {lag}: {images[0]} images rendered for {read} read")
    # the only extra images: the other camera's, cached for frames it has not read yet
    assert images[0] <= read + min(lag, mock._CACHE_MAX) + 2
