"""The receiver finds an LED array of a shape it was not told (issue 14: "decoded in one replay
with no config for the transmitter").

The pure inference (:func:`iscd.decode.tracking.detect.infer_grid` on the lit map of rendered
frames: several shapes, several distances, both apertures, dark LEDs), the acquisition that
uses it (:func:`iscd.decode.tracking.detect.detect_auto`: the same fit as a configured shape),
the config (``rows = cols = "auto"``; a receiver's config without ``[transmitter]``), the
stream decoder's checks of the inferred shape against the PHY header, and the must-show: one
rendered recording with a v1 transmission (8x8, PWM-8, the SPEC's K and F) and then a v2
transmission of another shape and M (4x8, PWM-16, RS(255,223)), decoded bit-exact by one
StreamDecoder (what ``iscd replay`` runs) whose config has no ``[transmitter]`` table.
All scenes from the simulator with fixed seeds.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from fakes import cli

from iscd.core.airinterface import AirInterface, AirInterfaceError
from iscd.core.airinterface_v2 import AirInterfaceV2
from iscd.core.config import ConfigError, default_config, loads
from iscd.decode.comms.packets import Packet
from iscd.decode.stream import StreamDecoder, _Track
from iscd.decode.tracking.detect import GridFit, detect_array, detect_auto, infer_grid, lit_map
from iscd.eval.suites import chapter4_cfg
from iscd.recording.iscr import IscrWriter
from iscd.sim.presets import override
from iscd.sim.scene import Scene
from iscd.sim.transmitter import ArraySource

W, H = 256, 192
"""Camera frame size of these scenes, px (the chapter 4 cameras, cropped: quicker)."""

FOCAL_PX = 3500.0
"""Focal length of the chapter 4 cameras (35 mm, 10 um pixels), px."""

RX_TOML = f"""
[camera]
width = {W}
height = {H}
baseline_m = 0.25
f_number_left = 4
f_number_right = 8
"""
"""A receiver's config for these scenes: cameras, no [transmitter]."""


def _scene(rows: int, cols: int, levels: int, distance_m: float, lv: np.ndarray, seed: int,
           f_right: float = 8.0) -> Scene:
    cfg = chapter4_cfg(default_config(), distance_m, levels, f_right, seed)
    cfg = override(cfg, transmitter={"rows": rows, "cols": cols}, camera={"width": W, "height": H})
    return Scene(cfg, ArraySource(lv))


def _random_levels(rows: int, cols: int, levels: int, n_sym: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(1, levels + 1, (n_sym, rows * cols)).astype(np.uint8)


@lru_cache(maxsize=8)
def _frames(rows: int, cols: int, distance_m: float, seed: int, dark: tuple[int, ...] = (),
            n: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(left f/4, right f/8) frames (n, H, W) of an array sending random PWM-16 levels; the
    LEDs ``dark`` stay off."""
    lv = _random_levels(rows, cols, 16, n, seed)
    lv[:, list(dark)] = 1
    sc = _scene(rows, cols, 16, distance_m, lv, seed)
    L, R = np.empty((n, H, W), np.uint8), np.empty((n, H, W), np.uint8)
    for k in range(n):
        sc.render_pair_into(k, L[k], R[k])
    return L, R


def _region(fit: GridFit, shape: tuple[int, ...]) -> tuple[slice, slice]:
    x0, y0, x1, y1 = fit.bbox(3)
    return slice(max(0, y0), min(shape[0], y1)), slice(max(0, x0), min(shape[1], x1))


SHAPES = [(1, 1), (4, 4), (8, 8), (4, 8), (8, 4)]


# --------------------------------------------------------------------------- the pure inference
@pytest.mark.parametrize("distance_m", [15.0, 30.0, 50.0, 70.0])
@pytest.mark.parametrize("rows,cols", SHAPES)
def test_infer_grid_on_rendered_arrays(rows: int, cols: int, distance_m: float) -> None:
    """The lit map around the array (the configured fit's box, 3 px margin) gives the array's
    rows x cols and its pitch within 5 % (6 cm LEDs: 210 / Z px), in the saturating f/4
    camera and in the f/8 one, 15-70 m (pitch 14 down to 3 px)."""
    L, R = _frames(rows, cols, distance_m, 11)
    for frames in (L, R):
        fit = detect_array(frames, rows, cols)
        assert fit is not None
        g = infer_grid(lit_map(frames)[_region(fit, frames.shape[1:])])
        assert g is not None and (g.rows, g.cols) == (rows, cols)
        if rows * cols > 1:
            assert g.pitch_px == pytest.approx(FOCAL_PX * 0.06 / distance_m, rel=0.05)
            assert g.fill == 1.0


def test_infer_grid_with_dark_leds() -> None:
    """8x8 at 40 m with a corner LED, an inner LED and a whole inner column dark over the
    window: still 8x8 (the lattice spans the gap), fill 54 / 64."""
    dark = (0, 28, *range(3, 64, 8))
    L, _ = _frames(8, 8, 40.0, 12, dark=dark)
    fit = detect_array(L, 8, 8)
    g = infer_grid(lit_map(L)[_region(fit, L.shape[1:])])
    assert g is not None and (g.rows, g.cols) == (8, 8)
    assert g.spots == 64 - len(set(dark)) and g.fill == pytest.approx(54 / 64)


def test_infer_grid_is_never_wrong_when_too_fine() -> None:
    """8x8 at 80 m (2.6 px pitch): the spots merge into one, which acquisition does not take
    for one LED (its halves send different data); no array at all rather than a wrong one.
    A scatter of spots on no lattice is no grid."""
    L, R = _frames(8, 8, 80.0, 13)
    for frames in (L, R):
        g = infer_grid(lit_map(frames)[96 - 20:96 + 20, 128 - 40:128 + 20])
        assert g is None or (g.rows, g.cols) in ((8, 8), (1, 1))
        fit = detect_auto(frames)
        assert fit is None or (fit.rows, fit.cols) == (8, 8)
    one, _ = _frames(1, 1, 80.0, 13)
    fit = detect_auto(one)
    assert fit is not None and (fit.rows, fit.cols) == (1, 1)
    rng = np.random.default_rng(5)
    lit = np.zeros((60, 60), np.float32)
    yy, xx = np.mgrid[0:60, 0:60]
    for x, y in rng.uniform(5, 55, (9, 2)):
        lit += 200 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 2.0)
    assert infer_grid(lit) is None
    assert infer_grid(np.zeros((20, 20), np.float32)) is None


def test_infer_grid_synthetic_spots() -> None:
    """Gaussian spots on a 3x5 grid of 6.3 px pitch at a sub-pixel origin: 3x5, the pitch
    and origin to 0.05 px."""
    yy, xx = np.mgrid[0:40, 0:50].astype(np.float64)
    lit = np.zeros((40, 50))
    for r in range(3):
        for c in range(5):
            lit += 220 * np.exp(-((xx - 7.3 - 6.3 * c) ** 2 + (yy - 9.6 - 6.3 * r) ** 2) / (2 * 1.1 ** 2))
    g = infer_grid(lit)
    assert g is not None and (g.rows, g.cols) == (3, 5)
    assert g.pitch_px == pytest.approx(6.3, abs=0.05)
    assert g.origin == pytest.approx((7.3, 9.6), abs=0.05)


# --------------------------------------------------------------------------- acquisition
@pytest.mark.parametrize("rows,cols,distance_m", [(8, 8, 30.0), (4, 8, 50.0), (8, 4, 20.0), (1, 1, 40.0)])
def test_detect_auto_is_the_configured_fit(rows: int, cols: int, distance_m: float) -> None:
    """Acquisition without the shape finds the same fit (origin, pitch, score, bit for bit)
    as acquisition told the shape: auto changes nothing once the shape is right."""
    L, R = _frames(rows, cols, distance_m, 14)
    for frames in (L, R):
        auto = detect_auto(frames)
        told = detect_array(frames, rows, cols)
        assert auto is not None and told is not None
        assert (auto.rows, auto.cols) == (rows, cols)
        assert auto == told


# --------------------------------------------------------------------------- config
def test_config_auto_shape() -> None:
    tx = loads('[transmitter]\nrows = "auto"\ncols = "auto"\n').transmitter
    assert tx.shape_auto and (tx.rows, tx.cols) == (0, 0)
    assert loads("[transmitter]\nrows = 0\ncols = 0\n").transmitter.shape_auto
    with pytest.raises(ConfigError, match="both or for neither"):
        loads('[transmitter]\nrows = "auto"\ncols = 8\n')
    with pytest.raises(ConfigError, match="transmitter.rows"):
        loads('[transmitter]\nrows = "many"\n')
    # a receiver's config without [transmitter] leaves the shape to the receiver; elsewhere
    # (simulator, mock rig, board) a missing table is the default 8x8
    rx = loads(RX_TOML, receiver=True).transmitter
    assert rx.shape_auto and (rx.levels, rx.training_symbols, rx.data_symbols) == (8, 40, 600)
    assert not loads(RX_TOML).transmitter.shape_auto
    assert not loads(RX_TOML + '[transmitter]\nrows = 4\n', receiver=True).transmitter.shape_auto
    # the shape is needed by whatever sends packets
    with pytest.raises(AirInterfaceError, match="auto"):
        AirInterface.from_config(rx)
    # v2 with an auto shape is a valid receiver config (checked when the shape is known)
    assert loads('[transmitter]\nrows = "auto"\ncols = "auto"\nair_interface = "v2"\n'
                 'payload_len = 100000\n').transmitter.shape_auto


def test_shape_checks_of_the_stream_decoder() -> None:
    """A v2 header naming another arrangement of as many LEDs restarts acquisition with the
    header's shape (counted); a v2 header that agrees confirms the shape; v1 packets that all
    fail on an unconfirmed shape restart acquisition after AUTO_BAD_PACKETS (counted)."""
    dec = StreamDecoder(loads(RX_TOML, receiver=True))
    assert dec.shape_auto and (dec.rows, dec.cols) == (1, 1)
    dec._set_shape(8, 4)
    assert dec.tx.n_leds == 32 and dec._use.size > 0
    fit = GridFit((100.0, 80.0), 5.0, 8, 4, 10.0)
    lv = np.ones((1, 32), np.uint8)

    def pkt(ok: bool, shape: tuple[int, int] | None) -> Packet:
        return Packet(frame=0, t_s=0.0, u0_frames=0.0, crc_ok=ok, payload=b"x" if ok else None, levels=lv,
                      raw=b"x", version=2 if shape else 1, shape=shape)

    dec.track = _Track(left=fit, right=fit, first_score=10.0, since_frame=0)
    dec._records([pkt(False, (8, 4))])
    assert dec.track.shape_confirmed and dec.counters["shape_mismatches"] == 0
    dec._records([pkt(True, (4, 8))])
    assert dec.counters["shape_mismatches"] == 1 and dec._reacquire and dec._shape_hint == (4, 8)
    dec.restart()
    assert not dec._reacquire and dec.track is None
    dec.track = _Track(left=fit, right=fit, first_score=10.0, since_frame=0)
    dec._records([pkt(False, None)] * (dec.AUTO_BAD_PACKETS - 1))
    assert not dec._reacquire
    dec._records([pkt(False, None)])
    assert dec._reacquire and dec.counters["shape_retries"] == 1
    dec.finish()


# --------------------------------------------------------------------------- must show
def test_v1_and_v2_of_other_shapes_in_one_replay_without_transmitter_config() -> None:
    """One rendered recording: a v1 packet from an 8x8 PWM-8 array at 30 m (the SPEC's K = 40,
    F = 600: 14 396 bytes), 300 dark frames, then two v2 packets from a 4x8 PWM-16 array at
    40 m (RS(255,223), 600 bytes each). One StreamDecoder whose config has cameras and no
    [transmitter] (``iscd replay --config`` of such a file) infers 8x8, then after the first
    array is lost 4x8, and delivers all three payloads bit-exact, each with its version.
    ([tracking] lost_packets = 0.2: the receiver's packet duration is the SPEC's v1 packet,
    1.3 s, and the scene should not wait 1.6 s of darkness between the two arrays.)"""
    rng = np.random.default_rng(7)
    v1 = AirInterface(levels=8, n_leds=64)
    v2 = AirInterfaceV2(levels=16, rows=4, cols=8, fec="rs255_223", payload_len=600)
    p1 = [rng.integers(0, 256, v1.payload_bytes, dtype=np.uint8).tobytes()]
    p2 = [rng.integers(0, 256, 600, dtype=np.uint8).tobytes() for _ in range(2)]
    lv_a = np.concatenate([v1.packets(p1), np.ones((4, 64), np.uint8)])
    lv_b = np.concatenate([v2.packets(p2), np.ones((4, 32), np.uint8)])
    a, b = _scene(8, 8, 8, 30.0, lv_a, 3), _scene(4, 8, 16, 40.0, lv_b, 4)
    start_b = lv_a.shape[0] * 2 + 8 + 300
    n = start_b + lv_b.shape[0] * 2 + 8
    rx = loads(RX_TOML + "[tracking]\nlost_packets = 0.2\n", "rx.toml", receiver=True)
    dec = StreamDecoder(rx)
    recs: list[dict] = []
    L, R = np.empty((32, H, W), np.uint8), np.empty((32, H, W), np.uint8)
    shapes = []
    for s in range(0, n, 32):
        ids = np.arange(s, min(s + 32, n))
        for i, k in enumerate(ids.tolist()):
            (a.render_pair_into(k, L[i], R[i]) if k < start_b else b.render_pair_into(k - start_b, L[i], R[i]))
        recs += [r for r in dec.push(ids, ids / 1000.0, L[:ids.size], R[:ids.size]) if r["type"] == "packet"]
        if dec.track is not None and (not shapes or shapes[-1] != (dec.rows, dec.cols)):
            shapes.append((dec.rows, dec.cols))
    recs += [r for r in dec.finish() if r["type"] == "packet"]
    assert shapes == [(8, 8), (4, 8)]
    assert [bytes.fromhex(r["payload_hex"]) for r in recs] == p1 + p2
    assert [r.get("version", 1) for r in recs] == [1, 2, 2]
    assert dec.counters["acquisitions"] == 2 and dec.counters["packets_bad"] == 0
    assert dec.counters["shape_mismatches"] == dec.counters["shape_retries"] == 0


def test_iscd_replay_with_a_config_without_transmitter(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``iscd replay LEFT RIGHT --config rx.toml`` (cameras only) of a rendered 4x8 PWM-16 v2
    recording at 40 m (two 600-byte packets, 556 frame pairs): both payloads delivered; the
    stats say one acquisition and no shape mismatch."""
    rng = np.random.default_rng(8)
    v2 = AirInterfaceV2(levels=16, rows=4, cols=8, fec="rs255_223", payload_len=600)
    payloads = [rng.integers(0, 256, 600, dtype=np.uint8).tobytes() for _ in range(2)]
    lv = np.concatenate([v2.packets(payloads), np.ones((50, 32), np.uint8)])
    sc = _scene(4, 8, 16, 40.0, lv, 6)
    n = lv.shape[0] * 2
    paths = [tmp_path / "left.iscr", tmp_path / "right.iscr"]
    writers = [IscrWriter(p, width=W, height=H, camera=c, fps=1000.0, exposure_s=1e-3)
               for p, c in zip(paths, ("left", "right"))]
    L, R = np.empty((H, W), np.uint8), np.empty((H, W), np.uint8)
    for k in range(n):
        sc.render_pair_into(k, L, R)
        writers[0].append(k, k * 1_000_000, L)
        writers[1].append(k, k * 1_000_000, R)
    for w in writers:
        w.close()
    (tmp_path / "rx.toml").write_text(RX_TOML)
    out = tmp_path / "out.jsonl"
    rc, _, err = cli(capsys, "replay", str(paths[0]), str(paths[1]), "--config", str(tmp_path / "rx.toml"),
                     "--out", str(out))
    assert rc == 0, err
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    pk = [r for r in recs if r["type"] == "packet"]
    assert [bytes.fromhex(r["payload_hex"]) for r in pk] == payloads and all(r["version"] == 2 for r in pk)
    stats = [r for r in recs if r["type"] == "stats"][-1]
    assert stats["acquisitions"] == 1 and stats["shape_mismatches"] == 0
