"""Sub-pixel phase in a clipped spot's light: what taking it out of the luminance would give.

    python -m iscd.eval.phaselight CASE SEED MODEL [--source oracle|receiver] [--labels decisions|truth]
                                   [--window N] [--centre-noise PX]

A clipped spot's light in a fixed window depends on where the spot sits within its pixel
(docs/eval.md, session 32; :mod:`iscd.eval.levelnoise`). This offline experiment takes the
oracle's ``+true positions`` luminance of a one-LED motion scene (:func:`iscd.eval.oracle.run_oracle`),
regresses each level's light, in windows of ``window`` frames, on a quadratic trend and the
first harmonics of the sub-pixel phase of the true centres (:func:`phase_features`), takes
the phase part out (:func:`take_out_phase`) and runs the receiver's packet assembler again. The
levels of the fit are either the truth's or those of one demodulation of each packet with the
true clock (``decisions``: what a receiver could use; header and training known). With
``--source receiver`` the luminance is the receiver's own (what its stream decoder hands its
packet assembler) and the phase is that of its followed centres, as a receiver would have
them (``--centre-noise`` adds white noise to the centres to see what their error costs).
Its "before" and "phase taken out" runs use an assembler given no centres, so that the
receiver's own phase attempt (:mod:`iscd.decode.comms.pixelphase`, built from this
experiment in session 33) stays out of them. Units: px, DN, frames.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any, Sequence

import numpy as np

from iscd.decode.comms.pixelphase import phase_features, take_out_phase

__all__ = ["phase_features", "take_out_phase", "run", "receiver_luminance", "main"]


def run(case_key: str, seed: int, model: str, *, source: str = "oracle", labels: str = "decisions",
        window: int = 400, centre_noise_px: float = 0.0, tracking: dict[str, Any] | None = None
        ) -> dict[str, Any]:
    """The experiment on one randomized one-LED motion scene.

    ``source``: ``oracle`` (the ``+true positions`` luminance, the true centres) or
    ``receiver`` (the receiver's own luminance and followed centres). ``tracking``: ``[tracking]``
    keys to set (e.g. ``growth_from_block=False``, the window of session 32's measurements).

    Returns
    -------
    dict
        ``wrong_labels`` (decisions that differ from the truth, 0 with ``labels="truth"``),
        and per stage (``before``: the luminance as it is, ``phase taken out``) a dict packet
        index -> (delivered bit-exact, wrong symbols).

    Raises
    ------
    ValueError
        An unknown case or labels, an array case, or bad numbers.
    """
    from iscd.core.airinterface import AirInterface
    from iscd.core.config import default_config
    from iscd.decode.comms.demod import PacketResult, demodulate_packet
    from iscd.decode.comms.packets import PacketAssembler
    from iscd.decode.comms.settings import receiver_config
    from iscd.decode.comms.timing import SymbolClock
    from iscd.eval.oracle import _assembler_scores, run_oracle, true_clock
    from iscd.eval.suites import MOTION_CASES, motion_cfg
    from iscd.eval.sweeps import ReceiverMode, _decoder_cfg
    from iscd.sim.scene import Scene

    case = next((c for c in MOTION_CASES if c.key == case_key), None)
    if case is None or case.leds != 1:
        raise ValueError(f"{case_key!r}: not a one-LED motion case "
                         f"(one of {', '.join(c.key for c in MOTION_CASES if c.leds == 1)})")
    if source not in ("oracle", "receiver"):
        raise ValueError(f"source: oracle or receiver, got {source!r}")
    if labels not in ("decisions", "truth"):
        raise ValueError(f"labels: decisions or truth, got {labels!r}")
    if seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed}")
    if not (window >= 16 and 0 <= centre_noise_px < math.inf):
        raise ValueError(f"need window >= 16 frames and a finite centre noise >= 0 px, got {window} and {centre_noise_px}")
    cfg, _ = motion_cfg(default_config(), case, seed, scene={"vibration_model": model}, randomize=True)
    if tracking:
        cfg = cfg.with_keys("tracking", **tracking)
    mode = ReceiverMode("diversity", "both")
    if source == "oracle":
        L = run_oracle(cfg, case.packets, mode=mode, genie=False).luminance["true positions"]  # (2, n, 1)
        truth = Scene(cfg).truth(np.arange(L.shape[1]))
        centres = np.stack([np.stack([truth.u_left[:, 0], truth.v_left[:, 0]], 1),
                            np.stack([truth.u_right[:, 0], truth.v_right[:, 0]], 1)])
    else:
        L, centres, truth = receiver_luminance(_decoder_cfg(cfg, mode), case.packets)
    n = L.shape[1]
    rx = receiver_config(_decoder_cfg(cfg, mode))
    air = AirInterface.from_config(cfg.transmitter)
    fps = cfg.camera.fps
    asm0 = PacketAssembler(cfg.transmitter, fps=fps, exposure_s=cfg.camera.exposure_s, cfg=rx)
    sym0 = int(truth.symbol_index[0])
    level = truth.levels[:, 0].astype(np.int64)  # per scheduled symbol
    wrong = 0
    if labels == "decisions":
        level = level.copy()
        e, p_nom = cfg.camera.exposure_s * fps, fps / cfg.transmitter.symbol_rate_hz
        P = air.packet_symbols
        for j in range(truth.packet_index.size):
            k0 = int(truth.packet_start_symbol[j]) - sym0
            if k0 < 0 or k0 + P + 1 > truth.symbol_t_s.size:
                continue
            clk = true_clock(truth.symbol_t_s[k0:k0 + P + 1], fps)
            lo, hi = max(0, int(np.floor(clk.u0)) - 8), min(n, int(np.ceil(clk.boundary(P))) + 8)
            if not np.isfinite(L[:, lo:hi]).all():  # a stretch the receiver did not measure
                continue
            buf = np.ascontiguousarray(L[list(rx.camera_indices), lo:hi])
            r = demodulate_packet(buf, clk.u0 - lo, air, e, p_nom, clk.p, rx.drift_max_ppm * 1e-6 * p_nom, rx,
                                  clock=SymbolClock(clk.u0 - lo, clk.p), grid=asm0.grid)
            if isinstance(r, PacketResult):
                d0 = k0 + air.data_offset
                got = r.levels.astype(np.int64).reshape(-1)
                wrong += int((got != level[d0:d0 + got.size]).sum())
                level[d0:d0 + got.size] = got
    per_frame = level[truth.symbol_mid - sym0]
    rng = np.random.default_rng(seed)
    Lc = L.copy()
    for c in (0, 1):
        known = np.isfinite(centres[c, :, 0])
        x, y = np.where(known, centres[c, :, 0], 0.0), np.where(known, centres[c, :, 1], 0.0)
        if centre_noise_px > 0:
            x, y = x + rng.normal(0.0, centre_noise_px, n), y + rng.normal(0.0, centre_noise_px, n)
        Lc[c, :, 0] = take_out_phase(L[c, :, 0], per_frame, truth.clean & known, phase_features(x, y),
                                     window=window)
    tol = 0.5 / cfg.transmitter.symbol_rate_hz
    want = {int(truth.packet_index[j]): j for j in range(truth.packet_index.size)
            if int(truth.packet_index[j]) < case.packets}
    out: dict[str, Any] = {"wrong_labels": wrong}
    for name, X in (("before", L), ("phase taken out", Lc)):
        asm = PacketAssembler(cfg.transmitter, fps=fps, exposure_s=cfg.camera.exposure_s, cfg=rx)
        got_packets: list[Any] = []
        ids = np.flatnonzero(np.isfinite(X[0, :, 0]))
        for s in range(0, ids.size, 32):
            i = ids[s:s + 32]
            got_packets += asm.push(i, i / fps, X[0, i], X[1, i])
        got_packets += asm.flush()
        sc = _assembler_scores(got_packets, truth, air, tol, want, 8)
        out[name] = {k: (bool(v.crc_ok and v.errors == 0), int(v.errors)) for k, v in sorted(sc.items())}
    return out


def receiver_luminance(dcfg: Any, packets: int, block: int = 32) -> tuple[np.ndarray, np.ndarray, Any]:
    """Render a one-LED scene and run the receiver's stream decoder over it in blocks,
    keeping what its luminance step measured for each frame.

    Returns
    -------
    tuple
        (2, n, 1) luminance DN and (2, n, 2) followed centres px per camera and frame (NaN
        where a frame was not measured), and the scene's truth.
    """
    from iscd.core.airinterface import AirInterface
    from iscd.decode.comms.demod import known_levels
    from iscd.decode.stream import StreamDecoder
    from iscd.eval.sweeps import _blocks, frames_for_packets
    from iscd.sim.scene import Scene

    scene = Scene(dcfg)
    n = frames_for_packets(scene, AirInterface.from_config(dcfg.transmitter), packets,
                           after_symbols=known_levels(AirInterface.from_config(dcfg.transmitter)).shape[0])
    L = np.full((2, n, 1), np.nan)
    C = np.full((2, n, 2), np.nan)

    class _Capturing(StreamDecoder):
        def _luminance(self, frame_ids: np.ndarray, left: np.ndarray, right: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
            out = super()._luminance(frame_ids, left, right)
            ids = np.asarray(frame_ids)
            for c in (0, 1):
                L[c, ids, 0] = out[c][:, 0]
                C[c, ids] = self.last_centres[c][:, 0, :]
            return out

    dec = _Capturing(dcfg)
    Lb = np.empty((block, scene.height, scene.width), np.uint8)
    Rb = np.empty_like(Lb)
    try:
        for ids in _blocks(n, block):
            for j, f in enumerate(ids):
                scene.render_pair_into(int(f), Lb[j], Rb[j])
            dec.push(ids, ids / scene.fps, Lb[:ids.size], Rb[:ids.size])
        dec.finish()
    finally:
        dec.close()
    return L, C, scene.truth(np.arange(n))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m iscd.eval.phaselight",
        description="Offline: the oracle's +true positions luminance of a one-LED motion scene with each "
                    "level's dependence on the sub-pixel phase taken out, and the packets the receiver's "
                    "assembler delivers before and after (docs/eval.md, session 32).")
    ap.add_argument("case", help="a one-LED motion case, e.g. 1led-40kmh-0.5px")
    ap.add_argument("seed", type=int, help="the scene's seed, e.g. 134326035")
    ap.add_argument("model", help="vibration model: smooth, engine or bumps")
    ap.add_argument("--source", default="oracle",
                    help="oracle (default: the +true positions luminance and the true centres) or receiver "
                         "(the receiver's own luminance and followed centres)")
    ap.add_argument("--labels", default="decisions", help="the levels of the fit: decisions (default) or truth")
    ap.add_argument("--window", type=int, default=400, help="frames per fit window (default 400)")
    ap.add_argument("--centre-noise", type=float, default=0.0, help="white noise on the centres, px (default 0)")
    a = ap.parse_args(argv)
    try:
        r = run(a.case, a.seed, a.model, source=a.source, labels=a.labels, window=a.window,
                centre_noise_px=a.centre_noise)
    except ValueError as e:
        print(f"phaselight: {e}", file=sys.stderr)
        return 2

    def fmt(d: dict[int, tuple[bool, int]]) -> str:
        return ", ".join(f"p{k} {'delivered' if ok else f'lost ({e} wrong)'}" for k, (ok, e) in d.items())

    print(f"{a.case} {a.seed} {a.model}: {a.source}'s luminance, labels {a.labels} ({r['wrong_labels']} wrong)")
    print(f"  as it is:         {fmt(r['before'])}")
    print(f"  phase taken out:  {fmt(r['phase taken out'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
