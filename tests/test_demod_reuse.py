"""The final pass reuses a stretch's decision when its inputs are unchanged
(:data:`iscd.decode.comms.demod.REUSE_UNCHANGED`): the packets must be exactly those that
deciding every stretch again gives, with fewer decisions made."""

from __future__ import annotations

import numpy as np
import pytest

import iscd.decode.comms.demod as demod
from iscd.core.airinterface import AirInterface
from iscd.core.config import TransmitterConfig
from iscd.decode.comms.packets import PacketAssembler
from iscd.decode.comms.synth import SynthCamera, synth_recording


def _packets(rec, tx: TransmitterConfig, monkeypatch: pytest.MonkeyPatch, reuse: bool) -> tuple[list, int]:
    calls = [0]
    real = demod.decide_span

    def counted(*a, **k):
        calls[0] += 1
        return real(*a, **k)

    monkeypatch.setattr(demod, "decide_span", counted)
    monkeypatch.setattr(demod, "REUSE_UNCHANGED", reuse)
    asm = PacketAssembler(tx, rec.fps, rec.exposure_s)
    out = []
    ids = np.arange(rec.t_s.size)
    for a in range(0, ids.size, 200):
        i = ids[a:a + 200]
        out += asm.push(i, rec.t_s[i], rec.L[0][i], rec.L[1][i])
    return out, calls[0]


@pytest.mark.parametrize("seed,peak", [(1, 60.0), (4, 120.0), (2, 25.0), (3, 14.0)])
def test_reuse_gives_exactly_the_packets_of_deciding_again(seed: int, peak: float,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    # an 8x8-like array at several SNRs down to where the decisions change between passes
    tx = TransmitterConfig(rows=4, cols=4, levels=8, data_symbols=400, idle_symbols=0)
    air = AirInterface.from_config(tx)
    cams = [SynthCamera(peak_dn=peak, read_noise_dn=1.5), SynthCamera(peak_dn=peak / 4, read_noise_dn=1.5)]
    rec = synth_recording(air, cams, n_packets=3, drift_ppm=80.0, seed=seed)
    fresh, n_fresh = _packets(rec, tx, monkeypatch, reuse=False)
    reused, n_reused = _packets(rec, tx, monkeypatch, reuse=True)
    assert len(fresh) == len(reused) >= 2
    for p, q in zip(fresh, reused):
        assert p.crc_ok == q.crc_ok
        np.testing.assert_array_equal(p.levels, q.levels)
        assert p.record() == q.record()
    print(f"decisions: {n_fresh} deciding again, {n_reused} with reuse")
    assert n_reused <= n_fresh
    if peak >= 60.0:  # where few decisions change between passes, most are reused
        assert n_reused < n_fresh
