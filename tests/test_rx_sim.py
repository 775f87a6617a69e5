"""End to end on rendered frames: simulator -> luminance at the true LED positions (from the
simulator's truth; detection is tested elsewhere) -> packets, against the sent payloads."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.core.config import default_config
from iscd.decode.tracking.luminance import SpotLuminance, roi_mean
from iscd.decode.comms.packets import Packet, PacketAssembler

sim = pytest.importorskip("iscd.sim", reason="the simulator (iscd.sim) is not available")
presets = pytest.importorskip("iscd.sim.presets")


def _decode(cfg, n_frames: int, method: str = "roi", size: int = 3, chunk: int = 128):
    scene = sim.Scene(cfg)
    truth = scene.truth(np.arange(n_frames))
    H, W = cfg.camera.height, cfg.camera.width
    buf = np.empty((2, chunk, H, W), np.uint8)
    asm = PacketAssembler(cfg.transmitter, cfg.camera.fps, cfg.camera.exposure_s)
    spot: list[SpotLuminance] = []
    out: list[Packet] = []
    for a in range(0, n_frames, chunk):
        b = min(n_frames, a + chunk)
        for n in range(a, b):
            scene.render_pair_into(n, buf[0, n - a], buf[1, n - a])
        L = []
        for c, (u, v) in enumerate([(truth.u_left, truth.v_left), (truth.u_right, truth.v_right)]):
            cen = np.stack([u[a:b], v[a:b]], -1)
            if method == "roi":
                L.append(roi_mean(buf[c, :b - a], cen, size))
            else:
                if len(spot) <= c:
                    spot.append(SpotLuminance(cen[0], size).fit(buf[c, :b - a]))
                L.append(spot[c](buf[c, :b - a]))
        out += asm.push(np.arange(a, b), truth.t_s[a:b], L[0], L[1])
    return out, truth, asm


def _check(out: list[Packet], truth, air: AirInterface, n_expected: int) -> None:
    assert len(out) == n_expected
    for p in out:
        j = int(np.argmin(np.abs(truth.packet_t_s - p.t_s)))
        assert abs(truth.packet_t_s[j] - p.t_s) < 20e-6  # header start within 20 us
        sent = truth.payloads[j]
        ser = float((p.levels != air.encode_data(sent)).mean())
        assert p.crc_ok and p.payload == sent and ser == 0.0


@pytest.mark.parametrize("levels,method", [(8, "roi"), (16, "spot")])
def test_8x8_array_at_50m_hdr(levels: int, method: str) -> None:
    cfg = presets.override(default_config(),
                           transmitter={"levels": levels},
                           scene={"distance_m": 50.0, "led_phase_s": 0.0007, "led_drift_ppm": 100.0,
                                  "seed": 3},
                           camera={"f_number_left": 4.0, "f_number_right": 8.0})
    air = AirInterface.from_config(cfg.transmitter)
    n = int(np.ceil((0.0007 + air.packet_symbols * 2e-3) * 1000)) + 8  # one whole packet
    out, truth, asm = _decode(cfg, n, method)
    _check(out, truth, air, 1)
    assert asm.stats["packets_bad"] == 0


def test_single_led_at_60m_pwm8() -> None:
    cfg = presets.single_led(default_config(), 60.0, led_phase_s=0.0013, led_drift_ppm=-100.0, seed=2)
    air = AirInterface.from_config(cfg.transmitter)
    n = int(np.ceil((0.0013 + air.packet_symbols * 2e-3) * 1000)) + 8
    out, truth, _ = _decode(cfg, n, "roi")
    _check(out, truth, air, 1)
