"""Frames handed over with ``push(owned=True)`` are kept as views while the decoder looks
for its transmitter (no copy), with the same records as frames it copies."""

from __future__ import annotations

import numpy as np

from iscd.core.config import default_config
from iscd.decode.stream import StreamDecoder


def _run(L: np.ndarray, R: np.ndarray, owned: bool) -> tuple[list[dict], StreamDecoder, list]:
    dec = StreamDecoder(default_config())
    buf_l, buf_r = np.empty((16,) + L.shape[1:], L.dtype), np.empty((16,) + R.shape[1:], R.dtype)
    out: list[dict] = []
    blocks = []
    for s in range(0, len(L), 16):
        ids = np.arange(s, s + 16)
        if owned:  # a fresh block each time, as the daemon's BlockReader gives whole frames
            bl, br = L[s:s + 16].copy(), R[s:s + 16].copy()
            blocks.append(bl)
        else:  # one reused buffer: the decoder must copy what it keeps
            buf_l[:] = L[s:s + 16]
            buf_r[:] = R[s:s + 16]
            bl, br = buf_l, buf_r
        out += dec.push(ids, ids / 1000.0, bl, br, owned=owned)
        if s == 32:
            kept = list(dec._acq_l)
            if owned:  # views of the blocks handed over, not copies
                assert all(k.base is blocks[i // 16] for i, k in enumerate(kept))
            else:
                assert all(k.base is None for k in kept)
    out += dec.finish()
    return out, dec, blocks


def test_owned_frames_are_kept_without_a_copy_and_decode_the_same(rendered_default) -> None:
    L, R = rendered_default
    a, dec_a, _ = _run(L[:160], R[:160], owned=False)
    b, dec_b, _ = _run(L[:160], R[:160], owned=True)
    assert dec_a.counters["acquisitions"] == dec_b.counters["acquisitions"] == 1
    ranges = [r for r in a if r["type"] == "range"]
    assert len(ranges) > 50
    assert a == b
