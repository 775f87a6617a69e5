"""Several transmitters at once (issue 15): :class:`iscd.decode.multi.MultiDecoder` on
rendered scenes with several transmitters on their own clocks and PWM-dimmed tail lights
that send nothing (``iscd/data/examples/three_tx.toml``), measured against each
transmitter's own simulator truth (:meth:`iscd.sim.scene.Scene.truths`).

The receiver's config has no shape (``rows = cols = "auto"``: each transmitter's shape is
inferred) and ``[tracking] max_transmitters = 6``; nothing in it names where the
transmitters are or how many.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.core.config import Config, ConfigError, load
from iscd.decode.multi import MultiDecoder, make_decoder
from iscd.decode.stream import StreamDecoder
from iscd.sim.scene import Scene

EXAMPLE = Path(__file__).resolve().parents[1] / "iscd" / "data" / "examples" / "three_tx.toml"
BLOCK = 16


def _receiver(cfg: Config, n: int = 6) -> Config:
    """The receiver's config: the rig's cameras, no transmitter shape, up to n transmitters."""
    return cfg.replace(transmitter=replace(cfg.transmitter, rows=0, cols=0)).with_keys(
        "tracking", max_transmitters=n)


def _decode(cfg: Config, dec: StreamDecoder | MultiDecoder, n_frames: int,
            defer: bool = False) -> tuple[list[dict], list]:
    """Render ``n_frames`` of ``cfg`` block by block into ``dec`` (``defer``: as the daemon,
    push(defer=True) then finish_block()); (records, truths)."""
    scene = Scene(cfg)
    truths = scene.truths(np.arange(n_frames))
    H, W = cfg.camera.height, cfg.camera.width
    left = np.empty((BLOCK, H, W), np.uint8)
    right = np.empty_like(left)
    out: list[dict] = []
    for f0 in range(0, n_frames - BLOCK + 1, BLOCK):
        for i in range(BLOCK):
            scene.render_pair_into(f0 + i, left[i], right[i])
        ids = np.arange(f0, f0 + BLOCK)
        if defer:
            out += dec.push(ids, ids / cfg.camera.fps, left, right, defer=True)
            out += dec.finish_block()
        else:
            out += dec.push(ids, ids / cfg.camera.fps, left, right)
    return out + dec.finish(), truths


def _packet_frames(cfg: Config) -> float:
    """A packet's duration in frames (the main transmitter's; the example's share it)."""
    air = AirInterface.from_config(cfg.transmitter)
    return air.period_symbols * cfg.camera.fps / cfg.transmitter.symbol_rate_hz


def _whole_packets(truth, n_frames: int, fps: float, packet_frames: float, since_frame: int = 0) -> list[bytes]:
    """Payloads of the packets that start at or after ``since_frame`` and end before ``n_frames``."""
    starts = np.asarray(truth.packet_t_s) * fps
    return [p for p, s in zip(truth.payloads, starts) if s >= since_frame and s + packet_frames < n_frames]


def _by_tx(records: list[dict]) -> dict[int, list[dict]]:
    out: dict[int, list[dict]] = {}
    for r in records:
        if r["type"] == "packet" and r["crc_ok"]:
            out.setdefault(int(r["tx"]), []).append(r)
    return out


def _range_mae(records: list[dict], tx: int, truth) -> float:
    rr = [r for r in records if r["type"] == "range" and r["tx"] == tx]
    f = np.array([r["frame"] for r in rr])
    z = np.array([r["z_m"] for r in rr])
    assert f.size > 1000
    return float(np.mean(np.abs(z - truth.z_m[f])))


def _alone(cfg: Config, k: int) -> Config:
    """The scene with transmitter k alone (no other transmitters, no tail lights)."""
    sc = replace(cfg.scene, transmitters=[], distractors=[])
    if k == 0:
        return cfg.replace(scene=sc)
    e = cfg.scene.transmitters[k - 1]
    return cfg.replace(transmitter=e.transmitter(cfg.transmitter, k - 1),
                       scene=replace(sc, distance_m=e.distance_m, lateral_m=e.lateral_m, vertical_m=e.vertical_m,
                                     led_drift_ppm=e.led_drift_ppm))


def test_make_decoder_picks_by_max_transmitters() -> None:
    cfg = load(EXAMPLE)
    one = cfg.with_keys("tracking", max_transmitters=1)
    assert type(make_decoder(one)) is StreamDecoder  # the default: one transmitter, as before
    multi = make_decoder(cfg)  # the example asks for up to 6, any shape
    assert isinstance(multi, MultiDecoder) and multi.cfg.transmitter.shape_auto
    listed = make_decoder(cfg.with_keys("tracking", shapes="8x8, 1x1"))
    assert listed.slots[0].dec.allowed_shapes == {(8, 8), (1, 1)}
    assert not make_decoder(cfg.with_keys("tracking", shapes="config")).cfg.transmitter.shape_auto
    with pytest.raises(ConfigError, match="tracking.shapes"):
        make_decoder(cfg.with_keys("tracking", shapes="8 by 8"))


def test_three_transmitters_and_two_tail_lights() -> None:
    """An 8x8 array at 40 m and single LEDs at 30 m and 55 m on their own clocks (+100,
    -100, +50 ppm), two PWM-dimmed tail lights (200 Hz at 30 %, 1 kHz at 50 %): every whole
    packet of each transmitter bit-exact under one tx per transmitter; no packet that was
    not sent (none from the tail lights); each transmitter's range MAE within 10 % of the
    same transmitter decoded alone."""
    cfg = load(EXAMPLE)
    n = 4000
    dec = MultiDecoder(_receiver(cfg))
    records, truths = _decode(cfg, dec, n)
    assert len(truths) == 3
    sent = {p for t in truths for p in t.payloads}
    got = _by_tx(records)
    # every CRC-valid payload was sent (none from the tail lights), none twice
    payloads = [bytes.fromhex(r["payload_hex"]) for rs in got.values() for r in rs]
    assert set(payloads) <= sent
    assert len(payloads) == len(set(payloads))
    # one tx per transmitter, and every whole packet of each
    tx_of = {}
    for k, t in enumerate(truths):
        want = _whole_packets(t, n, cfg.camera.fps, _packet_frames(cfg))
        assert len(want) >= 3
        txs = {tx for tx, rs in got.items() for r in rs if bytes.fromhex(r["payload_hex"]) in set(t.payloads)}
        assert len(txs) == 1, f"transmitter {k}'s packets came under tx {sorted(txs)}"
        tx_of[k] = txs.pop()
        have = [bytes.fromhex(r["payload_hex"]) for r in got[tx_of[k]]]
        assert all(p in have for p in want), f"transmitter {k}: {len(set(want) & set(have))} of {len(want)}"
    assert sorted(tx_of.values()) == [0, 1, 2]
    assert dec.counters["transmitters_confirmed"] == 3
    assert dec.counters["rejected_candidates"] >= 1  # the 200 Hz tail light, tried and rejected
    assert sorted(t["tx"] for t in dec.transmitters()) == [0, 1, 2]  # the final stats' figures
    # packets only from the three; the tail light tried as a candidate is rejected
    assert {int(r["tx"]) for r in records if r["type"] == "packet"} == {0, 1, 2}
    # ranging per transmitter, against the same transmitter alone in the scene
    for k, t in enumerate(truths):
        multi = _range_mae(records, tx_of[k], t)
        one_cfg = _alone(cfg, k)
        alone_recs, alone_truth = _decode(one_cfg, StreamDecoder(one_cfg), n)
        alone = _range_mae(alone_recs, 0, alone_truth[0])
        assert multi <= 1.10 * alone, f"transmitter {k} at {t.z_m[0]:.0f} m: MAE {multi * 1e3:.1f} mm, alone {alone * 1e3:.1f} mm"


def test_transmitter_enters_and_leaves() -> None:
    """The 55 m LED enters at 1.30 s, 8 frames before a packet of its own starts, and
    leaves at 4.5 s: decoded from that first whole packet (the searcher looks only every
    search_every_frames, but keeps the frames since its last look), given up within 1.5
    packet durations of leaving; the other two lose nothing meanwhile."""
    cfg = load(EXAMPLE)
    extras = list(cfg.scene.transmitters)
    extras[1] = replace(extras[1], start_s=1.30, stop_s=4.5)
    cfg = cfg.replace(scene=replace(cfg.scene, transmitters=extras))
    n = 7400
    # looks 512 frames apart: the packet's header comes long before the next look after it enters
    dec = MultiDecoder(_receiver(cfg).with_keys("tracking", search_every_frames=512))
    records, truths = _decode(cfg, dec, n)
    fps = cfg.camera.fps
    packet_frames = _packet_frames(cfg)
    got = _by_tx(records)
    payload_tx = {bytes.fromhex(r["payload_hex"]): tx for tx, rs in got.items() for r in rs}
    # the two that stay: every whole packet
    for k in (0, 1):
        want = _whole_packets(truths[k], n, fps, packet_frames)
        assert all(p in payload_tx for p in want), f"transmitter {k} lost packets"
        assert len({payload_tx[p] for p in want}) == 1
    # the one that comes and goes: every whole packet while it is in view
    t = truths[2]
    starts = np.asarray(t.packet_t_s) * fps
    want = [p for p, s in zip(t.payloads, starts) if s >= 1.30 * fps and s + packet_frames <= 4.5 * fps]
    first = min(s for s in starts if s >= 1.30 * fps)
    assert first - 1.30 * fps < 64, "the scene no longer starts a packet just after the LED enters"
    assert len(want) >= 2
    assert all(p in payload_tx for p in want)
    tx = payload_tx[want[0]]
    lost = [f for what, x, f in dec.events if what == "lost" and x == tx]
    assert lost, "the transmitter that left was never given up"
    assert 4.5 * fps < lost[0] <= 4.5 * fps + 1.5 * packet_frames
    # nothing of it after it was given up
    assert not [r for r in records if r.get("tx") == tx and r["frame"] > lost[0] + BLOCK]


def test_daemon_decodes_every_transmitter_of_the_mock_rig(tmp_path: Path) -> None:
    """``iscd run`` on the mock rig rendering the three-transmitter scene: packets of each
    transmitter under its own tx, bit-exact against the scene's truth, none from the tail
    lights; the stats name each transmitter; one demodulation worker for all of them. Runs
    until every transmitter has delivered two packets, on the unpaced rig, which waits for
    the decoder: nothing is dropped however busy the machine is (no wall-clock race)."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from fakes import run_daemon_until, stats_records

    text = EXAMPLE.read_text()
    assert "\npace = true\n" in text
    text = text.replace("\npace = true\n", "\npace = false\n")

    def done(recs: list[dict]) -> bool:
        ok = [r for r in recs if r["type"] == "packet" and r["crc_ok"]]
        return len({r["tx"] for r in ok}) >= 3 and all(
            sum(1 for r in ok if r["tx"] == tx) >= 2 for tx in {r["tx"] for r in ok})

    _, recs, stop = run_daemon_until(text, tmp_path, done, timeout_s=240.0)
    assert stop.met_at_s is not None, "not every transmitter delivered two packets"
    cfg = load(EXAMPLE)
    last = max(r["frame"] for r in recs if r["type"] == "packet")
    sent = {p for t in Scene(cfg).truths(np.arange(last + 2000)) for p in t.payloads}
    ok = [r for r in recs if r["type"] == "packet" and r["crc_ok"]]
    assert ok and all(bytes.fromhex(r["payload_hex"]) in sent for r in ok)
    assert {r["tx"] for r in ok} == {0, 1, 2}
    seen = [s for s in stats_records(recs) if s.get("transmitters")]
    assert seen and max(len(s["transmitters"]) for s in seen) == 3
    final = stats_records(recs)[-1]
    # none dropped while running (at the stop, what the ring still holds after stop_drain_s is)
    assert final["frames_dropped"] == final["stop_dropped"]
    assert final["pairs_decoded"] > last
    # one demodulation worker process for all of them (each has its slot in it)
    assert {s["demod_worker_processes"] for s in stats_records(recs, final=False) if s.get("transmitters")} == {1}


def test_a_find_at_a_rejected_blinkers_place_skips_its_look_back() -> None:
    """A candidate found again where a blinker was rejected before is decoded from its look
    on, not from the whole look-back (the frame loop would spend ~0.1 s at once on it every
    time the tail light comes back); a transmitter there is still tracked and confirmed."""
    cfg = load(EXAMPLE)
    dec = MultiDecoder(_receiver(cfg))
    # pretend the 30 m LED's place (left ~115, 255) was rejected once as a blinker
    dec._rejections = [((105, 245, 126, 266), 1)]
    records, truths = _decode(cfg, dec, 2400)
    assert dec.counters["lookbacks_skipped"] >= 1
    assert dec.counters["transmitters_confirmed"] == 3
    got = _by_tx(records)
    sent = {p for t in truths for p in t.payloads}
    payloads = [bytes.fromhex(r["payload_hex"]) for rs in got.values() for r in rs]
    assert payloads and set(payloads) <= sent


def test_a_rejection_backs_off_when_blocks_are_deferred() -> None:
    """As the daemon decodes (push(defer=True), then finish_block): the tail light rejected
    in the deferred part is registered for the back-off (its place left out longer each
    time, and a find there again skips its look-back) as in the in-line decode."""
    from iscd.core import jit

    cfg = load(EXAMPLE)
    dec = MultiDecoder(_receiver(cfg))
    jit.warm_up()
    before = jit.signatures()
    records, _ = _decode(cfg, dec, 4000, defer=True)
    # and nothing compiled in the middle of it (a compile there stalls the daemon's frame
    # loop for seconds on the first start after an install): every type the several
    # transmitters' path passes a kernel was warmed up
    grown = {k: (before.get(k), v) for k, v in jit.signatures().items() if v != before.get(k)}
    assert not grown, grown
    assert dec.counters["rejected_candidates"] >= 1
    assert dec._rejections, "the rejection was not registered"
    assert dec.counters["transmitters_confirmed"] == 3
    assert {int(r["tx"]) for r in records if r["type"] == "packet"} == {0, 1, 2}
