"""StreamDecoder.needed_windows() is a contract: the daemon copies only those pixels out of
the ring into buffers it reuses, so a pixel outside them holds whatever an earlier pair left
there. The decoder must give the same records whatever lies outside its windows."""

from __future__ import annotations

import numpy as np
import pytest

from fakes import render_pairs
from iscd.core.config import default_config
from iscd.decode.stream import StreamDecoder
from iscd.sim.presets import single_led


def _decode(cfg, frames, garbage: bool) -> list[dict]:
    L, R = frames
    n = L.shape[0]
    dec = StreamDecoder(cfg)
    rng = np.random.default_rng(7)
    bl = np.empty((16,) + L.shape[1:], L.dtype)
    br = np.empty_like(bl)
    out: list[dict] = []
    ids = np.arange(n)
    for s in range(0, n, 16):
        e = min(n, s + 16)
        win = dec.needed_windows()
        if win is None or not garbage:
            bl[:e - s], br[:e - s] = L[s:e], R[s:e]
        else:  # outside the windows: noise, as stale pixels of other pairs would be
            bl[:] = rng.integers(0, 256, bl.shape, dtype=np.uint8)
            br[:] = rng.integers(0, 256, br.shape, dtype=np.uint8)
            (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = win
            bl[:e - s, ay0:ay1, ax0:ax1] = L[s:e, ay0:ay1, ax0:ax1]
            br[:e - s, by0:by1, bx0:bx1] = R[s:e, by0:by1, bx0:bx1]
        out += dec.push(ids[s:e], ids[s:e] / cfg.camera.fps, bl[:e - s], br[:e - s])
    return out + dec.finish()




@pytest.mark.parametrize("which", ["one LED at 40 m", "8x8 array at 30 m"])
def test_pixels_outside_the_needed_windows_change_nothing(which: str) -> None:
    cfg = default_config()
    cfg = single_led(cfg, 40.0) if which.startswith("one") else cfg
    frames = render_pairs(cfg, 1500)
    clean = _decode(cfg, frames, garbage=False)
    noisy = _decode(cfg, frames, garbage=True)
    assert any(r["type"] == "packet" for r in clean)
    assert [r for r in noisy if r["type"] == "packet"] == [r for r in clean if r["type"] == "packet"]
    assert [r for r in noisy if r["type"] == "range"] == [r for r in clean if r["type"] == "range"]
