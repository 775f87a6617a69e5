"""One simulated evaluation point: render frames, run the real receiver, score against truth.

Communication (:func:`run_comms`): the scene is rendered block by block
(:class:`iscd.sim.Scene`) and every block goes to one :class:`iscd.decode.stream.StreamDecoder`
per receiver mode (single camera, diversity/HDR, project or dissertation decision rule), all
on the same frames. The decoders get only images, frame ids and timestamps -- detection,
tracking, timing and channel estimation are their own; the truth is used only to score:
each decoded packet is matched to the transmitted packet whose header starts within half a
symbol of it, and its decided levels are compared with the sent ones.

Ranging (:func:`run_ranging`): the same kind of stream goes to one decoder (it finds and
tracks the transmitter); for every block after acquisition each method of
:data:`iscd.decode.ranging.estimators.METHODS` ranges the block through its own
:class:`iscd.decode.ranging.stereo.StereoRanger`, on the same patches (the geometry comes from the
decoder's tracked grid fit, the one the daemon's ranging would use for that block). Errors
are against the truth's distance at mid-exposure, on the frames where the LED is lit.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from iscd.calibration.io import StereoCalibration
from iscd.core.airinterface import AirInterface
from iscd.core.airinterface_v2 import AirInterfaceV2, from_config as air_from_config
from iscd.core.config import Config, section
from iscd.eval.metrics import (ErrorStats, bit_errors, error_stats, goodput_kbps, match_packets,
                               symbol_errors, throughput_kbps)
from iscd.decode.stream import StreamDecoder
from iscd.decode.ranging.range import range_from_disparity
from iscd.decode.ranging.estimators import METHODS
from iscd.sim.scene import Scene
from iscd.decode.ranging.stereo import RangingSettings, StereoRanger

Progress = Callable[[int], None]
"""Called with the number of frames just processed (for a progress bar)."""


@dataclass(frozen=True)
class ReceiverMode:
    """How a decoder listens: which cameras (``both``/``left``/``right``) and which decision
    rule (``iscd``: the project's; ``dissertation``: eqs. 3.11/3.12 and 4.2/4.3).
    ``name`` labels it in the report (e.g. ``"HDR f/4+f/8"``)."""

    name: str
    cameras: str = "both"
    rule: str = "iscd"

    def receiver_table(self, base: dict[str, Any] | None = None) -> dict[str, Any]:
        """The ``[receiver]`` table for this mode (on top of ``base``)."""
        if self.cameras not in ("both", "left", "right"):
            raise ValueError(f"cameras: expected both, left or right, got {self.cameras!r}")
        t = dict(base or {})
        if self.rule == "iscd":
            t.update(rule="iscd", cameras=self.cameras)
        elif self.rule == "dissertation":
            t.update(rule="dissertation" if self.cameras == "both" else self.cameras)
            t.pop("cameras", None)
        else:
            raise ValueError(f"rule: expected iscd or dissertation, got {self.rule!r}")
        return t

    @property
    def label(self) -> str:
        return self.name if self.rule == "iscd" else f"{self.name} (dissertation rule)"


@dataclass
class CommsResult:
    """Scores of one receiver mode at one simulated point.

    Counts: ``packets_sent`` whole packets in the recording; ``found`` decoded packets matched
    to one of them; ``crc_ok`` of those with a valid CRC; ``exact`` CRC-valid and equal to the
    sent payload (the ones that count for goodput); ``undetected`` CRC-valid but wrong (must
    be 0); ``spurious`` decoded packets matching no transmitted packet (``spurious_crc_ok``
    of them with a valid CRC). Symbol and bit counts are over the data symbols (F x N each,
    padding included) of the found packets.
    """

    mode: ReceiverMode
    levels: int
    n_leds: int
    data_symbols: int
    packet_s: float
    payload_bytes: int
    packets_sent: int = 0
    found: int = 0
    crc_ok: int = 0
    exact: int = 0
    undetected: int = 0
    spurious: int = 0
    spurious_crc_ok: int = 0
    symbols: int = 0
    symbol_errors: int = 0
    bits: int = 0
    bit_errors: int = 0
    margin_p01: list[float] = field(default_factory=list)
    """per found packet: the receiver's 1st-percentile decision margin (its own metric)."""
    seconds: float = 0.0
    """wall time spent in this decoder, s (indicative)."""

    @property
    def ser(self) -> float:
        """Symbol error rate over the found packets' data symbols (NaN if none found)."""
        return self.symbol_errors / self.symbols if self.symbols else float("nan")

    @property
    def ber(self) -> float:
        return self.bit_errors / self.bits if self.bits else float("nan")

    @property
    def per(self) -> float:
        """Packet error rate: share of the sent packets not delivered bit-exact (missed,
        CRC failed or wrong)."""
        return 1.0 - self.exact / self.packets_sent if self.packets_sent else float("nan")

    @property
    def goodput_kbps(self) -> float:
        return goodput_kbps(self.exact, self.payload_bytes, self.packets_sent, self.packet_s)

    @property
    def throughput_kbps(self) -> float:
        """The dissertation's (4.4) with this point's SER (NaN when nothing was found)."""
        return throughput_kbps(self.levels, self.n_leds, self.data_symbols, self.packet_s, self.ser)

    def as_dict(self) -> dict[str, Any]:
        return {"mode": self.mode.name, "rule": self.mode.rule, "cameras": self.mode.cameras,
                "packets_sent": self.packets_sent, "found": self.found, "crc_ok": self.crc_ok,
                "exact": self.exact, "undetected": self.undetected, "spurious": self.spurious,
                "spurious_crc_ok": self.spurious_crc_ok, "symbols": self.symbols,
                "symbol_errors": self.symbol_errors, "bits": self.bits, "bit_errors": self.bit_errors,
                "ser": _num(self.ser), "ber": _num(self.ber), "per": _num(self.per),
                "goodput_kbps": _num(self.goodput_kbps), "throughput_kbps": _num(self.throughput_kbps),
                "margin_p01_min": _num(min(self.margin_p01)) if self.margin_p01 else None,
                "seconds": round(self.seconds, 3)}


def _num(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


def _decoder_cfg(cfg: Config, mode: ReceiverMode | None, ranging: bool = False) -> Config:
    out = cfg.with_keys("tracking", ranging=ranging)
    if mode is not None:
        out = out.with_keys("receiver", **mode.receiver_table(cfg.table("receiver")))
    return out


def frames_for_packets(scene: Scene, air: AirInterface | AirInterfaceV2, packets: int, tail_frames: int = 8,
                       after_symbols: int = 0) -> int:
    """Frames (from 0) that hold the first ``packets`` whole packets (their idle symbols
    included) and ``after_symbols`` symbols of the next, plus ``tail_frames``."""
    t_end = float(scene.clock.symbol_start_cam(packets * air.period_symbols + after_symbols))
    return int(math.ceil((t_end + scene.exposure_s) * scene.fps)) + tail_frames


def _blocks(n_frames: int, block: int) -> Iterator[np.ndarray]:
    for s in range(0, n_frames, block):
        yield np.arange(s, min(s + block, n_frames), dtype=np.int64)


def run_comms(cfg: Config, modes: Sequence[ReceiverMode], packets: int = 2, *, block: int = 32,
              progress: Progress | None = None) -> list[CommsResult]:
    """Render ``packets`` whole packets of ``cfg``'s scene (from frame 0, the transmitter's
    first packet starting at its random clock phase) and decode them with one receiver per
    mode; returns one :class:`CommsResult` per mode, in order."""
    if packets < 1:
        raise ValueError(f"packets: expected >= 1, got {packets}")
    if not modes:
        raise ValueError("modes: at least one receiver mode is needed")
    scene = Scene(cfg)
    air = air_from_config(cfg.transmitter)  # v1, or v2 (the receiver reads v2's header itself)
    n_frames = frames_for_packets(scene, air, packets)
    decoders = [StreamDecoder(_decoder_cfg(cfg, m)) for m in modes]
    records: list[list[dict]] = [[] for _ in modes]
    seconds = [0.0] * len(modes)
    H, W = scene.height, scene.width
    L = np.empty((block, H, W), np.uint8)
    R = np.empty_like(L)
    for ids in _blocks(n_frames, block):
        n = ids.size
        for i, k in enumerate(ids):
            scene.render_pair_into(int(k), L[i], R[i])
        t_s = ids / scene.fps
        for j, dec in enumerate(decoders):
            t0 = time.perf_counter()
            records[j] += [r for r in dec.push(ids, t_s, L[:n], R[:n]) if r["type"] == "packet"]
            seconds[j] += time.perf_counter() - t0
        if progress is not None:
            progress(n)
    for j, dec in enumerate(decoders):
        records[j] += [r for r in dec.finish() if r["type"] == "packet"]
    truth = scene.truth(np.arange(n_frames))
    tx = cfg.transmitter
    packet_s = air.period_symbols / tx.symbol_rate_hz
    out = []
    for mode, recs, sec in zip(modes, records, seconds):
        res = CommsResult(mode=mode, levels=tx.levels, n_leds=tx.n_leds, data_symbols=air.data_symbols,
                          packet_s=packet_s, payload_bytes=air.payload_bytes, packets_sent=packets,
                          seconds=sec)
        _score(res, recs, truth, air, packets, 0.5 / tx.symbol_rate_hz)
        out.append(res)
    return out


def _score(res: CommsResult, recs: list[dict], truth: Any, air: AirInterface | AirInterfaceV2, packets: int,
           tolerance_s: float) -> None:
    """Fill ``res`` from decoded packet records and the truth (see :class:`CommsResult`)."""
    match = match_packets([r["t_s"] for r in recs], truth.packet_t_s, tolerance_s)
    seen: set[int] = set()
    F, N, bps = air.data_symbols, air.n_leds, air.bits_per_symbol
    for rec, j in zip(recs, match):
        if j < 0:
            res.spurious += 1
            res.spurious_crc_ok += int(bool(rec["crc_ok"]))
            continue
        p = int(truth.packet_index[j])
        if p >= packets or p in seen:  # the partial packet after the last one, or a repeat
            if p in seen:
                res.spurious += 1
                res.spurious_crc_ok += int(bool(rec["crc_ok"]))
            continue
        seen.add(p)
        start = int(truth.packet_start_symbol[j]) + air.data_offset
        sent = truth.levels_of(start, start + F)
        got = np.asarray(rec["levels"], dtype=np.int64).reshape(F, N)
        res.found += 1
        res.symbols += F * N
        res.bits += F * N * bps
        res.symbol_errors += symbol_errors(sent, got)
        res.bit_errors += bit_errors(sent, got, air.levels)
        if "margin_p01" in rec:
            res.margin_p01.append(float(rec["margin_p01"]))
        if rec["crc_ok"]:
            res.crc_ok += 1
            if bytes.fromhex(rec["payload_hex"]) == truth.payloads[j]:
                res.exact += 1
            else:
                res.undetected += 1


# ----------------------------------------------------------------------------- ranging


@dataclass
class RangingResult:
    """Per-frame range errors of every method at one simulated point.

    ``frames`` (n,) the frames scored (after acquisition, LED lit), ``z_true_m`` (n,) truth
    distance at mid-exposure, ``errors_m[method]`` (n,) range - truth, m, with the range from
    the disparity the method found (NaN where it found none), so every method is scored on
    the same frames; ``reported[method]`` (n,) whether the ranger emits that range (its own
    gate: spot SNR, match quality). ``seconds[method]``: wall time of its ranging, s.
    """

    distance_m: float
    frames: np.ndarray
    z_true_m: np.ndarray
    errors_m: dict[str, np.ndarray]
    reported: dict[str, np.ndarray] = field(default_factory=dict)
    frames_rendered: int = 0
    seconds: dict[str, float] = field(default_factory=dict)
    project_method: str = "iscd"
    """the method the live pipeline uses (the ``[ranging]`` default), for the ratios."""

    def stats(self, method: str) -> ErrorStats:
        """Errors on every scored frame (the same frames for every method)."""
        return error_stats(self.errors_m[method], 0.0)

    def stats_reported(self, method: str) -> ErrorStats:
        """Errors on the frames where the ranger emits a range (its own gate)."""
        rep = self.reported.get(method)
        e = self.errors_m[method] if rep is None else self.errors_m[method][rep]
        return error_stats(e, 0.0)

    def emitted_by_all(self) -> np.ndarray:
        """(n,) frames that every method's ranger emits (passes its spot-SNR and match
        gate): the same frames for every method, and the only ones a user sees a range for
        (the gate is the same spot-SNR test for every method; ~0.1 % of the scored frames,
        the dimmest PWM level at a symbol edge, fail it)."""
        mask = np.ones(self.frames.size, bool)
        for m in self.errors_m:
            rep = self.reported.get(m)
            if rep is not None:
                mask &= rep
        return mask

    def stats_emitted(self, method: str) -> ErrorStats:
        """Errors on :meth:`emitted_by_all` frames."""
        return error_stats(self.errors_m[method][self.emitted_by_all()], 0.0)

    def reported_share(self, method: str) -> float:
        rep = self.reported.get(method)
        if rep is None or rep.size == 0:
            return float("nan")
        return float(np.mean(rep))

    def as_dict(self) -> dict[str, Any]:
        return {"distance_m": self.distance_m, "frames_rendered": self.frames_rendered,
                "frames_ranged": int(self.frames.size), "project_method": self.project_method,
                "methods": {m: {**self.stats(m).as_dict(),
                                "reported_share": _num(self.reported_share(m)),
                                "reported": self.stats_reported(m).as_dict(),
                                "seconds": round(self.seconds.get(m, 0.0), 3)}
                            for m in self.errors_m}}


def run_ranging(cfg: Config, frames: int, methods: Sequence[str] | None = None, *, block: int = 32,
                lit_fraction: float = 0.1, progress: Progress | None = None) -> RangingResult:
    """Render ``frames`` stereo frames of ``cfg``'s scene, track the transmitter with the
    pipeline's decoder, and range every block after acquisition with each method (default:
    all of :data:`iscd.decode.ranging.estimators.METHODS`), each through its own
    :class:`iscd.decode.ranging.stereo.StereoRanger` with the ``[ranging]`` settings of ``cfg`` and
    only the method changed.

    A frame is scored when the LED (mean over the array) is on for at least
    ``lit_fraction`` of the exposure in the truth: a dark symbol shows no spot to range,
    and the same frames are scored for every method."""
    methods = tuple(METHODS) if methods is None else tuple(methods)
    if frames < 1:
        raise ValueError(f"frames: expected >= 1, got {frames}")
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise ValueError(f"unknown ranging method(s) {', '.join(unknown)} (known: {', '.join(METHODS)})")
    scene = Scene(cfg)
    dec = StreamDecoder(_decoder_cfg(cfg, None))
    base = section(cfg, RangingSettings)
    cal = StereoCalibration.ideal(cfg.camera)
    rangers = {m: StereoRanger(cal, dataclasses.replace(base, method=m)) for m in methods}
    H, W = scene.height, scene.width
    L = np.empty((block, H, W), np.uint8)
    R = np.empty_like(L)
    got_frames: list[np.ndarray] = []
    disp: dict[str, list[np.ndarray]] = {m: [] for m in methods}
    rep: dict[str, list[np.ndarray]] = {m: [] for m in methods}
    seconds = {m: 0.0 for m in methods}
    for ids in _blocks(frames, block):
        n = ids.size
        for i, k in enumerate(ids):
            scene.render_pair_into(int(k), L[i], R[i])
        tr = dec.track  # the fit push() uses for this block
        if tr is not None:
            got_frames.append(ids)
            for m, rg in rangers.items():
                t0 = time.perf_counter()
                res = rg.measure(L[:n], R[:n], tr.left, tr.right)
                seconds[m] += time.perf_counter() - t0
                disp[m].append(np.asarray(res.disparity_px, dtype=np.float64))
                valid = getattr(res, "valid", None)
                rep[m].append(np.isfinite(res.z_m) if valid is None or np.size(valid) != n
                              else np.asarray(valid, bool))
        dec.push(ids, ids / scene.fps, L[:n], R[:n])
        if progress is not None:
            progress(n)
    if not got_frames:
        empty = np.zeros(0)
        return RangingResult(cfg.scene.distance_m, np.zeros(0, np.int64), empty,
                             {m: empty for m in methods}, {m: np.zeros(0, bool) for m in methods},
                             frames, seconds, base.method)
    f = np.concatenate(got_frames)
    truth = scene.truth(f)
    lit = truth.on_fraction.mean(axis=1) >= lit_fraction
    f_px, b_m = cfg.camera.focal_px, cfg.camera.baseline_m
    errors = {m: (range_from_disparity(np.concatenate(disp[m]), f_px, b_m) - truth.z_m)[lit] for m in methods}
    reported = {m: np.concatenate(rep[m])[lit] for m in methods}
    return RangingResult(cfg.scene.distance_m, f[lit], truth.z_m[lit], errors, reported, frames, seconds,
                         base.method)
