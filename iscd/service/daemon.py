"""The real-time daemon: cameras -> ring buffer -> streaming decode -> outputs.

Process layout (2 cores, so decoding and acquisition do not share a GIL):

* the acquisition process (:class:`iscd.rig.acquisition.AcquisitionProcess`) reads both
  cameras (mock, GenICam or V4L2, per ``[rig]``), pairs frames by trigger id and timestamp
  and writes pairs into a shared-memory ring (:class:`iscd.rig.ringbuffer.StereoRing`), dropping
  the oldest pair if the decoder falls behind (counted, never blocking the cameras);
* this process takes pairs from the ring in small blocks (at most ``block_max`` pairs, so
  that latency stays low), copies only the pixels the decoder needs once the transmitter
  is tracked, runs :class:`iscd.decode.stream.StreamDecoder` (per frame: tracking, the LEDs
  followed and their luminance, ranging) and hands records to the outputs (JSON Lines,
  optional ZeroMQ socket, optional Rerun view);
* a demodulation worker process (:mod:`iscd.decode.worker`) holds the packet assembler:
  a packet's demodulation (0.1-0.2 s of many small numpy calls) would otherwise hold the
  GIL against the frame loop. A killed worker is replaced (``demod_worker_restarts``).

A ``stats`` record is written every ``stats_interval_s`` and once at the end. SIGTERM and
SIGINT stop the loop gracefully (the final stats record is written and the files flushed);
under systemd the service reports READY/STATUS/WATCHDOG through ``NOTIFY_SOCKET``.
"""

from __future__ import annotations

import functools
import logging
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from iscd.core.config import Config, ConfigError, config_section, section
from iscd.core.records import StatsRecord

log = logging.getLogger(__name__)


@config_section("daemon")
@dataclass(frozen=True)
class DaemonSettings:
    """``[daemon]`` section."""

    ring_ms: float = field(default=500.0, metadata={"lo": 10, "hi": 60_000, "doc": "ring buffer length, ms of frames"})
    block_max: int = field(default=16, metadata={"lo": 1, "hi": 1024, "doc": "most pairs decoded in one step (a block's first pair waits for the rest: 15 ms at 16 and 1000 fps, most of the p99 latency; 8 halves that for ~0.14 cores more)"})
    block_wait_ms: float = field(default=20.0, metadata={"lo": 0, "hi": 1000, "doc": "wait this long to fill a block (whole blocks: the LED following takes its background over a block's frames)"})
    stats_interval_s: float = field(default=1.0, metadata={"lo": 0.05, "doc": "stats record period, s"})
    out: str = field(default="", metadata={"doc": "JSON Lines output (default: none unless --out)"})
    rotate_mb: float = field(default=256.0, metadata={"lo": 0.001, "doc": "rotate the output file at this size, MiB"})
    socket: str = field(default="", metadata={"doc": "ZeroMQ PUB endpoint, e.g. tcp://127.0.0.1:5556 ('' = off)"})
    calibration: str = field(default="", metadata={"doc": "stereo calibration YAML ('' = ideal rig of [camera])"})
    shed_led_fill: float = field(default=0.05, metadata={"lo": 0, "hi": 1, "doc": "overload level 1: shed per-LED ranges while the ring is fuller than this share (docs/realtime.md)"})
    shed_ranging_fill: float = field(default=0.15, metadata={"lo": 0, "hi": 1, "doc": "overload level 2: range only every shed_ranging_every-th frame above this ring fill"})
    shed_images_fill: float = field(default=0.35, metadata={"lo": 0, "hi": 1, "doc": "overload level 3: shed Rerun images above this ring fill (then the ring drops its oldest pairs)"})
    shed_ranging_every: int = field(default=4, metadata={"lo": 2, "hi": 1000, "doc": "frames between ranged frames at overload level 2"})
    restart_backoff_s: float = field(default=1.0, metadata={"lo": 0, "doc": "wait before restarting a dead acquisition"})
    stop_drain_s: float = field(default=0.3, metadata={"lo": 0, "hi": 60, "doc": "at the end of a run (--duration, SIGTERM), decode what the ring still holds for at most this long; the pairs left then are dropped (counted: stop_dropped, in frames_dropped) rather than overrun the end"})
    stop_demod_s: float = field(default=1.0, metadata={"lo": 0, "hi": 60, "doc": "at the end of a run, wait at most this long for the demodulation steps in flight (then the packets in progress are abandoned, counted: stop_demod_abandoned)"})
    start_timeout_s: float = field(default=30.0, metadata={"lo": 0, "doc": "--duration counts from when the acquisition runs (cameras up); if it has not started within this long, from then"})



class _UnpairedWatch:
    """Says, once a stats interval while it lasts, that pairing fails: more than
    :attr:`SHARE` of the frames that came in since the last stats record found no partner
    (free-running cameras, a trigger cable off, ids or clocks that do not match)."""

    SHARE = 0.05

    def __init__(self) -> None:
        self._in = 0
        self._unpaired = 0

    def check(self, rec: dict[str, Any]) -> bool:
        a = rec.get("acquisition") or {}
        unpaired = int(a.get("unpaired_left", 0)) + int(a.get("unpaired_right", 0))
        frames_in = int(rec.get("frames_in", 0))
        d_in, d_un = frames_in - self._in, unpaired - self._unpaired
        self._in, self._unpaired = frames_in, unpaired
        if d_in > 0 and d_un > self.SHARE * d_in:
            log.warning("pairing fails: %d of %d frames since the last stats record had no partner "
                        "(cameras not triggered together? ids or clocks that do not match?)", d_un, d_in)
            return True
        return False


class Daemon:
    """One run of the daemon (see module docstring)."""

    def __init__(self, cfg: Config, *, out: str | None = None, duration_s: float | None = None,
                 rerun: dict[str, Any] | None = None, socket: str | None = None,
                 calibration: str | None = None, install_signals: bool = True) -> None:
        self.cfg = cfg
        self.settings: DaemonSettings = section(cfg, DaemonSettings)
        from iscd.rig.acquisition import AcquisitionOptions
        from iscd.service.overload import OverloadSettings

        self.acquisition_options: AcquisitionOptions = section(cfg, AcquisitionOptions)
        """The ``[acquisition]`` table, handed to every acquisition process this run starts."""

        st = self.settings
        try:
            self.overload_settings = OverloadSettings(
                led_fill=st.shed_led_fill, ranging_fill=st.shed_ranging_fill, images_fill=st.shed_images_fill,
                ranging_every=st.shed_ranging_every)
        except ValueError:
            raise ConfigError(f"daemon.shed_led_fill <= daemon.shed_ranging_fill <= daemon.shed_images_fill "
                              f"expected, got {st.shed_led_fill}, {st.shed_ranging_fill}, {st.shed_images_fill}") from None
        self.out_path = out or self.settings.out or None
        self.duration_s = duration_s
        self.rerun_opts = rerun
        self.socket_endpoint = socket if socket is not None else (self.settings.socket or None)
        self.calibration_path = calibration or self.settings.calibration or None
        self.install_signals = install_signals
        self._stop = False
        self.final_stats: dict[str, Any] | None = None
        self.records_written = 0
        self.extra_outputs: list[Any] = []

    def request_stop(self, signum: object = None, *_: object) -> None:
        """Stop after the frames in hand (SIGTERM/SIGINT handler; also callable)."""
        if isinstance(signum, int) and not self._stop:
            log.info("%s: stopping (the final records follow)", signal.Signals(signum).name)
        self._stop = True

    # ------------------------------------------------------------------ helpers
    def _outputs(self) -> list[Any]:
        outs: list[Any] = list(self.extra_outputs)
        from iscd.outputs import output_config

        oc = output_config(self.cfg)
        if self.out_path:
            from iscd.outputs.jsonl import JsonlWriter

            Path(self.out_path).parent.mkdir(parents=True, exist_ok=True)
            outs.append(JsonlWriter(self.out_path, rotate_bytes=int(self.settings.rotate_mb * 2**20),
                                    keep=oc.keep, flush_interval_s=oc.flush_interval_s,
                                    fsync_interval_s=oc.fsync_interval_s))
        if self.socket_endpoint:
            from iscd.outputs.socket import ZmqPublisher

            outs.append(ZmqPublisher(self.socket_endpoint, hwm=oc.zmq_hwm, allow_remote=oc.zmq_allow_remote))
        return outs

    def _rerun(self, n_leds: int) -> Any:
        from types import SimpleNamespace

        from iscd.outputs import rerun_config
        from iscd.outputs.rerun_view import rerun_view_from

        rc = rerun_config(self.cfg)
        opts = self.rerun_opts or {}
        if not opts and not (rc.connect or rc.serve or rc.save):
            return None
        t = self.cfg.transmitter
        return rerun_view_from(SimpleNamespace(**opts), rc, fps=self.cfg.camera.fps,
                               frames_per_symbol=self.cfg.camera.fps / t.symbol_rate_hz, n_leds=n_leds)

    # ------------------------------------------------------------------ main loop
    def run(self) -> dict[str, Any]:
        """Run until the duration elapses or a stop is requested; returns the final stats."""
        from iscd.calibration.io import load_calibration
        from iscd.drivers.registry import make_stereo, settings_from_config
        from iscd.rig.acquisition import AcquisitionProcess, AcquisitionStats
        from iscd.service.notify import Notifier
        from iscd.service.overload import OverloadPolicy
        from iscd.decode.stream import StreamDecoder
        from iscd.rig.ringbuffer import StereoRing, capacity_for
        from iscd.service.stats import CpuMeter, LatencyWindow

        cfg, st = self.cfg, self.settings
        cal = load_calibration(self.calibration_path) if self.calibration_path else None
        # packets are demodulated in a worker process: no GIL shared with the frame loop
        decoder = StreamDecoder(cfg, cal, async_demod="process")
        H, W = cfg.camera.height, cfg.camera.width
        dtype = np.uint8 if cfg.camera.bit_depth == 8 else np.uint16
        ring = StereoRing.create(height=H, width=W, capacity=capacity_for(st.ring_ms, cfg.camera.fps), dtype=dtype,
                                 max_held=st.block_max)  # a block's pairs are taken at once
        factory = functools.partial(make_stereo, cfg)
        cam_settings = (settings_from_config(cfg, "left"), settings_from_config(cfg, "right"))
        acq = AcquisitionProcess(factory, ring, settings=cam_settings, options=self.acquisition_options)
        from iscd.outputs import Outputs

        view = self._rerun(decoder.air.n_leds)  # also drawn on directly: images, luminance
        outputs = Outputs([*self._outputs(), *([view] if view is not None else [])])
        notifier = Notifier.from_env()
        old_handlers = {}
        if self.install_signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                old_handlers[sig] = signal.signal(sig, self.request_stop)
        overload = OverloadPolicy(self.overload_settings)
        lat = LatencyWindow()
        wake = LatencyWindow(cap=2000)
        work = LatencyWindow(cap=2000)
        cpu = CpuMeter()
        B = st.block_max
        blk_l = np.zeros((B, H, W), dtype)
        blk_r = np.zeros((B, H, W), dtype)
        ids = np.zeros(B, np.int64)
        t_s = np.zeros(B, np.float64)
        arrival = np.zeros(B, np.int64)
        fps = cfg.camera.fps
        unpaired_watch = _UnpairedWatch()
        counters = {"pairs_decoded": 0, "pair_gaps": 0, "decode_errors": 0, "acquisition_restarts": 0,
                    "stop_dropped": 0, "stop_demod_abandoned": 0}
        # the compiled kernels are loaded from the cache (or compiled) before the cameras
        # start and before READY=1: the first frames are not spent compiling
        from iscd.core.jit import CACHE_DIR, warm_up

        notifier.status("loading compiled kernels")
        log.info("loading the compiled kernels (the first start after an install compiles them: "
                 "about a minute on 2 cores; later starts load them in under a second)")
        t_warm = warm_up()
        if not decoder.wait_ready(timeout_s=300.0):
            log.warning("the demodulation worker is not ready yet; starting anyway")
        log.info("compiled kernels ready in %.2f s (%s)", t_warm,
                 f"cache {CACHE_DIR}" if CACHE_DIR is not None else "no cache: they compile at every start")
        t_start = time.monotonic()
        next_stats = t_start + st.stats_interval_s
        # --duration counts from when the acquisition runs (its cameras opened and started),
        # not from the process start: the start-up (spawning the worker, the scene or the
        # cameras) is not part of the run. Set at the first sign of it (see acq_running).
        t_acq: float | None = None
        deadline: float | None = None
        t_spawn = time.monotonic()
        last_frame = -1
        last_t_s: float | None = None
        acq.start()
        notifier.ready(status="acquiring")
        log.info("daemon started: backend %s, %dx%d @ %g fps, ring %d pairs", cfg.rig.scheme, W, H, fps,
                 ring.capacity)

        def emit(records: list[dict]) -> None:
            for r in records:
                outputs.write(r)  # never raises: an output must never stop decoding
            self.records_written += len(records)

        def acq_running(now: float, a: Any = None) -> None:
            """Start the run's clock (t_acq, deadline) once the acquisition runs."""
            nonlocal t_acq, deadline
            if t_acq is not None:
                return
            if a is None:
                a = acq.stats()
            if (a.state != AcquisitionStats.STARTING or a.pairs_written > 0 or not acq.is_alive()
                    or now - t_spawn >= st.start_timeout_s):
                t_acq = now
                if self.duration_s:
                    deadline = now + self.duration_s
                log.info("acquisition running (%.2f s after its start)%s", now - t_spawn,
                         f"; the run ends in {self.duration_s:g} s" if self.duration_s else "")

        min_fps = 2 * cfg.transmitter.symbol_rate_hz  # iscd.core.config's check of camera.fps
        fps_state: dict[str, Any] = {"checked": {}, "error": None, "mismatch": False}

        def check_device_fps(a: Any) -> str | None:
            """The config's check (at least 2 frames per symbol) on the frame rate each camera
            reports after configuring (a device clamps what it cannot do: viky.cti runs 1000
            fps as 200). Returns the error line when it fails; a rate that passes but differs
            from camera.fps by more than 1 % is warned about once and flagged in the stats."""
            for side in ("left", "right"):
                mhz = int(getattr(a, f"fps_mhz_{side}", 0))
                if mhz <= 0 or fps_state["checked"].get(side) == mhz:
                    continue
                fps_state["checked"][side] = mhz
                got = mhz / 1000
                if got < min_fps * 0.999:
                    fps_state["error"] = (
                        f"the {side} camera runs at {got:g} frames/s after configuring (camera.fps = "
                        f"{fps:g} was asked; the device cannot do it): below 2 frames per symbol "
                        f"(transmitter.symbol_rate_hz = {cfg.transmitter.symbol_rate_hz:g} needs >= "
                        f"{min_fps:g} frames/s); symbols could not be decoded. Lower camera.fps and "
                        f"transmitter.symbol_rate_hz to what the camera can do")
                    return fps_state["error"]
                if abs(got - fps) > 0.01 * fps:
                    fps_state["mismatch"] = True
                    log.warning("the %s camera runs at %g frames/s, not camera.fps = %g: the decoder "
                                "counts frames per symbol from camera.fps; set it to %g", side, got, fps, got)
            return None

        def stats_record(final: bool) -> dict[str, Any]:
            a = acq.stats()
            rs = ring.stats()
            p50, p99 = lat.take()
            workers = decoder.worker_pids
            share, rss = cpu.sample([os.getpid()] + ([acq.pid] if acq.pid else []) + workers)
            by_process = {"frame_loop": cpu.shares.get(os.getpid()),
                          "acquisition": cpu.shares.get(acq.pid) if acq.pid else None,
                          "demod_worker": (round(sum(cpu.shares.get(p, 0.0) for p in workers), 3)
                                           if any(p in cpu.shares for p in workers) else None)}
            rec = {"uptime_s": round(time.monotonic() - t_start, 3), "final": final,
                   # seconds since the acquisition started running (what --duration counts)
                   "acquiring_s": round(time.monotonic() - t_acq, 3) if t_acq is not None else 0.0,
                   "frames_in": int(a.frames_left + a.frames_right),
                   # triggers that never reached the decoder as a pair, whatever the cause
                   # (camera buffer, unpaired, ring overflow); the parts follow
                   # (frame ids no pair reached the decoder with; frames left without a
                   # partner count too, two to an id, when pairing itself fails: cameras
                   # that are not triggered together give no ids to miss)
                   # (and the pairs left in the ring when a run had to end on time)
                   "frames_dropped": (max(counters["pair_gaps"], (int(a.frames_dropped) + 1) // 2)
                                      + counters["stop_dropped"]),
                   "unpaired_or_bad": int(a.frames_dropped),
                   "ring_dropped": int(rs.dropped_overflow), "ring_fill": int(rs.queued),
                   "ring_capacity": int(ring.capacity),
                   "pairs_decoded": counters["pairs_decoded"],
                   "packets_ok": decoder.counters["packets_ok"], "packets_bad": decoder.counters["packets_bad"],
                   "ranges": decoder.counters["ranges"], "ranging_skipped": decoder.counters["ranging_skipped"],
                   "led_ranges_shed": decoder.counters["led_ranges_shed"], **overload.counters,
                   "following_resets": decoder.counters.get("following_resets", 0),
                   "tracking": decoder.track is not None,
                   "latency_ms_p50": p50, "latency_ms_p99": p99,
                   # per block: its last pair's arrival to the block read, and the decoding
                   # (outputs excluded); the rest of a pair's latency is the block filling
                   "block_read_ms_p50_p99": wake.take(), "block_decode_ms_p50_p99": work.take(),
                   "cpu_cores": share, "cpu_cores_by_process": by_process, "rss_mb": round(rss / 2**20, 1),
                   "pair_gaps": counters["pair_gaps"],
                   "acquisition": a.as_dict(), "acquisition_restarts": counters["acquisition_restarts"],
                   "decode_errors": counters["decode_errors"],
                   "stop_dropped": counters["stop_dropped"], "stop_demod_abandoned": counters["stop_demod_abandoned"],
                   # the frame rate the cameras report (after the device's own clamping)
                   "device_fps": [a.fps_mhz_left / 1000 or None, a.fps_mhz_right / 1000 or None],
                   "device_fps_mismatch": fps_state["mismatch"],
                   "demod_worker_restarts": decoder.counters.get("demod_worker_restarts", 0)}
            rec.update(outputs.counters())  # output_errors and each output's own counters
            spec = {k: rec.pop(k) for k in StatsRecord.spec_fields()}
            # t_s: camera time of the last decoded frame, as in the other records
            return StatsRecord(tx=0, frame=int(last_frame), t_s=last_t_s, **spec, extra=rec).to_json()

        def discard_ring() -> int:
            """Take and drop what the ring still holds (the end of a run that is behind);
            counted in ``stop_dropped``. Returns how many pairs."""
            n_drop = 0
            while True:
                slots = ring.read_batch(max(B, 64), timeout_s=0.0)
                if not slots:
                    break
                n_drop += len(slots)
                ring.release_batch(slots)
            counters["stop_dropped"] += n_drop
            return n_drop

        def finish_decoder() -> list[dict]:
            """decoder.finish(), but without waiting on a demodulation backlog for more than
            stop_demod_s: steps still in flight then are abandoned (counted)."""
            out, abandoned = decoder.finish_within(st.stop_demod_s)
            if abandoned:
                counters["stop_demod_abandoned"] += abandoned
                log.warning("the run ends on time: %d demodulation steps still in flight are "
                            "abandoned (a packet in progress may be lost)", abandoned)
            return out

        _prof = None
        if os.environ.get("ISCD_PROFILE"):  # cProfile of the frame loop, written at the end
            import cProfile

            _prof = cProfile.Profile(time.process_time)  # CPU time: what the loop costs, not its waits
            _prof.enable()
        try:
            draining = False
            while True:
                now = time.monotonic()
                if t_acq is None:
                    acq_running(now)
                if len(fps_state["checked"]) < 2 or now >= next_stats:
                    if check_device_fps(acq.stats()) is not None:
                        # one line, from the caller (iscd run: "iscd run: error: ..."; exit 2)
                        acq.request_stop()
                        discard_ring()
                        break
                if not draining and (self._stop or (deadline is not None and now >= deadline)):
                    # stop the cameras first, then decode what the ring still holds, for at
                    # most stop_drain_s: a run that is behind drops (counted) the rest
                    # instead of ending late by the backlog
                    acq.request_stop()  # joined in the finally clause
                    draining = True
                    drain_until = now + st.stop_drain_s
                if draining and now > drain_until:
                    left_over = discard_ring()
                    if left_over:
                        log.warning("the run ends on time: %d pairs still in the ring are dropped "
                                    "(the decoder was behind)", left_over)
                    break
                if now >= next_stats:
                    rec = stats_record(False)
                    emit([rec])
                    unpaired_watch.check(rec)
                    notifier.status(f"pairs {rec['pairs_decoded']} packets ok {rec['packets_ok']} "
                                    f"bad {rec['packets_bad']} dropped {rec['frames_dropped']}")
                    next_stats += st.stats_interval_s
                    if next_stats < now:
                        next_stats = now + st.stats_interval_s
                notifier.watchdog()
                if not draining and not acq.is_alive():
                    log.error("acquisition process died (exit code %s); restarting", acq.exitcode)
                    counters["acquisition_restarts"] += 1
                    time.sleep(st.restart_backoff_s)
                    acq = AcquisitionProcess(factory, ring, settings=cam_settings, options=self.acquisition_options)
                    acq.start()
                    continue
                # ---- take up to B pairs, waiting at most block_wait_ms for the block to fill
                n = 0
                windows = decoder.needed_windows()
                t_fill = time.monotonic() + st.block_wait_ms / 1000
                if not draining:
                    # sleep until the block is about due instead of waking for every pair
                    # (a thousand wake-ups a second cost a tenth of a core)
                    missing = B - ring.queued
                    if missing > 1:
                        time.sleep(min(st.block_wait_ms / 1000, (missing - 1) / fps))
                while n < B:
                    timeout = max(0.0, t_fill - time.monotonic()) if n else 0.05
                    # every pair already queued in one go (one lock to take them, one to
                    # give them back: not four lock operations a pair)
                    slots = ring.read_batch(B - n, timeout_s=timeout)
                    if not slots:
                        break
                    try:
                        for slot in slots:
                            if windows is None:
                                blk_l[n] = slot.left
                                blk_r[n] = slot.right
                            else:
                                (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = windows
                                blk_l[n, ay0:ay1, ax0:ax1] = slot.left[ay0:ay1, ax0:ax1]
                                blk_r[n, by0:by1, bx0:bx1] = slot.right[by0:by1, bx0:bx1]
                            ids[n] = slot.frame_id
                            t_s[n] = slot.ts_left_ns * 1e-9 if slot.ts_left_ns else slot.frame_id / fps
                            arrival[n] = slot.arrival_ns
                            n += 1
                    finally:
                        ring.release_batch(slots)
                    if time.monotonic() >= t_fill:
                        break
                if n == 0:
                    if ring.finished or (draining and (not acq.is_alive() or now > drain_until)):
                        if draining and not ring.finished:
                            discard_ring()
                        break
                    continue
                t_read_ns = time.monotonic_ns()
                if t_acq is None:
                    acq_running(time.monotonic())
                prev = last_frame if last_frame >= 0 else int(ids[0]) - 1
                steps = np.diff(np.concatenate([[prev], ids[:n]]))
                counters["pair_gaps"] += int(np.clip(steps - 1, 0, None).sum())
                # falling behind: shed work in the policy's order so that no packet is lost
                svc = overload.service(ring.stats().queued / ring.capacity)
                try:
                    # the block's ranges first; its demodulation hand-off and tracking update
                    # after they are out (finish_block below)
                    records = decoder.push(ids[:n].copy(), t_s[:n].copy(), blk_l[:n], blk_r[:n],
                                           ranging_every=svc.ranging_every, per_led=svc.per_led, defer=True)
                except Exception:  # a decoder bug on odd frames must not stop the service
                    counters["decode_errors"] += 1
                    log.exception("decoding frames %d..%d failed; the decoder restarts acquisition",
                                  int(ids[0]), int(ids[n - 1]))
                    decoder.restart()
                    records = []
                done_ns = time.monotonic_ns()
                counters["pairs_decoded"] += n
                last_frame = int(ids[n - 1])
                last_t_s = float(t_s[n - 1])
                lat.add((done_ns - arrival[:n]) / 1e6)
                # where a block's latency goes: waiting for its last pair, then decoding it
                wake.add(np.array([(t_read_ns - arrival[n - 1]) / 1e6]))
                work.add(np.array([(done_ns - t_read_ns) / 1e6]))
                emit(records)
                try:
                    emit(decoder.finish_block())  # packets that came back; the blocks still in the buffers
                except Exception:  # as a failed push
                    counters["decode_errors"] += 1
                    log.exception("finishing frames %d..%d failed; the decoder restarts acquisition",
                                  int(ids[0]), int(ids[n - 1]))
                    decoder.restart()
                if view is not None and decoder.last_luminance is not None and svc.images:
                    li, lt, ll, lr = decoder.last_luminance
                    view.log_luminance(li, lt, ll, lr)
                    decoder.last_luminance = None
                if view is not None and view.want_image(last_frame) and not svc.images:
                    overload.shed_images()
                elif view is not None and view.want_image(last_frame):
                    tr = decoder.track
                    boxes_l = boxes_r = None
                    if tr is not None:
                        boxes_l = np.array([tr.left.bbox(2)], float)
                        boxes_r = np.array([tr.right.bbox(2)], float)
                    view.log_images(last_frame, float(t_s[n - 1]), blk_l[n - 1], blk_r[n - 1], boxes_l, boxes_r)
            if _prof is not None:
                _prof.disable()
                _prof.dump_stats(os.environ["ISCD_PROFILE"])
            records = finish_decoder()
            emit(records)
            final = stats_record(True)
            if fps_state["error"]:
                final["error"] = fps_state["error"]
            emit([final])
            self.final_stats = final
            if final.get("jsonl_io_dropped"):  # the file lacks them, maybe this record too: say it here
                log.warning("jsonl output: %d of %d records could not be written (disk full or I/O errors)",
                            final["jsonl_io_dropped"], final.get("jsonl_records", 0))
            if fps_state["error"]:
                notifier.stopping(status="stopped: " + fps_state["error"][:200])
                raise ConfigError(fps_state["error"])
            notifier.stopping(status="stopped")
            return final
        finally:
            decoder.close()  # no demodulation worker outlives the daemon (after finish: a no-op)
            try:
                acq.stop()
            except Exception as e:  # pragma: no cover - best effort on the way out
                log.error("stopping acquisition: %s", e)
            outputs.close()  # the Rerun view among them
            ring.close()
            notifier.close()
            for sig, h in old_handlers.items():
                signal.signal(sig, h)
