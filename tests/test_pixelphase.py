"""iscd.decode.comms.pixelphase and the packet assembler's phase attempt: a one-LED packet
that every other attempt failed is demodulated again with each level's dependence on the
followed centre's sub-pixel phase taken out of its luminance.

The synthetic recordings here are :func:`iscd.decode.comms.synth.synth_recording`'s, with a
phase term added: each camera's light moves by ``AMP_DN`` x the frame's duty x a fixed
combination of the harmonics of a centre that drifts over the pixel grid and vibrates --
what a clipped spot does to a fixed window (docs/eval.md, session 32), made exact so that
what is asserted is the plumbing and the fit, not a renderer."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.core.config import default_config
from iscd.decode.comms import packets as packets_mod
from iscd.decode.comms import pixelphase
from iscd.decode.comms.demod import known_levels
from iscd.decode.comms.packets import PacketAssembler
from iscd.decode.comms.pixelphase import phase_corrected, phase_features
from iscd.decode.comms.synth import SynthCamera, SynthRecording, synth_recording
from iscd.decode.comms.timing import SymbolClock, frame_map_range

AMP_DN = 3.0
"""The phase term's amplitude at full duty, DN (the level step is about 4 DN here)."""


def _one_led() -> tuple[object, AirInterface]:
    tx = replace(default_config().transmitter, rows=1, cols=1)
    return tx, AirInterface.from_config(tx)


def _with_phase(seed: int) -> tuple[SynthRecording, np.ndarray, np.ndarray]:
    """A two-packet one-LED recording, its luminance with the phase term, and the centres
    (2, n, 1, 2) px the term was made from."""
    _, air = _one_led()
    rec = synth_recording(air, [SynthCamera(), SynthCamera()], n_packets=2, seed=seed)
    n = rec.t_s.size
    t = np.arange(n, dtype=np.float64)
    rng = np.random.default_rng(seed)
    L = rec.L.copy()
    centres = np.empty((2, n, 1, 2))
    for c in (0, 1):
        x = 200.0 - 0.013 * t + 0.3 * c
        y = 255.0 + 0.4 * np.sin(2 * np.pi * t / (37.0 + 5 * c))
        w = rng.normal(0.0, 1.0, 4)
        L[c, :, 0] += AMP_DN * rec.x[:, 0] * (phase_features(x, y) @ (w / np.linalg.norm(w)))
        centres[c, :, 0] = np.stack([x, y], 1)
    return rec, L, centres


def _decode(rec: SynthRecording, L: np.ndarray, centres: np.ndarray | None, block: int = 32
            ) -> tuple[list, PacketAssembler]:
    tx, _ = _one_led()
    asm = PacketAssembler(tx, fps=rec.fps, exposure_s=rec.exposure_s)
    out: list = []
    for s in range(0, rec.t_s.size, block):
        i = np.arange(s, min(rec.t_s.size, s + block))
        out += asm.push(i, rec.t_s[i], L[0, i], L[1, i],
                        None if centres is None else (centres[0, i], centres[1, i]))
    return out + asm.flush(), asm


def test_with_the_true_levels_the_phase_part_goes_to_the_noise() -> None:
    """With the true levels and clock, the clean frames of a packet come back to the light
    without the phase term (their spread about it falls 3x or more); frames outside the
    packet and straddling frames are left as they were."""
    _, air = _one_led()
    rec, L, centres = _with_phase(0)
    j = 0
    u0 = rec.packet_starts_s[j] * rec.fps
    p = rec.fps / 500.0 / (1 + 100e-6)  # synth_recording's default rate and drift
    s0 = int(rec.packet_symbol0[j])
    lev = rec.levels[s0:s0 + air.packet_symbols, 0].astype(np.int64) - 1
    assert np.array_equal(lev[:known_levels(air).shape[0]], known_levels(air)[:, 0])
    clock = SymbolClock(u0, p)
    Lc = phase_corrected(L, centres, lev, clock, rec.exposure_s * rec.fps)
    assert Lc is not None and Lc.shape == L.shape
    lo, hi = int(np.ceil(u0)), int(clock.boundary(air.packet_symbols))
    k, alpha = frame_map_range(lo, hi, clock, rec.exposure_s * rec.fps)
    clean = np.arange(lo, hi)[alpha >= 1.0]
    for c in (0, 1):
        before = np.std(L[c, clean, 0] - rec.L[c, clean, 0])
        after = np.std(Lc[c, clean, 0] - rec.L[c, clean, 0])
        assert before > 0.8 and after < before / 3, (c, before, after)
    straddle = np.arange(lo, hi)[alpha < 1.0]
    assert np.array_equal(Lc[:, straddle], L[:, straddle])
    assert np.array_equal(Lc[:, :int(u0) - 1], L[:, :int(u0) - 1])
    assert np.array_equal(Lc[:, hi + 2:], L[:, hi + 2:])


def test_no_known_centres_or_an_array_is_no_attempt() -> None:
    _, air = _one_led()
    rec, L, centres = _with_phase(0)
    lev = rec.levels[:air.packet_symbols, 0].astype(np.int64) - 1
    clock = SymbolClock(rec.packet_starts_s[0] * rec.fps, 2.0)
    assert phase_corrected(L, np.full_like(centres, np.nan), lev, clock, 1.0) is None
    with pytest.raises(ValueError, match="one LED"):
        phase_corrected(np.repeat(L, 2, axis=2), centres, lev, clock, 1.0)
    with pytest.raises(ValueError, match="centres"):
        phase_corrected(L, centres[:, :-1], lev, clock, 1.0)


@pytest.fixture(scope="module")
def decoded() -> list[tuple[SynthRecording, list, list, dict]]:
    """Seeds 1-4: the packets without centres, with them, and the assembler's stats."""
    out = []
    for seed in (1, 2, 3, 4):
        rec, L, centres = _with_phase(seed)
        plain, _ = _decode(rec, L, None)
        phased, asm = _decode(rec, L, centres)
        out.append((rec, plain, phased, dict(asm.stats)))
    return out


def test_the_phase_attempt_delivers_what_the_others_lost(decoded: list) -> None:
    """Without centres every packet fails (the phase term squeezes the top levels); with
    them the assembler's phase attempt delivers at least 3 of the 8 (4 when written), each bit-exact and
    flagged ``phase_corrected`` in its record, and says so in its stats."""
    delivered = 0
    for rec, plain, phased, stats in decoded:
        assert len(plain) == 2 and not any(p.crc_ok for p in plain)
        assert len(phased) == 2
        for j, p in enumerate(phased):
            if p.crc_ok:
                delivered += 1
                assert p.payload == rec.payloads[j]
                assert p.quality.get("phase_corrected") is True
                assert p.record()["phase_corrected"] is True
            else:
                assert "phase_corrected" not in p.quality and p.payload is None
        assert stats["phase_delivered"] == sum(p.crc_ok for p in phased)
        assert stats["phase_tries"] >= 2
    assert delivered >= 3, delivered


def test_switched_off_it_changes_nothing(monkeypatch: pytest.MonkeyPatch, decoded: list) -> None:
    rec, plain, _, _ = decoded[0]
    monkeypatch.setattr(pixelphase, "PHASE_RETRY", False)
    _, L, centres = _with_phase(1)
    off, asm = _decode(rec, L, centres)
    assert [(p.crc_ok, p.levels.tolist()) for p in off] == [(p.crc_ok, p.levels.tolist()) for p in plain]
    assert asm.stats["phase_tries"] == 0


def test_the_centres_stay_with_their_frames() -> None:
    """Through the buffer's growth, trimming, a gap (NaN rows), frames that do not increase
    (dropped) and a camera without centres, each kept centre is its own frame's."""
    tx, _ = _one_led()
    asm = PacketAssembler(tx, fps=1000.0, exposure_s=1e-3)
    rng = np.random.default_rng(5)
    ids = np.concatenate([np.arange(0, 3000), np.arange(3050, 6000)])
    for s in range(0, ids.size, 37):
        i = ids[s:s + 37]
        lum = rng.uniform(20, 40, (i.size, 1))
        cen = np.stack([i.astype(float), -i.astype(float)], 1)[:, None, :]
        right = None if s % 5 == 0 else cen + 0.5
        asm.push(i, i / 1000.0, lum, lum, (cen, right))
        if s == 74:  # ids that do not increase: dropped with their centres
            asm.push(i[:3], i[:3] / 1000.0, lum[:3], lum[:3], (cen[:3] + 99, None))
    assert asm.stats["frames_rejected"] == 3
    assert asm._X is not None and asm._base and asm._base > 0  # trimmed
    rows = asm._base + np.arange(asm._n)
    X = asm._X[:, :asm._n, 0]
    have = np.isin(rows, ids)
    assert np.array_equal(X[0, have, 0], rows[have]) and np.array_equal(X[0, have, 1], -rows[have])
    assert np.isnan(X[:, ~have]).all()
    right = X[1, have, 0]
    assert np.isnan(right).any() and np.array_equal(right[np.isfinite(right)], rows[have][np.isfinite(right)] + 0.5)
    with pytest.raises(ValueError, match="centres"):
        asm.push(np.array([7000]), np.array([7.0]), np.ones((1, 1)), np.ones((1, 1)), (np.ones((2, 1, 2)), None))


def test_an_array_keeps_no_centres() -> None:
    tx = default_config().transmitter
    asm = PacketAssembler(tx, fps=1000.0, exposure_s=1e-3)
    N = tx.rows * tx.cols
    asm.push(np.arange(4), np.arange(4) / 1e3, np.ones((4, N)), np.ones((4, N)),
             (np.ones((4, N, 2)), np.ones((4, N, 2))))
    assert asm._X is None and packets_mod.PacketAssembler._phase_attempt is not None


def test_the_demodulation_worker_gets_the_centres(decoded: list) -> None:
    """The daemon's worker process (over its pipes) gets the centres with the luminance: the
    same packets as the assembler in this process, phase-corrected ones included."""
    from iscd.decode.comms.settings import ReceiverConfig
    from iscd.decode.pipe import PipeDemodWorker

    tx, _ = _one_led()
    rec, _, phased, _ = next(d for d in decoded if any(p.crc_ok for p in d[2]))
    seed = 1 + decoded.index(next(d for d in decoded if d[0] is rec))
    _, L, centres = _with_phase(seed)
    w = PipeDemodWorker()
    try:
        futs = [w.submit("new", tx, rec.fps, rec.exposure_s, ReceiverConfig())]
        for s in range(0, rec.t_s.size, 32):
            i = np.arange(s, min(rec.t_s.size, s + 32))
            futs.append(w.submit("push", i, rec.t_s[i], L[0, i], L[1, i], (centres[0, i], centres[1, i])))
        futs.append(w.submit("flush"))
        got = [p for f in futs for p in f.result(timeout=300)]
    finally:
        w.shutdown(wait=False)
    assert [(p.crc_ok, p.payload, p.quality.get("phase_corrected")) for p in got] == \
        [(p.crc_ok, p.payload, p.quality.get("phase_corrected")) for p in phased]
    assert any(p.quality.get("phase_corrected") for p in got)


def test_a_rendered_approach_the_receiver_lost_is_delivered(monkeypatch: pytest.MonkeyPatch) -> None:
    """Set 72001's 134326035 (40 km/h from 50 m, 0.5 px of smooth vibration, randomized
    physics): the receiver lost both packets to the squeezed top levels (tests/test_phaselight.py);
    its stream decoder now hands the followed centres on, and the second packet is
    delivered bit-exact by the phase attempt. (The smoothed-channel attempt after it, session
    35, delivers it as well: both are switched off for the receiver that loses it.)"""
    from iscd.eval.suites import MOTION_CASES, motion_cfg
    from iscd.eval.sweeps import ReceiverMode, run_comms

    case = next(c for c in MOTION_CASES if c.key == "1led-40kmh-0.5px")
    cfg, _ = motion_cfg(default_config(), case, 134326035, scene={"vibration_model": "smooth", "background_motion": "whole"}, randomize=True)
    res = run_comms(cfg, [ReceiverMode("diversity", "both")], packets=case.packets)[0]
    assert res.packets_sent == 2 and res.exact >= 1 and res.spurious_crc_ok == 0, res.as_dict()
    monkeypatch.setattr(pixelphase, "PHASE_RETRY", False)
    monkeypatch.setattr(packets_mod, "SMOOTH_RETRY", False)
    off = run_comms(cfg, [ReceiverMode("diversity", "both")], packets=case.packets)[0]
    assert off.exact == 0 and off.found == 2, off.as_dict()
