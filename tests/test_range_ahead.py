"""A block's first pairs ranged before the rest of it is in (``range_ahead``, the daemon's
half-block latency cut): every frame ranged once, the same packets, the ranges those of the
whole block to well within a range's own spread; none ahead while per-LED ranges need the
block's luminance."""

from __future__ import annotations

import numpy as np

from iscd.core.config import default_config
from iscd.decode.multi import make_decoder
from iscd.decode.stream import StreamDecoder


def _run(dec, L: np.ndarray, R: np.ndarray, ahead: int) -> tuple[list[dict], list[int]]:
    out: list[dict] = []
    counts: list[int] = []
    for s in range(0, len(L), 16):
        ids = np.arange(s, s + 16)
        t = ids / 1000.0
        if ahead:
            out += dec.range_ahead(ids[:ahead], t[:ahead], L[s:s + ahead], R[s:s + ahead])
            counts.append(dec.ranged_ahead)
        out += dec.push(ids, t, L[s:s + 16], R[s:s + 16])
    out += dec.finish()
    return out, counts


def _ranges(records: list[dict]) -> dict[int, float]:
    frames = [r["frame"] for r in records if r["type"] == "range"]
    assert len(frames) == len(set(frames))  # no frame ranged twice
    return {r["frame"]: r["z_m"] for r in records if r["type"] == "range"}


def test_ranged_ahead_once_and_as_the_whole_block(rendered_default) -> None:
    L, R = rendered_default
    whole, _ = _run(StreamDecoder(default_config()), L, R, 0)
    split, counts = _run(StreamDecoder(default_config()), L, R, 7)
    # nothing ahead until the transmitter is tracked, then the 7 pairs asked for
    assert counts[0] == 0 and counts[-1] == 7 and set(counts) == {0, 7}
    za, zb = _ranges(whole), _ranges(split)
    assert sorted(za) == sorted(zb) and len(za) > 150
    dz = np.abs(np.array([za[f] - zb[f] for f in za]))
    # the split changes only the running background's and the noise's blocks: per-frame
    # ranges at 30 m scatter by centimetres (docs/ranging.md); the split moves them by far less
    assert np.median(dz) < 1e-3 and dz.max() < 0.02, (np.median(dz), dz.max())
    assert [r for r in whole if r["type"] != "range"] == [r for r in split if r["type"] != "range"]


def test_several_transmitters_range_ahead_with_their_tx() -> None:
    """MultiDecoder: a candidate's ranges ahead are held with its others until its first
    packet, then come out under its ``tx``, each frame once."""
    from iscd.sim.scene import Scene

    sc = Scene(default_config())
    n = 1600  # a whole packet (1.3 s): a candidate's records are held until then
    L = np.empty((n, sc.height, sc.width), np.uint8)
    R = np.empty_like(L)
    for i in range(n):
        sc.render_pair_into(i, L[i], R[i])
    cfg = default_config().with_keys("tracking", max_transmitters=2)
    whole, _ = _run(make_decoder(cfg), L, R, 0)
    split, counts = _run(make_decoder(cfg), L, R, 8)
    assert counts[0] == 0 and counts[-1] == 8
    za, zb = _ranges(whole), _ranges(split)
    assert sorted(za) == sorted(zb) and len(za) > 1000
    assert {r["tx"] for r in split if r["type"] == "range"} == {0}
    assert [r for r in whole if r["type"] == "packet"] == [r for r in split if r["type"] == "packet"]


def test_nothing_ahead_while_per_led_ranges_need_the_luminance(rendered_default) -> None:
    L, R = rendered_default
    cfg = default_config().with_keys("ranging", per_led=True)
    split, counts = _run(StreamDecoder(cfg), L[:128], R[:128], 8)
    assert set(counts) == {0}
    whole, _ = _run(StreamDecoder(cfg), L[:128], R[:128], 0)
    assert split == whole


def test_dropped_ahead_is_ranged_by_the_push(rendered_default) -> None:
    """After a range_ahead whose records were lost (the daemon's error path), drop_ahead
    makes the push range every pair again: no frame without its range."""
    L, R = rendered_default
    dec = StreamDecoder(default_config())
    out: list[dict] = []
    for s in range(0, 128, 16):
        ids = np.arange(s, s + 16)
        dec.range_ahead(ids[:8], ids[:8] / 1000.0, L[s:s + 8], R[s:s + 8])  # records thrown away
        dec.drop_ahead()
        assert dec.ranged_ahead == 0
        out += dec.push(ids, ids / 1000.0, L[s:s + 16], R[s:s + 16])
    whole, _ = _run(StreamDecoder(default_config()), L[:128], R[:128], 0)
    assert sorted(_ranges(out)) == sorted(_ranges(whole)) and len(_ranges(out)) > 30
