"""The Rerun live view of the daemon (rerun-sdk 0.41): images, LEDs, luminance, levels, range, counters.

Entities (docs/outputs.md has the full list):

- ``left/image``, ``right/image`` — the camera images, one pair every ``image_every`` frames,
  downscaled by ``image_scale`` (and JPEG-compressed with ``jpeg_quality`` > 0);
  ``left/leds``, ``right/leds`` — the LED regions as boxes in the same (scaled) pixels, one
  class id per LED.
- ``luminance/left``, ``luminance/right`` — mean ROI luminance of every LED (eq. 3.10), one
  series per LED, grey levels.
- ``levels`` — decided levels 1..M of every LED (eqs. 3.12/4.3), one series per LED.
- ``range/z_m/tx<k>``, ``range/disparity_px/tx<k>``, ``range/sigma_m/tx<k>`` (``/led<i>``
  below for per-LED records) — from ``range`` records.
- ``packets/ok/tx<k>``, ``packets/bad/tx<k>`` — running counts of ``packet`` records;
  ``log/packets`` — one text line per packet.
- ``stats/<group>/<key>`` — every number of a ``stats`` record; groups ``frames``,
  ``packets``, ``latency``, ``ring``, ``link`` (SER, throughput), ``outputs`` (drop and error
  counters of the outputs), ``process`` (CPU, memory), ``other``.

Timelines: ``frame`` (left-camera frame index, a sequence) and ``time`` (``t_s``, a
duration).

Cheap by design: time series are buffered and sent with ``send_columns`` every
``flush_interval_s`` (one call per entity, ~0.2 ms, instead of ~0.1 ms per value with
``log``); images go at a reduced rate. Every public method catches its own exceptions
(logged, rate-limited, counted in :attr:`RerunView.errors`): the view can never stop the
daemon. With no sink (no ``connect``, ``serve`` or ``save``) the view is disabled and every
call returns at once.
"""

from __future__ import annotations

import functools
import logging
import time
import uuid
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from iscd.outputs.base import Output, OutputError

log = logging.getLogger(__name__)

DEFAULT_CONNECT_URL = "rerun+http://127.0.0.1:9876/proxy"

_STAT_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("outputs", ("jsonl_", "zmq_", "rerun_", "output_")),
    ("latency", ("latency",)),
    ("ring", ("ring", "buffer")),
    ("packets", ("packets_", "packet_")),
    ("link", ("ser", "throughput", "goodput", "bits", "symbols_", "kbps", "bps")),
    ("frames", ("frames_", "pairs_", "fps", "frame_")),
    ("process", ("cpu", "rss", "mem")),
)
_SKIP_KEYS = frozenset({"type", "tx", "frame", "t_s", "led"})

F = TypeVar("F", bound=Callable[..., Any])


def stat_group(key: str) -> str:
    """The ``stats/<group>`` a stats key is plotted in (by its prefix/substring)."""
    k = key.lower()
    for group, marks in _STAT_GROUPS:
        if any(k.startswith(m) or (len(m) > 3 and m in k) for m in marks):
            return group
    return "other"


def _guarded(fn: F) -> F:
    """Run ``fn`` only when enabled; log and count any exception instead of raising."""

    @functools.wraps(fn)
    def wrapper(self: "RerunView", *args: Any, **kwargs: Any) -> Any:
        if self._rec is None:
            return None
        try:
            return fn(self, *args, **kwargs)
        except Exception as e:  # noqa: BLE001 - the view must never stop the daemon
            self.errors += 1
            if self.errors <= 5 or self.errors % 100 == 0:
                log.warning("rerun view: %s failed: %s: %s (error %d)", fn.__name__,
                            type(e).__name__, e, self.errors)
            return None

    return wrapper  # type: ignore[return-value]


class _SeriesBuffer:
    """Rows of one scalar entity waiting for ``send_columns``: frames, times, values (n, k)."""

    __slots__ = ("frames", "times", "values")

    def __init__(self) -> None:
        self.frames: list[np.ndarray] = []
        self.times: list[np.ndarray] = []
        self.values: list[np.ndarray] = []

    def add(self, frames: np.ndarray, times: np.ndarray, values: np.ndarray) -> None:
        self.frames.append(frames)
        self.times.append(times)
        self.values.append(values)


class RerunView(Output):
    """Streams the daemon's state to Rerun (see the module docstring for the entities).

    Sinks, as Rerun's own examples name them (any combination):
    ``connect`` — a viewer's URL (``""`` = :data:`DEFAULT_CONNECT_URL`, ``rerun`` started
    on this machine); ``serve`` — host a gRPC server on ``serve_bind:serve_port``
    (loopback by default) that viewers connect to (``rerun rerun+http://HOST:9876/proxy``);
    ``save`` — write a ``.rrd`` file. None of them: disabled.

    ``image_every``: frames between logged image pairs. ``image_scale``: image downscale.
    ``jpeg_quality``: 1..100 compresses 8-bit images (0 = raw). ``fps`` and
    ``frames_per_symbol`` place the rows of a packet's level matrix on the frame timeline.
    ``flush_interval_s``: how long time series are buffered before they are sent, s.
    ``n_leds``: LEDs of the transmitter, to show a packet record's ``levels`` per LED (0: not
    shown) when records come through :meth:`write` (the daemon's fan-out).

    Raises :class:`~iscd.outputs.OutputError` when a sink cannot be set up (bad URL,
    unwritable file, port in use). Not thread-safe: call it from one thread (the decode loop).
    """

    def __init__(self, app_id: str = "iscd", *, connect: str | None = None, serve: bool = False,
                 save: str | None = None, image_every: int = 50, image_scale: float = 0.5,
                 jpeg_quality: int = 0, fps: float = 1000.0, frames_per_symbol: float = 2.0,
                 flush_interval_s: float = 0.25, serve_bind: str = "127.0.0.1",
                 serve_port: int = 9876, server_memory_limit: str = "256MiB",
                 recording_id: str | None = None, n_leds: int = 0) -> None:
        if image_every < 1:
            raise OutputError(f"image_every must be >= 1, got {image_every}")
        if not 0 < image_scale <= 1:
            raise OutputError(f"image_scale must be in (0, 1], got {image_scale}")
        self.image_every = int(image_every)
        self.image_scale = float(image_scale)
        self.jpeg_quality = int(jpeg_quality)
        self.fps = float(fps)
        self.frames_per_symbol = float(frames_per_symbol)
        self.flush_interval_s = float(flush_interval_s)
        self.n_leds = int(n_leds)
        self.errors = 0
        self.images_logged = 0
        self.serve_uri: str | None = None
        self._rec: Any = None
        self._series: dict[str, _SeriesBuffer] = {}
        self._named: set[str] = set()
        self._packets: dict[tuple[int, bool], int] = {}
        self._last_image_frame: int | None = None
        self._last_flush = time.monotonic()
        if connect is None and not serve and not save:
            return
        import rerun as rr

        sinks: list[Any] = []
        try:
            if connect is not None:
                sinks.append(rr.GrpcSink(connect or DEFAULT_CONNECT_URL))
            if serve:
                _check_port_free(serve_bind, int(serve_port))
                server = rr.GrpcServerSink(serve_bind, int(serve_port),
                                           server_memory_limit=server_memory_limit)
                self.serve_uri = server.uri
                sinks.append(server)
            if save:
                sinks.append(rr.FileSink(save))
            rec = rr.RecordingStream(app_id, recording_id=recording_id or uuid.uuid4())
            rec.set_sinks(*sinks, default_blueprint=default_blueprint())
        except Exception as e:  # noqa: BLE001 - rerun raises ValueError/RuntimeError/OSError
            raise OutputError(f"rerun view: cannot set up "
                              f"{' '.join(self.sink_names(connect, serve, save))}: {e}") from None
        self._rec = rec
        if self.serve_uri:
            log.info("rerun: serving on %s (connect with: rerun %s)", self.serve_uri, self.serve_uri)

    @staticmethod
    def sink_names(connect: str | None, serve: bool, save: str | None) -> list[str]:
        return ([f"--connect {connect or DEFAULT_CONNECT_URL}"] if connect is not None else []) + \
            (["--serve"] if serve else []) + ([f"--save {save}"] if save else [])

    @property
    def enabled(self) -> bool:
        return self._rec is not None

    # -- images ------------------------------------------------------------------------

    def want_image(self, frame: int) -> bool:
        """True when :meth:`log_images` would log this frame (so the caller can skip copies)."""
        if self._rec is None:
            return False
        last = self._last_image_frame
        return last is None or frame - last >= self.image_every or frame < last

    @_guarded
    def log_images(self, frame: int, t_s: float, left: np.ndarray | None, right: np.ndarray | None,
                   boxes_left: np.ndarray | None = None, boxes_right: np.ndarray | None = None,
                   *, labels: list[str] | None = None) -> bool:
        """Log a left/right image pair and LED boxes (N, 4: x0, y0, x1, y1 in px) if
        :meth:`want_image`; True when logged. Images: 2-D grey (uint8/uint16) or 3-D colour.
        ``labels``: one per box (several transmitters: ``"tx 1"``)."""
        if not self.want_image(frame):
            return False
        import rerun as rr

        self._last_image_frame = int(frame)
        self._set_time(int(frame), float(t_s))
        for side, img, boxes in (("left", left, boxes_left), ("right", right, boxes_right)):
            if img is None:
                continue
            small, sx, sy = self._downscale(np.asarray(img))
            self._rec.log(f"{side}/image", self._image(small))
            if boxes is not None:
                b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4) * (sx, sy, sx, sy)
                self._rec.log(f"{side}/leds", rr.Boxes2D(array=b, array_format=rr.Box2DFormat.XYXY,
                                                          class_ids=np.arange(len(b)),
                                                          labels=labels if labels and len(labels) == len(b) else None))
        self.images_logged += 1
        return True

    def _downscale(self, img: np.ndarray) -> tuple[np.ndarray, float, float]:
        if self.image_scale >= 1.0:
            return img, 1.0, 1.0
        import cv2

        h, w = img.shape[:2]
        nw, nh = max(1, round(w * self.image_scale)), max(1, round(h * self.image_scale))
        small = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        return small, nw / w, nh / h

    def _image(self, img: np.ndarray) -> Any:
        import rerun as rr

        if self.jpeg_quality > 0 and img.dtype == np.uint8:
            import cv2

            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            if ok:
                return rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg")
        return rr.Image(img)

    # -- time series -------------------------------------------------------------------

    @_guarded
    def log_luminance(self, frames: np.ndarray, t_s: np.ndarray, lum_left: np.ndarray | None,
                      lum_right: np.ndarray | None) -> None:
        """Per-LED mean luminance (eq. 3.10), grey levels: ``frames`` (n,), ``t_s`` (n,) s,
        ``lum_*`` (n, N) (or (N,) for one frame); buffered, sent in batches."""
        fr = np.atleast_1d(np.asarray(frames, dtype=np.int64))
        ts = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        for side, lum in (("left", lum_left), ("right", lum_right)):
            if lum is not None:
                v = np.asarray(lum, dtype=np.float64).reshape(len(fr), -1)
                self._add(f"luminance/{side}", fr, ts, v, names="led")
        self._maybe_flush()

    @_guarded
    def log_levels(self, frame: int, t_s: float, levels: np.ndarray) -> None:
        """Decided levels 1..M of every LED: (N,) for one symbol at ``frame``, or (F, N) for a
        packet's data whose first symbol is at ``frame`` (row k at frame + k·frames_per_symbol)."""
        lv = np.asarray(levels, dtype=np.float64)
        if lv.ndim == 1:
            lv = lv[None, :]
        k = np.arange(len(lv))
        fr = int(frame) + np.round(k * self.frames_per_symbol).astype(np.int64)
        ts = float(t_s) + (fr - int(frame)) / self.fps
        self._add("levels", fr, ts, lv, names="led", points=True)
        self._maybe_flush()

    def write(self, record: dict[str, Any]) -> None:
        """A record from the daemon's fan-out (:class:`~iscd.outputs.Outputs`): logged with
        :meth:`log_record`, and a packet's decided levels with :meth:`log_levels`."""
        self.log_record(record)
        if self.n_leds and record.get("type") == "packet" and record.get("levels"):
            self.log_levels(record["frame"], record["t_s"],
                            np.asarray(record["levels"]).reshape(-1, self.n_leds))

    @_guarded
    def log_record(self, record: dict[str, Any]) -> None:
        """A SPEC section 7 record (``range``, ``packet``, ``stats``) or one of the project's
        (``range_leds``, ``range_filtered``); other types are ignored."""
        kind = record.get("type")
        # a record may carry null frame / t_s (the first stats record, before any frame): the
        # frame falls back to the last one seen, the time to frame / fps
        f_v, t_v = record.get("frame"), record.get("t_s")
        frame = int(f_v) if f_v is not None else getattr(self, "_last_frame", 0)
        t_s = float(t_v) if t_v is not None else max(frame, 0) / self.fps
        self._last_frame = frame
        tx = int(record.get("tx", 0))
        fr, ts = np.array([frame], np.int64), np.array([t_s])
        if kind == "range":
            led = record.get("led")
            suffix = f"tx{tx}" + (f"/led{int(led)}" if led is not None else "")
            for key in ("z_m", "disparity_px", "sigma_m"):
                v = record.get(key)
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    self._add(f"range/{key}/{suffix}", fr, ts, np.array([[float(v)]]))
        elif kind == "range_leds":  # one range per LED of the array ([ranging] per_led)
            for i, v in enumerate(record.get("z_m") or []):
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    self._add(f"range/z_m/tx{tx}/led{i}", fr, ts, np.array([[float(v)]]))
        elif kind == "range_filtered":  # [ranging] kalman
            for key in ("z_m", "closing_speed_mps"):
                v = record.get(key)
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    self._add(f"range_filtered/{key}/tx{tx}", fr, ts, np.array([[float(v)]]))
        elif kind == "packet":
            ok = bool(record.get("crc_ok"))
            n = self._packets[(tx, ok)] = self._packets.get((tx, ok), 0) + 1
            self._add(f"packets/{'ok' if ok else 'bad'}/tx{tx}", fr, ts, np.array([[float(n)]]))
            self._log_packet_text(record, tx, ok, frame, t_s)
        elif kind == "stats":
            for key, v in record.items():
                if key in _SKIP_KEYS or isinstance(v, bool) or not isinstance(v, (int, float)):
                    continue
                self._add(f"stats/{stat_group(key)}/{key}", fr, ts, np.array([[float(v)]]))
        self._maybe_flush()

    def _log_packet_text(self, record: dict[str, Any], tx: int, ok: bool, frame: int, t_s: float) -> None:
        import rerun as rr

        payload = str(record.get("payload_hex", ""))
        text = (f"tx{tx} frame {frame}: CRC {'ok' if ok else 'BAD'}, {len(payload) // 2} B"
                + (f": {payload[:32]}{'…' if len(payload) > 32 else ''}" if payload else ""))
        self._set_time(frame, t_s)
        self._rec.log("log/packets", rr.TextLog(text, level="INFO" if ok else "WARN"))

    def _add(self, entity: str, frames: np.ndarray, times: np.ndarray, values: np.ndarray,
             names: str | None = None, points: bool = False) -> None:
        if names and entity not in self._named:
            self._name_series(entity, values.shape[1], names, points)
        buf = self._series.get(entity)
        if buf is None:
            buf = self._series[entity] = _SeriesBuffer()
        buf.add(frames, times, values)

    def _name_series(self, entity: str, n: int, prefix: str, points: bool) -> None:
        import rerun as rr

        names = [f"{prefix} {i}" for i in range(n)]
        style = rr.SeriesPoints(names=names, marker_sizes=[2.0] * n) if points else \
            rr.SeriesLines(names=names, widths=[1.0] * n)
        self._rec.log(entity, style, static=True)
        self._named.add(entity)

    def _maybe_flush(self) -> None:
        now = time.monotonic()
        if now - self._last_flush >= self.flush_interval_s:
            self._last_flush = now
            self._send_series()

    def _send_series(self) -> None:
        import rerun as rr

        pending, self._series = self._series, {}
        for entity, buf in pending.items():
            frames = np.concatenate(buf.frames)
            times = np.concatenate(buf.times)
            widths = {v.shape[1] for v in buf.values}
            if len(widths) != 1:  # the LED count changed mid-batch: send row by row
                for f, t, v in zip(frames, times, (r for vs in buf.values for r in vs)):
                    self._set_time(int(f), float(t))
                    self._rec.log(entity, rr.Scalars(v))
                continue
            values = np.concatenate(buf.values)
            self._rec.send_columns(
                entity,
                indexes=[rr.TimeColumn("frame", sequence=frames),
                         rr.TimeColumn("time", duration=times)],
                columns=rr.Scalars.columns(scalars=values if values.shape[1] > 1 else values[:, 0]))

    def _set_time(self, frame: int, t_s: float) -> None:
        self._rec.set_time("frame", sequence=frame)
        self._rec.set_time("time", duration=t_s)

    # -- lifetime ----------------------------------------------------------------------

    @_guarded
    def flush(self) -> None:
        """Send every buffered series now (the daemon need not call it; close does)."""
        self._last_flush = time.monotonic()
        self._send_series()
        self._rec.flush(timeout_sec=2.0)

    def counters(self) -> dict[str, int]:
        """For the daemon's stats record."""
        return {"rerun_errors": self.errors, "rerun_images": self.images_logged}

    def close(self) -> None:
        """Send what is buffered, finish the sinks (the .rrd footer). Idempotent, never raises."""
        if self._rec is None:
            return
        self.flush()
        try:
            self._rec.disconnect()
        except Exception as e:  # noqa: BLE001
            self.errors += 1
            log.warning("rerun view: disconnect failed: %s", e)
        self._rec = None

    def __enter__(self) -> "RerunView":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _check_port_free(host: str, port: int) -> None:
    """Raise OSError if ``host:port`` cannot be bound (rerun's server would fail only later,
    in its own thread)."""
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as e:
            raise OSError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None


def default_blueprint() -> Any:
    """Images side by side over luminance and levels; range, counters and the packet log on the right."""
    import rerun.blueprint as rrb

    last_10s = rrb.VisibleTimeRange("time", start=rrb.TimeRangeBoundary.cursor_relative(seconds=-10.0),
                                    end=rrb.TimeRangeBoundary.cursor_relative())

    def series(origin: str, name: str) -> Any:
        return rrb.TimeSeriesView(origin=origin, name=name, time_ranges=last_10s)

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Horizontal(rrb.Spatial2DView(origin="left", name="left camera"),
                               rrb.Spatial2DView(origin="right", name="right camera")),
                rrb.Horizontal(series("luminance/left", "luminance left (DN)"),
                               series("luminance/right", "luminance right (DN)")),
                series("levels", "decided levels"),
                row_shares=[3, 2, 1.5]),
            rrb.Vertical(
                series("range/z_m", "range Z (m)"),
                rrb.Tabs(series("range/disparity_px", "disparity (px)"),
                         series("range/sigma_m", "range sigma (m)")),
                rrb.Tabs(series("packets", "packets ok / bad"),
                         series("stats/frames", "frames"),
                         series("stats/latency", "latency (ms)"),
                         series("stats/ring", "ring buffer"),
                         series("stats/link", "SER / throughput"),
                         series("stats/outputs", "output drops"),
                         series("stats/process", "CPU / memory"),
                         series("stats/other", "other")),
                rrb.TextLogView(origin="log", name="packets"),
                row_shares=[2, 1.5, 2, 1]),
            column_shares=[3, 2]),
        collapse_panels=True)


def add_rerun_arguments(parser: Any) -> None:
    """Add Rerun's usual ``--connect [URL]``, ``--serve``, ``--save FILE.rrd`` to an argparse parser."""
    g = parser.add_argument_group("Rerun live view (docs/outputs.md)")
    g.add_argument("--connect", nargs="?", const="", default=None, metavar="URL",
                   help=f"stream the live view to a running Rerun viewer (start one with 'rerun'); "
                        f"URL default {DEFAULT_CONNECT_URL}")
    g.add_argument("--serve", action="store_true",
                   help="host a Rerun gRPC server (rerun.serve_bind:serve_port, default "
                        "127.0.0.1:9876) that viewers connect to: rerun rerun+http://HOST:9876/proxy")
    g.add_argument("--save", metavar="FILE.rrd", default=None,
                   help="write the live view to a Rerun recording file (open it with 'rerun FILE.rrd')")


def rerun_view_from(args: Any, cfg: Any = None, *, fps: float = 1000.0,
                    frames_per_symbol: float = 2.0, n_leds: int = 0) -> RerunView:
    """A :class:`RerunView` from the command-line flags of :func:`add_rerun_arguments`, falling
    back to the ``[rerun]`` section ``cfg`` (a :class:`~iscd.outputs.RerunConfig`, or None
    for defaults). Disabled when neither asks for a sink."""
    from iscd.outputs.base import RerunConfig

    rc = cfg if cfg is not None else RerunConfig()
    connect = getattr(args, "connect", None)
    if connect is None and rc.connect:
        connect = rc.connect
    save = getattr(args, "save", None) or rc.save or None
    return RerunView(connect=connect, serve=bool(getattr(args, "serve", False) or rc.serve), save=save,
                     image_every=rc.image_every, image_scale=rc.image_scale,
                     jpeg_quality=rc.jpeg_quality, fps=fps, frames_per_symbol=frames_per_symbol,
                     serve_bind=rc.serve_bind, serve_port=rc.serve_port,
                     server_memory_limit=rc.server_memory_limit, n_leds=n_leds)
