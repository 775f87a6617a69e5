"""Issue 3's "must show" communication claims, on simulated frames decoded by the real
receiver (detection, tracking, timing, channel estimation: no truth given to it).

Fixed seeds (the same per-point seeds as ``iscd eval --seed 1``), random LED clock phase
per point, >= 2 whole packets a point. A target that is not met is kept as the target and
marked ``xfail(strict=True)`` with the measured value, so fixing the receiver turns it into
a failure that asks for the mark to be removed.
"""

from __future__ import annotations

from functools import lru_cache

import pytest

from fakes import xfail_where
from iscd.core.config import Config, default_config
from iscd.eval.suites import (APPROACH_SPEED_MPS, APPROACH_VIBRATION_PX, CH3_MODES, COMMS_DISTANCES_M,
                              chapter3_cfg, chapter4_cfg, ch4_modes, point_seed)
from iscd.eval.sweeps import CommsResult, ReceiverMode, run_comms

DIVERSITY = ReceiverMode("diversity", "both")  # the project's default receiver
MATCHED_WINDOW = {"one_led_window_scale": 1.0, "growth_from_block": False, "stereo_hold": False,
                  "registered_subpixel": False}
"""One LED's luminance window matched to its spot, as before session 30, scaled by the
growth measured from each block's starting positions, as before session 33, its centres
not held to the stereo disparity, as before session 34, and its background read at whole
pixels only, as before session 36: the scenes of the tests that name it
were found with that following and window, and the defaults (1.5x; the growth from the last
block's median disparity; the stereo hold) move them off the failure each test is about (they
decode them without the attempt under test, or lose other symbols)."""

@lru_cache(maxsize=None)
def _one_led(distance_m: float, levels: int, packets: int) -> CommsResult:
    cfg = chapter3_cfg(default_config(), distance_m, levels, point_seed(1, "comms", distance_m, levels))
    (res,) = run_comms(cfg, [DIVERSITY], packets)
    print(f"one LED {levels}-level {distance_m:g} m: found {res.found}/{res.packets_sent}, "
          f"SER {res.ser:.3g} over {res.symbols} symbols, BER {res.ber:.3g}, goodput {res.goodput_kbps:.3f} kbps")
    return res


def _check_delivery(res: CommsResult) -> None:
    assert res.found == res.packets_sent, f"found {res.found} of {res.packets_sent} packets"
    assert res.undetected == 0 and res.spurious_crc_ok == 0  # every CRC-valid payload is the sent one


# ----------------------------------------------------------------------------- one LED, fig. 3.8

@pytest.mark.parametrize("distance_m", [20.0, 40.0, 55.0, 60.0])
def test_one_led_pwm8_matches_fig_3_8(distance_m: float) -> None:
    """PWM-8, b = 0.6 m, 100 ppm drift: SER = 0 from 20 to 55 m, <= 6e-3 at 60 m (2 packets)."""
    res = _one_led(distance_m, 8, 2)
    _check_delivery(res)
    assert res.symbols == 2 * 600
    if distance_m <= 55.0:
        assert res.ser == 0.0
    else:
        assert res.ser <= 6e-3


@pytest.mark.parametrize("distance_m", [20.0, 60.0])
def test_one_led_ook_error_free(distance_m: float) -> None:
    res = _one_led(distance_m, 2, 2)
    _check_delivery(res)
    assert res.ser == 0.0 and res.exact == res.packets_sent


SLOW_FAILS: dict[float, str] = {}


@pytest.mark.slow
@pytest.mark.parametrize("distance_m", xfail_where(list(COMMS_DISTANCES_M), SLOW_FAILS))
@pytest.mark.parametrize("levels", [8, 2])
def test_one_led_full_sweep(distance_m: float, levels: int) -> None:
    """The whole fig. 3.8 sweep, 20-60 m every 5 m, 10 packets a point (6000 symbols)."""
    res = _one_led(distance_m, levels, 10)
    _check_delivery(res)
    if distance_m <= 55.0 or levels == 2:
        assert res.ser == 0.0
    else:
        assert res.ser <= 6e-3


# ----------------------------------------------------------------------------- 8x8 HDR at 50 m

@lru_cache(maxsize=None)
def _hdr_50m(levels: int) -> dict[str, CommsResult]:
    """8x8 at 50 m, b = 0.25 m, left f/4, right f/8: left alone, right alone and HDR on the
    same frames (2 packets)."""
    cfg = chapter4_cfg(default_config(), 50.0, levels, 8.0, point_seed(1, "hdr", 50.0, levels, 8.0))
    modes = ch4_modes(8.0, quick=True)
    res = run_comms(cfg, modes, 2)
    out = {m.cameras: r for m, r in zip(modes, res)}
    for k, r in out.items():
        print(f"PWM-{levels} {r.mode.name}: SER {r.ser:.3g} ({r.symbol_errors}/{r.symbols}), found "
              f"{r.found}/{r.packets_sent}, CRC ok {r.crc_ok}, margin p01 {r.margin_p01}")
    return out


@pytest.mark.parametrize("levels, limit", [(8, 1e-3), (16, 1e-2)])
def test_hdr_8x8_at_50m_ser(levels: int, limit: float) -> None:
    """PWM-8 SER <= 1e-3 and PWM-16 SER <= 1e-2 with HDR f/4 + f/8 (the dissertation reached
    about 1e-1 for PWM-16)."""
    hdr = _hdr_50m(levels)["both"]
    assert hdr.symbols == 2 * 600 * 64
    assert hdr.ser <= limit


@pytest.mark.parametrize("levels", [8, 16])
def test_hdr_better_than_either_camera_alone(levels: int) -> None:
    """HDR's SER is no worse than each camera's alone, and it is strictly better: a lower SER
    or, where both are error-free, a larger worst-1 % decision margin (the receiver's own
    reliability measure)."""
    r = _hdr_50m(levels)
    hdr = r["both"]
    for cam in ("left", "right"):
        single = r[cam]
        assert hdr.ser <= single.ser, f"HDR SER {hdr.ser} > {cam} alone {single.ser}"
        if hdr.ser == single.ser:
            assert min(hdr.margin_p01) > max(single.margin_p01), (cam, hdr.margin_p01, single.margin_p01)
    if levels == 16:  # at PWM-16 the f/4 camera alone makes errors that HDR does not
        assert hdr.ser < r["left"].ser


@pytest.mark.parametrize("levels", [8, 16])
def test_hdr_every_packet_found_and_every_valid_payload_exact(levels: int) -> None:
    r = _hdr_50m(levels)
    _check_delivery(r["both"])
    assert r["both"].exact == r["both"].packets_sent
    for res in r.values():
        assert res.undetected == 0 and res.spurious_crc_ok == 0
        assert res.crc_ok == res.exact


# ----------------------------------------------------------------------------- a car approaching

@pytest.mark.parametrize("seed", [1, 2])
def test_car_approaching_at_40kmh_with_vibration_still_decodes(seed: int) -> None:
    """8x8, PWM-8, HDR f/4 + f/8, closing at 40 km/h from 50 m (to 21 m over the two
    packets: the LEDs brighten 5.7x, the pitch grows 4.2 -> 10 px), 0.3 px RMS rig
    vibration: every packet found, CRC-valid and bit-exact, no symbol error."""
    cfg = chapter4_cfg(default_config(), 50.0, 8, 8.0, point_seed(seed, "approach"),
                       speed_mps=APPROACH_SPEED_MPS, vibration_px=APPROACH_VIBRATION_PX)
    (res,) = run_comms(cfg, [ReceiverMode("HDR f/4+f/8", "both")], 2)
    print(f"approach: found {res.found}/{res.packets_sent}, exact {res.exact}, SER {res.ser:.3g}")
    _check_delivery(res)
    assert res.exact == res.packets_sent
    assert res.ser == 0.0


@pytest.mark.parametrize("model", ["smooth", pytest.param("bumps", marks=pytest.mark.slow),
                                   pytest.param("engine", marks=pytest.mark.slow)])
@pytest.mark.parametrize("vibration_px", [0.3, pytest.param(0.5, marks=pytest.mark.slow)])
@pytest.mark.parametrize("seed", [3, pytest.param(4, marks=pytest.mark.slow), pytest.param(5, marks=pytest.mark.slow)])
def test_one_led_hdr_approaching_at_40kmh_decodes_every_packet(seed: int, vibration_px: float, model: str) -> None:
    """One LED, PWM-8, the HDR pair f/4 + f/8 (b = 0.6 m), closing at 40 km/h from 50 m to
    25 m, rig vibration 0.3 (and, slow, 0.5) px RMS, smooth (and, slow, road bumps and engine
    shake), the project's physics otherwise (issue 12): every
    packet found, CRC-valid and bit-exact, SER 0. With f/4 + f/4 the top two levels, which a
    clipping f/4 core compresses as the LED closes in, cost every packet of such scenes
    (docs/eval.md); these seeds were not among the ones looked at."""
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next(c for c in MOTION_CASES if c.key == "1led-hdr-40kmh-0.3px")
    cfg, _ = motion_cfg(default_config(), case, point_seed(seed, "1led-hdr-test"),
                        scene={"vibration_px": vibration_px, "vibration_model": model})
    assert cfg.camera.f_number_right == 8.0 and cfg.scene.min_distance_m == 25.0
    (res,) = run_comms(cfg, [ReceiverMode("HDR f/4+f/8", "both")], 2)
    print(f"one LED HDR approach: found {res.found}/{res.packets_sent}, exact {res.exact}, SER {res.ser:.3g}")
    _check_delivery(res)
    assert res.exact == res.packets_sent
    assert res.ser == 0.0


def test_modes_decode_on_the_same_frames() -> None:
    """The sweep's decoders are independent: a mode's result does not depend on the other
    modes run beside it (same frames, same seed)."""
    cfg = chapter3_cfg(default_config(), 40.0, 8, point_seed(1, "comms", 40.0, 8))
    both = run_comms(cfg, list(CH3_MODES), 2)
    assert [r.mode for r in both] == list(CH3_MODES)
    alone = _one_led(40.0, 8, 2)
    div = both[1]
    assert (div.found, div.symbol_errors, div.exact) == (alone.found, alone.symbol_errors, alone.exact)


def test_a_road_bump_caught_between_two_fits_does_not_restart_following() -> None:
    """A regression scene (issue 12; randomized physics, seed 2028979640 of the motion case
    1led-hdr-40kmh-0.5px under road bumps, found in an unseen seed set): a bump swung the spot
    2-3 px and back between two grid fits, whose motion carried on put the LED 5 px from where
    it was followed; the decoder restarted following there and lost the LED for a block
    (4 symbol errors, one packet not delivered). Now the fits' swing widens what counts as
    lost: both packets CRC-valid, and the followed centres stay within 0.5 px of the truth on
    every lit frame (before: 2.7-9.3 px off for a block)."""
    import numpy as np

    from iscd.decode.stream import StreamDecoder
    from iscd.eval.sweeps import _decoder_cfg, frames_for_packets
    from iscd.eval.suites import MOTION_CASES, motion_cfg
    from iscd.eval.oracle import true_centres
    from iscd.core.airinterface_v2 import from_config as air_from_config
    from iscd.sim.scene import Scene

    case = next(c for c in MOTION_CASES if c.key == "1led-hdr-40kmh-0.5px")
    cfg, note = motion_cfg(default_config(), case, 2028979640, scene={"vibration_model": "bumps", "background_motion": "whole"}, randomize=True)
    assert note.startswith("randomized")
    scene = Scene(cfg)
    n = frames_for_packets(scene, air_from_config(cfg.transmitter), 2)
    truth = scene.truth(np.arange(n))
    dec = StreamDecoder(_decoder_cfg(cfg, ReceiverMode("diversity", "both")))
    H, W = scene.height, scene.width
    L, R = np.empty((16, H, W), np.uint8), np.empty((16, H, W), np.uint8)
    worst = 0.0
    for a in range(0, n, 16):
        ids = np.arange(a, min(n, a + 16))
        for i, k in enumerate(ids):
            scene.render_pair_into(int(k), L[i], R[i])
        dec.push(ids, ids / scene.fps, L[:ids.size], R[:ids.size])
        if dec.last_centres is not None and ids[0] >= 64:  # acquired
            lit = truth.on_fraction[ids, 0] > 0.3
            for c in (0, 1):
                err = np.hypot(*(dec.last_centres[c][:, 0] - true_centres(truth, c)[ids].reshape(ids.size, -1)[:, :2]).T)
                worst = max(worst, float(err[lit].max(initial=0.0)))
    dec.finish()
    dec.close()
    print(f"worst followed-centre error on lit frames {worst:.2f} px; packets {dec.counters}")
    assert worst < 0.5
    assert dec.counters["packets_ok"] == 2 and dec.counters["packets_bad"] == 0


def test_a_channel_derailed_mid_packet_is_tried_again_with_a_longer_window() -> None:
    """A regression scene (issue 12; randomized physics, seed 895488494 of the motion case
    1led-hdr-40kmh-0.3px, found in an unseen seed set, failing under every vibration model):
    the second packet, closing 35 -> 25 m, had 90 wrong symbols from its middle on with the
    tracked channel (96 symbols), and one channel for the whole packet could not follow the
    light growing; the true channel had none. A failed CRC now also tries a window twice as
    long (iscd.decode.comms.demod.WIDER_WINDOW), and the CRC decides: both packets bit-exact."""
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next(c for c in MOTION_CASES if c.key == "1led-hdr-40kmh-0.3px")
    cfg, note = motion_cfg(default_config(), case, 895488494, scene={"vibration_model": "smooth", "background_motion": "whole"}, randomize=True)
    assert note.startswith("randomized")
    (res,) = run_comms(cfg, [ReceiverMode("diversity", "both")], 2, block=16)
    print(f"found {res.found}/{res.packets_sent}, exact {res.exact}, SER {res.ser:.3g}")
    _check_delivery(res)
    assert res.exact == res.packets_sent == 2
    assert res.ser == 0.0


def test_one_leds_background_is_taken_at_the_images_own_shift() -> None:
    """The decoder's registered background (issue 12, iscd.decode.tracking.registered_background)
    on a rendered scene: one LED at 40 m under 0.5 px road bumps over the default texture. The
    shifts it finds in each frame, measured against the map it started at the first followed
    block, are the simulator's whole-pixel vibration (truth) in >= 95 % of the frames, and
    the image moved by a pixel or more in some of them."""
    import numpy as np

    from iscd.decode.stream import StreamDecoder
    from iscd.sim.presets import override, single_led
    from iscd.sim.scene import Scene

    cfg = override(single_led(default_config(), 40.0),
                   scene={"vibration_model": "bumps", "vibration_px": 0.5, "bump_rate_hz": 4.0})
    scene = Scene(cfg)
    n = 1200
    dec = StreamDecoder(cfg)
    H, W = scene.height, scene.width
    L, R = np.empty((16, H, W), np.uint8), np.empty((16, H, W), np.uint8)
    found, frames = [[], []], []
    for a in range(0, n, 16):
        ids = np.arange(a, min(n, a + 16))
        for i, k in enumerate(ids):
            scene.render_pair_into(int(k), L[i], R[i])
        dec.push(ids, ids / scene.fps, L[:ids.size], R[:ids.size])
        sh = dec.image_shifts
        if sh[0] is not None and (not frames or frames[-1] < ids[-1]):
            # this push's luminance: the block's frames (the first, after acquisition, holds
            # the frames acquisition read too)
            k = sh[0].shape[0]
            frames.extend(range(int(ids[-1]) + 1 - k, int(ids[-1]) + 1))
            for c in (0, 1):
                found[c].append(sh[c].copy())
    dec.close()
    assert len(frames) > 600, "the LED was not followed"
    vib = np.rint(scene.frame_state(np.array(frames))["vib"]).astype(np.int64)
    moved = (np.abs(vib - vib[0]) >= 1).any(axis=1).mean()
    for c in (0, 1):
        got = np.concatenate(found[c])
        agree = ((got - got[0]) == (vib - vib[0])).all(axis=1)
        print(f"camera {c}: shift agrees with the truth in {agree.mean():.3f} of {agree.size} frames, moved {moved:.2f}")
        assert agree[64:].mean() >= 0.95
    assert moved > 0.05


@pytest.mark.parametrize("key, seed, model, short", [
    ("1led-hdr-100kmh-0.5px", 1410139778, "smooth", 64),
    pytest.param("1led-hdr-100kmh-0.5px", 1153262362, "smooth", 128, marks=pytest.mark.slow)])
def test_a_header_during_failed_first_attempts_is_decoded_once_the_led_is_found(key: str, seed: int, model: str,
                                                                               short: int) -> None:
    """Regression scenes (issue 12; randomized physics, each found in a seed set nobody had
    looked at): a far or outshone LED found only by a later detection attempt (each looks at
    64 frames), while the first packet's header came during an earlier one. Seed 1410139778
    (100 km/h, 100 m): found by the second attempt, header at frames 2-28; 1153262362 (set
    44001, 100 km/h) and 1375409207 (set 24001, 40 km/h, distractors outranking it under
    engine vibration): found by the third. The decoder keeps the last acquire_lookback_frames
    (default 256: four attempts) while it looks and decodes from the first of them: both
    packets. Keeping ``short`` frames (64: the finding attempt's own, before session 17; 128:
    sessions 17-18) loses the first. (1375409207 was a third scene; the receiver at the end of
    session 34, bf05507, finds that LED at its first attempt, so it no longer tests the frames
    kept.)"""
    import numpy as np

    from iscd.core.airinterface_v2 import from_config as air_from_config
    from dataclasses import replace

    from iscd.core.config import section
    from iscd.decode.stream import PipelineSettings, StreamDecoder
    from iscd.eval.suites import MOTION_CASES, motion_cfg
    from iscd.eval.sweeps import _decoder_cfg, frames_for_packets
    from iscd.sim.scene import Scene

    case = next(c for c in MOTION_CASES if c.key == key)
    cfg, note = motion_cfg(default_config(), case, seed, scene={"vibration_model": model, "background_motion": "whole"}, randomize=True)
    assert note.startswith("randomized")
    scene = Scene(cfg)
    n = frames_for_packets(scene, air_from_config(cfg.transmitter), 2)
    H, W = scene.height, scene.width
    L, R = np.empty((n, H, W), np.uint8), np.empty((n, H, W), np.uint8)
    for k in range(n):
        scene.render_pair_into(k, L[k], R[k])
    dcfg = _decoder_cfg(cfg, ReceiverMode("diversity", "both"))
    default = section(dcfg, PipelineSettings).acquire_lookback_frames
    assert default == 256
    got = {}
    for keep in (default, short):
        dec = StreamDecoder(dcfg, settings=replace(section(dcfg, PipelineSettings), acquire_lookback_frames=keep))
        for a in range(0, n, 16):
            ids = np.arange(a, min(n, a + 16))
            dec.push(ids, ids / scene.fps, L[a:a + ids.size], R[a:a + ids.size])
        dec.finish()
        dec.close()
        got[keep] = (dec.counters["packets_ok"], dec.counters["packets_bad"], dec.counters["acquisitions"])
    print(f"packets ok / bad / acquisitions: keeping {default} frames {got[default]}, {short} {got[short]}")
    assert got[default][0] == 2 and got[default][1] == 0
    assert got[short][0] == 1  # the scene still needs the later attempt (else this tests nothing)


def test_an_arrays_first_packet_finds_its_clock_across_the_exposure_gap() -> None:
    """A regression scene (issue 12; randomized physics, seed 2098650435 of the motion case
    8x8-40kmh-0.3px under smooth vibration, found in an unseen seed set): exposure 0.635
    frames, the LED clock 144 ppm slow, its first packet's symbol boundaries at the end of
    the dark gap between exposures; the header left the clock at the gap's start and the
    first packet's clock updates, pivoting on a wrong centre, stayed at 7 ppm (2 641 wrong
    symbols with the true positions). Now each update searches both ends of the decided span
    (iscd.decode.comms.demod, timing.refine_clock(search_ends=True)): both packets bit-exact."""
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next(c for c in MOTION_CASES if c.key == "8x8-40kmh-0.3px")
    cfg, note = motion_cfg(default_config(), case, 2098650435, scene={"vibration_model": "smooth", "background_motion": "whole"}, randomize=True)
    assert note.startswith("randomized")
    e = cfg.camera.exposure_s * cfg.camera.fps
    assert e < 0.9, "the case this test is for: an exposure gap"
    (res,) = run_comms(cfg, [ReceiverMode("HDR f/4+f/8", "both")], 2, block=16)
    print(f"found {res.found}/{res.packets_sent}, exact {res.exact}, SER {res.ser:.3g}")
    _check_delivery(res)
    assert res.exact == res.packets_sent == 2
    assert res.ser == 0.0


def _with_and_without(flag: str, key: str, seed: int, vibration: str, mode: ReceiverMode,
                      monkeypatch: pytest.MonkeyPatch, **tracking: object) -> tuple[CommsResult, CommsResult]:
    """A randomized motion scene (2 packets) decoded as it is and with the receiver's
    ``iscd.decode.comms.demod.<flag>`` attempt off (``module.FLAG``: that module's in
    ``iscd.decode.comms``). For an attempt before the last resort, CRC-aided list decoding
    (``listdecode.LIST_DECODE``) is off in both runs, so that the attempt's own effect shows;
    so is the smoothed-channel attempt that comes after all of them (``packets.SMOOTH_RETRY``,
    session 35: it delivers 149046880's second packet without the symbol-by-symbol attempt).
    ``tracking``: ``[tracking]`` keys to decode with (the receiver as it was when a scene
    was found, where a later change of the following moved it off the failure)."""
    import importlib

    from iscd.decode.comms import listdecode, packets

    mod_name, _, flag = flag.rpartition(".")
    demod = importlib.import_module(f"iscd.decode.comms.{mod_name or 'demod'}")
    if demod is not listdecode:
        monkeypatch.setattr(listdecode, "LIST_DECODE", False)
    monkeypatch.setattr(packets, "SMOOTH_RETRY", False)
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next(c for c in MOTION_CASES if c.key == key)
    cfg, note = motion_cfg(default_config(), case, seed, scene={"vibration_model": vibration, "background_motion": "whole"}, randomize=True)
    assert note.startswith("randomized")
    if tracking:
        cfg = cfg.with_keys("tracking", **tracking)
    return _decode_twice(cfg, mode, demod, flag, False, monkeypatch)


def _decode_twice(cfg: Config, mode: ReceiverMode, module: object, name: str, value: object,
                  monkeypatch: pytest.MonkeyPatch) -> tuple[CommsResult, CommsResult]:
    """Two packets of ``cfg`` decoded as they are (each delivery checked against the truth),
    then with ``module.name`` set to ``value``."""
    (res,) = run_comms(cfg, [mode], 2, block=16)
    print(f"as is: found {res.found}/{res.packets_sent}, exact {res.exact}, errors {res.symbol_errors}")
    _check_delivery(res)
    monkeypatch.setattr(module, name, value)
    (patched,) = run_comms(cfg, [mode], 2, block=16)
    print(f"{name} = {value!r}: found {patched.found}/{patched.packets_sent}, exact {patched.exact}, "
          f"errors {patched.symbol_errors}")
    return res, patched


@pytest.mark.parametrize("key, seed, exact", [("1led-hdr-40kmh-0.5px", 1711133418, 2),
                                              pytest.param("1led-hdr-100kmh-0.3px", 1909465834, 1,
                                                           marks=pytest.mark.slow)])
def test_one_leds_failed_packet_is_tried_with_an_arrays_tracking_step(key: str, seed: int, exact: int,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Two randomized one-LED approaches under smooth vibration (seeds of sets 35001 and
    34001, in the failures the ten sets of session 18 left): a packet the one-LED tracking
    step (64 symbols) and its fallbacks lose by one symbol is delivered by the last attempt,
    the array's 16-symbol step (iscd.decode.comms.demod.SHORT_STEP_RETRY). Without that
    attempt one packet fewer is exact; the first packet of 1909465834 (100 -> 64 m) is lost
    either way (the oracle's genie luminance with the true channel loses it too).

    Decoded with the LED followed in the image (``stabilized_following = false``): followed in
    the background's frame (session 26) 1711133418's packets are bit-exact without the attempt.
    And without the symbol-by-symbol attempt after it (``SEQUENTIAL_RETRY``): since that
    attempt's changes of session 27 (survivors, their own decisions listed) it delivers
    1711133418's packet too when the short step is off."""
    from iscd.decode.comms import demod

    monkeypatch.setattr(demod, "SEQUENTIAL_RETRY", False)
    res, without = _with_and_without("SHORT_STEP_RETRY", key, seed, "smooth", DIVERSITY, monkeypatch,
                                      stabilized_following=False, **MATCHED_WINDOW)
    assert res.exact == exact
    assert without.found == 2 and without.exact == exact - 1
    assert without.symbol_errors > res.symbol_errors


@pytest.mark.parametrize("seed", [149046880, pytest.param(1726752588, marks=pytest.mark.slow)])
def test_a_packet_whose_levels_squeeze_is_tracked_symbol_by_symbol(seed: int,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Two scenes of set 57001 (one LED at 100 km/h, 0.3 px smooth vibration, randomized
    physics; issue 12, session 25): in the second packet (64 -> 27 m) one camera's upper
    levels squeeze within a few dozen symbols as the spot's core clips, the stepwise
    tracking pass decides a level as its neighbour, the level drops out of its fits and the
    rest of the packet slips (dozens of wrong symbols in every other attempt, the anchored
    and list-decoded ones too). Tracked symbol by symbol with Kalman-filtered centroids
    (demod.SEQUENTIAL_RETRY) both packets are bit-exact; without that attempt the second is
    lost."""
    from iscd.decode.comms.sequential import sequential_levels

    res, without = _with_and_without("SEQUENTIAL_RETRY", "1led-100kmh-0.3px", seed, "smooth", DIVERSITY,
                                     monkeypatch)
    assert res.exact == 2 and res.symbol_errors == 0
    assert without.found == 2 and without.exact == 1 and without.symbol_errors > 0
    # the receiver calls the kernel with the argument types warm_up compiles (no compile mid-stream)
    assert len(sequential_levels.signatures) == 1


def test_a_squeezed_packet_a_few_symbols_off_is_list_decoded_from_its_sequential_attempt(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Seed 2145744630 (set 57001, one LED at 100 km/h, 0.3 px smooth vibration): the second
    packet's symbol-by-symbol attempt misses by two symbols at its very end (levels 2-3 DN
    apart at 27 m), every other attempt by ~100. Its decisions ride along with the failed
    packet (PacketResult.sequential) and are list-decoded last: both packets bit-exact;
    without that attempt the second is lost.

    Decoded with the LED followed in the image (``stabilized_following = false``), as when
    the scene was found: followed in the background's frame (session 26; the lit frames'
    centres as close to the truth, 0.02-0.05 px RMS, the dark frames' within 0.6 px either
    way) the second packet was reported with 108 wrong symbols and lost -- a packet at the
    edge of what this channel allows, on which small changes of the luminance decide --
    until the symbol-by-symbol attempt kept several decision sequences (session 27,
    ``test_a_squeezed_packet_is_decoded_by_the_sequential_attempts_survivors``)."""
    from iscd.decode.comms import demod
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next(c for c in MOTION_CASES if c.key == "1led-100kmh-0.3px")
    cfg, _ = motion_cfg(default_config(), case, 2145744630, scene={"vibration_model": "smooth", "background_motion": "whole"}, randomize=True)
    # (the background read at whole pixels only, as before session 36: with the residual
    # shift fitted this packet is delivered without the sequential attempt)
    cfg = cfg.with_keys("tracking", stabilized_following=False, registered_subpixel=False)
    (res,) = run_comms(cfg, [DIVERSITY], 2, block=16)
    _check_delivery(res)
    monkeypatch.setattr(demod, "SEQUENTIAL_RETRY", False)
    (without,) = run_comms(cfg, [DIVERSITY], 2, block=16)
    print(f"with: exact {res.exact}, errors {res.symbol_errors}; without: exact {without.exact}, "
          f"errors {without.symbol_errors}")
    assert res.exact == 2 and res.symbol_errors == 0
    assert without.found == 2 and without.exact == 1 and without.symbol_errors > 10


def _as_is_and_patched(seed: int, key: str, vibration: str, module: object, name: str, value: object,
                       monkeypatch: pytest.MonkeyPatch, **tracking: object) -> tuple[CommsResult, CommsResult]:
    """A randomized motion scene (2 packets) decoded as it is, then with ``module.name`` set
    to ``value`` (list decoding on in both); ``tracking`` as for :func:`_with_and_without`."""
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next(c for c in MOTION_CASES if c.key == key)
    cfg, _ = motion_cfg(default_config(), case, seed, scene={"vibration_model": vibration, "background_motion": "whole"}, randomize=True)
    if tracking:
        cfg = cfg.with_keys("tracking", **tracking)
    return _decode_twice(cfg, DIVERSITY, module, name, value, monkeypatch)


def test_a_squeezed_packet_is_decoded_by_the_sequential_attempts_survivors(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seed 2145744630 (set 57001, one LED at 100 km/h, 0.3 px smooth vibration) with the
    receiver as it is (the LED followed in the background's frame): the second packet's
    upper levels squeeze to 2-3 DN apart near 27 m. With one decision sequence in the
    symbol-by-symbol attempt (``sequential.BEAM = 1``, the filter of session 25) a noisy
    decision slips the centroids and the packet is lost (108 wrong symbols reported); with
    ``BEAM`` survivors (per-survivor processing, session 27) that attempt passes its CRC:
    both packets bit-exact. (Both without the fixed-clock attempt of session 33, which comes
    later and delivers the packet with one sequence too.)"""
    from iscd.decode.comms import demod, packets

    monkeypatch.setattr(packets, "FIXED_CLOCK_RETRY", False)
    res, one = _as_is_and_patched(2145744630, "1led-100kmh-0.3px", "smooth", demod, "BEAM", 1, monkeypatch,
                                  **MATCHED_WINDOW)
    assert res.exact == 2 and res.symbol_errors == 0
    assert one.found == 2 and one.exact == 1 and one.symbol_errors > 10


def test_a_squeezed_packet_is_list_decoded_from_the_survivors_own_decisions(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seed 282473233 (set 64001, never tuned on when it was found; one LED at 100 km/h,
    0.3 px smooth vibration): the second packet (64 -> 27 m) squeezes levels 6 and 7 to
    2-3 DN apart. The sequential attempt's survivors decide it with one wrong symbol; its
    final pass (the channel fitted per 48 symbols on those decisions) changes two right ones
    and keeps the wrong one: 3 wrong, beyond its list. Listed from the survivors' own
    decisions instead (``demod._survivors_own``: the final pass's reliabilities, its level
    as the alternative where the two differ), one flip passes the CRC: both packets
    bit-exact; listed from the final pass's, the second is lost."""
    from iscd.decode.comms import demod

    res, final = _as_is_and_patched(282473233, "1led-100kmh-0.3px", "smooth", demod, "_survivors_own",
                                    lambda *a: None, monkeypatch, **MATCHED_WINDOW)
    assert res.exact == 2 and res.symbol_errors == 0
    assert final.found == 2 and final.exact == 1 and final.symbol_errors > 10


@pytest.mark.slow
def test_the_sequential_attempt_leaves_the_reported_attempt_as_it_was() -> None:
    """Seed 745685058 (set 58001, one LED at 40 km/h, 0.3 px road bumps): both packets fail
    their first attempts by a few symbols and are delivered by the later ones (anchored,
    list decoding). When the symbol-by-symbol attempt's failure replaced the reported
    attempt by mean margin, the anchored attempt started from its clock and both packets
    were lost; it now leaves the report as it was: both bit-exact."""
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next(c for c in MOTION_CASES if c.key == "1led-40kmh-0.3px")
    cfg, _ = motion_cfg(default_config(), case, 745685058, scene={"vibration_model": "bumps", "background_motion": "whole"}, randomize=True)
    (res,) = run_comms(cfg, [DIVERSITY], 2, block=16)
    _check_delivery(res)
    assert res.exact == 2 and res.symbol_errors == 0


def test_a_failed_packet_is_tried_anchored_on_the_next_header(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seed 1174170399 (set 50001, one LED HDR f/4+f/8 at 100 km/h, 0.3 px bumps; issue 12):
    the first packet (100 -> 64 m) slips mid-packet -- 63 wrong symbols in its second half,
    every attempt of demodulate_packet alike, while the true channel per 96 symbols decodes
    it. Demodulated once more with the channel tracked backwards from the second packet's
    header and training (demod.ANCHOR_RETRY, held by the assembler until those frames are
    in), it is delivered bit-exact; without that attempt it is lost. (Both without the
    symbol-by-symbol attempt, which comes before it: since session 27's changes to that
    attempt it delivers this packet too.)"""
    from iscd.decode.comms import demod

    monkeypatch.setattr(demod, "SEQUENTIAL_RETRY", False)
    res, without = _with_and_without("ANCHOR_RETRY", "1led-hdr-100kmh-0.3px", 1174170399, "bumps", DIVERSITY,
                                     monkeypatch, **MATCHED_WINDOW)
    assert res.exact == 2 and res.symbol_errors == 0
    assert without.found == 2 and without.exact == 1 and without.symbol_errors > 10


def test_a_packet_a_symbol_off_is_list_decoded_under_its_crc(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seed 444861739 (set 22001, one LED HDR f/4+f/8 at 100 km/h, 0.5 px road bumps; issue
    12): the first packet (100 -> 64 m) misses by one symbol, a weak decision one level off,
    in every attempt, the anchored one too (the true channel misses it as well). CRC-aided
    list decoding (listdecode.LIST_DECODE) finds it among the runner-ups of the least
    reliable decisions: both packets bit-exact; without it the first is lost. (Both without
    the symbol-by-symbol attempt: since session 27's changes to that attempt it delivers this
    packet too.)"""
    from iscd.decode.comms import demod

    monkeypatch.setattr(demod, "SEQUENTIAL_RETRY", False)
    res, without = _with_and_without("listdecode.LIST_DECODE", "1led-hdr-100kmh-0.5px", 444861739, "bumps",
                                     DIVERSITY, monkeypatch, **MATCHED_WINDOW)
    assert res.exact == 2 and res.symbol_errors == 0
    assert without.found == 2 and without.exact == 1 and 1 <= without.symbol_errors <= 10


def test_a_packet_locked_on_a_delivered_packets_period_is_tried_with_it_free(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seed 1987386013 (set 43001, 8x8 HDR at 40 km/h, smooth vibration; issue 12): the first
    packet is delivered with its period at 179 ppm for a true 187 ppm while its own spread
    (timing.period_sigma) said 1.3 ppm; the second, its period locked at 20 ppm around that,
    loses its last 456 symbols. Retried with the period free (as a first packet; demod
    UNLOCKED_RETRY), it is delivered; without that attempt it is not."""
    res, without = _with_and_without("UNLOCKED_RETRY", "8x8-40kmh-0.3px", 1987386013, "smooth",
                                     ReceiverMode("HDR f/4+f/8", "both"), monkeypatch)
    assert res.exact == 2 and res.ser == 0.0
    assert without.found == 2 and without.exact == 1
    assert without.symbol_errors > 100


@pytest.mark.parametrize("model", ["smooth", pytest.param("bumps", marks=pytest.mark.slow),
                                   pytest.param("engine", marks=pytest.mark.slow)])
def test_an_8x8_array_approaching_on_randomized_physics_stays_below_1e3(model: str) -> None:
    """Issue 12's must-show for the array: 8x8 HDR f/4 + f/8, PWM-8, closing at 40 km/h from
    50 m to 25 m with 0.3 px of vibration, three scenes whose physics the randomizer draws
    (seed set 43001, the same seeds `iscd eval --suite motion --seed 43001 --randomize` uses;
    first run after the session's other measurements, not tuned on): SER <= 1e-3 over the
    three scenes' two packets each, and every packet found. Smooth vibration met it only
    with the retry of a locked packet with its period free (session 19: before, one scene
    at SER 5.9e-3, the three at 2.0e-3; the test above)."""
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next(c for c in MOTION_CASES if c.key == "8x8-40kmh-0.3px")
    errors = symbols = 0
    for i in range(3):
        cfg, note = motion_cfg(default_config(), case, point_seed(43001, "motion", case.key, i),
                               scene={"vibration_model": model, "background_motion": "whole"}, randomize=True)
        assert note.startswith("randomized")
        (res,) = run_comms(cfg, [ReceiverMode("HDR f/4+f/8", "both")], 2, block=16)
        print(f"scene {i}: found {res.found}/{res.packets_sent}, exact {res.exact}, SER {res.ser:.3g}")
        _check_delivery(res)
        assert res.found == res.packets_sent == 2
        errors += res.symbol_errors
        symbols += res.symbols
    assert symbols == 3 * 2 * 600 * 64
    assert errors / symbols <= 1e-3


def test_one_leds_clipped_spot_is_measured_in_a_wider_window(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seed 1116575497 (set 73001, one LED at 40 km/h from 50 m, 0.5 px smooth vibration; a
    bright LED, 752 DN effective, with a sharp PSF, 0.46 px): as the car closes in the
    spot's core clips and its level lives in the wings, which the window matched to the
    spot's half-maximum weighs little (session 30). With one LED's window 1.5x the matched
    one (``[tracking] one_led_window_scale``, the default) both packets are bit-exact; with
    the matched window (1.0, the receiver before) the first is lost (11 wrong symbols) --
    without the sub-pixel phase attempt (session 33), which delivers it there too, and is
    switched off for the matched window's run."""
    from iscd.decode.comms import pixelphase
    from iscd.core.config import section
    from iscd.decode.stream import PipelineSettings
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next(c for c in MOTION_CASES if c.key == "1led-40kmh-0.5px")
    cfg, note = motion_cfg(default_config(), case, 1116575497, scene={"vibration_model": "smooth", "background_motion": "whole"}, randomize=True)
    assert note.startswith("randomized")
    assert section(cfg, PipelineSettings).one_led_window_scale == 1.5  # the default under test
    (res,) = run_comms(cfg, [DIVERSITY], 2, block=16)
    _check_delivery(res)
    monkeypatch.setattr(pixelphase, "PHASE_RETRY", False)
    (matched,) = run_comms(cfg.with_keys("tracking", one_led_window_scale=1.0), [DIVERSITY], 2, block=16)
    print(f"1.5x: exact {res.exact}, errors {res.symbol_errors}; matched: exact {matched.exact}, "
          f"errors {matched.symbol_errors}")
    assert res.exact == 2 and res.symbol_errors == 0
    assert matched.found == 2 and matched.exact < 2 and matched.symbol_errors > 0


def test_the_one_led_window_scale_leaves_an_arrays_window_alone() -> None:
    """``one_led_window_scale`` multiplies ``window_scale`` for one LED only: an array's
    window (its neighbours 4-6 px away) is as before."""
    from iscd.decode.stream import StreamDecoder

    cfg = default_config().with_keys("tracking", window_scale=1.2, one_led_window_scale=1.5)
    dec = StreamDecoder(cfg)
    assert dec._window_scale(64) == pytest.approx(1.2)
    assert dec._window_scale(1) == pytest.approx(1.8)
