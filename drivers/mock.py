"""The mock stereo rig: two :class:`~iscd.drivers.base.Camera` objects on one shared trigger,
showing the simulated scene (:class:`iscd.sim.Scene`).

    left, right = MockRig.from_config(cfg)
    for cam in (left, right): cam.open(); cam.start()
    fl, fr = left.read(), right.read()      # fl.frame_id == fr.frame_id, same timestamp
    scene = left.truth                       # the Scene, for ground truth

Timing: trigger n fires at ``t0 + n / fps`` (rig clock = host ``time.monotonic_ns``; t0 is
10 ms after the first ``start()`` so that both cameras started back to back catch trigger
0). ``frame_id`` = n, ``timestamp_ns`` = trigger time, the image is scene frame n.
With ``rig.pace = true`` frames become available at their trigger time + exposure, in real
time; each camera has a queue of ``buffer_frames``: frames that arrive while it is full are
dropped (like a camera without free buffers) and counted in ``stats``. With ``pace = false``
frames are delivered as fast as they are read and never dropped (the rig waits for the
consumer; timestamps still say t0 + n / fps).

Injected faults (``[[rig.faults]]``, :class:`iscd.core.config.FaultConfig`), per camera:
``drop`` (frame ``frame`` never arrives), ``duplicate`` (delivered twice), ``stall``
(frames triggered during ``duration_ms`` from ``frame`` are lost, then it resumes),
``id_offset`` (``offset`` added to frame ids from ``frame`` on), ``vanish`` (from trigger
``frame`` reads raise CameraLost and ``open()`` fails for ``duration_ms``; then the camera
can be reopened and started again; frames triggered meanwhile are lost).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from iscd.drivers import urls
from iscd.drivers.base import (Camera, CameraError, CameraLost, CameraSettings, CameraTimeout, Frame, PairMeta,
                          Roi, StereoPairSource)
from iscd.core.config import Config, ConfigError, FaultConfig

_START_DELAY_NS = 10_000_000
_CACHE_MAX = 64


@dataclass
class CameraStats:
    """Counters of one mock camera."""

    delivered: int = 0
    dropped_buffer: int = 0
    """frames lost because the consumer was late and the queue was full"""
    dropped_fault: int = 0
    """frames lost to injected drop/stall/vanish faults"""
    duplicated: int = 0
    skipped: int = 0
    """frames discarded unread by :meth:`MockCamera.skip_to` (a reader catching up)"""


@dataclass
class _CamState:
    name: str
    idx: int
    opened: bool = False
    started: bool = False
    settings: CameraSettings = field(default_factory=CameraSettings)
    cursor: int = 0  # next trigger index to consider
    queue: deque = field(default_factory=deque)  # trigger indices waiting (duplicates twice)
    lost_until_n: int | None = None  # vanish: lost for triggers < this
    lost_until_ns: int = 0
    must_reopen: bool = False
    stats: CameraStats = field(default_factory=CameraStats)


class MockRig(StereoPairSource):
    """The shared core of two mock cameras: scene, trigger clock, faults, frame cache.

    cfg: configuration (camera, scene, transmitter, ... and rig.pace / rig.faults).
    level_source: optional :class:`iscd.sim.LevelSource` for the scene (e.g. the LED-board
      emulator); default: packets per ``[payload]``.
    buffer_frames: per-camera queue length when paced.
    noise: passed to the scene (False: noise-free frames).
    """

    def __init__(self, cfg: Config, level_source: object | None = None, *,
                 buffer_frames: int = 8, noise: bool = True) -> None:
        self.cfg = cfg
        self.level_source = level_source
        self.noise = noise
        self.pace = cfg.rig.pace
        self.buffer_frames = max(1, int(buffer_frames))
        self.faults = cfg.rig.faults
        self._lock = threading.RLock()
        self._scene = None
        self._fps = cfg.camera.fps
        self._exposure_s = cfg.camera.exposure_s
        self._t0_ns: int | None = None
        self._soft_count = 0
        self._cache: dict[int, list] = {}
        self._cams = [_CamState("left", 0), _CamState("right", 1)]
        self._pair_queue: deque | None = None
        """triggers waiting for :meth:`read_pair_into` (None until it is first used)"""
        full = Roi(0, 0, cfg.camera.width, cfg.camera.height)
        for c in self._cams:
            c.settings = CameraSettings(fps=self._fps, exposure_s=self._exposure_s, roi=full)
        self.left = MockCamera(self, 0)
        self.right = MockCamera(self, 1)

    @classmethod
    def from_config(cls, cfg: Config, **kw: object) -> tuple["MockCamera", "MockCamera"]:
        """(left, right) cameras of a new rig (``cam.rig`` is the rig)."""
        rig = cls(cfg, **kw)  # type: ignore[arg-type]
        return rig.left, rig.right

    # ----------------------------------------------------------------- scene and clock
    @property
    def scene(self):  # -> iscd.sim.Scene
        """The simulated scene (built on first use, with its render kernels compiled or loaded
        from the cache; rebuilt when fps/exposure change)."""
        with self._lock:
            if self._scene is None:
                from iscd.sim import Scene

                cam = dataclasses.replace(self.cfg.camera, fps=self._fps, exposure_s=self._exposure_s)
                self._scene = Scene(self.cfg.replace(camera=cam), self.level_source,  # type: ignore[arg-type]
                                    noise=self.noise)
                self._scene.warm_up()  # compile the render kernels before any clock starts
            return self._scene

    @property
    def fps(self) -> float:
        return self._fps

    def trigger_time_ns(self, n: int) -> int:
        """Rig-clock time (ns) of trigger ``n``."""
        t0 = self._t0_ns if self._t0_ns is not None else 0
        return t0 + round(n * 1e9 / self._fps)

    def _triggers_done(self, now_ns: int) -> int:
        """Number of triggers whose frames are complete (exposure ended) at ``now_ns``."""
        assert self._t0_ns is not None
        dt = now_ns - self._t0_ns - self._exposure_s * 1e9
        return max(0, math.floor(dt * self._fps / 1e9) + 1) if dt >= 0 else 0

    def stats(self, camera: int) -> CameraStats:
        return self._cams[camera].stats

    @property
    def waits_for_consumer(self) -> bool:  # type: ignore[override]
        """Unpaced (``rig.pace = false``): frames are made when read, none is ever due."""
        return not self.pace

    # ----------------------------------------------------------------- faults
    @property
    def faults(self) -> tuple[FaultConfig, ...]:
        """The injected faults (assign a new sequence to change them)."""
        return self._fault_list

    @faults.setter
    def faults(self, faults: Sequence[FaultConfig]) -> None:
        self._fault_list = tuple(faults)
        index: dict[tuple[str, str], list[FaultConfig]] = {}
        for f in self._fault_list:
            index.setdefault((f.camera, f.kind), []).append(f)
        self._fault_index = {k: tuple(v) for k, v in index.items()}  # (camera, kind) -> faults
        self._faulty = frozenset(f.camera for f in self._fault_list)

    def _faults(self, c: _CamState, kind: str) -> tuple[FaultConfig, ...]:
        return self._fault_index.get((c.name, kind), ())

    def _frames_in(self, ms: float) -> int:
        return max(1, math.ceil(ms * 1e-3 * self._fps - 1e-9))

    def _arrivals(self, c: _CamState, n: int) -> int:
        """How many copies of trigger ``n`` reach camera ``c`` (0, 1 or 2); may start a vanish."""
        if c.lost_until_n is None and c.name not in self._faulty:
            return 1
        for f in self._faults(c, "vanish"):
            if n == f.frame:
                c.lost_until_n = n + self._frames_in(f.duration_ms)
                c.lost_until_ns = self.trigger_time_ns(n) + round(f.duration_ms * 1e6)
                c.must_reopen = True
                return 0
        if c.lost_until_n is not None and n < c.lost_until_n:
            return 0
        for f in self._faults(c, "drop"):
            if n == f.frame:
                return 0
        for f in self._faults(c, "stall"):
            if f.frame <= n < f.frame + self._frames_in(f.duration_ms):
                return 0
        for f in self._faults(c, "duplicate"):
            if n == f.frame:
                return 2
        return 1

    def _frame_id(self, c: _CamState, n: int) -> int:
        offsets = self._faults(c, "id_offset")
        return n + sum(f.offset for f in offsets if n >= f.frame) if offsets else n

    # ----------------------------------------------------------------- camera operations
    def _open(self, c: _CamState) -> None:
        with self._lock:
            if c.must_reopen:
                if self.pace and time.monotonic_ns() < c.lost_until_ns:
                    raise CameraError(f"mock {c.name} camera not found (vanished)")
                c.must_reopen = False
            c.opened = True

    def _configure(self, c: _CamState, s: CameraSettings) -> CameraSettings:
        with self._lock:
            if not c.opened:
                raise CameraError(f"mock {c.name} camera is not open")
            if c.started:
                raise CameraError(f"mock {c.name} camera: configure only while stopped")
            W, H = self.cfg.camera.width, self.cfg.camera.height
            r = s.roi
            if r.x + r.width > W or r.y + r.height > H:
                raise CameraError(f"mock {c.name} camera: ROI {r} exceeds the {W}x{H} sensor")
            if s.trigger == "software":
                raise CameraError(f"mock {c.name} camera: no software trigger (the rig runs on "
                                  f"its own clock; use free, master or slave)")
            if (s.fps, s.exposure_s) != (self._fps, self._exposure_s):
                other = self._cams[1 - c.idx]
                if other.started:
                    raise CameraError(f"mock {c.name} camera: fps/exposure are shared by the rig "
                                      f"and the {other.name} camera is running")
                try:
                    dataclasses.replace(self.cfg.camera, fps=s.fps, exposure_s=s.exposure_s)
                except ConfigError as e:
                    raise CameraError(f"mock {c.name} camera: {e}") from None
                self._fps, self._exposure_s = s.fps, s.exposure_s
                self._scene = None
                self._cache.clear()
                for o in self._cams:
                    o.settings = o.settings.with_(fps=s.fps, exposure_s=s.exposure_s)
            c.settings = s.with_(gain_db=0.0, pixel_format="Mono8")
            return c.settings

    def _start(self, c: _CamState) -> None:
        with self._lock:
            if not c.opened:
                raise CameraError(f"mock {c.name} camera is not open")
            if c.must_reopen:
                raise CameraLost(f"mock {c.name} camera vanished; reopen it")
            if c.started:
                return
            self.scene  # build before the clock starts  # noqa: B018
            other = self._cams[1 - c.idx]
            now = time.monotonic_ns()
            if self._t0_ns is None:
                self._t0_ns = now + (_START_DELAY_NS if self.pace else 0)
            if self.pace:
                # first trigger not yet fired
                dt = now - self._t0_ns
                c.cursor = 0 if dt <= 0 else math.floor(dt * self._fps / 1e9) + 1
            else:
                c.cursor = max(other.cursor if other.started else 0, c.cursor)
            if c.lost_until_n is not None:
                c.cursor = max(c.cursor, c.lost_until_n)
                c.lost_until_n = None
            c.queue.clear()
            c.started = True

    def _stop(self, c: _CamState) -> None:
        with self._lock:
            self._pair_queue = None
            c.started = False
            c.queue.clear()

    def _trigger(self, c: _CamState) -> None:
        raise CameraError("the mock rig has no software trigger (it runs on its own clock)")

    def _next_index(self, c: _CamState, timeout_s: float) -> int:
        """The trigger index of the next frame for camera ``c`` (waits when paced)."""
        if not c.started:
            if c.must_reopen:
                raise CameraLost(f"mock {c.name} camera vanished")
            raise CameraError(f"mock {c.name} camera is not started")
        if not self.pace:
            if not c.queue and not c.must_reopen and c.lost_until_n is None \
                    and c.name not in self._faulty:  # the common case: the next trigger
                n = c.cursor
                c.cursor += 1
                return n
            while not c.queue:
                if c.must_reopen:
                    c.started = False
                    raise CameraLost(f"mock {c.name} camera vanished")
                n = c.cursor
                c.cursor += 1
                k = self._arrivals(c, n)
                if c.must_reopen:
                    c.started = False
                    raise CameraLost(f"mock {c.name} camera vanished")
                if k == 0:
                    c.stats.dropped_fault += 1
                for _ in range(k):
                    c.queue.append(n)
                c.stats.duplicated += max(0, k - 1)
            return c.queue.popleft()
        deadline = time.monotonic_ns() + round(timeout_s * 1e9)
        while True:
            now = time.monotonic_ns()
            done = self._triggers_done(now)
            while c.cursor < done and not c.must_reopen:  # arrivals since the last read
                n = c.cursor
                c.cursor += 1
                k = self._arrivals(c, n)
                if c.must_reopen:  # vanished: the triggers of the vanish window are lost
                    c.cursor = max(c.cursor, c.lost_until_n or 0)
                    break
                if k == 0:
                    c.stats.dropped_fault += 1
                for _ in range(k):
                    if len(c.queue) < self.buffer_frames:
                        c.queue.append(n)
                    else:
                        c.stats.dropped_buffer += 1
                c.stats.duplicated += max(0, k - 1)
            if c.queue:  # frames buffered before a vanish are still delivered
                return c.queue.popleft()
            if c.must_reopen:
                c.started = False
                raise CameraLost(f"mock {c.name} camera vanished")
            next_ns = self.trigger_time_ns(c.cursor) + round(self._exposure_s * 1e9)
            if next_ns > deadline:
                wait = deadline - now
                if wait > 0:
                    time.sleep(wait / 1e9)
                raise CameraTimeout(f"mock {c.name} camera: no frame within {timeout_s:g} s")
            wait = next_ns - now
            if wait > 0:
                time.sleep(wait / 1e9)

    @staticmethod
    def _next_read(c: _CamState) -> int:
        """The trigger index camera ``c`` reads next: the head of its queue, else its cursor
        (read from another camera's thread: a snapshot, exact enough for the render cache)."""
        try:
            return int(c.queue[0]) if c.queue else int(c.cursor)
        except IndexError:  # emptied meanwhile by its reader
            return int(c.cursor)

    def _image(self, c: _CamState, n: int) -> np.ndarray:
        """Camera ``c``'s image of trigger ``n`` (renders the pair once, caches the other)."""
        with self._lock:
            entry = self._cache.get(n)
            if entry is not None and entry[c.idx] is not None:
                img = entry[c.idx]
                entry[c.idx] = None
                if entry[0] is None and entry[1] is None:
                    del self._cache[n]
                return img
            scene = self._scene if self._scene is not None else self.scene
            H, W = scene.height, scene.width
            other = self._cams[1 - c.idx]
            # the other camera's image is rendered with this one's (and cached) only where the
            # other will read frame n while its image is still cached: not when it has read n
            # already, nor when it lags so far behind (by _CACHE_MAX or more) that n's entry is
            # evicted before it gets there -- then each camera rendered every pair itself
            # (twice the cost) and a reader that fell behind on a loaded host stayed behind
            lag = n - self._next_read(other)
            want_other = other.started and 0 <= lag < _CACHE_MAX - 2
            if want_other and entry is None:
                l = np.empty((H, W), np.uint8)
                r = np.empty((H, W), np.uint8)
                scene.render_pair_into(n, l, r)
                pair = [l, r]
                img = pair[c.idx]
                self._cache[n] = [None, None]
                self._cache[n][1 - c.idx] = pair[1 - c.idx]
                while len(self._cache) > _CACHE_MAX:
                    self._cache.pop(min(self._cache))
                return img
            img = np.empty((H, W), np.uint8)
            scene.render(n, c.idx, img)
            return img

    def _read(self, c: _CamState, timeout_s: float) -> Frame:
        if self.pace:  # each camera's cursor/queue is touched only by its own reader
            n = self._next_index(c, timeout_s)
        else:
            with self._lock:
                n = self._next_index(c, timeout_s)
        img = self._image(c, n)
        r = c.settings.roi
        if r.x or r.y or r.width != img.shape[1] or r.height != img.shape[0]:
            img = img[r.y:r.y + r.height, r.x:r.x + r.width].copy()
        c.stats.delivered += 1
        return Frame(c.name, self._frame_id(c, n), self.trigger_time_ns(n), img)

    def _skip_to(self, c: _CamState, until_ns: int, timeout_s: float,
                 max_frames: int) -> tuple[int, Frame | None]:
        """:meth:`Camera.skip_to` without rendering the discarded frames: the triggers
        waiting for camera ``c`` (its queue, or with ``pace = false`` the next ones, faults
        applied) whose time is below ``until_ns`` are counted in ``stats.skipped``."""
        n_skipped = 0
        try:
            while n_skipped < max_frames:
                if self.pace:
                    n = self._next_index(c, timeout_s)
                else:
                    with self._lock:
                        n = self._next_index(c, timeout_s)
                if self.trigger_time_ns(n) >= until_ns:
                    c.queue.appendleft(n)  # the first one kept: read next
                    return n_skipped, self._read(c, timeout_s)
                n_skipped += 1
                c.stats.skipped += 1
        except CameraTimeout:
            pass
        return n_skipped, None


    # ----------------------------------------------------------------- pairs at once
    def pair_capable(self) -> bool:
        """Whether :meth:`read_pair_into` can serve: both cameras started, whole frames,
        no injected faults (those are per camera: the frame-by-frame path simulates them)."""
        full = (0, 0, self.cfg.camera.width, self.cfg.camera.height)
        return (not self.faults and all(c.started and not c.must_reopen for c in self._cams)
                and all((c.settings.roi.x, c.settings.roi.y, c.settings.roi.width,
                         c.settings.roi.height) == full for c in self._cams))

    def read_pair_into(self, left: np.ndarray, right: np.ndarray, timeout_s: float = 1.0) -> PairMeta:
        """Both cameras' frames of the next trigger rendered straight into ``left`` and
        ``right`` ((H, W) uint8): the same frames, ids, timestamps and (paced) buffer
        overflows as reading the two cameras one by one, without the pairing and copies.
        Only while :meth:`pair_capable`."""
        if not self.pair_capable():
            raise CameraError("mock rig: pairs at once need both cameras started, whole frames "
                              "and no injected faults")
        a, b = self._cams
        if self._pair_queue is None:
            self._pair_queue = deque()
            a.cursor = b.cursor = max(a.cursor, b.cursor)
        q = self._pair_queue
        if not self.pace:
            n = a.cursor
        else:
            deadline = time.monotonic_ns() + round(timeout_s * 1e9)
            while True:
                now = time.monotonic_ns()
                done = self._triggers_done(now)
                while a.cursor < done:  # arrivals since the last read (a full queue drops them)
                    if len(q) < self.buffer_frames:
                        q.append(a.cursor)
                    else:
                        a.stats.dropped_buffer += 1
                        b.stats.dropped_buffer += 1
                    a.cursor += 1
                b.cursor = a.cursor
                if q:
                    break
                next_ns = self.trigger_time_ns(a.cursor) + round(self._exposure_s * 1e9)
                if next_ns > deadline:
                    if deadline > now:
                        time.sleep((deadline - now) / 1e9)
                    raise CameraTimeout(f"mock rig: no pair within {timeout_s:g} s")
                if next_ns > now:
                    time.sleep((next_ns - now) / 1e9)
            n = q.popleft()
        if not self.pace:
            a.cursor += 1
            b.cursor = a.cursor
        self.scene.render_pair_into(n, left, right)
        a.stats.delivered += 1
        b.stats.delivered += 1
        t = self.trigger_time_ns(n)
        return PairMeta(n, n, t, t)


class MockCamera(Camera):
    """One camera of a :class:`MockRig` (``"left"`` or ``"right"``)."""

    def __init__(self, rig: MockRig, idx: int) -> None:
        self.rig = rig
        self._c = rig._cams[idx]
        self.name = self._c.name

    @property
    def truth(self):  # -> iscd.sim.Scene
        """The simulated scene behind the images (ground truth: ``truth.truth(frames)``)."""
        return self.rig.scene

    @property
    def stats(self) -> CameraStats:
        return self._c.stats

    @property
    def settings(self) -> CameraSettings | None:
        return self._c.settings

    @property
    def waits_for_consumer(self) -> bool:  # type: ignore[override]
        """Unpaced (``rig.pace = false``): its frames are made when read."""
        return not self.rig.pace

    reuses_buffers = False  # every read renders into (or takes from the cache) a new array
    makes_images_on_read = True  # the renderer runs in the reader's thread

    def open(self) -> None:
        self.rig._open(self._c)

    def configure(self, settings: CameraSettings) -> CameraSettings:
        return self.rig._configure(self._c, settings)

    def start(self) -> None:
        self.rig._start(self._c)

    def read(self, timeout_s: float = 1.0) -> Frame:
        return self.rig._read(self._c, timeout_s)

    def skip_to(self, until_ns: int, timeout_s: float = 1.0,
                max_frames: int = 1 << 16) -> tuple[int, Frame | None]:
        return self.rig._skip_to(self._c, until_ns, timeout_s, max_frames)

    def stop(self) -> None:
        self.rig._stop(self._c)

    def close(self) -> None:
        self.rig._stop(self._c)
        self._c.opened = False

    def trigger(self) -> None:
        self.rig._trigger(self._c)

    def pair_source(self) -> "MockRig | None":
        """The rig, which renders both cameras' frames of a trigger at once into caller
        buffers (:meth:`MockRig.read_pair_into`), while it can."""
        return self.rig if self.rig.pair_capable() else None


# ----------------------------------------------------------------- mock:// URLs
def waits_for_consumer(cfg: Config) -> bool:
    """Whether the rig of ``cfg`` is the mock rig that waits for its consumer: unpaced
    (``rig.pace = false``). Its pairs come from :class:`MockRig` as a pair source, or with
    injected faults frame by frame from its cameras, read in step
    (:attr:`MockCamera.waits_for_consumer`); either way nothing is dropped for want of
    time. The daemon then waits for its demodulation worker too and sheds nothing."""
    return cfg.rig.scheme == "mock" and not cfg.rig.pace


SCENES = ("default",)
"""``mock://NAME``: ``default`` is the scene of the config the rig is opened with (the
embedded default scene without one)."""


def _check_url(u: urls.CameraURL) -> None:
    if u.target not in SCENES:
        raise urls.fail(u, f"unknown mock scene {u.target!r} (scenes: {', '.join(SCENES)}; "
                           f"mock://default shows the config's own scene)")
    urls.int_option(u, "seed")
    urls.bool_option(u, "noise")


def _open_url(u: urls.CameraURL, cfg: Config | None = None, *, level_source: object | None = None,
              buffer_frames: int | None = None, noise: bool | None = None) -> tuple["MockCamera", "MockCamera"]:
    """``mock://default?seed=N&noise=false``: the (left, right) cameras of a new rig showing
    the scene of ``cfg`` (None: the embedded default config), with ``[scene] seed`` = N
    and noise-free frames if asked; queues of ``buffer_frames`` (default ``[rig]
    buffer_frames``)."""
    if cfg is None:
        from iscd.core.config import default_config

        cfg = default_config()
    seed = urls.int_option(u, "seed")
    if seed is not None:
        cfg = cfg.replace(scene=dataclasses.replace(cfg.scene, seed=seed))
    url_noise = urls.bool_option(u, "noise")
    return MockRig.from_config(cfg, level_source=level_source,
                               buffer_frames=cfg.rig.buffer_frames if buffer_frames is None else buffer_frames,
                               noise=url_noise if url_noise is not None else (True if noise is None else noise))


urls.register(urls.Backend(
    "mock", _open_url, stereo=True, target="host", what="scene", form="mock://default",
    options={"seed": "scene seed (replaces [scene] seed)", "noise": "false: noise-free frames"},
    check=_check_url, default_target="default", hardware=False,
    discover=lambda **_: [{"backend": "mock", "name": "default", "url": "mock://default"}],
    summary="the simulated stereo rig (scene of the config), no hardware"))
