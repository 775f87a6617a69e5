"""Streaming packet assembly end to end on synthetic luminance (iscd.decode.comms.synth):
every packet found, CRC-valid payloads bit-exact, failed CRCs never delivered as valid."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.core.config import ConfigError, TransmitterConfig
from iscd.decode.comms.packets import Packet, PacketAssembler
from iscd.decode.comms.settings import ReceiverConfig, receiver_config
from iscd.decode.comms.synth import SynthCamera, SynthRecording, synth_recording


def _tx(levels: int = 8, rows: int = 1, data: int = 600, idle: int = 0) -> TransmitterConfig:
    return TransmitterConfig(rows=rows, cols=rows, levels=levels, data_symbols=data,
                             idle_symbols=idle)


def _run(tx: TransmitterConfig, rec: SynthRecording, block: int = 250,
         cfg: ReceiverConfig | None = None, keep: np.ndarray | None = None,
         L: np.ndarray | None = None) -> tuple[list[Packet], PacketAssembler]:
    asm = PacketAssembler(tx, rec.fps, rec.exposure_s, cfg)
    L = rec.L if L is None else L
    ids = np.arange(rec.t_s.size)
    if keep is not None:
        ids = ids[keep]
    out: list[Packet] = []
    for a in range(0, ids.size, block):
        i = ids[a:a + block]
        out += asm.push(i + 1000, rec.t_s[i], L[0][i], L[1][i])
    return out + asm.flush(), asm  # (the end of the stream: a failed packet held for its anchor)


def _match(rec: SynthRecording, air: AirInterface, pk: list[Packet]) -> list[tuple[int, Packet, float]]:
    """(packet index, packet, SER) for each decoded packet; asserts it is a real one."""
    out = []
    for p in pk:
        j = int(np.argmin(np.abs(rec.packet_starts_s - p.t_s)))
        assert abs(rec.packet_starts_s[j] - p.t_s) < 20e-6, "packet at a wrong time"
        out.append((j, p, float((p.levels != air.encode_data(rec.payloads[j])).mean())))
    return out


def _check_valid_exact(rec: SynthRecording, matched) -> None:
    for j, p, _ in matched:
        if p.crc_ok:
            assert p.payload == rec.payloads[j]
        else:
            assert p.payload is None and p.record()["payload_hex"] == ""


@pytest.mark.parametrize("drift", [-200.0, 0.0, 200.0])
@pytest.mark.parametrize("levels", [2, 8])
def test_packets_error_free_under_drift(drift: float, levels: int) -> None:
    tx = _tx(levels)
    air = AirInterface.from_config(tx)
    cams = [SynthCamera(peak_dn=100), SynthCamera(peak_dn=100)]
    rec = synth_recording(air, cams, n_packets=3, drift_ppm=drift, phase_s=0.00093, seed=4)
    pk, asm = _run(tx, rec)
    m = _match(rec, air, pk)
    assert sorted(j for j, _, _ in m) == [0, 1, 2]
    for j, p, ser in m:
        assert ser == 0 and p.crc_ok and p.payload == rec.payloads[j]
        assert abs(p.quality["drift_ppm"] - drift) < 15
        # the reported frame is the header's first (clean) frame
        u0 = rec.packet_starts_s[j] * rec.fps + 1000
        assert u0 - 0.01 <= p.frame <= u0 + 1.01
    assert asm.stats["packets_ok"] == 3 and asm.stats["packets_bad"] == 0


def test_64_leds_pwm16_hdr() -> None:
    tx = _tx(16, rows=8)
    air = AirInterface.from_config(tx)
    cams = [SynthCamera(peak_dn=500, led_gain_spread=0.1, read_noise_dn=2),
            SynthCamera(peak_dn=125, led_gain_spread=0.1, read_noise_dn=2)]
    rec = synth_recording(air, cams, n_packets=2, drift_ppm=-150, phase_s=0.0017, seed=5)
    q = np.rint(rec.x * 15)
    step = [rec.L[0][q == s].mean() - rec.L[0][q == s - 1].mean() for s in (1, 15)]
    assert step[1] < 0.5 * step[0]  # the f/4 camera saturates
    pk, _ = _run(tx, rec, block=400)
    m = _match(rec, air, pk)
    assert len(m) == 2
    for j, p, ser in m:
        assert ser == 0 and p.crc_ok and p.payload == rec.payloads[j]
        assert len(p.record()["levels"]) == 600 * 64


def test_recording_starting_mid_packet_decodes_from_the_next_header() -> None:
    tx = _tx(8)
    air = AirInterface.from_config(tx)
    cams = [SynthCamera(peak_dn=100), SynthCamera(peak_dn=100)]
    rec = synth_recording(air, cams, n_packets=3, drift_ppm=80, seed=6)
    t0 = rec.packet_starts_s[0]
    # starts inside the header, in the training, in the data, at the end of the data
    for start in (t0 + 0.010, t0 + 0.05, t0 + 0.6, t0 + 1.29):
        rec = synth_recording(air, cams, n_packets=3, drift_ppm=80, seed=6, start_s=start)
        pk, asm = _run(tx, rec)
        m = _match(rec, air, pk)
        assert [j for j, _, _ in m] == [1, 2]
        assert all(p.crc_ok and ser == 0 for _, p, ser in m)
        assert asm.stats["packets_bad"] == 0


def test_idle_symbols_between_packets() -> None:
    tx = _tx(4, data=200, idle=9)
    air = AirInterface.from_config(tx)
    rec = synth_recording(air, [SynthCamera(peak_dn=80)] * 2, n_packets=4, drift_ppm=120, seed=7)
    m = _match(rec, air, _run(tx, rec)[0])
    assert [j for j, _, _ in m] == [0, 1, 2, 3] and all(p.crc_ok for _, p, _ in m)


def test_block_size_does_not_change_the_result() -> None:
    tx = _tx(8, data=150)
    air = AirInterface.from_config(tx)
    rec = synth_recording(air, [SynthCamera(peak_dn=40)] * 2, n_packets=2, drift_ppm=60, seed=8)
    a, _ = _run(tx, rec, block=1)
    b, _ = _run(tx, rec, block=10_000)
    assert len(a) == len(b) == 2
    for p, q in zip(a, b):
        assert p.frame == q.frame and p.crc_ok == q.crc_ok
        np.testing.assert_array_equal(p.levels, q.levels)


def test_gaps_become_erasures_and_never_false_valid_packets() -> None:
    tx = _tx(8, rows=2)
    air = AirInterface.from_config(tx)
    rec = synth_recording(air, [SynthCamera(peak_dn=100)] * 2, n_packets=3, drift_ppm=100, seed=9)
    rng = np.random.default_rng(9)
    keep = np.ones(rec.t_s.size, bool)
    for g in rng.integers(200, rec.t_s.size - 10, 12):
        keep[g:g + 3] = False  # 3 lost frames: one symbol entirely
    pk, asm = _run(tx, rec, keep=keep)
    m = _match(rec, air, pk)
    assert sorted(j for j, _, _ in m) == [0, 1, 2]  # every packet still found
    assert asm.stats["frames_missing"] == int((~keep).sum())
    assert sum(p.quality["erasures"] for _, p, _ in m) > 0
    _check_valid_exact(rec, m)
    # one camera losing frames costs nothing: the other one decides
    L = rec.L.copy()
    L[0, ~keep] = np.nan
    m = _match(rec, air, _run(tx, rec, L=L)[0])
    assert len(m) == 3 and all(p.crc_ok and ser == 0 for _, p, ser in m)


def test_a_failed_crc_is_reported_and_never_delivered() -> None:
    tx = _tx(8)
    air = AirInterface.from_config(tx)
    rec = synth_recording(air, [SynthCamera(peak_dn=100)] * 2, n_packets=2, drift_ppm=0,
                          phase_s=0.0005, seed=10)
    L = rec.L.copy()
    # packet 0, data symbol 300: overwrite its frames with another level's luminance
    t_sym = rec.packet_starts_s[0] + (air.data_offset + 300) * 2e-3
    n = np.flatnonzero((rec.t_s >= t_sym - 1e-3) & (rec.t_s < t_sym + 2e-3))
    src = np.flatnonzero(rec.x[:, 0] == 0)[:n.size]  # dark frames
    L[:, n] = L[:, src] if rec.x[n, 0].min() > 0.1 else L[:, np.flatnonzero(rec.x[:, 0] == 1)[:n.size]]
    pk, asm = _run(tx, rec, L=L)
    m = _match(rec, air, pk)
    assert [j for j, _, _ in m] == [0, 1]
    bad, good = m[0][1], m[1][1]
    assert not bad.crc_ok and bad.payload is None and 0 < m[0][2] <= 2 / 600
    rec0 = bad.record(tx=3)
    assert rec0["payload_hex"] == "" and rec0["crc_ok"] is False and rec0["tx"] == 3
    assert good.crc_ok and good.payload == rec.payloads[1]
    assert good.record()["payload_hex"] == rec.payloads[1].hex()
    assert asm.stats["packets_bad"] == 1 and asm.stats["packets_ok"] == 1


def test_low_snr_packets_valid_only_when_exact() -> None:
    tx = _tx(8)
    air = AirInterface.from_config(tx)
    rec = synth_recording(air, [SynthCamera(peak_dn=19.5)] * 2, n_packets=8, drift_ppm=100, seed=11)
    m = _match(rec, air, _run(tx, rec)[0])
    assert len(m) == 8
    n_ok = sum(p.crc_ok for _, p, _ in m)
    assert 0 < n_ok < 8  # some packets fail at this SNR, some pass
    _check_valid_exact(rec, m)
    assert all((ser == 0) == p.crc_ok for _, p, ser in m)


def test_no_packets_from_noise_or_headerless_data() -> None:
    tx = _tx(8, rows=2)
    air = AirInterface.from_config(tx)
    rec = synth_recording(air, [SynthCamera(peak_dn=100)] * 2, n_packets=0, lead_symbols=4000,
                          seed=12, payloads=[])
    pk, asm = _run(tx, rec)
    assert pk == [] and asm.stats["packets_ok"] == asm.stats["packets_bad"] == 0
    noise = 10 + np.random.default_rng(1).normal(0, 1, rec.L.shape)
    assert _run(tx, rec, L=noise)[0] == []


def test_hdr_iscd_rule_beats_the_dissertation_rule_and_single_cameras() -> None:
    tx = _tx(16, rows=4)
    air = AirInterface.from_config(tx)
    # f/4: the top levels saturate; f/8 (1/4 the light): the low levels drown in noise
    cams = [SynthCamera(peak_dn=1500, led_gain_spread=0.03, read_noise_dn=6),
            SynthCamera(peak_dn=375, led_gain_spread=0.03, read_noise_dn=6)]
    rec = synth_recording(air, cams, n_packets=2, drift_ppm=100, seed=3, phase_s=0.0021)
    ser = {}
    for name, cfg in {"iscd": ReceiverConfig(), "dissertation": ReceiverConfig(rule="dissertation"),
                      "iscd-left": ReceiverConfig(cameras="left"),
                      "iscd-right": ReceiverConfig(cameras="right"),
                      "left": ReceiverConfig(rule="left"), "right": ReceiverConfig(rule="right")}.items():
        m = _match(rec, air, _run(tx, rec, cfg=cfg)[0])
        assert len(m) == 2, name
        _check_valid_exact(rec, m)
        ser[name] = np.mean([s for _, _, s in m])
    assert ser["iscd"] < 0.1 * ser["dissertation"]
    assert ser["iscd"] < 0.5 * min(ser["iscd-left"], ser["iscd-right"])
    assert ser["dissertation"] <= min(ser["left"], ser["right"])


def test_bad_input_is_a_clear_error() -> None:
    tx = _tx(8, rows=2)
    asm = PacketAssembler(tx, 1000.0, 1e-3)
    with pytest.raises(ValueError, match="4 LEDs"):
        asm.push(np.arange(3), np.arange(3) * 1e-3, np.zeros((3, 5)), np.zeros((3, 5)))
    with pytest.raises(ValueError, match="timestamps"):
        asm.push(np.arange(3), np.arange(2) * 1e-3, np.zeros((3, 4)), np.zeros((3, 4)))
    assert asm.push(np.arange(5), np.arange(5) * 1e-3, np.zeros((5, 4)), None) == []
    assert asm.push(np.array([3, 4, 9, 8]), np.arange(4) * 1e-3, np.zeros((4, 4)), None) == []
    assert asm.stats["frames_rejected"] == 3 and asm.stats["frames_missing"] == 4
    with pytest.raises(ValueError):
        PacketAssembler(tx, 800.0, 1e-3)  # below 2 frames per symbol
    with pytest.raises(ConfigError, match="receiver.rule"):
        receiver_config(table={"rule": "mrc"})
    with pytest.raises(ConfigError, match="receiver.chunk"):
        receiver_config(table={"chunk": 3})
    assert receiver_config(table={"rule": "left"}).camera_indices == (0,)


def test_memory_stays_bounded_over_a_long_stream() -> None:
    tx = _tx(8, data=100)
    air = AirInterface.from_config(tx)
    rec = synth_recording(air, [SynthCamera(peak_dn=100)] * 2, n_packets=12, drift_ppm=50, seed=14)
    asm = PacketAssembler(tx, rec.fps, rec.exposure_s)
    n_max, got = 0, []
    L = np.concatenate([rec.L, 10 + np.random.default_rng(0).normal(0, 1, (2, 3000, 1))], axis=1)
    t = np.arange(L.shape[1]) / rec.fps
    for a in range(0, L.shape[1], 50):
        got += asm.push(np.arange(a, min(a + 50, L.shape[1])), t[a:a + 50], L[0, a:a + 50], L[1, a:a + 50])
        n_max = max(n_max, asm._n)
    assert len(got) == 12 and all(p.crc_ok for p in got)
    assert n_max <= asm.keep + asm.TRIM_MIN + 50  # about two packets, whatever the length


@pytest.mark.parametrize("levels", [2, 8])
def test_false_headers_in_long_random_data_hide_no_packet(levels: int) -> None:
    # one LED sending 6 s of random data before its packets: many stretches look like
    # Barker-13 (one-LED OOK especially); none may become a packet or mask a real one
    tx = _tx(levels)
    air = AirInterface.from_config(tx)
    for seed in range(3):
        rec = synth_recording(air, [SynthCamera(peak_dn=100)] * 2, n_packets=2, drift_ppm=50,
                              seed=seed, lead_symbols=3000)
        pk, asm = _run(tx, rec, block=200)
        m = _match(rec, air, pk)
        assert [j for j, _, _ in m] == [0, 1]
        assert all(p.crc_ok and ser == 0 for _, p, ser in m)
        assert asm.stats["false_headers"] > 5 and asm.stats["packets_bad"] == 0


def test_flush_decodes_a_packet_that_just_ended() -> None:
    tx = _tx(8, data=100)
    air = AirInterface.from_config(tx)
    rec = synth_recording(air, [SynthCamera(peak_dn=100)] * 2, n_packets=1, seed=15,
                          tail_symbols=0, phase_s=0.0004)
    n = rec.t_s.size  # the recording ends with the packet's last symbol
    end = rec.packet_starts_s[0] * rec.fps + air.packet_symbols * 2 / (1 + 100e-6)  # frames
    assert end - 2 < n < end + 1
    asm = PacketAssembler(tx, rec.fps, rec.exposure_s)
    assert asm.push(np.arange(n), rec.t_s[:n], rec.L[0, :n], rec.L[1, :n]) == []
    got = asm.flush()
    assert len(got) == 1 and got[0].crc_ok and got[0].payload == rec.payloads[0]
    assert asm.flush() == []


def test_a_packet_after_a_long_dark_period_and_a_single_camera() -> None:
    from iscd.core.airinterface import random_payload
    from iscd.decode.comms.synth import integrated_duty

    tx = _tx(8, rows=2, data=100)
    air = AirInterface.from_config(tx)
    rng = np.random.default_rng(16)
    payload = random_payload(air, rng)
    levels = np.concatenate([np.ones((3000, 4), np.uint8), air.packet(payload),
                             np.ones((50, 4), np.uint8)])
    t = np.arange(2 * levels.shape[0] - 2) / 1000.0
    x = integrated_duty(levels, 8, t, 1e-3, 500.0, phase_s=0.0003, drift_ppm=50.0)
    L = SynthCamera(peak_dn=100).luminance(x, rng)
    for left, right in ((L, None), (None, L)):
        asm = PacketAssembler(tx, 1000.0, 1e-3)
        got = []
        for a in range(0, t.size, 10):
            got += asm.push(np.arange(a, min(a + 10, t.size)), t[a:a + 10],
                            None if left is None else left[a:a + 10],
                            None if right is None else right[a:a + 10])
        got += asm.flush()
        assert len(got) == 1 and got[0].crc_ok and got[0].payload == payload


def test_the_retry_with_the_period_free_is_asked_at_most_once_per_delivered_packet(monkeypatch) -> None:
    """demodulate_packet's ``retry_unlocked`` (a failed packet whose period was locked on a
    delivered packet's is tried again with it free): the assembler asks it only while its
    prior is a CRC-valid packet's, so a run of failing packets costs at most one such retry."""
    from types import SimpleNamespace

    import iscd.decode.comms.packets as packets

    asked: list[bool] = []

    def fake(*a, retry_unlocked: bool = False, **k):
        asked.append(retry_unlocked)
        return None

    monkeypatch.setattr(packets, "demodulate_packet", fake)
    tx = _tx()
    asm = PacketAssembler(tx, 1000.0, 1e-3)
    air = AirInterface.from_config(tx)

    def res(ok: bool, rho: float = 0.95) -> SimpleNamespace:
        return SimpleNamespace(crc_ok=ok, training_rho=rho, p=asm.p_nom, p_sigma=1e-6, u0=0.0, air=air)

    asm._demod(0.0)  # no packet yet: the period is not a delivered packet's
    asm._accept(res(True))
    asm._demod(0.0)
    asm._accept(res(False))  # failed (a real packet: the lock moves to it)
    asm._demod(0.0)
    asm._accept(res(True))
    asm._accept(res(False, rho=0.1))  # failed, not even a real packet: the lock stays, the retry not
    asm._demod(0.0)
    assert asked == [False, True, False, False]


def _corrupted(seed: int = 10) -> tuple[TransmitterConfig, AirInterface, SynthRecording, np.ndarray]:
    """Two one-LED packets, the first with data symbol 300's frames overwritten by another
    level's luminance: a failure no channel estimate can mend."""
    tx = _tx(8)
    air = AirInterface.from_config(tx)
    rec = synth_recording(air, [SynthCamera(peak_dn=100)] * 2, n_packets=2, drift_ppm=0,
                          phase_s=0.0005, seed=seed)
    L = rec.L.copy()
    t_sym = rec.packet_starts_s[0] + (air.data_offset + 300) * 2e-3
    n = np.flatnonzero((rec.t_s >= t_sym - 1e-3) & (rec.t_s < t_sym + 2e-3))
    src = np.flatnonzero(rec.x[:, 0] == 0)[:n.size]
    L[:, n] = L[:, src] if rec.x[n, 0].min() > 0.1 else L[:, np.flatnonzero(rec.x[:, 0] == 1)[:n.size]]
    return tx, air, rec, L


def _summary(pk: list[Packet]) -> list[tuple[int, bool, bytes]]:
    return [(p.frame, p.crc_ok, p.levels.tobytes()) for p in pk]


@pytest.mark.parametrize("block", [1, 16, 250, 10_000])
def test_a_failed_packet_held_for_its_anchor_comes_out_as_it_was(block: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """demod.ANCHOR_RETRY: a failed packet waits for the next packet's header and training
    and is demodulated once more anchored on them; where that fails too (a corrupted symbol)
    the same record comes out as without the retry, before the next packet, whatever the
    block size (the wait spans blocks and buffer trims)."""
    from iscd.decode.comms import demod

    tx, air, rec, L = _corrupted()
    pk, asm = _run(tx, rec, L=L, block=block)
    assert [p.crc_ok for p in pk] == [False, True]
    assert asm.stats["anchored_tries"] == 1 and asm.stats["anchored_delivered"] == 0
    assert "channel_anchored" not in pk[0].quality
    # the last resort tried the anchored attempt's and the first attempt's lists, in vain
    # (the overwritten symbol is a confident decision, not a weak one)
    assert asm.stats["list_tries"] >= 2 and asm.stats["list_delivered"] == 0
    assert "list_flips" not in pk[0].quality
    monkeypatch.setattr(demod, "ANCHOR_RETRY", False)
    off, asm_off = _run(tx, rec, L=L, block=block)
    assert asm_off.stats["anchored_tries"] == 0
    assert _summary(pk) == _summary(off)


def test_a_held_packet_is_not_lost_at_a_gap_or_the_end_of_the_stream() -> None:
    """A failed packet held for the frames after it comes out when a long gap resets the
    receiver before they arrive, and at the end of the stream (flush): nothing decoded is
    dropped."""
    tx, air, rec, L = _corrupted()
    ids = np.arange(rec.t_s.size)
    end0 = int(np.ceil((rec.packet_starts_s[0] + air.packet_symbols * 2e-3) * rec.fps)) + 6
    for how in ("gap", "flush", "reset"):
        asm = PacketAssembler(tx, rec.fps, rec.exposure_s)
        out: list[Packet] = []
        for a in range(0, end0, 50):
            i = ids[a:min(a + 50, end0)]
            out += asm.push(i, rec.t_s[i], L[0][i], L[1][i])
        assert out == [] and asm._held is not None, how  # held: the anchor is not in yet
        if how == "gap":
            i = ids[end0:end0 + 10] + 5000
            out += asm.push(i, i / rec.fps, L[0][ids[end0:end0 + 10]], L[1][ids[end0:end0 + 10]])
            assert asm.stats["resyncs"] == 1
        elif how == "flush":
            out += asm.flush()
        else:
            out += asm.reset()
        assert [p.crc_ok for p in out] == [False], how
        assert asm._held is None


def test_a_packet_one_weak_decision_off_is_list_decoded(monkeypatch) -> None:  # noqa: ANN001
    """One mid-level data symbol of the first packet (level 4, both cameras) given the light
    of 0.6 of a level step more, in each frame by the share of its exposure within the
    symbol: every attempt decides the level above, with a small margin and the level sent
    as runner-up. CRC-aided list decoding (listdecode.LIST_DECODE) delivers the sent
    payload with that one symbol changed; without it the packet fails. (The one-LED
    symbol-by-symbol attempt, demod.SEQUENTIAL_RETRY, decides that symbol right -- each
    cost widened by its centroid's own uncertainty -- so it is off here: this tests the list.)"""
    import pytest as _pytest

    from iscd.decode.comms import demod, listdecode

    monkeypatch.setattr(demod, "SEQUENTIAL_RETRY", False)

    tx = _tx(8)
    air = AirInterface.from_config(tx)
    rec = synth_recording(air, [SynthCamera(peak_dn=100)] * 2, n_packets=2, drift_ppm=0,
                          phase_s=0.0005, seed=12)
    d0 = int(rec.packet_symbol0[0]) + air.data_offset
    j = 300 + int(np.flatnonzero(rec.levels[d0 + 300:d0 + 600, 0] == 4)[0])
    t_sym = rec.packet_starts_s[0] + (air.data_offset + j) * 2e-3
    share = np.clip((np.minimum(rec.t_s + 1e-3, t_sym + 2e-3) - np.maximum(rec.t_s, t_sym)) / 1e-3, 0, 1)
    step = 100.0 * float(SynthCamera(peak_dn=100).profile.mean()) / (air.levels - 1)  # DN a level
    L = rec.L + 0.6 * step * share[None, :, None]
    pk, asm = _run(tx, rec, L=L)
    assert [p.crc_ok for p in pk] == [True, True]
    assert [p.payload for p in pk] == rec.payloads[:2]
    assert pk[0].quality["list_flips"] == 1 and "list_flips" not in pk[1].quality
    assert asm.stats["list_delivered"] == 1
    with _pytest.MonkeyPatch.context() as mp:
        mp.setattr(listdecode, "LIST_DECODE", False)
        off, _ = _run(tx, rec, L=L)
    assert [p.crc_ok for p in off] == [False, True]
