"""A packet that fails its CRC says why (issue 12: "too close, both cameras saturated"),
from the receiver's own channel estimates, never from the truth."""

from __future__ import annotations

import numpy as np

from iscd.decode.comms.channel import ChannelModel
from iscd.decode.comms.demod import SEPARATION_MIN, failure_reason, level_separation


def _model(mu_per_cam: list[list[float]], sd: float = 1.0) -> ChannelModel:
    mu = np.array(mu_per_cam, dtype=np.float64)[:, None, :]  # (C, 1, M)
    return ChannelModel(mu=mu, var=np.full_like(mu, sd * sd), kind="t")


def test_separation_is_in_noise_rms_units() -> None:
    m = _model([[0, 10, 30, 60]], sd=2.0)
    np.testing.assert_allclose(level_separation(m)[0, 0], [5.0, 10.0, 15.0])


def test_saturated_in_every_camera() -> None:
    clipped = [10, 60, 110, 160, 200, 250, 254, 255]  # the top levels clip
    m = _model([clipped, clipped])
    r = failure_reason([m], np.full(600, 2.0))
    assert r.startswith("saturated: levels 6-8")


def test_one_camera_still_apart_is_not_saturation() -> None:
    # HDR: the f/8 camera keeps the upper levels apart, so saturation is not the reason
    m = _model([[10, 60, 110, 160, 200, 250, 254, 255], [5, 30, 55, 80, 105, 130, 155, 180]])
    r = failure_reason([m], np.r_[np.full(590, 20.0), np.full(10, 1.0)])
    assert r.startswith("few symbol errors: 10 of 600")


def test_low_light_and_weak_decisions() -> None:
    dim = [10, 12, 14, 40, 80, 120, 160, 200]
    assert failure_reason([_model([dim, dim])], np.full(100, 20.0)).startswith("low light")
    apart = [0, 20, 40, 60, 80, 100, 120, 140]
    assert failure_reason([_model([apart])], np.r_[np.full(90, 20.0), np.full(10, 1.0)]).startswith("weak decisions")


def test_the_worst_stretch_counts() -> None:
    good = _model([[0, 20, 40, 60, 80, 100, 120, 140]] * 2)
    late = _model([[0, 20, 40, 60, 80, 100, 140, 140 + 0.5 * SEPARATION_MIN]] * 2)
    assert failure_reason([good], np.full(10, 20.0)).startswith("few symbol errors")
    assert failure_reason([good, late], np.full(10, 20.0)).startswith("saturated: levels 7-8")


def test_a_saturated_close_led_says_so_in_its_packet_record() -> None:
    """One very bright LED at 8 m: both apertures clip; with the luminance window matched to
    the spot (``one_led_window_scale = 1``, the receiver before session 30) the packet fails
    and its record says "saturated"; the same LED at 30 m decodes (no reason in a good
    packet). With the default window, 1.5x as wide, the 8 m packet is delivered: the level
    lives in the clipped spot's wings, which that window reaches."""
    from iscd.core.airinterface import AirInterface
    from iscd.core.config import default_config
    from iscd.eval.sweeps import ReceiverMode, _decoder_cfg, frames_for_packets
    from iscd.decode.stream import StreamDecoder
    from iscd.sim.presets import override, single_led
    from iscd.sim.scene import Scene

    seen = {}
    # name: (distance m, one LED's window scale; None = the default)
    runs = {"8 m": (8.0, 1.0), "30 m": (30.0, 1.0), "8 m, default window": (8.0, None)}
    for name, (dist, scale) in runs.items():
        cfg = override(single_led(default_config(), dist, seed=3), transmitter={"radiance_dn": 3000.0})
        if scale is not None:
            cfg = cfg.with_keys("tracking", one_led_window_scale=scale)
        sc = Scene(cfg)
        n = frames_for_packets(sc, AirInterface.from_config(cfg.transmitter), 1)
        dec = StreamDecoder(_decoder_cfg(cfg, ReceiverMode("both", "both")))
        L = np.empty((32, sc.height, sc.width), np.uint8)
        R = np.empty_like(L)
        recs = []
        for s in range(0, n, 32):
            ids = np.arange(s, min(s + 32, n))
            for i, k in enumerate(ids):
                sc.render_pair_into(int(k), L[i], R[i])
            recs += dec.push(ids, ids / sc.fps, L[:ids.size], R[:ids.size])
        recs += dec.finish()
        seen[name] = [r for r in recs if r["type"] == "packet"]
    assert len(seen["8 m"]) == 1 and not seen["8 m"][0]["crc_ok"]
    assert seen["8 m"][0]["reason"].startswith("saturated")
    assert len(seen["30 m"]) == 1 and seen["30 m"][0]["crc_ok"] and "reason" not in seen["30 m"][0]
    wide = seen["8 m, default window"]
    assert len(wide) == 1 and wide[0]["crc_ok"] and "reason" not in wide[0]


def test_evenly_spaced_levels_lost_in_noise_are_low_light_not_saturation() -> None:
    """One LED at 100 m (randomized physics, seed 2115230248; the models of its failed packet):
    an f/4 camera's levels 4 DN apart, evenly, with the upper levels' shot noise the larger,
    and a dim f/8 camera. The upper levels are closest in noise RMS, but nothing clips: the
    label is low light, where it was "saturated" before the squeeze test."""
    f4 = [1.0, 5.2, 9.4, 13.7, 17.7, 22.2, 26.5, 30.3]
    f8 = [0.7, 1.6, 2.5, 3.8, 4.8, 6.0, 7.0, 8.2]
    mu = np.array([f4, f8])[:, None, :]
    sd = np.array([[0.5, 0.6, 0.6, 0.6, 0.7, 0.8, 1.4, 1.4], [0.3] * 8])[:, None, :]
    m = ChannelModel(mu=mu, var=sd ** 2, kind="t")
    assert (level_separation(m)[..., 4:] < SEPARATION_MIN).any(axis=-1).all()  # the old rule's case
    assert failure_reason([m], np.full(600, 3.0)).startswith("low light")
    # the f/4 camera's top squeezed by clipping: saturated where both cameras clip, low
    # light where the other one is only dim
    f4c = [1.0, 5.2, 9.4, 13.7, 17.7, 19.0, 19.8, 20.2]
    both = ChannelModel(mu=np.array([f4c, f4c])[:, None, :], var=sd[[0, 0]] ** 2, kind="t")
    assert failure_reason([both], np.full(600, 3.0)).startswith("saturated: levels 5-8")
    one = ChannelModel(mu=np.array([f4c, f8])[:, None, :], var=sd ** 2, kind="t")
    assert failure_reason([one], np.full(600, 3.0)).startswith("low light")
