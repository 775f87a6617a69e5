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
import math
import os
import signal
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
    """The daemon: ring, blocks, outputs, control socket, overload shedding, the end of a run (docs/realtime.md)."""

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
    control: str = field(default="", metadata={"doc": "ZeroMQ REP endpoint for commands from other in-car software (iscd.service.control: blackbox, ping), e.g. tcp://127.0.0.1:5557 ('' = off; --control)"})
    start_timeout_s: float = field(default=30.0, metadata={"lo": 0, "doc": "--duration counts from when the acquisition runs (cameras up); if it has not started within this long, from then"})



def _mock_waits(cfg: Config) -> bool:
    from iscd.drivers.mock import waits_for_consumer  # the mock rig's module only for a mock rig

    return waits_for_consumer(cfg)


LOSSLESS_STEPS = 32
"""Demodulation steps the frame loop may run ahead of the worker with a source that waits
for the consumer (``_Run.lossless``)."""


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
                 calibration: str | None = None, install_signals: bool = True,
                 control: str | None = None) -> None:
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
        self.control_endpoint = control if control is not None else (self.settings.control or None)
        self._stop = False
        self.final_stats: dict[str, Any] | None = None
        self.records_written = 0
        self.extra_outputs: list[Any] = []

    def stop_requested(self) -> bool:
        """Whether a stop was requested (:meth:`request_stop`)."""
        return self._stop

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
        """Run until the duration elapses or a stop is requested; returns the final stats.

        The order of a run: the parts built (:class:`_Run`), the compiled kernels loaded,
        the acquisition started and READY=1, then blocks of pairs decoded until the end
        (:meth:`_loop`), what the decoder still holds, the final stats record."""
        old_handlers = {}
        if self.install_signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                old_handlers[sig] = signal.signal(sig, self.request_stop)
        run: _Run | None = None
        try:
            run = _Run(self)
            if self.install_signals and run.recorder is not None:  # SIGUSR1: the blackbox trigger
                old_handlers[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, run.recorder.on_signal)
            run.warm_up()
            if self._stop:  # stopped while the kernels were loading: the cameras never start
                return run.finish()
            run.start()
            _prof = None
            if os.environ.get("ISCD_PROFILE"):  # cProfile of the frame loop, written at the end
                import cProfile

                # this thread's CPU time: what the loop costs, not its waits nor the other threads'
                _prof = cProfile.Profile(time.thread_time)
                _prof.enable()
            self._loop(run)
            if _prof is not None:
                _prof.disable()
                _prof.dump_stats(os.environ["ISCD_PROFILE"])
            return run.finish()
        finally:
            if run is not None:
                run.close()
            for sig, h in old_handlers.items():
                signal.signal(sig, h)

    def _loop(self, run: "_Run") -> None:
        """Blocks of pairs from the ring to the outputs until the run ends: the duration
        elapsed or a stop requested (then what the ring holds is decoded for at most
        ``stop_drain_s``), the cameras' rate refused, or the ring finished."""
        st = self.settings
        draining = False
        drain_until = math.inf
        while True:
            now = time.monotonic()
            run.acq_running(now)
            if run.fps_unchecked() or now >= run.next_stats:
                if run.check_device_fps(run.acq.stats()) is not None:
                    # one line, from the caller (iscd run: "iscd run: error: ..."; exit 2)
                    run.acq.request_stop()
                    run.discard_ring()
                    return
            if not draining and (self._stop or (run.deadline is not None and now >= run.deadline)):
                # stop the cameras first, then decode what the ring still holds, for at
                # most stop_drain_s: a run that is behind drops (counted) the rest
                # instead of ending late by the backlog
                run.acq.request_stop()  # joined when the run closes
                draining = True
                drain_until = now + st.stop_drain_s
            if draining and now > drain_until:
                left_over = run.discard_ring()
                if left_over:
                    log.warning("the run ends on time: %d pairs still in the ring are dropped "
                                "(the decoder was behind)", left_over)
                return
            if now >= run.next_stats:
                run.periodic_stats(now)
            run.notifier.watchdog()
            if run.control is not None:
                run.control.poll()  # one command at most, never waits
            if not draining and not run.acq.is_alive():
                run.restart_acquisition()
                continue
            n = run.blocks.read(run.decoder.needed_windows(), pace=not draining, on_part=run.range_part)
            if n == 0:
                if run.ring.finished or (draining and (not run.acq.is_alive() or now > drain_until)):
                    if draining and not run.ring.finished:
                        run.discard_ring()
                    return
                continue
            run.decode_block(n)


class _Run:
    """One run's parts and state: the decoder, the ring and its block reader, the
    acquisition process, the outputs (the Rerun view among them), sd_notify, the overload
    policy, the latency and CPU meters, the counters. Built in this order; :meth:`close`
    closes what was built, whatever failed."""

    def __init__(self, daemon: Daemon) -> None:
        from iscd.service.overload import OverloadPolicy
        from iscd.service.stats import CpuMeter, LatencyHistogram, LatencyWindow

        self.daemon = daemon
        cfg, st = daemon.cfg, daemon.settings
        self.cfg, self.st = cfg, st
        self.decoder: Any = None
        self.ring: Any = None
        self.acq: Any = None
        self.outputs: Any = None
        self.notifier: Any = None
        self.recorder: Any = None
        self.control: Any = None
        try:
            self._build()
        except BaseException:
            self.close()  # what was built before the failure
            raise
        self.overload = OverloadPolicy(daemon.overload_settings)
        self.lat = LatencyWindow()
        self.lat_run = LatencyHistogram()
        """every pair's latency since the run started (the stats' latency_run_ms_*)"""
        self.wake = LatencyWindow(cap=2000)
        self.work = LatencyWindow(cap=2000)
        self.cpu = CpuMeter()
        self.unpaired_watch = _UnpairedWatch()
        self.counters = {"pairs_decoded": 0, "pair_gaps": 0, "decode_errors": 0, "acquisition_restarts": 0,
                         "stop_dropped": 0, "stop_demod_abandoned": 0, "pairs_ranged_ahead": 0}
        self.min_fps = 2 * cfg.transmitter.symbol_rate_hz  # iscd.core.config's check of camera.fps
        self.fps_checked: dict[str, int] = {}
        self.fps_error: str | None = None
        self.fps_mismatch = False
        self.last_frame = -1
        self.svc: Any = None
        """the overload policy's service for the block being read (chosen at its first part)"""
        self.ahead = 0
        """pairs of the block being read whose range records are already out (range_part)"""
        self.last_t_s: float | None = None
        self.lossless = cfg.rig.scheme == "mock" and _mock_waits(cfg)
        """the unpaced mock rig: it waits for the consumer (the acquisition waits for room in
        the ring, this loop for the demodulation worker), so no frame is dropped however busy
        the machine is (tests, a laptop); overload shedding does not apply"""
        self.t_start = self.next_stats = self.t_spawn = time.monotonic()
        # --duration counts from when the acquisition runs (its cameras opened and started),
        # not from the process start: the start-up (spawning the worker, the scene or the
        # cameras) is not part of the run. Set at the first sign of it (acq_running).
        self.t_acq: float | None = None
        self.deadline: float | None = None

    def _build(self) -> None:
        """The parts that hold resources (processes, shared memory, files, sockets)."""
        from iscd.calibration.io import load_calibration
        from iscd.decode.multi import make_decoder
        from iscd.drivers.registry import make_stereo, settings_from_config
        from iscd.outputs import Outputs
        from iscd.rig.acquisition import AcquisitionProcess
        from iscd.rig.ringbuffer import StereoRing, capacity_for
        from iscd.service.blocks import BlockReader
        from iscd.service.notify import Notifier

        daemon, cfg, st = self.daemon, self.cfg, self.st
        cal = load_calibration(daemon.calibration_path) if daemon.calibration_path else None
        # packets are demodulated in a worker process: no GIL shared with the frame loop
        self.decoder = make_decoder(cfg, cal, async_demod="process")
        H, W = cfg.camera.height, cfg.camera.width
        dtype = np.uint8 if cfg.camera.bit_depth == 8 else np.uint16
        from iscd.rig.ringbuffer import reclaim_stale_rings

        for name in reclaim_stale_rings():  # the ring of a daemon killed with its resource tracker
            log.warning("removed /dev/shm/%s: the ring of an iscd process that is gone", name)
        self.ring = StereoRing.create(height=H, width=W, capacity=capacity_for(st.ring_ms, cfg.camera.fps),
                                      dtype=dtype, max_held=st.block_max)  # a block's pairs are taken at once
        self.fps = cfg.camera.fps
        # whole-frame blocks a searcher keeps (its look-back) made and touched now, not
        # while the first frames wait (several transmitters: hundreds of frames)
        kept = int(self.decoder.lookback_frames)
        self.blocks = BlockReader(self.ring, H, W, dtype, st.block_max, self.fps, st.block_wait_ms / 1000,
                                  pool_blocks=-(-kept // st.block_max) + 3)
        self.decoder.prepare(H, W, dtype)  # its look buffers, touched now too
        self._factory = functools.partial(make_stereo, cfg)
        self._cam_settings = (settings_from_config(cfg, "left"), settings_from_config(cfg, "right"))
        self._new_acquisition = functools.partial(AcquisitionProcess, self._factory, self.ring,
                                                  settings=self._cam_settings, options=daemon.acquisition_options)
        self.acq = self._new_acquisition()
        self.view = daemon._rerun(self.decoder.air.n_leds)  # also drawn on directly: images, luminance
        self.outputs = Outputs([*daemon._outputs(), *([self.view] if self.view is not None else [])])
        self.notifier = Notifier.from_env()
        from iscd.service.recording import live_recording

        self.recorder = live_recording(cfg, daemon.calibration_path, lambda: self.decoder.counters.get("losses", 0),
                                       st.block_max)
        self.blocks.tap = self.recorder  # [record]: every pair taken, before its slot goes back
        if daemon.control_endpoint:
            from iscd.outputs import output_config
            from iscd.service.control import ControlSocket

            self.control = ControlSocket(daemon.control_endpoint, {b"blackbox": self._blackbox_command},
                                         allow_remote=output_config(cfg).zmq_allow_remote)
            log.info("control socket on %s (commands: blackbox, ping)", self.control.endpoint)

    def _blackbox_command(self) -> str:
        """The control socket's ``blackbox``: trigger the blackbox recording."""
        if self.recorder is None:
            raise RuntimeError("no recording in this run (iscd run --record DIR --record-mode blackbox)")
        mode = self.recorder.recorder.mode
        if mode != "blackbox":
            raise RuntimeError(f"the recording is in {mode} mode, not blackbox (--record-mode blackbox)")
        self.recorder.trigger("control command")
        return "ok"

    # ------------------------------------------------------------------ start and end
    def warm_up(self) -> None:
        """The compiled kernels loaded from the cache (or compiled) before the cameras start
        and before READY=1: the first frames are not spent compiling."""
        from iscd.core.jit import CACHE_DIR, warm_up

        self.notifier.status("loading compiled kernels")
        log.info("loading the compiled kernels (the first start after an install compiles them: "
                 "about three minutes on 2 cores; later starts load them in under a second)")
        stopping = self.daemon.stop_requested
        t_warm = warm_up(should_stop=stopping)
        if stopping():
            log.info("stopped while the compiled kernels were loading (%.1f s)", t_warm)
            return
        if not self.decoder.wait_ready(timeout_s=300.0, should_stop=stopping) and not stopping():
            log.warning("the demodulation worker is not ready yet; starting anyway")
        log.info("compiled kernels ready in %.2f s (%s)", t_warm,
                 f"cache {CACHE_DIR}" if CACHE_DIR is not None else "no cache: they compile at every start")

    def start(self) -> None:
        """The acquisition started, READY=1 sent."""
        self.t_start = time.monotonic()
        self.next_stats = self.t_start + self.st.stats_interval_s
        self.t_spawn = time.monotonic()
        self.acq.start()
        self.notifier.ready(status="acquiring")
        log.info("daemon started: backend %s, %dx%d @ %g fps, ring %d pairs", self.cfg.rig.scheme,
                 self.cfg.camera.width, self.cfg.camera.height, self.fps, self.ring.capacity)

    def finish(self) -> dict[str, Any]:
        """The end of a run: what the decoder still holds, the final stats record (with the
        cameras' rate error, raised as ConfigError after it is written)."""
        self.emit(self.finish_decoder())
        if self.recorder is not None:
            self.recorder.drain()  # what is queued written: the final stats count it
        final = self.stats_record(True)
        if self.fps_error:
            final["error"] = self.fps_error
        self.emit([final])
        self.daemon.final_stats = final
        if final.get("jsonl_io_dropped"):  # the file lacks them, maybe this record too: say it here
            log.warning("jsonl output: %d of %d records could not be written (disk full or I/O errors)",
                        final["jsonl_io_dropped"], final.get("jsonl_records", 0))
        if self.fps_error:
            self.notifier.stopping(status="stopped: " + self.fps_error[:200])
            raise ConfigError(self.fps_error)
        self.notifier.stopping(status="stopped")
        return final

    def close(self) -> None:
        """Close what was built: no demodulation worker or acquisition process outlives the
        daemon, the outputs flushed (the Rerun view among them), the ring unlinked."""
        if self.decoder is not None:
            self.decoder.close()  # (after finish: a no-op)
        if self.acq is not None:
            try:
                self.acq.stop()
            except Exception as e:  # pragma: no cover - best effort on the way out
                log.error("stopping acquisition: %s", e)
        if self.outputs is not None:
            self.outputs.close()
        if self.recorder is not None:
            self.recorder.close()
        if self.control is not None:
            self.control.close()
        if self.ring is not None:
            self.ring.close()
        if self.notifier is not None:
            self.notifier.close()

    # ------------------------------------------------------------------ the acquisition
    def acq_running(self, now: float, a: Any = None) -> None:
        """Start the run's clock (t_acq, deadline) once the acquisition runs."""
        if self.t_acq is not None:
            return
        if a is None:
            a = self.acq.stats()
        from iscd.rig.acquisition import AcquisitionStats

        if (a.state != AcquisitionStats.STARTING or a.pairs_written > 0 or not self.acq.is_alive()
                or now - self.t_spawn >= self.st.start_timeout_s):
            self.t_acq = now
            duration = self.daemon.duration_s
            if duration:
                self.deadline = now + duration
            log.info("acquisition running (%.2f s after its start)%s", now - self.t_spawn,
                     f"; the run ends in {duration:g} s" if duration else "")

    def restart_acquisition(self) -> None:
        """A dead acquisition process replaced (after ``restart_backoff_s``), counted."""
        log.error("acquisition process died (exit code %s); restarting", self.acq.exitcode)
        self.counters["acquisition_restarts"] += 1
        time.sleep(self.st.restart_backoff_s)
        self.acq = self._new_acquisition()
        self.acq.start()

    def fps_unchecked(self) -> bool:
        """Not both cameras' reported frame rates checked yet."""
        return len(self.fps_checked) < 2

    def check_device_fps(self, a: Any) -> str | None:
        """The config's check (at least 2 frames per symbol) on the frame rate each camera
        reports after configuring (a device clamps what it cannot do: viky.cti runs 1000
        fps as 200). Returns the error line when it fails; a rate that passes but differs
        from camera.fps by more than 1 % is warned about once and flagged in the stats."""
        fps = self.fps
        for side in ("left", "right"):
            mhz = int(getattr(a, f"fps_mhz_{side}", 0))
            if mhz <= 0 or self.fps_checked.get(side) == mhz:
                continue
            self.fps_checked[side] = mhz
            got = mhz / 1000
            if got < self.min_fps * 0.999:
                self.fps_error = (
                    f"the {side} camera runs at {got:g} frames/s after configuring (camera.fps = "
                    f"{fps:g} was asked; the device cannot do it): below 2 frames per symbol "
                    f"(transmitter.symbol_rate_hz = {self.cfg.transmitter.symbol_rate_hz:g} needs >= "
                    f"{self.min_fps:g} frames/s); symbols could not be decoded. Lower camera.fps and "
                    f"transmitter.symbol_rate_hz to what the camera can do")
                return self.fps_error
            if abs(got - fps) > 0.01 * fps:
                self.fps_mismatch = True
                log.warning("the %s camera runs at %g frames/s, not camera.fps = %g: the decoder "
                            "counts frames per symbol from camera.fps; set it to %g", side, got, fps, got)
        return None

    def discard_ring(self) -> int:
        """Take and drop what the ring still holds (the end of a run that is behind);
        counted in ``stop_dropped``. Returns how many pairs."""
        n_drop = self.blocks.discard()
        self.counters["stop_dropped"] += n_drop
        return n_drop

    # ------------------------------------------------------------------ decoding
    def emit(self, records: list[dict]) -> None:
        if self.recorder is not None:
            self.recorder.observe(records)  # a failed packet triggers the blackbox
        for r in records:
            self.outputs.write(r)  # never raises: an output must never stop decoding
        self.daemon.records_written += len(records)

    def range_part(self, k: int) -> None:
        """The first ``k`` pairs of the block being read are in (the rest still coming):
        their ranges out now (``decoder.range_ahead``: the filling of the block's second
        half no longer adds to their latency), their latency stamped; :meth:`decode_block`
        ranges the others. The overload policy's service is chosen here for the whole
        block. A decoder error here is counted and logged as in :meth:`decode_block` (the
        push then ranges every pair)."""
        b = self.blocks
        self.svc = self.overload.service(self.ring_fill())
        try:
            records = self.decoder.range_ahead(b.ids[:k].copy(), b.t_s[:k].copy(), b.left[:k], b.right[:k],
                                               ranging_every=self.svc.ranging_every, per_led=self.svc.per_led)
            self.ahead = self.decoder.ranged_ahead
        except Exception:
            self.counters["decode_errors"] += 1
            log.exception("ranging frames %d..%d ahead failed", int(b.ids[0]), int(b.ids[k - 1]))
            self.decoder.drop_ahead()  # what a transmitter did range is not out: the push ranges it
            records, self.ahead = [], 0
        if self.ahead:
            self.counters["pairs_ranged_ahead"] += self.ahead
            lat = (time.monotonic_ns() - b.arrival_ns[:self.ahead]) / 1e6
            self.lat.add(lat)
            self.lat_run.add(lat)
        self.emit(records)

    def decode_block(self, n: int) -> None:
        """The block of ``n`` pairs in the reader decoded: its ranges out first, then its
        demodulation hand-off and tracking update (``finish_block``); latency and the
        Rerun view. A decoder error is counted and logged and restarts the decoder's
        acquisition of the transmitter, never the service."""
        b, counters, decoder = self.blocks, self.counters, self.decoder
        ids, t_s = b.ids, b.t_s
        t_read_ns = time.monotonic_ns()
        self.acq_running(time.monotonic())
        prev = self.last_frame if self.last_frame >= 0 else int(ids[0]) - 1
        steps = np.diff(np.concatenate([[prev], ids[:n]]))
        counters["pair_gaps"] += int(np.clip(steps - 1, 0, None).sum())
        # falling behind: shed work in the policy's order so that no packet is lost (the
        # service chosen at the block's first part, if it had one: range_part)
        svc, self.svc = self.svc, None
        ahead, self.ahead = self.ahead, 0
        if svc is None:
            svc = self.overload.service(self.ring_fill())
        if self.recorder is not None:  # what is shed (and ranged ahead) goes into the recording: its replay does the same
            self.recorder.note_block(b.blocks_read - 1, svc.ranging_every, svc.per_led, ahead)
        try:
            # the block's ranges first; its demodulation hand-off and tracking update
            # after they are out (finish_block below)
            records = decoder.push(ids[:n].copy(), t_s[:n].copy(), b.left[:n], b.right[:n],
                                   ranging_every=svc.ranging_every, per_led=svc.per_led, defer=True,
                                   owned=b.fresh)
        except Exception:  # a decoder bug on odd frames must not stop the service
            counters["decode_errors"] += 1
            log.exception("decoding frames %d..%d failed; the decoder restarts acquisition",
                          int(ids[0]), int(ids[n - 1]))
            decoder.restart()
            records = []
        done_ns = time.monotonic_ns()
        counters["pairs_decoded"] += n
        self.last_frame = int(ids[n - 1])
        self.last_t_s = float(t_s[n - 1])
        lat = (done_ns - b.arrival_ns[ahead:n]) / 1e6  # the first `ahead` were stamped in range_part
        self.lat.add(lat)
        self.lat_run.add(lat)
        # where a block's latency goes: waiting for its last pair, then decoding it
        self.wake.add(np.array([(t_read_ns - b.arrival_ns[n - 1]) / 1e6]))
        self.work.add(np.array([(done_ns - t_read_ns) / 1e6]))
        self.emit(records)
        try:
            self.emit(decoder.finish_block())  # packets that came back; the blocks still in the buffers
        except Exception:  # as a failed push
            counters["decode_errors"] += 1
            log.exception("finishing frames %d..%d failed; the decoder restarts acquisition",
                          int(ids[0]), int(ids[n - 1]))
            decoder.restart()
        if self.view is not None:
            self._draw(n, svc.images)
        if self.lossless:  # the source waits for the frame loop; the loop waits for the worker
            decoder.wait_for_worker(LOSSLESS_STEPS)

    def ring_fill(self) -> float:
        """The ring's fill (0..1) that the overload policy sheds by; 0 for a source that
        waits for the consumer (nothing falls behind there: the ring is full by design)."""
        return 0.0 if self.lossless else self.ring.stats().queued / self.ring.capacity

    def _draw(self, n: int, images: bool) -> None:
        """The Rerun view's luminance plots and (at its image rate) the block's last pair
        with the tracked boxes; images shed (counted) at overload level 3."""
        view, decoder = self.view, self.decoder
        if decoder.last_luminance is not None and images:
            li, lt, ll, lr = decoder.last_luminance
            view.log_luminance(li, lt, ll, lr)
            decoder.last_luminance = None
        if view.want_image(self.last_frame) and not images:
            self.overload.shed_images()
        elif view.want_image(self.last_frame):
            tracks = decoder.tracks() if hasattr(decoder, "tracks") else (
                [(0, decoder.track)] if decoder.track is not None else [])
            boxes_l = boxes_r = labels = None
            if tracks:
                boxes_l = np.array([tr.left.bbox(2) for _, tr in tracks], float)
                boxes_r = np.array([tr.right.bbox(2) for _, tr in tracks], float)
                z = {d["tx"]: d["z_m"] for d in decoder.transmitters()} if hasattr(decoder, "transmitters") else {}
                labels = [f"tx {tx}" + (f" {z[tx]:.1f} m" if z.get(tx) is not None else "") for tx, _ in tracks]
            b = self.blocks
            view.log_images(self.last_frame, float(b.t_s[n - 1]), b.left[n - 1], b.right[n - 1], boxes_l, boxes_r,
                            labels=labels)

    def finish_decoder(self) -> list[dict]:
        """decoder.finish(), but without waiting on a demodulation backlog for more than
        stop_demod_s: steps still in flight then are abandoned (counted)."""
        out, abandoned = self.decoder.finish_within(self.st.stop_demod_s)
        if abandoned:
            self.counters["stop_demod_abandoned"] += abandoned
            log.warning("the run ends on time: %d demodulation steps still in flight are "
                        "abandoned (a packet in progress may be lost)", abandoned)
        return out

    # ------------------------------------------------------------------ stats
    def periodic_stats(self, now: float) -> None:
        """The stats record of the last interval out, sd_notify's STATUS, the pairing watch."""
        rec = self.stats_record(False)
        self.emit([rec])
        self.unpaired_watch.check(rec)
        self.notifier.status(f"pairs {rec['pairs_decoded']} packets ok {rec['packets_ok']} "
                             f"bad {rec['packets_bad']} dropped {rec['frames_dropped']}")
        self.next_stats += self.st.stats_interval_s
        if self.next_stats < now:
            self.next_stats = now + self.st.stats_interval_s

    def stats_record(self, final: bool) -> dict[str, Any]:
        """The ``stats`` record now (SPEC section 7; every finer counter in its extras)."""
        acq, decoder, counters, cpu = self.acq, self.decoder, self.counters, self.cpu
        a = acq.stats()
        rs = self.ring.stats()
        p50, p99 = self.lat.take()
        workers = decoder.worker_pids
        share, rss = cpu.sample([os.getpid()] + ([acq.pid] if acq.pid else []) + workers)
        by_process = {"frame_loop": cpu.shares.get(os.getpid()),
                      "acquisition": cpu.shares.get(acq.pid) if acq.pid else None,
                      "demod_worker": (round(sum(cpu.shares.get(p, 0.0) for p in workers), 3)
                                       if any(p in cpu.shares for p in workers) else None)}
        rec = {"uptime_s": round(time.monotonic() - self.t_start, 3), "final": final,
               # seconds since the acquisition started running (what --duration counts)
               "acquiring_s": round(time.monotonic() - self.t_acq, 3) if self.t_acq is not None else 0.0,
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
               "ring_capacity": int(self.ring.capacity),
               "pairs_decoded": counters["pairs_decoded"],
               "packets_ok": decoder.counters["packets_ok"], "packets_bad": decoder.counters["packets_bad"],
               "ranges": decoder.counters["ranges"], "ranging_skipped": decoder.counters["ranging_skipped"],
               "led_ranges_shed": decoder.counters["led_ranges_shed"], **self.overload.counters,
               "following_resets": decoder.counters.get("following_resets", 0),
               "stereo_holds": decoder.counters.get("stereo_holds", 0),
               "tracking": decoder.track is not None,
               "latency_ms_p50": p50, "latency_ms_p99": p99,
               # pairs whose ranges went out before the rest of their block was in (range_part)
               "pairs_ranged_ahead": counters["pairs_ranged_ahead"],
               # the same over every pair since the run started (0.1 ms bins)
               "latency_run_ms_p50": self.lat_run.percentile(50), "latency_run_ms_p99": self.lat_run.percentile(99),
               "latency_run_ms_max": round(self.lat_run.max_ms, 3) if self.lat_run.n else None,
               # per block: its last pair's arrival to the block read, and the decoding
               # (outputs excluded); the rest of a pair's latency is the block filling
               "block_read_ms_p50_p99": self.wake.take(), "block_decode_ms_p50_p99": self.work.take(),
               "cpu_cores": share, "cpu_cores_by_process": by_process, "rss_mb": round(rss / 2**20, 1),
               "pair_gaps": counters["pair_gaps"],
               "acquisition": a.as_dict(), "acquisition_restarts": counters["acquisition_restarts"],
               "decode_errors": counters["decode_errors"],
               "stop_dropped": counters["stop_dropped"], "stop_demod_abandoned": counters["stop_demod_abandoned"],
               # the frame rate the cameras report (after the device's own clamping)
               "device_fps": [a.fps_mhz_left / 1000 or None, a.fps_mhz_right / 1000 or None],
               "device_fps_mismatch": self.fps_mismatch,
               "demod_worker_restarts": decoder.counters.get("demod_worker_restarts", 0),
               "demod_worker_processes": len(workers)}
        if hasattr(decoder, "transmitters"):  # several transmitters: each one's own figures
            rec["transmitters"] = decoder.transmitters()
            rec.update({k: decoder.counters[k] for k in ("transmitters_confirmed", "transmitters_lost",
                                                         "candidate_records_dropped", "search_attempts",
                                                         "lookbacks_skipped")})
        rec.update(self.outputs.counters())  # output_errors and each output's own counters
        if self.control is not None:
            rec.update(self.control.counters())  # control_commands, control_refused
        if self.recorder is not None:
            rec.update(self.recorder.counters())  # record_written, record_dropped, record_mb_per_s...
        spec = {k: rec.pop(k) for k in StatsRecord.spec_fields()}
        # t_s: camera time of the last decoded frame, as in the other records
        return StatsRecord(tx=0, frame=int(self.last_frame), t_s=self.last_t_s, **spec, extra=rec).to_json()
