"""Pairs at once (iscd.drivers.base.StereoPairSource): the mock rig renders both frames of a
trigger straight into the acquisition's ring slots. The same frames, ids and timestamps
as reading the cameras one by one; the per-camera path where faults are injected."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.drivers.base import CameraError
from iscd.drivers import mock
from iscd.drivers.mock import MockRig
from iscd.rig.acquisition import Acquisition, AcquisitionOptions
from iscd.core.config import default_config
from iscd.rig.ringbuffer import StereoRing
from iscd.sim.presets import override


def _rig(pace: bool, **rig) -> MockRig:
    cfg = override(default_config(), rig={"pace": pace, **rig})
    r = MockRig(cfg)
    for c in (r.left, r.right):
        c.open()
        c.start()
    return r


def test_pairs_at_once_equal_the_frames_read_one_by_one() -> None:
    a, b = _rig(False), _rig(False)
    assert a.left.pair_source() is a and a.right.pair_source() is a
    L = np.empty((512, 512), np.uint8)
    R = np.empty_like(L)
    for _ in range(12):
        meta = a.read_pair_into(L, R)
        fl, fr = b.left.read(), b.right.read()
        assert (meta.left_id, meta.right_id) == (fl.frame_id, fr.frame_id)
        # each rig's clock starts when it starts: the same times after its first trigger
        ta, tb = a.trigger_time_ns(0), b.trigger_time_ns(0)
        assert (meta.ts_left_ns - ta, meta.ts_right_ns - ta) == (fl.timestamp_ns - tb, fr.timestamp_ns - tb)
        np.testing.assert_array_equal(L, fl.image)
        np.testing.assert_array_equal(R, fr.image)
    assert a.stats(0).delivered == a.stats(1).delivered == 12


def test_no_pair_source_with_injected_faults() -> None:
    r = _rig(False, faults=[{"kind": "drop", "camera": "left", "frame": 5}])
    assert r.left.pair_source() is None
    with pytest.raises(CameraError, match="pairs at once"):
        r.read_pair_into(np.empty((512, 512), np.uint8), np.empty((512, 512), np.uint8))


def test_a_late_reader_loses_the_newest_frames_as_a_full_camera_buffer_does(fake_clock) -> None:
    fake_clock.install(mock)  # the rig's trigger clock runs on virtual time
    r = _rig(True)
    L = np.empty((512, 512), np.uint8)
    R = np.empty_like(L)
    first = r.read_pair_into(L, R, timeout_s=1.0).left_id
    fake_clock.sleep(0.05)  # 50 triggers pass; the queue keeps the oldest buffer_frames
    ids = [r.read_pair_into(L, R, timeout_s=1.0).left_id for _ in range(r.buffer_frames)]
    assert ids[0] > first and all(b > a for a, b in zip(ids, ids[1:]))  # oldest first
    assert r.stats(0).dropped_buffer > 0 and r.stats(0).dropped_buffer == r.stats(1).dropped_buffer
    nxt = r.read_pair_into(L, R, timeout_s=1.0).left_id
    assert nxt > ids[-1] + 1  # the dropped ones never come
    # every trigger that never came was counted as a drop (on a busy machine some may have
    # been dropped before the sleep already, or after it: counted all the same)
    seen = [first, *ids, nxt]
    gaps = sum(b - a - 1 for a, b in zip(seen, seen[1:]))
    assert 0 < gaps <= r.stats(0).dropped_buffer


def test_acquisition_fills_the_ring_with_whole_pairs_from_the_rig() -> None:
    cfg = override(default_config(), rig={"pace": True})
    rig = MockRig(cfg)
    ring = StereoRing.create(height=512, width=512, capacity=1024)
    try:
        acq = Acquisition(rig.left, rig.right, ring, options=AcquisitionOptions(read_timeout_s=0.05))
        st = acq.run(duration_s=0.6)  # ~600 triggers: >= 100 pairs even on a busy machine
        assert st.pairs_written >= 100 and st.frames_left == st.frames_right == st.pairs_written
        got = []
        while (slot := ring.read()) is not None:
            got.append(slot.frame_id)
            if len(got) in (1, 50):
                ref_l, ref_r = rig.scene.render_pair(slot.frame_id)
                np.testing.assert_array_equal(slot.left, ref_l)
                np.testing.assert_array_equal(slot.right, ref_r)
            slot.release()
        # in order, and every gap is a counted drop (a reader late on a busy machine loses
        # frames as a camera with full buffers does: counted, never silently)
        assert all(b > a for a, b in zip(got, got[1:]))
        gaps = sum(b - a - 1 for a, b in zip(got, got[1:]))
        assert gaps <= rig.stats(0).dropped_buffer
        assert len(got) >= 100
    finally:
        ring.close()
