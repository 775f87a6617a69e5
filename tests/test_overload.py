"""The overload policy (iscd.service.overload) driven with made-up ring fills, the decoder's
shedding (ranging every k-th frame, per-LED ranges), and the daemon shedding in order on
the mock rig when a stage is made slow."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from iscd.service.overload import OverloadPolicy, OverloadSettings


def test_levels_in_order_with_hysteresis_and_return_to_full_service() -> None:
    pol = OverloadPolicy(OverloadSettings(led_fill=0.05, ranging_fill=0.15, images_fill=0.35, ranging_every=4))
    seen = [pol.service(f) for f in (0.0, 0.06, 0.2, 0.5, 0.3, 0.1, 0.06, 0.02, 0.0)]
    levels = [s.level for s in seen]
    # up one threshold at a time; down only below half of a level's threshold
    assert levels == [0, 1, 2, 3, 3, 2, 1, 0, 0], levels
    # what each level sheds is cumulative, in the stated order
    for s in seen:
        assert s.per_led == (s.level < 1)
        assert s.ranging_every == (1 if s.level < 2 else 4)
        assert s.images == (s.level < 3)
    assert pol.counters["overload_max_level"] == 3 and pol.counters["overload_level"] == 0
    assert pol.counters["overload_blocks"] == 6


def test_a_jump_goes_straight_to_the_level_of_the_fill() -> None:
    pol = OverloadPolicy()
    assert pol.service(0.9).level == 3
    assert pol.service(0.0).level == 0


def test_bad_order_of_thresholds_is_refused() -> None:
    with pytest.raises(ValueError, match="led_fill <= ranging_fill <= images_fill"):
        OverloadSettings(led_fill=0.5, ranging_fill=0.1)


def test_daemon_refuses_thresholds_out_of_order() -> None:
    from iscd.core import config as C
    from iscd.service.daemon import Daemon

    cfg = C.loads("[daemon]\nshed_led_fill = 0.5\nshed_ranging_fill = 0.2\n")
    with pytest.raises(C.ConfigError, match="daemon.shed_led_fill"):
        Daemon(cfg, duration_s=1, install_signals=False)


def test_decoder_ranges_every_kth_frame_when_told(rendered_default) -> None:
    from iscd.core.config import default_config
    from iscd.decode.stream import StreamDecoder

    L, R = rendered_default
    ids = np.arange(L.shape[0])
    full, shed = StreamDecoder(default_config()), StreamDecoder(default_config())
    rf, rs = [], []
    for s in range(0, L.shape[0], 16):
        sl = slice(s, s + 16)
        rf += full.push(ids[sl], ids[sl] / 1000.0, L[sl], R[sl])
        rs += shed.push(ids[sl], ids[sl] / 1000.0, L[sl], R[sl], ranging_every=4)
    zf = {r["frame"]: r["z_m"] for r in rf if r["type"] == "range"}
    zs = {r["frame"]: r["z_m"] for r in rs if r["type"] == "range"}
    assert zs and all(f % 4 == 0 for f in zs)
    assert len(zs) >= len(zf) // 4 - 2
    # the ranged frames are ranged as well as with full service
    common = sorted(set(zs) & set(zf))
    assert len(common) >= len(zs) - 2
    assert np.median(np.abs(np.array([zs[f] - 30.0 for f in common]))) < 0.1
    decoded = shed.counters["frames_decoded"]
    assert shed.counters["ranging_skipped"] >= decoded - decoded // 4 - 16
    # the luminance (and so the packets) never shed: the same frames decoded
    assert shed.counters["frames_decoded"] == full.counters["frames_decoded"]


from fakes import LIGHT_PACED  # noqa: E402  (the daemon tests' light transmitter, paced)


def test_daemon_sheds_in_order_and_keeps_the_packets(tmp_path: Path, monkeypatch) -> None:
    """An injected slow stage: full-service ranging costs 40 ms a block of 16 pairs (the
    camera gives 16 ms): the ring fills, the daemon sheds ranging (level 2), keeps every
    packet, says so in the stats, and returns to full service when it has caught up."""
    from iscd.core import config as C
    from iscd.service.daemon import Daemon
    from iscd.decode.ranging.stereo import StereoRanger

    real = StereoRanger.measure

    def slow(self, left, right, fl, fr):  # ranging every frame of a block is slow
        if left.shape[0] >= 8:
            time.sleep(0.04)
        return real(self, left, right, fl, fr)

    monkeypatch.setattr(StereoRanger, "measure", slow)
    out = tmp_path / "out.jsonl"
    d = Daemon(C.loads(LIGHT_PACED), out=str(out), duration_s=8.0, install_signals=False)
    d.run()
    recs = [json.loads(x) for x in out.read_text().splitlines()]
    stats = [r for r in recs if r["type"] == "stats"]
    final = stats[-1]
    assert final["overload_max_level"] >= 2, final
    assert final["ranging_skipped"] > 0 and final["overload_blocks"] > 0
    pk = [r for r in recs if r["type"] == "packet"]
    assert final["packets_bad"] == 0 and final["packets_ok"] >= 10, (final["packets_ok"], final["packets_bad"])
    assert all(r["crc_ok"] for r in pk)
    # shedding kept the ring from overflowing
    assert final["ring_dropped"] == 0, final
    # the level came back down between overloads (full service returns)
    assert min(s["overload_level"] for s in stats[1:]) <= 1
