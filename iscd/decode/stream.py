"""The streaming decode pipeline shared by ``iscd run`` (live) and ``iscd replay`` (offline).

Stereo frames arrive in blocks (ids, timestamps, left and right images); the pipeline

1. acquires the transmitter (:func:`iscd.decode.tracking.detect.detect_array` on both cameras,
   matched on the same rectified rows) and then tracks it block by block;
2. extracts each LED's luminance in both cameras (ROI mean, eq. 3.10) and feeds the
   packet assembler (timing, channel estimation, decision, CRC: :mod:`iscd.decode.comms`);
3. measures the range every frame (:class:`iscd.decode.ranging.stereo.StereoRanger`);

and returns JSON-ready records (SPEC section 7). It holds no threads and does no I/O, so
``replay`` and the daemon produce the same records from the same frames.

A candidate that blinks but never sends a header within ``verify_packets`` packet
durations (a flickering lamp) is excluded and acquisition starts again; a steady light
never shows in the temporal gradient at all.

With ``[transmitter] rows = cols = "auto"`` (``iscd replay`` of a config without a
``[transmitter]`` table) the array's shape is not configured: each acquisition infers it
from the lit spots (:func:`iscd.decode.tracking.detect.detect_auto`), v1 packets are read
with the config's (or the SPEC's) M, K, F, and a v2 PHY header that names another shape
restarts acquisition with the header's shape (``shape_mismatches``).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from iscd.calibration.io import StereoCalibration
from iscd.core.airinterface import AirInterface
from iscd.core.config import Config, ConfigError, config_section, section
from iscd.core.records import RangeFilteredRecord, RangeLedsRecord, RangeRecord
from iscd.decode.pipe import PipeDemodWorker as DemodWorker
from iscd.decode.tracking.follow_kernel import follow_and_measure_compiled
from iscd.decode.tracking.luminance import PixelBackground, area_sigma, follow_and_measure, grid_sample, patch_half
from iscd.decode.tracking.registered_background import RING_PX, RegisteredBackground, ShiftLeader, window_half
from iscd.decode.tracking.stereo_hold import StereoTrend, hold_block
from iscd.decode.tracking.stabilize import stabilize_into
from iscd.decode.tracking.partner import find_partner, reference_series
from iscd.decode.tracking.detect import (GridFit, square_grid, detect_array, detect_auto, light_map, match_stereo, track_box,
                                         track_on_light)
from iscd.decode.tracking.track_kernel import LightAccumulator, square_grid_compiled, track_on_light_compiled
from iscd.decode.tracking import path_kernel  # noqa: F401  (its kernels warm up with the others)
from iscd.decode.tracking.trajectory import PATH_REACH_PX, follow_path
from iscd.decode.comms.packets import Packet, PacketAssembler
from iscd.decode.comms.settings import receiver_config
from iscd.decode.ranging.kalman import RangeKalman
from iscd.decode.ranging.range import LedRanger
from iscd.decode.ranging.stereo import RangingSettings, StereoRanger

log = logging.getLogger(__name__)


@config_section("tracking")
@dataclass(frozen=True)
class PipelineSettings:
    """Finding, following and measuring the LEDs: detection, tracking, the luminance window (docs/receiver.md)."""

    acquire_frames: int = field(default=64, metadata={"lo": 8, "hi": 1024, "doc": "frames per detection attempt"})
    acquire_lookback_frames: int = field(default=256, metadata={"lo": 0, "hi": 4096, "doc": "frames kept while looking for the transmitter (the last ones; each attempt looks at the last acquire_frames of them): once found it is decoded from the first kept, so a packet whose header came during attempts that failed (a far, dim LED found at the second to fourth try) is not lost; at most acquire_frames = only the finding attempt's own frames (before session 17; 128 in sessions 17-18)"})
    track_every_frames: int = field(default=32, metadata={"lo": 4, "hi": 4096, "doc": "re-fit the LED grid this often"})
    verify_packets: float = field(default=2.5, metadata={"lo": 1.2, "doc": "packets to wait for a header before rejecting a candidate"})
    exclude_packets: float = field(default=8.0, metadata={"lo": 0, "doc": "a rejected candidate is ignored this many packets"})
    reset_gap_frames: int = field(default=32, metadata={"lo": 1, "doc": "a gap of more frames restarts the packet search"})
    lost_packets: float = field(default=1.2, metadata={"lo": 0.1, "doc": "dark this many packet durations = lost"})
    lost_score_ratio: float = field(default=0.2, metadata={"lo": 0, "hi": 1, "doc": "grid score below this share of the first fit = lost"})
    roi_radius_px: int = field(default=-1, metadata={"lo": -1, "hi": 8, "doc": "half-size of the box that follows each spot frame by frame, px ((2r+1)^2 pixels); -1 = from the spot size and LED pitch"})
    roi_sigma_px: float = field(default=-1.0, metadata={"lo": -1.0, "hi": 8.0, "doc": "luminance window: Gaussian weights of this RMS radius, px; -1 = matched to the spot (its FWHM / 2.355, at most (pitch - 0.8) / 4 in an array)"})
    ranging: bool = field(default=True, metadata={"doc": "measure the range every frame"})
    background: bool = field(default=False, metadata={"doc": "luminance and centroids of the light above a per-pixel background (each pixel's least value in the frames its LEDs were dark): a textured background under a window that moves with the LED then cancels"})
    lit_background: bool = field(default=False, metadata={"doc": "judge which LEDs are lit (they steer the following) on the light above the per-pixel background held across blocks, not on each block's own minimum: blocks shorter than 16 pairs ([daemon] block_max = 8 for lower latency) then judge as well as long ones; costs ~20 % of the frame loop, so off for the daemon's blocks of 16"})
    window_scale: float = field(default=1.0, metadata={"lo": 0.5, "hi": 4.0, "doc": "luminance window relative to the spot-matched Gaussian (roi_sigma_px = -1): wider reaches the unsaturated wings of a spot whose core clips"})
    one_led_window_scale: float = field(default=1.5, metadata={"lo": 0.5, "hi": 4.0, "doc": "one LED's luminance window relative to the spot-matched Gaussian, times window_scale: its brightest pixels clip as a car closes in and the level then lives in the spot's wings and blooming, which a wider window reaches (one LED has no neighbour to let in); measured on randomized approaches never looked at (docs/eval.md, session 30)"})
    growth_from_block: bool = field(default=True, metadata={"doc": "one LED: its image's growth (the luminance window's and the following box's scale) from the median disparity of the last block's followed frames; false = from the disparity of the block's starting positions alone, where one frame followed 2 px off widened the window 10 % for a block (docs/eval.md, session 33)"})
    window_follows_spot: bool = field(default=False, metadata={"doc": "the luminance window follows the spot's measured size (its half-maximum area, smoothed over ~10 blocks) times window_scale, instead of the size at acquisition grown with the array"})
    background_rise_dn: float = field(default=0.25, metadata={"lo": 0, "doc": "how fast the per-pixel background follows a background that brightens, DN per block"})
    background_one_led: bool = field(default=True, metadata={"doc": "the per-pixel background (as background) whenever the transmitter is one LED: measured on a moving car's randomized scenes it delivered more packets (4 seed sets, docs/eval.md), and one LED's static suites (SER, range errors) are unchanged; an array keeps background's setting (its neighbours' light under a pixel cost static f/4 receivers packets)"})
    follow_passes: int = field(default=3, metadata={"lo": 0, "hi": 8, "doc": "further following passes per block along the LEDs' path (their lit frames' centres smoothed in time), while the path moves more than path_settle_px; dark and dimly lit frames are measured on the path; 0 = one pass from the last block's end (before issue 12)"})
    max_transmitters: int = field(default=1, metadata={"lo": 1, "hi": 16, "doc": "transmitters decoded at once (each its own tracking, timing, channel, packets, ranging, and a tx index once its first packet is valid); 1 = the one strongest, as before; > 1: iscd.decode.multi.MultiDecoder (docs/receiver.md)"})
    shapes: str = field(default="auto", metadata={"doc": "with max_transmitters > 1, which transmitters to look for: \"auto\" (any shape, each inferred; v1 packets read with [transmitter]'s M, K, F), \"config\" (only [transmitter]'s rows x cols), or a list such as \"8x8, 1x1\""})
    search_every_frames: int = field(default=256, metadata={"lo": 8, "hi": 100000, "doc": "with max_transmitters > 1 and a transmitter tracked: look for another one every this many frames (each look reads acquire_frames whole frames)"})
    registered_background: bool = field(default=True, metadata={"doc": "with the per-pixel background and one LED: the luminance takes the background from a map held in the scene's frame, at the image's own whole-pixel shift measured each frame on a ring of background pixels (iscd.decode.tracking.registered_background): rig vibration moves the texture under the spot with it; false = the image-indexed least value as before"})
    registered_subpixel: bool = field(default=True, metadata={"doc": "with registered_background: also each frame's residual image shift beyond the whole pixels (a least-squares fit of the ring's light against the map's gradient) and the background under the window moved on by it to first order (a real rig's image moves continuously, not by whole pixels); false = whole pixels only (before session 36)"})
    shift_hint: bool = field(default=True, metadata={"doc": "with registered_background: one camera makes the other's image move (shift step) in a frame where its own ring matches the moved shift at least as well (a rigid rig's cameras move together; a defocused camera's blurred texture often cannot tell a 1 px move by itself); the camera whose ring tells the shifts apart more clearly leads (iscd.decode.tracking.registered_background.ShiftLeader)"})
    stabilized_following: bool = field(default=True, metadata={"doc": "with registered_background: the LED is followed in the background's own frame (the frames moved back by the image shifts predicted against the registered map, iscd.decode.tracking.stabilize), so the per-pixel background under the centroids holds the texture that vibration moves under the spot; false = followed in the image as before"})
    stereo_hold: bool = field(default=True, metadata={"doc": "one LED over the registered background: a frame whose followed disparity (right minus left) jumps by more than a pixel from the median of the last kept frames (carried on at the last blocks' rate) has the camera that walked off (onto a texture edge) put back beside the other's centre at that disparity, until it comes back or for 64 frames at most; a disparity that drifts is never held against; counted in stereo_holds (iscd.decode.tracking.stereo_hold)"})
    path_settle_px: float = field(default=0.5, metadata={"lo": 0.05, "hi": 5.0, "doc": "no further following pass once the path is within this of where the last pass started, px"})

    def __post_init__(self) -> None:
        parse_shapes(self.shapes)  # a bad list is a config error naming the key (iscd config --check)


def parse_shapes(text: str) -> set[tuple[int, int]] | str | None:
    """``[tracking] shapes``: ``"auto"`` -> None (any shape), ``"config"`` -> "config", or
    ``"8x8, 1x1"`` -> {(8, 8), (1, 1)}. Raises ConfigError naming the key on anything else."""
    t = str(text).strip().lower()
    if t in ("auto", ""):
        return None
    if t == "config":
        return "config"
    out: set[tuple[int, int]] = set()
    for part in t.split(","):
        r, x, c = part.strip().partition("x")
        if not (x and r.strip().isdigit() and c.strip().isdigit()) or int(r) < 1 or int(c) < 1:
            raise ConfigError(f'tracking.shapes: expected "auto", "config" or a list like "8x8, 1x1", got {text!r}')
        out.add((int(r), int(c)))
    return out


def _jsonable(rec: dict[str, Any]) -> dict[str, Any]:
    """numpy scalars -> Python numbers, so that json.dumps takes the record."""
    out: dict[str, Any] = {}
    for k, v in rec.items():
        if isinstance(v, np.generic):
            v = v.item()
        if isinstance(v, float) and not math.isfinite(v):
            v = None
        out[k] = v
    return out


def _mean0(a: np.ndarray) -> np.ndarray:
    """``a.mean(0)`` of a float64 array, the same value (numpy's mean is this sum and division)
    without its Python wrapper (the decoder takes a dozen a block)."""
    return np.add.reduce(a, 0) / a.shape[0]


def _spread(centres: np.ndarray) -> float:
    """RMS distance of points (N, 2) from their mean, px (0 for one point)."""
    c = np.asarray(centres, dtype=np.float64)
    if c.shape[0] <= 1:
        return 0.0
    d = c - _mean0(c)
    return float(np.sqrt(np.add.reduce(np.add.reduce(d * d, 1)) / c.shape[0]))  # (d ** 2).sum(1).mean()


def _extent(xy: np.ndarray) -> tuple[list[float], list[float]]:
    """The least and largest (x, y) of points (N, 2), px."""
    return xy.min(0).tolist(), xy.max(0).tolist()


def _clip(b: tuple[int, int, int, int], W: int, H: int) -> tuple[int, int, int, int]:
    return max(0, b[0]), max(0, b[1]), min(W, b[2]), min(H, b[3])


def _union(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    return min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])


def _track_window(fit: GridFit, W: int, H: int) -> tuple[int, int, int, int]:
    """The pixels that tracking and luminance read around a fit (as track_array's margin)."""
    return _clip(fit.bbox(2 * fit.pitch_px + 4), W, H)


def _track_in(light: np.ndarray, window: tuple[int, int, int, int], fit: GridFit,
              compiled: bool = True) -> GridFit:
    """:func:`iscd.decode.tracking.detect.track_array` of ``fit`` on the light map of the
    tracking window (x0, y0, x1, y1) px."""
    ax0, ay0 = window[0], window[1]
    p = fit.shifted(-ax0, -ay0)
    x0, y0, x1, y1 = track_box(p, light.shape)
    track = track_on_light_compiled if compiled else track_on_light
    return track(light[y0:y1, x0:x1], p, x0, y0).shifted(ax0, ay0)


@dataclass
class _Track:
    left: GridFit
    right: GridFit
    first_score: float
    since_frame: int
    last_header_frame: int | None = None
    frames_since_header: int = 0
    """decoded frames since acquisition, the last packet or a search restart"""
    roi_radius: tuple[int, int] = (1, 1)
    """half-size of the box that follows each spot, per camera"""
    spread0: tuple[float, float] = (0.0, 0.0)
    """RMS distance of the LEDs from the array's centre at acquisition, px, per camera"""
    roi_sigma: tuple[float, float] = (1.0, 1.0)
    """Gaussian luminance window per camera, px, fixed while the track lasts (a changing
    window would change the channel within a packet)"""
    low_frames: int = 0
    """decoded frames since the grid last fitted well (dark stretches hold the fit)"""
    fit_frame: float = math.nan
    """mean frame id of the frames the current fits came from"""
    fit_shift: tuple[np.ndarray, np.ndarray] | None = None
    """per camera the mean image shift (x, y) px over the current fits' frames, as the
    registered background of one LED measured it (None where it was not measured)"""
    prev: tuple[GridFit, GridFit] | None = None
    """the fits before the current ones (for the grid's motion), fitted at ``prev_frame``"""
    prev_frame: float = math.nan
    disparity0: float = 0.0
    """right x - left x of the array's centre at acquisition, px (one LED's growth)"""
    shape_confirmed: bool = False
    """auto shape: a packet was delivered, or a v2 PHY header named the tracked shape"""
    unconfirmed_bad: int = 0
    """auto shape: v1 packets failed while the shape is not confirmed"""


def touched_buffers(n: int, shape: tuple[int, ...], dtype: Any) -> tuple[np.ndarray, np.ndarray]:
    """Two (n, *shape) arrays whose every page has been written (no page faults later)."""
    out = (np.empty((n,) + tuple(shape), dtype), np.empty((n,) + tuple(shape), dtype))
    for a in out:
        a.fill(0)
    return out


def shared_buffers(store: dict[tuple, tuple[np.ndarray, np.ndarray]], frame: np.ndarray, n: int,
                   use: str) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) buffers of at least ``n`` frames like ``frame`` for ``use`` from
    ``store`` (by use, frame size and dtype), made and touched (:func:`touched_buffers`)
    when none there is large enough."""
    key = (use,) + frame.shape + (frame.dtype.str,)
    buf = store.get(key)
    if buf is None or buf[0].shape[0] < n:
        buf = store[key] = touched_buffers(n, frame.shape, frame.dtype)
    return buf


@dataclass
class KeptFrames:
    """Frames a searcher kept (:meth:`StreamDecoder.set_lookback`): ids, t_s (s) and the
    left/right images, one (H, W) copy each (not stacked: a stack of hundreds is ~100 ms of
    fresh memory; they are decoded in steps)."""

    ids: np.ndarray
    t_s: np.ndarray
    left: list[np.ndarray]
    right: list[np.ndarray]
    start: int = 0
    """the first frame the finder decodes (a place rejected before as a blinker: only the
    look's frames, not the whole look-back; a searcher adopting them looks at all)"""

    def __len__(self) -> int:
        return len(self.left)

    def take(self, a: int, b: int, out: tuple[np.ndarray, np.ndarray] | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Frames a..b-1 as (ids, t_s, left (n, H, W), right (n, H, W)); ``out``: (left,
        right) buffers of at least b - a frames to stack them into (memory already touched:
        a fresh stack's page faults are most of its cost)."""
        if out is None or out[0].shape[0] < b - a:
            return self.ids[a:b], self.t_s[a:b], np.stack(self.left[a:b]), np.stack(self.right[a:b])
        lo, ro = out[0][:b - a], out[1][:b - a]
        np.stack(self.left[a:b], out=lo)
        np.stack(self.right[a:b], out=ro)
        return self.ids[a:b], self.t_s[a:b], lo, ro


class StreamDecoder:
    """Decodes one transmitter from a stream of stereo frame blocks (see module docstring)."""

    def __init__(self, cfg: Config, calibration: StereoCalibration | None = None, *, tx_index: int = 0,
                 settings: PipelineSettings | None = None, ranging: RangingSettings | None = None,
                 async_demod: bool | str = False, compiled: bool = True, demod_worker: Any = None) -> None:
        """``async_demod``: run the packet assembler elsewhere, so that demodulating a
        whole packet (0.1-0.2 s for an 8x8 array) does not delay the per-frame work;
        packets then come out of a later :meth:`push` (in order) or of :meth:`finish`.
        ``"process"`` (the daemon): a worker process (:mod:`iscd.decode.worker`'s
        operations over :mod:`iscd.decode.pipe`; no GIL and no helper thread shared with
        the frame loop); ``True`` or ``"thread"``: a worker thread. Replay and
        tests run synchronously. ``compiled``: the per-frame kernels compiled
        (:mod:`iscd.decode.tracking.follow_kernel`); ``False`` runs their numpy references (the
        same records to float tolerance; for tests). ``demod_worker``: with
        ``async_demod="process"``, a worker to use instead of starting one."""
        self.compiled = compiled
        if async_demod not in (False, True, "thread", "process"):
            raise ValueError(f"async_demod: expected False, True, 'thread' or 'process', got {async_demod!r}")
        self.cfg = cfg
        self._pool: ThreadPoolExecutor | None = (
            ThreadPoolExecutor(max_workers=1, thread_name_prefix="iscd-demod")
            if async_demod in (True, "thread") else None)
        self._worker: Any = (demod_worker if demod_worker is not None
                             else DemodWorker() if async_demod == "process" else None)
        """the demodulation worker (``demod_worker``: a slot of one shared by several
        transmitters, :class:`iscd.decode.worker.SlotWorker`)"""
        self._pending: deque[tuple[Future, int]] = deque()
        self._late: list[Packet] = []
        """packets a replaced assembler still held (synchronous decoding): the next records"""
        """asynchronous demodulation steps in order, each with the frames it pushes (a
        track's header wait counts frames once they are demodulated: a worker that is
        still starting must not condemn the transmitter)"""
        if self._worker is not None:  # the worker starts and loads its kernels right away
            self._pending.append((self._worker.submit("warm"), 0))
        self.tx_index = tx_index
        self.settings = settings or section(cfg, PipelineSettings)
        rs = ranging or section(cfg, RangingSettings)
        self.cal = calibration or StereoCalibration.ideal(cfg.camera)
        self.ranger = StereoRanger(self.cal, rs, compiled=compiled) if self.settings.ranging else None
        self.led_ranger = (LedRanger(self.cal, method="iscd", patch_px=rs.patch_px)
                           if self.ranger is not None and rs.per_led else None)
        self.per_led_every = rs.per_led_every_frames
        self.last_centres: tuple[np.ndarray, np.ndarray] | None = None
        """(left, right) (F, N, 2) LED centres px followed in the last block decoded."""
        self.image_shifts: list[np.ndarray | None] = [None, None]
        """Per camera the last block's image shifts (F, 2) px of the registered background
        (``[tracking] registered_background``; None when it is not used)."""
        self.kalman = (RangeKalman(accel_psd=rs.accel_psd, gate=rs.kalman_gate)
                       if self.ranger is not None and rs.kalman else None)
        self.shape_auto = cfg.transmitter.shape_auto
        """the array's shape is inferred at each acquisition ([transmitter] rows = cols = "auto")"""
        self._shape_hint: tuple[int, int] | None = None
        """auto shape: the (rows, cols) a v2 PHY header named, for the next acquisitions"""
        self._hint_tries = 0
        """acquisition attempts left with ``_shape_hint`` (then the shape is inferred again)"""
        self._reacquire = False
        """auto shape: drop the track at the next step (a PHY header named another shape)"""
        self.tx = cfg.transmitter
        """the transmitter the packets are read with: the config's, or with an auto shape
        the config's M, K, F (v1) and the shape of the track (one LED until the first)"""
        self._set_shape(*((1, 1) if self.shape_auto else (cfg.transmitter.rows, cfg.transmitter.cols)))
        self.air = AirInterface.from_config(self.tx)
        self.rx_cfg = receiver_config(cfg)
        self.fps = cfg.camera.fps
        self.packet_frames = self.air.period_symbols * self.fps / cfg.transmitter.symbol_rate_hz
        self.symbol_frames = self.fps / cfg.transmitter.symbol_rate_hz  # acquisition's pace test
        self.track: _Track | None = None
        self.excluded: list[tuple[tuple[int, int, int, int], int]] = []
        """(bbox, until frame id) of rejected candidates."""
        self.extra_exclude: tuple[list[tuple[int, int, int, int]], list[tuple[int, int, int, int]]] = ([], [])
        self.blinker_places: list[tuple[int, int, int, int]] = []
        """left boxes, px, where candidates were rejected as blinkers before (a searcher of
        :class:`iscd.decode.multi.MultiDecoder`): a find there is decoded from its look on"""
        """(left, right) boxes (x0, y0, x1, y1) px that acquisition leaves out besides its own
        rejected candidates: the transmitters other decoders track
        (:class:`iscd.decode.multi.MultiDecoder` sets them before each block)."""
        self.attempts = 0
        """detection attempts made (each on ``acquire_frames`` frames)"""
        self.allowed_shapes: set[tuple[int, int]] | None = None
        """auto shape: only arrays of these (rows, cols) are taken (None: any)"""
        self._ranged_ahead: tuple[int, int] | None = None
        """(first frame id, count) ranged by :meth:`range_ahead` for the next push"""
        self.catch_buffers: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        """buffers a searcher's kept frames are decoded through and its looks stack their
        frames into, by (use, frames, H, W, dtype) (:class:`iscd.decode.multi.MultiDecoder`
        gives all its decoders one dict, filled and touched before the first frame)"""
        self.look_lock = threading.Lock()
        """held by a look while it uses its buffers (one lock for a MultiDecoder's decoders)"""
        """(left, right) buffers of acquire_frames frames the kept frames are decoded through"""
        self._lookback: int | None = None
        self._look: Future | None = None
        """a look in flight in ``_look_pool``"""
        self._look_pool: ThreadPoolExecutor | None = None
        """with ``look_async``: the thread a searcher's looks run in (set_lookback)"""
        self._search_every = self.settings.acquire_frames
        self._since_look = 0
        self.keep_acquired = False
        self.acquired: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | KeptFrames | None = None
        """with ``keep_acquired``: the (ids, t_s, left, right) frames of the last successful
        detection, for the caller to take (another transmitter may be among them)"""
        # room for a detection attempt's frames plus one more block of any size up to
        # acquire_frames: a block that does not divide acquire_frames loses none of the
        # frames collected since the last attempt (a first header among them)
        keep = 2 * self.settings.acquire_frames
        self._acq_l: deque[np.ndarray] = deque(maxlen=keep)
        self._acq_r: deque[np.ndarray] = deque(maxlen=keep)
        self._acq_ids: deque[tuple[int, float]] = deque(maxlen=keep)
        self._own_lookback = False
        """the look-back is the single decoder's ``acquire_lookback_frames`` (not a searcher's)"""
        if self.settings.acquire_lookback_frames > self.settings.acquire_frames:
            # an attempt looks at the last acquire_frames; a find decodes all kept frames
            self.set_lookback(self.settings.acquire_frames, self.settings.acquire_lookback_frames)
            self._own_lookback = True
        self._since_fit = 0
        self._last_id: int | None = None
        self._reach = 0  # px around an LED start that the following read last block (needed_windows)
        self.last_luminance: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._deferred: tuple[np.ndarray, ...] | None = None
        """the rest of a block pushed with ``defer=True`` (see :meth:`finish_block`)"""
        """(ids, t_s, lum_left, lum_right) of the last block decoded (for live views)."""
        self._blk_l: list[np.ndarray] = []
        self._blk_r: list[np.ndarray] = []
        self._acc: tuple[LightAccumulator, LightAccumulator] | None = None
        """the tracking interval's light maps, per camera (the compiled path)"""
        self._ids_sum = 0.0
        self._shift_sum = np.zeros((2, 2))
        self._shift_n = 0
        self._followed: list[np.ndarray | None] = [None, None]
        self._stereo_trend = StereoTrend()
        """one LED: the stereo hold's state carried from block to block (:meth:`_hold_to_stereo`)"""
        self._followed_disparity: float | None = None
        """one LED: the median over the last decoded block's frames of its followed right minus
        left x, px (:meth:`_growth`)"""
        self._motion_memo: list[Any] = [None, None]  # _grid_motion's per camera
        self._extent_memo: list[Any] = [None, None]  # _reach_window's: (fit, extent of its centres)
        """per camera, the LED centres (N, 2) px refined in the last decoded frame"""
        self._lit_light: np.ndarray | None = None
        self._lum_floor: list[np.ndarray | None] = [None, None]
        self._path_end: list[np.ndarray | None] = [None, None]
        self.follow_passes_run = 0
        """following passes run after the first, over the decoder's life (follow_passes)"""
        self._backgrounds: list[PixelBackground] | None = None
        self._stab_last: list[np.ndarray] | None = None
        """Per camera the image shift of the last block's last frame (stabilized_following;
        None: the registered maps are new, shift 0)."""
        self._block_shifts: tuple[np.ndarray, np.ndarray] | None = None
        """the image shifts of the block just measured, for the fits' interval (_retrack)"""
        self._stab_bufs: list[np.ndarray | None] = [None, None]
        """Per camera the stabilized frames' buffer (stabilized_following)."""
        self._registered: list[RegisteredBackground] | None = None
        self._shift_leader = ShiftLeader()
        self._spot_area: np.ndarray | None = None
        """per camera, the box light of a lit LED (following ignores LEDs far below it)"""
        self._win: tuple[tuple[int, int, int, int], tuple[int, int, int, int]] = ((0, 0, 0, 0), (0, 0, 0, 0))
        self._new_assembler()
        self.counters: dict[str, int] = {"acquisitions": 0, "guided_acquisitions": 0, "losses": 0, "rejected_candidates": 0,
                                         "packets_ok": 0, "packets_bad": 0, "ranges": 0,
                                         "frames_decoded": 0, "assembler_resets": 0,
                                         "ranging_skipped": 0, "led_ranges_shed": 0,
                                         "demod_worker_restarts": 0, "following_resets": 0, "stereo_holds": 0,
                                         "shape_mismatches": 0, "shape_retries": 0, "lookbacks_skipped": 0}

    def _set_shape(self, rows: int, cols: int) -> None:
        """The array's shape (of the config, or inferred at acquisition) and what follows
        from it: the LEDs that steer the following, the transmitter the packets are read
        with (auto shape: v1 geometry; v2 packets bring their own)."""
        if (int(rows), int(cols)) != (getattr(self, "rows", rows), getattr(self, "cols", cols)):
            # per-LED state of the last track
            self._lum_floor = [None, None]
            self._path_end = [None, None]
            self._followed = [None, None]
            self._followed_disparity = None
            self._stereo_trend = StereoTrend()
        self.rows, self.cols = int(rows), int(cols)
        self._use = grid_sample(self.rows, self.cols)
        """the LEDs whose centroids steer the following (fixed by the array's shape)"""
        if self.shape_auto:
            self.tx = replace(self.cfg.transmitter, rows=self.rows, cols=self.cols, air_interface="v1")

    # ------------------------------------------------------------------ demodulation hook
    def _make_assembler(self) -> PacketAssembler:
        return PacketAssembler(self.tx, fps=self.fps, exposure_s=self.cfg.camera.exposure_s,
                               cfg=self.rx_cfg)

    def _records(self, packets: list[Packet]) -> list[dict]:
        out: list[dict] = []
        for pkt in packets:
            self.counters["packets_ok" if pkt.crc_ok else "packets_bad"] += 1
            if self.shape_auto and self.track is not None and not self._reacquire:
                self._check_shape(self.track, pkt)
            if self.track is not None:
                self.track.last_header_frame = int(pkt.frame)
                self.track.frames_since_header = 0
            out.append(_jsonable(pkt.record(self.tx_index)))
        return out

    AUTO_BAD_PACKETS = 3
    """Auto shape: v1 packets that fail in a row, none delivered and no v2 header read on
    the track, before the shape is inferred again (a wrong shape reads no header)."""

    def _check_shape(self, tr: _Track, pkt: Packet) -> None:
        """Auto shape: the packet's word on the inferred shape. A v2 PHY header is read
        whenever rows x cols is the LED count tracked; if it names another arrangement of
        as many LEDs the LED order is not the one tracked: acquisition restarts with the
        header's shape (``shape_mismatches``). A track whose first
        :attr:`AUTO_BAD_PACKETS` packets all fail as v1 restarts acquisition too
        (``shape_retries``)."""
        if pkt.shape is not None and pkt.shape != (self.rows, self.cols):
            self.counters["shape_mismatches"] += 1
            log.warning("the PHY header says %dx%d LEDs, the array was inferred %dx%d: re-acquiring",
                        *pkt.shape, self.rows, self.cols)
            self._shape_hint = pkt.shape
            self._hint_tries = self.HINT_TRIES
            self._reacquire = True
        elif pkt.crc_ok or pkt.shape is not None:
            tr.shape_confirmed = True
        elif not tr.shape_confirmed:
            tr.unconfirmed_bad += 1
            if tr.unconfirmed_bad >= self.AUTO_BAD_PACKETS:
                self.counters["shape_retries"] += 1
                log.warning("%d packets failed on the inferred %dx%d array: inferring its shape again",
                            tr.unconfirmed_bad, self.rows, self.cols)
                self._reacquire = True

    def wait_ready(self, timeout_s: float = 300.0, should_stop: Callable[[], bool] | None = None) -> bool:
        """Wait until the demodulation worker has started and loaded (or compiled) its
        kernels, at most ``timeout_s`` s, and, with ``should_stop``, only until it says True
        (asked every 0.2 s); True when it is ready (or there is none). The daemon calls it
        before the cameras start."""
        if self._worker is None or not self._pending:
            return True
        fut = self._pending[0][0]
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            try:
                fut.result(timeout=max(0.0, min(left, 0.2) if should_stop is not None else left))
                return True
            except TimeoutError:
                if left <= 0.2 or (should_stop is not None and should_stop()):
                    return False
            except Exception:  # noqa: BLE001 - a dead worker: _collect handles it
                return False

    @property
    def pending_steps(self) -> int:
        """Demodulation steps handed to the worker and not yet collected."""
        return len(self._pending)

    def wait_for_worker(self, most: int) -> None:
        """Block until at most ``most`` demodulation steps are in flight (done steps are
        collected by the next :meth:`push` as ever). For a source that waits for the
        consumer: the frame loop must not run ahead of the worker without bound."""
        if len(self._pending) > most:
            try:
                self._pending[len(self._pending) - most - 1][0].result()  # steps finish in order
            except Exception:  # noqa: BLE001 - a dead worker: _collect handles it
                pass

    @property
    def worker_pids(self) -> list[int]:
        """Process ids of the demodulation worker (``async_demod="process"``), else []."""
        return self._worker.pids if self._worker is not None else []

    def _new_assembler(self) -> None:
        """A fresh assembler (a new track); steps already queued finish on the old one."""
        if self._worker is None:
            old = getattr(self, "assembler", None)
            if old is not None:  # a failed packet it held for the frames after it is not dropped
                if self._pool is None:
                    self._late += old.reset()
                else:
                    self._pending.append((self._pool.submit(old.reset), 0))
            self.assembler = self._make_assembler()
        else:
            self._pending.append((self._worker.submit("new", self.tx, self.fps,
                                                      self.cfg.camera.exposure_s, self.rx_cfg), 0))

    def _demod(self, frame_ids: np.ndarray, t_s: np.ndarray, lum_l: np.ndarray, lum_r: np.ndarray,
               centres: tuple[np.ndarray, np.ndarray] | None = None) -> list[dict]:
        n = len(frame_ids)
        if self._worker is not None:
            self._pending.append((self._worker.submit("push", frame_ids, t_s, lum_l, lum_r, centres), n))
            return []
        if self._pool is None:
            if self.track is not None:
                self.track.frames_since_header += n
            return self._records(self.assembler.push(frame_ids, t_s, lum_l, lum_r, centres))
        self._pending.append((self._pool.submit(self.assembler.push, frame_ids, t_s, lum_l, lum_r, centres), n))
        return []

    def _block_centres(self, n: int) -> tuple[np.ndarray, np.ndarray] | None:
        """One LED: the centres the luminance of the block of ``n`` frames was measured at
        (:attr:`last_centres`), for the packet assembler's phase attempt
        (:mod:`iscd.decode.comms.pixelphase`); None for an array (the assembler keeps none)."""
        c = self.last_centres
        if self.rows * self.cols != 1 or c is None or c[0].shape[0] != n or c[1].shape[0] != n:
            return None
        return c

    def _reset_assembler(self) -> list[dict]:
        """Restart the packet search; returns the records of a failed packet the assembler
        held (decoded synchronously; with a worker or pool they come with its steps)."""
        if self._worker is not None:
            self._pending.append((self._worker.submit("reset"), 0))
        elif self._pool is None:
            return self._records(self.assembler.reset())
        else:  # in order with the pushes already queued
            self._pending.append((self._pool.submit(self.assembler.reset), 0))
        return []

    def _collect(self, wait: bool = False) -> list[dict]:
        """Records of the finished asynchronous demodulation steps, in order."""
        out: list[dict] = self._records(self._late) if self._late else []
        self._late = []
        while self._pending and (wait or self._pending[0][0].done()):
            fut, nf = self._pending.popleft()
            try:
                packets = fut.result()
                if self.track is not None:
                    self.track.frames_since_header += nf
                out += self._records(packets)
            except BrokenProcessPool:
                # the worker died (killed, out of memory): the packet in progress is lost;
                # a new worker starts with a fresh assembler
                log.error("demodulation worker died; starting a new one (packet in progress lost)")
                self.counters["demod_worker_restarts"] += 1
                self._pending.clear()
                assert self._worker is not None
                self._worker.shutdown(wait=False)
                self._worker = DemodWorker()
                self._pending.append((self._worker.submit("warm"), 0))
                self._new_assembler()
                break
        return out

    # ------------------------------------------------------------------ main entry
    def push(self, frame_ids: np.ndarray, t_s: np.ndarray, left: np.ndarray | None, right: np.ndarray | None,
             *, ranging: bool = True, ranging_every: int = 1, per_led: bool = True,
             defer: bool = False, adopt: KeptFrames | None = None, owned: bool = False) -> list[dict]:
        """Process a block of stereo frames; returns the records it produced.

        frame_ids: (n,) int (left-camera frame ids of the pairs); t_s: (n,) exposure start,
        s; left/right: (n, H, W) images of the same pairs. What the daemon sheds when it
        falls behind (:mod:`iscd.service.overload`; packets are never shed): ``ranging=False``
        skips the range measurement for this block, ``ranging_every=k`` ranges only the
        frames whose id is a multiple of k (counted in ``counters["ranging_skipped"]``),
        ``per_led=False`` skips the per-LED ranges (``counters["led_ranges_shed"]``).

        ``defer=True`` (the daemon): return the block's range records as soon as they are
        measured and leave the rest of the block -- following the LEDs and measuring their
        luminance, handing it to the demodulation, the tracking update, the packets that
        came back -- to
        :meth:`finish_block`, which must be called (with ``left``/``right`` untouched)
        before the next push; the same steps in the same order among themselves, so the
        same records (packets then come out of :meth:`finish_block`). The ranges do not
        depend on those steps; their latency then does not include them.

        ``adopt`` (a searcher, :class:`iscd.decode.multi.MultiDecoder`): instead of a block,
        the frames another searcher kept (:attr:`acquired`), taken over without a copy
        (``frame_ids``/``t_s`` are theirs, ``left``/``right`` None).

        ``owned=True``: ``left``/``right`` are the decoder's to keep (the caller never writes
        them again: :attr:`iscd.service.blocks.BlockReader.fresh`); frames kept while
        looking for a transmitter are then views of them, not copies.
        """
        if self._deferred is not None:  # a caller that did not finish the last block
            pending = self.finish_block()
        else:
            pending = []
        n = len(frame_ids)
        if n == 0:
            return pending
        records: list[dict] = pending
        if self._reacquire:
            self.restart()
        if self.track is None:
            got = self._acquire(frame_ids, t_s, left, right, adopt, owned)
            if got is None:
                return records
            if isinstance(got, KeptFrames):
                # a searcher's kept frames (hundreds): decoded in steps of acquire_frames
                # (no stack of them all: ~100 ms of fresh memory each); their packets matter,
                # their ranges are past: only the last step's (this block's) are measured
                kw = dict(ranging_every=ranging_every, per_led=per_led)
                A = self.settings.acquire_frames
                last = max(0, len(got) - (n if adopt is None else A))
                for c0 in list(range(min(got.start, last), last, A)) + [last]:
                    c1 = len(got) if c0 == last else min(last, c0 + A)
                    if c1 <= c0 or self.track is None:
                        continue
                    # one buffer for every step (but a deferred last one, whose frames must
                    # outlive this call): its memory touched once, as a fresh stack's page
                    # faults cost more than the copy (~80 ms for 64 frames of 512 x 512 here)
                    deferred_step = defer and c0 == last
                    buf = None if deferred_step else self._buffers(got.left[0], A)
                    ids_c, t_c, l_c, r_c = got.take(c0, c1, buf)
                    records += self.push(ids_c, t_c, l_c, r_c, ranging=ranging and c0 == last,
                                         defer=defer and c0 == last, **kw)
                return records
            # decode the whole acquisition window: a header in it is not lost
            frame_ids, t_s, left, right = got
            n = len(frame_ids)
        tr = self.track
        assert tr is not None
        frame_ids = np.asarray(frame_ids, dtype=np.int64)
        t_s = np.asarray(t_s, dtype=np.float64)
        self.counters["frames_decoded"] += n
        # deferred, the following and luminance wait for finish_block too (the ranges do
        # not use them; per-LED ranges do: then they run here)
        lum_l = lum_r = None
        if not (defer and (self.led_ranger is None or not per_led)):
            lum_l, lum_r = self._luminance(frame_ids, left, right)
            self.last_luminance = (frame_ids, t_s, lum_l, lum_r)
        if not defer:
            assert lum_l is not None and lum_r is not None
            records += self._demod_block(frame_ids, t_s, lum_l, lum_r)
        # frames ranged ahead (range_ahead: the first part of this very block) are not again
        a0 = 0
        if self._ranged_ahead is not None:
            first, count = self._ranged_ahead
            self._ranged_ahead = None
            if n and int(frame_ids[0]) == first:
                a0 = min(count, n)
        some = ranging and (ranging_every <= 1 or bool(np.any(frame_ids % int(ranging_every) == 0)))
        if self.ranger is not None:
            records += self._range(frame_ids[a0:], t_s[a0:], left[a0:], right[a0:], ranging, ranging_every)
        if self.ranger is not None and some:
            if self.led_ranger is not None and per_led:
                records += self._per_led(frame_ids, t_s, left, right)
            elif self.led_ranger is not None:
                self.counters["led_ranges_shed"] += int(np.sum(frame_ids % self.per_led_every == 0))
        if defer:
            self._deferred = (frame_ids, t_s, lum_l, lum_r, left, right)
            return records
        self._retrack(frame_ids, left, right)
        return self._collect() + records

    def _range(self, frame_ids: np.ndarray, t_s: np.ndarray, left: np.ndarray, right: np.ndarray,
               ranging: bool, ranging_every: int) -> list[dict]:
        """The range records of these frames with the current fits (the block's ranging in
        :meth:`push`, or a block's first part in :meth:`range_ahead`), counted."""
        tr = self.track
        assert tr is not None and self.ranger is not None
        n = len(frame_ids)
        records: list[dict] = []
        ranged = np.arange(n) if ranging_every <= 1 else np.flatnonzero(frame_ids % int(ranging_every) == 0)
        if not ranging or ranged.size == 0:
            self.counters["ranging_skipped"] += n
            return records
        self.counters["ranging_skipped"] += n - ranged.size
        rl, rr = (left, right) if ranged.size == n else (left[ranged], right[ranged])
        res = self.ranger.measure(rl, rr, tr.left, tr.right)
        z, dsp, sg = res.z_m.tolist(), res.disparity_px.tolist(), res.sigma_m.tolist()
        fid, ts = frame_ids.tolist(), t_s.tolist()
        tx, json_of, isfinite = self.tx_index, RangeRecord.json_of, math.isfinite
        records = [json_of(tx, fid[i], ts[i], z[k], dsp[k], sg[k])
                   for k, i in enumerate(ranged.tolist()) if isfinite(z[k])]
        self.counters["ranges"] += int(np.isfinite(res.z_m).sum())
        if self.kalman is not None:
            records += self._filtered(frame_ids[ranged], t_s[ranged], res.z_m, res.sigma_m)
        return records

    def range_ahead(self, frame_ids: np.ndarray, t_s: np.ndarray, left: np.ndarray, right: np.ndarray,
                    *, ranging: bool = True, ranging_every: int = 1, per_led: bool = True) -> list[dict]:
        """Range the first pairs of the next block now, before the rest of it is in (the
        daemon: half a block's filling less latency for them); the :meth:`push` of the
        whole block (starting with these same frames, unchanged) then ranges only the
        others. The ranges use the fits the last block left, as the push would: only the
        running background's minimum is taken over fewer frames at a time. Nothing (an
        empty list, and the push ranges them all) while no transmitter is tracked or a
        deferred block is pending, nor while per-LED ranges are on (``per_led`` and a
        ``[ranging] per_led`` ranger: they need the block's luminance, so these pairs'
        records are all out only after the push).

        Parameters
        ----------
        frame_ids, t_s : ndarray
            (k,) the pairs' left-camera frame ids and exposure starts, s.
        left, right : ndarray
            (k, H, W) their images, DN (the block's buffers: the push gets them again).
        ranging, ranging_every, per_led : bool, int, bool
            As :meth:`push` (what the overload policy sheds); the push must get the same.

        Returns
        -------
        list of dict
            The range records (and filtered ranges) of these pairs; :attr:`ranged_ahead`
            then says how many pairs they cover.
        """
        self.drop_ahead()
        k = len(frame_ids)
        if (k == 0 or self.track is None or self.ranger is None or self._reacquire
                or self._deferred is not None or (per_led and self.led_ranger is not None)):
            return []
        frame_ids = np.asarray(frame_ids, dtype=np.int64)
        t_s = np.asarray(t_s, dtype=np.float64)
        records = self._range(frame_ids, t_s, left, right, ranging, ranging_every)
        self._ranged_ahead = (int(frame_ids[0]), k)
        return records

    @property
    def ranged_ahead(self) -> int:
        """Pairs the last :meth:`range_ahead` ranged (0: none; the next push ranges them all)."""
        return self._ranged_ahead[1] if self._ranged_ahead is not None else 0

    def drop_ahead(self) -> None:
        """Forget what :meth:`range_ahead` ranged: the next push ranges every pair (after a
        failed range_ahead, whose records were not put out)."""
        self._ranged_ahead = None

    def finish_block(self) -> list[dict]:
        """The rest of a block pushed with ``defer=True``: the LEDs followed and their
        luminance measured (unless per-LED ranges needed them in :meth:`push`), handed to
        the demodulation, the tracking update; returns the packet records that are ready
        (none if nothing was deferred)."""
        if self._deferred is None:
            return []
        frame_ids, t_s, lum_l, lum_r, left, right = self._deferred
        self._deferred = None
        if self.track is None:  # restarted in between
            return self._collect()
        if lum_l is None:
            lum_l, lum_r = self._luminance(frame_ids, left, right)
            self.last_luminance = (frame_ids, t_s, lum_l, lum_r)
        records = self._demod_block(frame_ids, t_s, lum_l, lum_r)
        self._retrack(frame_ids, left, right)
        return self._collect() + records

    def _demod_block(self, frame_ids: np.ndarray, t_s: np.ndarray, lum_l: np.ndarray,
                     lum_r: np.ndarray) -> list[dict]:
        """A block's luminance to the packet assembler; a long gap (a stalled camera, a
        burst of drops) restarts the packet search first. Returns the packet records
        decoded synchronously (none with a worker)."""
        tr = self.track
        assert tr is not None
        n = len(frame_ids)
        records: list[dict] = []
        centres = self._block_centres(n)
        first, last = int(frame_ids[0]), int(frame_ids[-1])
        if last - first == n - 1 and (n < 3 or bool((frame_ids[1:] > frame_ids[:-1]).all())) \
                and (self._last_id is None or first - self._last_id <= self.settings.reset_gap_frames):
            # consecutive ids (the usual block): no gap in it
            cuts = np.zeros(0, np.int64)
        else:
            prev = np.concatenate([[self._last_id if self._last_id is not None else frame_ids[0] - 1],
                                   frame_ids[:-1]])
            cuts = np.flatnonzero(frame_ids - prev > self.settings.reset_gap_frames)
        bounds = [0, *cuts.tolist(), n]
        for a, b in zip(bounds[:-1], bounds[1:]):
            if a in cuts:
                records += self._reset_assembler()
                self.counters["assembler_resets"] += 1
                tr.since_frame = int(frame_ids[a])  # the header wait starts again
                tr.frames_since_header = 0
            if b > a:
                records += self._demod(frame_ids[a:b], t_s[a:b], lum_l[a:b], lum_r[a:b],
                                       None if centres is None else (centres[0][a:b], centres[1][a:b]))
        self._last_id = int(frame_ids[-1])
        return records

    def _per_led(self, frame_ids: np.ndarray, t_s: np.ndarray, left: np.ndarray, right: np.ndarray) -> list[dict]:
        """``range_leds`` records ([ranging] per_led): one range per LED of the array on the
        frames whose id is a multiple of ``per_led_every_frames``, each LED ranged in its
        own patch (:class:`iscd.decode.ranging.range.LedRanger`) at the position it was followed
        to in that frame; JSON null where an LED gave no valid range (dark in that frame,
        or a poor match). Separate from the whole-array ``range`` records."""
        assert self.led_ranger is not None and self.last_centres is not None
        c_l, c_r = self.last_centres
        if c_l.shape[0] != len(frame_ids):
            return []
        out: list[dict] = []
        for i in np.flatnonzero(np.asarray(frame_ids) % self.per_led_every == 0):
            est = self.led_ranger.measure(left[i], right[i], c_l[i], c_r[i])
            ok = est.valid
            out.append(RangeLedsRecord(
                tx=self.tx_index, frame=int(frame_ids[i]), t_s=float(t_s[i]), n_valid=int(ok.sum()),
                z_m=[round(float(z), 4) if v else None for z, v in zip(est.z_m, ok)],
                sigma_m=[round(float(q), 4) if v else None for q, v in zip(est.sigma_m, ok)]).to_json())
        return out

    def _filtered(self, frame_ids: np.ndarray, t_s: np.ndarray, z: np.ndarray, sig: np.ndarray) -> list[dict]:
        """Kalman-filtered range and closing speed ([ranging] kalman): a separate record
        type, ``range_filtered``, never mixed with the per-frame ``range`` records."""
        kf = self.kalman
        assert kf is not None
        out: list[dict] = []
        for i in range(len(frame_ids)):
            if not math.isfinite(z[i]):
                continue
            st = kf.update(float(t_s[i]), float(z[i]), float(sig[i]))
            if math.isfinite(st.z_m):
                out.append(RangeFilteredRecord(
                    tx=self.tx_index, frame=int(frame_ids[i]), t_s=float(t_s[i]), z_m=st.z_m,
                    sigma_m=st.sigma_z_m, closing_speed_mps=st.closing_speed_mps,
                    accepted=st.accepted).to_json())
        return out

    def finish(self) -> list[dict]:
        """End of stream: decode what the assembler still holds."""
        if self._look_pool is not None:  # a look in flight finds nothing more to decode
            self._look_pool.shutdown(wait=False, cancel_futures=True)
            self._look_pool = None
            self._look = None
        if self._deferred is not None:
            pending = self.finish_block()
            return pending + self.finish()
        if self._worker is not None:
            self._pending.append((self._worker.submit("flush"), 0))
            out = self._collect(wait=True)
            self._worker.shutdown()
            return out
        out = self._collect(wait=True)
        if self._pool is not None:
            self._pool.shutdown(wait=True)
        flush = getattr(self.assembler, "flush", None)
        return out + (self._records(flush()) if flush is not None else [])

    def finish_within(self, timeout_s: float) -> tuple[list[dict], int]:
        """:meth:`finish`, but waiting at most ``timeout_s`` s for the demodulation steps
        still in flight (a daemon that must end on time); returns the records and how many
        steps were abandoned (0: the orderly :meth:`finish` ran). Abandoned steps lose the
        packet in progress; the worker is stopped either way."""
        if self._pending:
            t_end = time.monotonic() + timeout_s
            not_done = 0
            for f, _ in list(self._pending):
                try:
                    f.exception(timeout=max(0.0, t_end - time.monotonic()))
                except TimeoutError:
                    pass
                except Exception:  # noqa: BLE001 - cancelled or broken: _collect reports it
                    pass
                not_done += not f.done()
            if not_done:
                out = self._collect()
                self.close()
                return out, not_done
        return self.finish(), 0

    def drop(self) -> tuple[list[dict], int]:
        """Stop without waiting for anything: the records of the demodulation steps already
        done, and how many were still in flight (abandoned; no flush of the assembler).
        For a searcher no longer needed (:class:`iscd.decode.multi.MultiDecoder`)."""
        out = self._collect()
        left = len(self._pending)
        self.close()
        return out, left

    def close(self) -> None:
        """Stop the demodulation worker (process or thread) without waiting for what it
        still holds: for a daemon leaving on an error (:meth:`finish` is the orderly end).
        Idempotent."""
        if self._look_pool is not None:
            self._look_pool.shutdown(wait=False, cancel_futures=True)
            self._look_pool = None
            self._look = None
        if self._worker is not None:
            self._worker.shutdown(wait=False)
            self._worker = None
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
        self._pending.clear()

    def restart(self) -> None:
        """Drop the track and every per-track buffer: acquisition starts again (the daemon
        calls it after a decoding error so that one bad block cannot wedge the decoder)."""
        self.track = None
        self._reacquire = False
        self._deferred = None
        self._blk_l.clear()
        self._blk_r.clear()
        self._acc = None
        self._ids_sum = 0.0
        self._shift_sum = np.zeros((2, 2))
        self._shift_n = 0
        self._followed = [None, None]
        self._followed_disparity = None
        self._stereo_trend = StereoTrend()
        self._lit_light = None
        self._lum_floor = [None, None]
        self._path_end = [None, None]
        self._backgrounds = None
        self._registered = None
        self._stab_last = None
        self._block_shifts = None
        self._spot_area = None
        self._since_fit = 0
        self._acq_l.clear()
        self._acq_r.clear()
        self._acq_ids.clear()
        self._look = None  # a look in flight: its answer is for frames no longer kept

    FOLLOW_MAX_PX = 2.0
    """The LEDs are followed from the last frame's refined centres unless the array's
    centre there is further than this (or :attr:`FOLLOW_LOST_PITCH` of a pitch, if more)
    from the grid fit's prediction (then the fit restarts them). The centre, not each LED:
    from close by the fit's pitch lags and its edge LEDs are pixels off while the followed
    ones are right. Most of a pitch, as the tracking's own test of following that walked
    off: the prediction is the last fit moved by the fits' motion up to
    :attr:`MOTION_HORIZON` intervals ahead, and a sub-pixel lock of one fit, so
    extrapolated, reached half a pitch (a randomized 8x8 approach at 41 m: 2.65 px at a
    5.1 px pitch; restarted from it, following settled on the next LED row for a block)."""

    MOTION_HORIZON = 4.0
    """The grid's motion is extrapolated at most this many tracking intervals ahead."""

    def _still_distance(self, side: int, prev: np.ndarray, fit: GridFit) -> float:
        """How far the last frame's followed centres lie from the grid fit once the image's own
        shifts are taken out of both, px (largest of x, y; +inf where the shifts are not
        known): the followed centres less the image shift of that frame against the fit less
        the mean image shift over its interval (the registered background of one LED,
        ``stabilized_following``). A road bump moves the image 4-5 px between two fits
        (100 km/h, 0.5 px RMS: the spots from +3.1 to -1.4 px within 32 frames); the LED has
        not moved in the background's frame, and following it is not lost (before, the
        check restarted it at the stale fit, 5 px off, for two blocks)."""
        tr = self.track
        if tr is None or tr.fit_shift is None or self._stab_last is None or not self.settings.stabilized_following:
            return math.inf
        a = _mean0(prev) - self._stab_last[side]
        b = _mean0(np.asarray(fit.centers)) - tr.fit_shift[side]
        return float(np.abs(a - b).max())

    def _fit_swing(self, side: int) -> float:
        """How far the last two grid fits of camera ``side`` lie apart, px (largest of x, y;
        0 without two fits of consecutive good intervals). A fit is the average position of
        its interval's light: while the rig swings (a road bump ringing at 6-15 Hz moves the
        spots 2-4 px), the spots are that much further from the last fit than a still
        scene allows, and following them is not lost."""
        tr = self.track
        if tr is None or tr.prev is None:
            return 0.0
        fo, po = (tr.left if side == 0 else tr.right).origin, tr.prev[side].origin
        return float(max(abs(fo[0] - po[0]), abs(fo[1] - po[1])))

    def led_centres(self, side: int, frame_ids: np.ndarray) -> np.ndarray:
        """(F, N, 2) LED centres px in each frame from the grid fits alone: the last fit
        moved on at the rate (origin and pitch) between the last two fits. The fits are
        averages over tens of frames made after the fact; an approaching array grows
        (4.2 -> 6 px pitch within a packet at 40 km/h), so the last fit lags by a
        fraction of a pixel at the edges, which is what this removes."""
        tr = self.track
        assert tr is not None
        fit = tr.left if side == 0 else tr.right
        base = fit.centers
        ids = np.asarray(frame_ids, dtype=np.float64)
        if tr.prev is None or not tr.fit_frame > tr.prev_frame:
            return np.broadcast_to(base, (ids.size,) + base.shape)
        grid = self._grid_motion(side)[3]
        out = np.empty((ids.size,) + grid.shape)
        for f, i in enumerate(ids.tolist()):  # (one or two frames a call, but for a restart)
            ox, oy, pitch = self._grid_at(side, i)
            np.multiply(grid, pitch, out=out[f])
            out[f] += np.array([ox, oy])
        return out

    def _grid_at(self, side: int, frame_id: float) -> tuple[float, float, float]:
        """Camera ``side``'s grid carried to frame ``frame_id`` (the last fit moved on at the
        rate between the last two fits, at most :attr:`MOTION_HORIZON` intervals ahead):
        its origin x, y and pitch, px. Needs two fits (``track.prev``)."""
        tr = self.track
        assert tr is not None
        o, v_o, v_p = self._grid_motion(side)[:3]
        horizon = self.MOTION_HORIZON * self.settings.track_every_frames
        a = min(max(frame_id - tr.fit_frame, -horizon), horizon)
        pitch = (tr.left if side == 0 else tr.right).pitch_px + a * v_p
        return o[0] + a * v_o[0], o[1] + a * v_o[1], pitch

    def _grid_motion(self, side: int) -> tuple[tuple[float, float], tuple[float, float], float, np.ndarray,
                                               tuple[float, float], tuple[float, float]]:
        """:meth:`led_centres`' terms of camera ``side`` that change only with the fits: the
        origin (2,) px, its rate (2,) px / frame, the pitch's rate px / frame, the LEDs'
        grid positions (N, 2) in pitches from the origin and their least and largest (2,)
        (:meth:`_reach_window`); kept until a fit or its frame changes (the fits are
        frozen; the decoder asks four times a block)."""
        tr = self.track
        assert tr is not None and tr.prev is not None
        fit, prev = (tr.left, tr.prev[0]) if side == 0 else (tr.right, tr.prev[1])
        got = self._motion_memo[side]
        if got is not None and got[0] is fit and got[1] is prev and got[2] == tr.fit_frame \
                and got[3] == tr.prev_frame:
            return got[4]
        dt = tr.fit_frame - tr.prev_frame
        o = np.asarray(fit.origin)
        v_o = (o - np.asarray(prev.origin)) / dt  # px / frame
        v_p = (fit.pitch_px - prev.pitch_px) / dt
        base = fit.centers
        grid = (base - o) / fit.pitch_px if fit.pitch_px > 0 else np.zeros_like(base)
        # (the scalars as Python floats: the same float64 arithmetic, without numpy's per-scalar cost)
        terms = (tuple(o.tolist()), tuple(v_o.tolist()), float(v_p), grid, tuple(grid.min(0).tolist()),
                 tuple(grid.max(0).tolist()))
        self._motion_memo[side] = (fit, prev, tr.fit_frame, tr.prev_frame, terms)
        return terms

    def _luminance(self, frame_ids: np.ndarray, left: np.ndarray, right: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """(F, N) luminance DN of every LED in each camera: a Gaussian-weighted ROI mean
        (:func:`iscd.decode.tracking.luminance.gauss_mean`, eq. 3.10 with smooth weights, the same
        at every sub-pixel phase) at the LED's position in each frame -- followed from the
        last frame (or the grid's motion, :meth:`led_centres`) and refined by the frame's
        own shift and scale (:func:`iscd.decode.tracking.luminance.refine_centres`: rig
        vibration moves every spot together, faster than the grid fits follow). Both
        cameras go through one vectorized pass (frames stacked)."""
        tr = self.track
        assert tr is not None
        starts = []
        for side in (0, 1):
            # the grid's prediction for the block's first frame decides; the whole block's
            # is made only when it is used (the same values row by row)
            first = self.led_centres(side, frame_ids[:1])
            prev = self._followed[side]
            fit = tr.left if side == 0 else tr.right
            limit = max(self.FOLLOW_MAX_PX, self.FOLLOW_LOST_PITCH * fit.pitch_px) + self._fit_swing(side)
            # lost only when far from the fit both as made and as its motion carries it on:
            # the fits' motion is carried up to MOTION_HORIZON intervals ahead, and a road
            # bump's swing caught between two fits (averages of their interval's light) is
            # no motion that goes on (a bump at 40 km/h: fits 1.9 px apart, carried on
            # 5 px past spots that had swung back, and the last fit itself 3.1 px from
            # them; restarted there, following lost the LED for a block)
            held = _mean0(prev) if prev is not None and prev.shape == first.shape[1:] else None
            if held is not None and \
                    min(float(np.abs(held - _mean0(first[0])).max()),
                        float(np.abs(held - _mean0(np.asarray(fit.centers))).max()),
                        self._still_distance(side, prev, fit)) <= limit:
                start = prev  # where the LEDs were in the last frame
                if self.rows * self.cols > 1:
                    # put back on the array's square grid: carried from block to block, each
                    # LED's position would keep its own errors (a centroid pulled by the
                    # neighbours' light, by texture, by the clip to max_px) and they add up
                    # (an 8x8 closing to 25 m: its edge columns 1-7 px off before)
                    start = (square_grid_compiled if self.compiled else square_grid)(prev, self.rows, self.cols)
            else:
                start = self.led_centres(side, frame_ids)
            starts.append(start)
        growth = self._growth(starts)
        box = 2 * max(1, int(round(max(tr.roi_radius) * max(growth)))) + 1
        info: dict[str, np.ndarray] = {}
        follow = follow_and_measure_compiled if self.compiled else follow_and_measure
        subtract = self.background_on
        if (subtract or self.settings.lit_background) and self._backgrounds is None:
            rise = self.settings.background_rise_dn
            self._backgrounds = [PixelBackground(left.shape[1:], rise), PixelBackground(right.shape[1:], rise)]
        sigmas = [min(max(sig * g, 0.6), max(sig, self.MAX_SIGMA_PX)) for sig, g in zip(tr.roi_sigma, growth)]
        spot_r = None
        if self.settings.window_follows_spot:
            sigmas = self._spot_window(tr, growth, sigmas)
            # measure within half a pitch of each LED (an array's neighbours stay out)
            spot_r = 0.5 * tr.left.pitch_px * max(growth) if self.rows * self.cols > 1 else 8.0
        # how far from an LED's start the following reads (its patch half, as the kernel
        # takes it): needed_windows() covers it for the next block
        registered = subtract and self.settings.registered_background and self.rows * self.cols == 1
        self._reach = max(patch_half(box), int(np.ceil(3.5 * max(sigmas))) + 1,
                          window_half(max(sigmas)) + RING_PX if registered else 0) + self.REACH_MARGIN_PX \
            + int(np.ceil(PATH_REACH_PX * self.settings.follow_passes))
        backgrounds = self._backgrounds
        if registered and self._registered is None:
            rise = self.settings.background_rise_dn
            sub = self.settings.registered_subpixel
            self._registered = [RegisteredBackground(left.shape[1:], rise, subpixel=sub),
                                RegisteredBackground(right.shape[1:], rise, subpixel=sub)]
            self._shift_leader = ShiftLeader()
            self._stab_last = None
        # one LED over a registered background: followed in the background's own frame
        # (iscd.decode.tracking.stabilize), where vibration does not move the texture
        stab = self._stabilize([left, right], starts, sigmas) if registered and self.settings.stabilized_following \
            else None
        frames_f, starts_f = ([left, right], starts) if stab is None else stab[:2]
        if self.settings.follow_passes > 0:
            # followed along the LEDs' path through the block (docs/receiver.md, "Following
            # along the path"): a road bump carries the spots pixels within a block; the path
            # itself is smoothed in image positions (offsets: the stabilized frames' shifts)
            res = follow_path(follow, frames_f, starts_f, box, sigmas, self._lum_floor,
                              self._path_end, use=self._use, lit_light=self._lit_light,
                              backgrounds=backgrounds, spot_radius_px=spot_r,
                              subtract=subtract, passes=self.settings.follow_passes,
                              settle_px=self.settings.path_settle_px, compiled=self.compiled,
                              offsets=None if stab is None else stab[2])
            (c_l, c_r), (lum_l, lum_r) = res.centres, res.luminance
            info = res.info
            self._lum_floor = res.floors
            self._path_end = res.path_end
            self.follow_passes_run += res.passes
        else:
            (c_l, c_r), (lum_l, lum_r) = follow(
                frames_f, starts_f, box, sigmas,
                use=self._use, lit_light=self._lit_light, info=info,
                backgrounds=backgrounds, spot_radius_px=spot_r, subtract=subtract)
        if stab is not None:  # back to image positions
            shifts = stab[2]
            c_l, c_r = c_l + shifts[0][:, None, :], c_r + shifts[1][:, None, :]
            self._stab_last = [shifts[0][-1].copy(), shifts[1][-1].copy()]
        if self.rows * self.cols == 1 and registered and self.settings.stereo_hold:
            c_l, c_r = self._hold_to_stereo(frame_ids, c_l, c_r, None if stab is None else stab[2])
        if registered:
            # the light above the background under the window in this frame: held in the
            # scene's frame at the image's own shift (rig vibration moves the texture too)
            assert self._registered is not None
            frames_lr, centres_lr, lum_lr = (left, right), (c_l, c_r), [lum_l, lum_r]
            hint = None
            for c in self._shift_order():
                lum_lr[c], self.image_shifts[c] = self._registered[c].measure(
                    frames_lr[c], centres_lr[c], sigmas[c], hint=hint, compiled=self.compiled)
                hint = self.image_shifts[c] if self.settings.shift_hint else None
            if self.settings.shift_hint:
                self._shift_leader.update([r.contrast for r in self._registered])
            lum_l, lum_r = lum_lr
            self._block_shifts = (self.image_shifts[0], self.image_shifts[1])
        if spot_r is not None:
            self._fold_spot_area(info["spot_area"])
        # the light of a lit LED, held over dark stretches (halves in ~5 s of darkness)
        light = info["light"]
        self._lit_light = light if self._lit_light is None else np.maximum(light, self.LIT_DECAY * self._lit_light)
        self._followed = [c_l[-1].copy(), c_r[-1].copy()]
        if self.rows * self.cols == 1:
            d = c_r[:, 0, 0] - c_l[:, 0, 0]
            d = d[np.isfinite(d)]
            self._followed_disparity = float(np.median(d)) if d.size else None
        self.last_centres = (c_l, c_r)
        return lum_l, lum_r

    def _hold_to_stereo(self, frame_ids: np.ndarray, c_l: np.ndarray, c_r: np.ndarray,
                        shifts: list[np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
        """One LED's followed centres held where one camera's following jumped off the stereo
        disparity (:mod:`iscd.decode.tracking.stereo_hold`, ``[tracking] stereo_hold``): the
        walked-off camera's frames are put back beside the other camera's centre at the
        disparity before the jump (counted in ``stereo_holds``; the held camera's path end
        too, so that the next block starts on the LED).

        Parameters
        ----------
        frame_ids : ndarray
            (F,) the block's frames.
        c_l, c_r : ndarray
            (F, 1, 2) followed centres, image px.
        shifts : list of ndarray or None
            Per camera (F, 2) the block's image shifts px (stabilized following), or None.

        Returns
        -------
        c_l, c_r : ndarray
            The centres, held where one camera jumped off.
        """
        still = [c[:, 0, :] - (shifts[k] if shifts is not None else 0.0) for k, c in enumerate((c_l, c_r))]
        c_l, c_r, held, self._stereo_trend = hold_block(self._stereo_trend, frame_ids, c_l, c_r, still[0], still[1])
        if held.any():
            self.counters["stereo_holds"] += int(held.sum())
            if held[-1] and self._stereo_trend.side >= 0 and self._path_end[self._stereo_trend.side] is not None:
                self._path_end[self._stereo_trend.side] = (c_l, c_r)[self._stereo_trend.side][-1].copy()
        return c_l, c_r

    def _shift_order(self) -> tuple[int, int]:
        """The cameras in the order their image shifts are found: with ``shift_hint`` the one
        that tells the shifts apart better first (its moves are the other's hint), else 0, 1."""
        lead = self._shift_leader.lead if self.settings.shift_hint else 0
        return lead, 1 - lead

    def _stabilize(self, frames: list[np.ndarray], starts: list[np.ndarray], sigmas: list[float]
                   ) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
        """One LED's block in the background's own frame (:mod:`iscd.decode.tracking.stabilize`):
        each camera's image shifts predicted against its registered map
        (:meth:`RegisteredBackground.predict_shifts`, around where the LED was; the camera
        that leads the shifts first, its shifts the other's hint, as in the measurement),
        the pixels the following reads copied into a buffer held still, and the starts moved
        with them.

        Returns
        -------
        frames : list of ndarray
            Per camera (F, H, W) stabilized frames (only the following's reach is filled), DN.
        starts : list of ndarray
            Per camera (F, N, 2) starting centres in them, px.
        shifts : list of ndarray
            Per camera (F, 2) int64 image shifts: image position = stabilized + shift, px.
        """
        assert self._registered is not None
        F = frames[0].shape[0]
        st = [np.broadcast_to(np.asarray(s, np.float64), (F,) + np.shape(s)[-2:]) for s in starts]
        shifts: list[np.ndarray] = [np.zeros((F, 2), np.int64), np.zeros((F, 2), np.int64)]
        hint = None
        for c in self._shift_order():
            shifts[c] = self._registered[c].predict_shifts(frames[c], st[c], sigmas[c], hint=hint,
                                                           compiled=self.compiled)
            hint = shifts[c] if self.settings.shift_hint else None
        out_frames, out_starts = [], []
        for c in (0, 1):
            fr = frames[c]
            buf = self._stab_bufs[c]
            if buf is None or buf.shape[1:] != fr.shape[1:] or buf.dtype != fr.dtype or buf.shape[0] < F:
                buf = self._stab_bufs[c] = np.zeros((F,) + fr.shape[1:], fr.dtype)
            s_c = st[c] - shifts[c][:, None, :]
            reach = self._reach + 1
            box = (int(np.floor(s_c[..., 0].min())) - reach, int(np.floor(s_c[..., 1].min())) - reach,
                   int(np.ceil(s_c[..., 0].max())) + reach + 1, int(np.ceil(s_c[..., 1].max())) + reach + 1)
            out_frames.append(stabilize_into(fr, shifts[c], box, buf, compiled=self.compiled))
            out_starts.append(s_c)
        return out_frames, out_starts, shifts

    @property
    def background_on(self) -> bool:
        """Whether the luminance and the centroids are of the light above the per-pixel
        background (``[tracking] background``, or ``background_one_led`` for one LED)."""
        return bool(self.settings.background or (self.settings.background_one_led and self.rows * self.cols == 1))

    MAX_SIGMA_PX = 4.0
    """Largest Gaussian luminance window, px (an array seen from close by)."""

    REACH_MARGIN_PX = 2
    """Added to the following's patch half in :meth:`needed_windows`, px: the rounding of a
    start to a pixel and one block's growth of the box or window."""

    SPOT_SMOOTHING = 0.1
    """Share of a block's measured spot area in the running one (``window_follows_spot``):
    the window changes over ~10 blocks, smoothly, never in one jump mid-packet."""

    def _fold_spot_area(self, area: np.ndarray) -> None:
        """Fold one block's half-maximum areas (2,) px^2 into the running ones."""
        a = np.asarray(area, dtype=np.float64)
        old = np.full(2, np.nan) if self._spot_area is None else self._spot_area
        k = self.SPOT_SMOOTHING
        self._spot_area = np.where(np.isfinite(a), np.where(np.isfinite(old), (1 - k) * old + k * a, a), old)

    def _spot_window(self, tr: _Track, growth: list[float], sigmas: list[float]) -> list[float]:
        """Per camera the Gaussian window that follows the measured spot: ``window_scale``
        times the sigma of its running half-maximum area (:func:`iscd.decode.tracking.luminance.
        area_sigma`), in an array at most (pitch - 0.8) / 4 (the pitch grown as the array);
        ``sigmas`` (the acquisition's, grown) until a lit spot has been measured."""
        if self._spot_area is None:
            return sigmas
        out = []
        for side, (s0, g) in enumerate(zip(sigmas, growth)):
            a = self._spot_area[side]
            if not np.isfinite(a):
                out.append(s0)
                continue
            s = self._window_scale(self.rows * self.cols) * float(area_sigma(a))
            fit = tr.left if side == 0 else tr.right
            if self.rows * self.cols > 1 and fit.pitch_px > 0:
                s = min(s, (fit.pitch_px * g - 0.8) / 4.0)
            out.append(float(np.clip(s, 0.6, self.MAX_SIGMA_PX)))
        return out

    def _growth(self, starts: list[np.ndarray]) -> list[float]:
        """Per camera how much the array's image has grown since acquisition (its spread
        now over its spread then; 1 for one LED). The following box and the Gaussian
        window grow with it: an array that comes from 50 to 10 m grows 5x, its spots
        become discs, and a window fixed at 50 m would see only their saturated cores and
        a box inside a flat core no centroid. The growth within a block is small and
        smooth, which the tracked channel follows."""
        tr = self.track
        assert tr is not None
        if self.rows * self.cols == 1:
            # one LED: its image grows as 1/Z, as the stereo disparity does (raw x
            # difference; ``disparity0`` at acquisition). Both cameras alike. The disparity
            # is the last block's median over its frames, not that of the block's starts:
            # one frame followed 2 px off (a right camera's last frame, 195152883 at 80 m)
            # made the growth 1.41 for a block between 1.28 and 1.30, the window 10 % wider
            # and the light of an unresolved spot 13 % lower in both cameras for that block
            # alone -- a step mid-packet that cost the packet (docs/eval.md, session 33)
            c = [np.asarray(st, dtype=np.float64).reshape(-1, 2)[0] for st in starts]
            d = float(c[1][0] - c[0][0])
            if self.settings.growth_from_block and self._followed_disparity is not None \
                    and np.isfinite(self._followed_disparity):
                d = self._followed_disparity
            g = abs(d) / abs(tr.disparity0) if abs(tr.disparity0) >= self.MIN_DISPARITY_PX else 1.0
            g = float(np.clip(g, 1.0, self.MAX_GROWTH))
            return [g, g]
        out = []
        for side, st in enumerate(starts):
            ref = tr.spread0[side]
            c = np.asarray(st, dtype=np.float64).reshape(-1, st.shape[-2], 2)[0]
            out.append(max(1.0, _spread(c) / ref) if ref > 0 else 1.0)
        return out

    MIN_DISPARITY_PX = 4.0
    """One LED's growth from the disparity only when it is at least this at acquisition, px
    (a nearly zero disparity -- very far, or uncalibrated cameras -- says nothing)."""

    MAX_GROWTH = 8.0
    """Largest growth of one LED's image taken from the disparity."""

    def _roi_sigma(self, fit: GridFit) -> float:
        """Gaussian luminance window, px: the configured one, or (auto) matched to the
        spot (FWHM / 2.355), at most (pitch - 0.8) / 4 in an array (a neighbour's
        light then weighs ~1 %)."""
        s = self.settings.roi_sigma_px
        if s > 0:
            return float(s)
        k = self._window_scale(fit.rows * fit.cols)
        s = k * fit.spot_px / 2.355
        if fit.rows * fit.cols > 1 and fit.pitch_px > 0:
            s = min(s, (fit.pitch_px - 0.8) / 4.0)
        return float(np.clip(s, 0.6, 2.0 * max(1.0, k)))

    def _window_scale(self, leds: int) -> float:
        """The luminance window relative to the spot-matched Gaussian: ``window_scale``, for
        one LED (``leds == 1``) times ``one_led_window_scale`` (in both cameras: widening only
        the wider aperture's window of an HDR pair lost more packets, docs/eval.md, session 30)."""
        k = self.settings.window_scale
        return k * self.settings.one_led_window_scale if leds == 1 else k

    def _roi_radius(self, fit: GridFit) -> int:
        """ROI half-size: the configured one, or (auto) half the spot so that a saturated
        spot's unsaturated rim is included, but never reaching a neighbouring LED."""
        r = self.settings.roi_radius_px
        if r >= 0:
            return r
        r = int(np.floor(fit.spot_px / 2 + 0.25))
        if fit.rows * fit.cols > 1:
            r = min(r, int((fit.pitch_px - 1) // 2))
        return int(np.clip(r, 1, 4))

    def needed_windows(self) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]] | None:
        """(left, right) pixel windows (x0, y0, x1, y1) that :meth:`push` will read, or
        ``None`` while acquiring (then it needs whole frames). Lets the daemon copy only
        these pixels out of the ring."""
        tr = self.track
        if tr is None:
            return None
        W, H = self.cfg.camera.width, self.cfg.camera.height
        wl, wr = _track_window(tr.left, W, H), _track_window(tr.right, W, H)
        if self._reach:  # the following's patches around where the LEDs were and are predicted
            wl, wr = _union(wl, self._reach_window(0, W, H)), _union(wr, self._reach_window(1, W, H))
        if self._acc is not None:
            wl, wr = _union(wl, self._win[0]), _union(wr, self._win[1])
        if self.ranger is not None:
            x0l, y0, x0r, w, h = self.ranger.patch_geometry(tr.left, tr.right)
            if self.ranger.identity:
                wl = _union(wl, _clip((x0l, y0, x0l + w, y0 + h), W, H))
                wr = _union(wr, _clip((x0r, y0, x0r + w, y0 + h), W, H))
            else:  # rectification reads around the patch: be generous
                return None
        return wl, wr

    def _reach_window(self, side: int, W: int, H: int) -> tuple[int, int, int, int]:
        """The pixels (x0, y0, x1, y1) the next block's following can read in camera
        ``side``: its patches (half-size ``_reach`` px) around the LEDs' last followed
        positions and the grid's prediction a block or two ahead (what it may start from)."""
        tr = self.track
        assert tr is not None
        fit = tr.left if side == 0 else tr.right
        memo = self._extent_memo[side]
        if memo is None or memo[0] is not fit:
            memo = self._extent_memo[side] = (fit, _extent(fit.centers))
        lo, hi = memo[1]
        if self._followed[side] is not None:
            f_lo, f_hi = _extent(self._followed[side])
            lo, hi = [min(a, b) for a, b in zip(lo, f_lo)], [max(a, b) for a, b in zip(hi, f_hi)]
        if self._last_id is not None:
            ahead = [self._last_id + 1, self._last_id + 2 * self.settings.track_every_frames]
            for p_lo, p_hi in self._predicted_extents(side, ahead):
                lo, hi = [min(a, b) for a, b in zip(lo, p_lo)], [max(a, b) for a, b in zip(hi, p_hi)]
        r = self._reach
        return _clip((math.floor(lo[0]) - r, math.floor(lo[1]) - r,
                      math.ceil(hi[0]) + r + 1, math.ceil(hi[1]) + r + 1), W, H)

    def _predicted_extents(self, side: int, frame_ids: list[int]
                           ) -> list[tuple[list[float], list[float]]]:
        """Per frame the least and largest (x, y) of :meth:`led_centres` px, the same values
        (the centres are ``origin + grid * pitch``, each rounding monotonic in the grid
        position while the pitch is positive: the extremes are those of the grid's extremes;
        otherwise from the centres themselves)."""
        tr = self.track
        assert tr is not None
        fit = tr.left if side == 0 else tr.right
        if tr.prev is None or not tr.fit_frame > tr.prev_frame:
            return [_extent(fit.centers)] * len(frame_ids)
        g_lo, g_hi = self._grid_motion(side)[4:]
        out = []
        for i in frame_ids:
            ox, oy, pitch = self._grid_at(side, float(i))
            if not pitch > 0:
                out.append(_extent(self.led_centres(side, np.array([i]))[0]))
                continue
            out.append(([g_lo[0] * pitch + ox, g_lo[1] * pitch + oy],
                        [g_hi[0] * pitch + ox, g_hi[1] * pitch + oy]))
        return out

    # ------------------------------------------------------------------ acquisition/tracking
    def _acquire(self, frame_ids: np.ndarray, t_s: np.ndarray, left: np.ndarray | None, right: np.ndarray | None,
                 adopt: KeptFrames | None = None, owned: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | KeptFrames | None:
        """Collect frames; every ``acquire_frames`` try to detect. On success returns the
        collected (ids, t_s, left, right) so that they are decoded too (a searcher with
        :meth:`set_lookback`: its kept frames, :class:`KeptFrames`)."""
        if adopt is not None:  # another searcher's kept frames: already copies
            self._acq_l.extend(adopt.left)
            self._acq_r.extend(adopt.right)
            self._acq_ids.extend(zip(adopt.ids.tolist(), adopt.t_s.tolist()))
        else:
            assert left is not None and right is not None
            keep = (lambda a: a) if owned else np.array  # copies unless the frames are ours
            for i in range(len(frame_ids)):
                self._acq_l.append(keep(left[i]))
                self._acq_r.append(keep(right[i]))
                self._acq_ids.append((int(frame_ids[i]), float(t_s[i])))
        A = self.settings.acquire_frames
        lookback = self._lookback is not None
        self._since_look += len(frame_ids)
        if lookback and self._look is not None:
            # a look in flight (a thread, the daemon): its answer once it has one
            if not self._look.done():
                return None
            found = self._look.result()
            self._look = None
        else:
            if len(self._acq_l) < A:
                return None
            if lookback:
                # several transmitters: a look every search_every frames on the last A
                # frames; the frames before them are kept for a transmitter found (its
                # first header)
                if self._since_look < self._search_every:
                    return None
                self._since_look = 0
                k = len(self._acq_l) - A
                wl = [self._acq_l[i] for i in range(k, k + A)]
                wr = [self._acq_r[i] for i in range(k, k + A)]
                meta = np.array([self._acq_ids[i] for i in range(k, k + A)])
            else:
                wl, wr = list(self._acq_l), list(self._acq_r)
                meta = np.array(self._acq_ids)
                self._acq_l.clear()
                self._acq_r.clear()
                self._acq_ids.clear()
            now = int(meta[-1, 0])
            self.attempts += 1
            self.excluded = [(b, until) for b, until in self.excluded if until > now]
            exclude = [b for b, _ in self.excluded] + list(self.extra_exclude[0])
            exclude_right = list(self.extra_exclude[1])  # a snapshot: a look may run in a thread
            shape = self._shape_hint or (self.rows, self.cols)
            auto = self.shape_auto and self._shape_hint is None
            if not auto:
                self._hint_tries -= 1
                if self._hint_tries <= 0:
                    self._shape_hint = None
            if lookback and self._look_pool is not None:
                self._look = self._look_pool.submit(self._look_for, wl, wr, meta, exclude, exclude_right, shape, auto)
                return None
            found = self._look_for(wl, wr, meta, exclude, exclude_right, shape, auto)
        if found is None:
            return None
        fl, fr, meta, L, R = found
        if self.shape_auto:
            if (fl.rows, fl.cols) != (self.rows, self.cols) or self.counters["acquisitions"] == 0:
                log.info("transmitter's shape inferred: %dx%d LEDs, pitch %.2f px", fl.rows, fl.cols, fl.pitch_px)
            self._set_shape(fl.rows, fl.cols)
            self._shape_hint = None
        self._followed = [None, None]
        self._followed_disparity = None
        self._stereo_trend = StereoTrend()
        self._lit_light = None
        self._backgrounds = None
        self._registered = None
        self._stab_last = None
        self._block_shifts = None
        self._spot_area = None
        self.track = _Track(left=fl, right=fr, first_score=min(fl.score, fr.score),
                            roi_radius=(self._roi_radius(fl), self._roi_radius(fr)),
                            roi_sigma=(self._roi_sigma(fl), self._roi_sigma(fr)),
                            spread0=(_spread(fl.centers), _spread(fr.centers)),
                            disparity0=float(fr.center[0] - fl.center[0]),
                            since_frame=int(frame_ids[-1]), fit_frame=float(meta[:, 0].mean()))
        self.counters["acquisitions"] += 1
        self._new_assembler()
        if self.kalman is not None:
            self.kalman.reset()
        log.info("transmitter acquired at frame %d: left %.1f,%.1f right %.1f,%.1f pitch %.2f px", int(meta[-1, 0]),
                 *fl.center, *fr.center, fl.pitch_px)
        if lookback and self._own_lookback and len(self._acq_ids) == meta.shape[0]:
            # found by the first look, nothing kept before it: decoded as without a look-back
            lookback = False
            self._acq_l.clear()
            self._acq_r.clear()
            self._acq_ids.clear()
            self._since_look = 0
        if lookback:  # decode from the first frame kept: a header before the look is not lost
            meta = np.array(self._acq_ids)
            kept = KeptFrames(meta[:, 0].astype(np.int64), meta[:, 1], list(self._acq_l), list(self._acq_r))
            cx, cy = fl.center
            if any(b[0] <= cx < b[2] and b[1] <= cy < b[3] for b in self.blinker_places):
                # found again where a blinker was rejected: most likely it again; its
                # look-back is not decoded (~0.1 s of the frame loop at once), only from the look on
                kept.start = max(0, len(kept) - A)
                self.counters["lookbacks_skipped"] += 1
            self._acq_l.clear()
            self._acq_r.clear()
            self._acq_ids.clear()
            self._since_look = 0
            if self.keep_acquired:
                self.acquired = kept
            return kept
        got = meta[:, 0].astype(np.int64), meta[:, 1], L, R
        if self.keep_acquired:
            self.acquired = got
        return got

    def _look_for(self, wl: list[np.ndarray], wr: list[np.ndarray], meta: np.ndarray,
                  exclude: list[tuple[int, int, int, int]], exclude_right: list[tuple[int, int, int, int]],
                  shape: tuple[int, int], auto: bool
                  ) -> tuple[GridFit, GridFit, np.ndarray, np.ndarray, np.ndarray] | None:
        """One detection attempt on the frames ``wl``/``wr`` (lists of (H, W) images, ids and
        t_s in ``meta``), leaving out ``exclude`` / ``exclude_right`` (boxes, px, per camera):
        (left fit, right fit, meta, L, R) of the transmitter found, or None. Reads no decoder
        state that a block changes (it may run in a thread: a look of :meth:`set_lookback`'s
        searcher in the daemon)."""
        with self.look_lock:  # one look at a time in the shared buffers (a searcher's runs in a thread)
            return self._look_in(wl, wr, meta, exclude, exclude_right, shape, auto)

    def _look_in(self, wl: list[np.ndarray], wr: list[np.ndarray], meta: np.ndarray,
                 exclude: list[tuple[int, int, int, int]], exclude_right: list[tuple[int, int, int, int]],
                 shape: tuple[int, int], auto: bool
                 ) -> tuple[GridFit, GridFit, np.ndarray, np.ndarray, np.ndarray] | None:
        """:meth:`_look_for` under :attr:`look_lock`: the frames stacked into buffers made
        and touched once (a fresh 16 MB stack a look cost ~80 ms of page faults here)."""
        bufs = self._buffers(wl[0], len(wl), "look")
        L = np.stack(wl, out=bufs[0][:len(wl)])
        R: np.ndarray | None = None
        own_right: dict[tuple[int, int], GridFit | None] = {}  # the right's own search, once a shape
        for _ in range(self.ACQUIRE_CANDIDATES):
            # the left camera's best candidate; one that the right camera does not confirm
            # is left out and the next one tried on the same frames (so that a packet whose
            # header is in them is not lost to a distractor)
            fl = (detect_auto(L, exclude=exclude, symbol_frames=self.symbol_frames) if auto
                  else detect_array(L, *shape, exclude=exclude, symbol_frames=self.symbol_frames))
            if fl is None:
                return None
            if auto and self.allowed_shapes is not None and (fl.rows, fl.cols) not in self.allowed_shapes:
                log.debug("a %dx%d array at %s is not among the shapes looked for", fl.rows, fl.cols, fl.center)
                exclude = exclude + [fl.bbox(margin=2.0)]
                continue
            if R is None:
                R = np.stack(wr, out=bufs[1][:len(wr)])
            found = self._partner(fl, L, R, own_right, exclude_right)
            if found is not None:
                return found[0], found[1], meta, L, R
            exclude = exclude + [fl.bbox(margin=2.0)]
        return None

    def prepare(self, height: int, width: int, dtype: Any) -> None:
        """Make and touch the look buffers for frames of this size now (the daemon, before
        its first frame: their page faults are ~0.1 s here, and the first acquisition
        happens while frames arrive)."""
        self._buffers(np.empty((int(height), int(width)), dtype), self.settings.acquire_frames + self.LOOK_SPARE, "look")

    @property
    def lookback_frames(self) -> int:
        """Most recent whole frames this decoder keeps while it looks for its transmitter
        (an acquisition's frames, or a searcher's look-back), for the daemon's block pool."""
        return int(self._lookback or self.settings.acquire_frames)

    def _buffers(self, frame: np.ndarray, n: int, use: str = "catch") -> tuple[np.ndarray, np.ndarray]:
        """(left, right) buffers of at least ``n`` frames like ``frame`` for ``use``
        ("catch": a find's kept frames, the frame loop; "look": a look, under
        :attr:`look_lock`), from :attr:`catch_buffers` (by use, frame size and dtype), made
        and touched when none is large enough."""
        return shared_buffers(self.catch_buffers, frame, n, use)

    LOOK_SPARE = 32
    """Frames a look's buffers hold beyond ``acquire_frames`` (an acquisition's frames come
    in whole blocks: up to a block more than it needs)."""

    def set_lookback(self, search_every: int, lookback: int, *, look_async: bool = False) -> None:
        """Search every ``search_every`` frames (on the last ``acquire_frames``) and keep
        the last ``lookback`` frames while searching; a transmitter found is decoded from
        the first of them (:class:`iscd.decode.multi.MultiDecoder`: a transmitter that
        enters is read from its first whole packet though the searcher looks only now and
        then). ``look_async`` (the daemon): each look runs in a thread of its own while the
        blocks go on (the detection's numpy and OpenCV work releases the GIL), and its
        answer is taken at a later block; the frames kept since cover the wait."""
        A = self.settings.acquire_frames
        self._own_lookback = False  # a searcher's (the caller sets it back for its own)
        if look_async and self._look_pool is None:
            self._look_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="iscd-look")
        self._search_every = max(int(search_every), 1)
        if self._lookback == max(int(lookback), A):
            return
        self._lookback = max(int(lookback), A)
        self._acq_l = deque(self._acq_l, maxlen=self._lookback)
        self._acq_r = deque(self._acq_r, maxlen=self._lookback)
        self._acq_ids = deque(self._acq_ids, maxlen=self._lookback)

    ACQUIRE_CANDIDATES = 3
    """Left-camera candidates tried on one acquisition's frames before the next frames."""

    def _partner(self, fl: GridFit, L: np.ndarray, R: np.ndarray,
                 own_right: dict[tuple[int, int], GridFit | None],
                 exclude_right: list[tuple[int, int, int, int]]) -> tuple[GridFit, GridFit] | None:
        """(left, right) fits of the transmitter the left camera found as ``fl``: the right
        camera's own detection when it pairs with it, else the right camera searched for the
        left's light (:func:`iscd.decode.tracking.partner.find_partner`); None if neither.
        ``own_right`` holds the right camera's own detection per shape for these frames (it
        does not depend on the left's candidate: run once however many candidates are tried)."""
        max_dy = 3.0 + 0.5 * fl.spot_px
        if self._lookback is not None:
            # several transmitters: the right camera's own detection within the left
            # candidate's epipolar band (elsewhere in the frame a brighter one would win)
            fr = self._detect_in_band(R, fl, max_dy, exclude_right)
        else:
            if (fl.rows, fl.cols) not in own_right:
                own_right[(fl.rows, fl.cols)] = detect_array(R, fl.rows, fl.cols,
                                                             exclude=exclude_right or None,
                                                             symbol_frames=self.symbol_frames)
            fr = own_right[(fl.rows, fl.cols)]
        fr = match_stereo(fl, [fr], max_dy=max_dy) if fr is not None else None
        if fr is None:
            # the right camera's own search found nothing or something else (the HDR pair's
            # f/8 camera sees a far LED a few DN above a textured scene): look along the
            # epipolar band for the left's light over these frames
            fr = find_partner(R, fl, reference_series(L, fl), max_dy=max_dy)
            if fr is None:
                log.debug("transmitter seen in the left camera at %s but not found in the right", fl.center)
                return None
            self.counters["guided_acquisitions"] += 1
            log.info("transmitter found in the right camera by the left's light (correlation %.2f)", fr.score)
        return fl, fr

    def _detect_in_band(self, R: np.ndarray, fl: GridFit, max_dy: float,
                        exclude_right: list[tuple[int, int, int, int]]) -> GridFit | None:
        """The right camera's own detection of a ``fl``-shaped array on the rows of ``fl``'s
        epipolar band (its box +- ``max_dy`` + a pitch), the boxes ``exclude_right`` (px)
        left out; image px."""
        H = R.shape[1]
        x0, y0, x1, y1 = fl.bbox(max_dy + max(fl.pitch_px, fl.spot_px) + 2)
        y0, y1 = max(0, int(y0)), min(H, int(y1))
        if y1 - y0 < 4:
            return None
        ex = [(b[0], b[1] - y0, b[2], b[3] - y0) for b in exclude_right]
        try:
            fit = detect_array(R[:, y0:y1], fl.rows, fl.cols, exclude=ex or None, symbol_frames=self.symbol_frames)
        except ValueError:
            return None
        if fit is None:
            return None
        return replace(fit, origin=(fit.origin[0], fit.origin[1] + y0))

    HINT_TRIES = 4
    """Acquisition attempts with the shape a PHY header named before inferring it again."""

    def _retrack(self, frame_ids: np.ndarray, left: np.ndarray, right: np.ndarray) -> None:
        if self._reacquire:
            self.restart()
            return
        tr = self.track
        assert tr is not None
        H, W = left.shape[1:]
        if self._acc is None:
            self._win = (_track_window(tr.left, W, H), _track_window(tr.right, W, H))
            self._acc = (LightAccumulator(self._win[0]), LightAccumulator(self._win[1]))
        # fold the tracking windows into the interval's light maps (no frames kept: the
        # caller may reuse its frame buffers)
        if self.compiled:
            self._acc[0].add(left)
            self._acc[1].add(right)
        else:
            (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = self._win
            self._blk_l.append(np.array(left[:, ay0:ay1, ax0:ax1]))
            self._blk_r.append(np.array(right[:, by0:by1, bx0:bx1]))
        self._ids_sum += float(np.add.reduce(frame_ids, dtype=np.float64))  # (np.sum's own reduction)
        bs, self._block_shifts = self._block_shifts, None
        if bs is not None and bs[0].shape[0] == len(frame_ids) == bs[1].shape[0]:
            self._shift_sum += np.stack([bs[0].sum(0), bs[1].sum(0)])
            self._shift_n += len(frame_ids)
        self._since_fit += len(frame_ids)
        if self._since_fit < self.settings.track_every_frames:
            return
        fit_frame = self._ids_sum / self._since_fit
        n_fit = self._since_fit
        # the image's mean shift over the interval (where most of its frames measured one)
        fit_shift = (self._shift_sum[0] / self._shift_n, self._shift_sum[1] / self._shift_n) \
            if self._shift_n >= 0.5 * n_fit else None
        acc = self._acc
        if self.compiled:
            lights = (acc[0].light_map(), acc[1].light_map())
        else:  # the numpy reference
            lights = (light_map(np.concatenate(self._blk_l)), light_map(np.concatenate(self._blk_r)))
        self._blk_l.clear()
        self._blk_r.clear()
        self._acc = None
        self._ids_sum = 0.0
        self._shift_sum = np.zeros((2, 2))
        self._shift_n = 0
        self._since_fit = 0
        try:
            nl = _track_in(lights[0], acc[0].window, tr.left, self.compiled)
            nr = _track_in(lights[1], acc[1].window, tr.right, self.compiled)
        except ValueError:
            nl = nr = None  # type: ignore[assignment]
        if nl is not None and nr is not None:
            nl, nr = self._agree_with_followed(0, nl), self._agree_with_followed(1, nr)
        score = min(nl.score, nr.score) if nl is not None and nr is not None else 0.0
        if score < self.settings.lost_score_ratio * tr.first_score:
            # too little modulated light to fit (a dark stretch: zero padding, idle
            # symbols, an occlusion): hold the last fit
            tr.low_frames += n_fit
        else:
            # the grid's motion only between fits of consecutive good intervals
            good_before = tr.low_frames == 0 and math.isfinite(tr.fit_frame)
            tr.prev, tr.prev_frame = ((tr.left, tr.right), tr.fit_frame) if good_before else (None, math.nan)
            tr.low_frames = 0
            tr.left, tr.right = nl, nr  # type: ignore[assignment]
            tr.fit_frame = fit_frame
            tr.fit_shift = fit_shift
        now = int(frame_ids[-1])
        if tr.low_frames > self.settings.lost_packets * self.packet_frames:
            # every packet lights every LED in its header: a whole packet's time dark is gone
            self.counters["losses"] += 1
            if tr.last_header_frame is None:
                # it blinked for a while but never sent a header: not ours
                self._exclude(tr, now, "lost before it sent any header")
            else:
                log.warning("transmitter lost at frame %d; re-acquiring", now)
            self.track = None
        elif tr.frames_since_header > self.settings.verify_packets * self.packet_frames:
            # counted in decoded frames, so dropped frames never condemn a transmitter
            self._exclude(tr, now, f"sent no header for {self.settings.verify_packets:g} packets")
            self.track = None

    LIT_DECAY = 0.998
    """Per block, how much of the remembered light of a lit LED is kept."""

    FOLLOW_LOST_PITCH = 0.75
    """Followed positions further than this many pitches (RMS) from a grid fit are lost:
    the fit wins and following restarts from it."""

    FOLLOW_TRUST_PX = 1.0
    """A grid fit further than this (RMS over the LEDs) from the LEDs as followed frame by
    frame is replaced by the grid through the followed positions."""

    def _agree_with_followed(self, side: int, fit: GridFit) -> GridFit:
        """The grid fit, or the grid through the LEDs' followed positions (least squares
        origin and pitch) when they disagree: the fit is made on an activity map of tens of
        frames and, from close by, with discs for spots, can lock a fraction of a pitch off
        while the followed positions stay within hundredths of a pixel."""
        fol = self._followed[side]
        if fol is None or fit.rows * fit.cols < 2 or fol.shape != (fit.rows * fit.cols, 2):
            return fit
        d = fit.centers - fol
        off = float(np.sqrt(np.add.reduce(np.add.reduce(d * d, 1)) / d.shape[0]))  # ((c - f) ** 2).sum(1).mean()
        if off <= self.FOLLOW_TRUST_PX:
            return fit
        if off > self.FOLLOW_LOST_PITCH * fit.pitch_px:
            # more than most of a pitch: not the fit's sub-pixel lock but following that
            # walked off (along a blooming column, onto a neighbour's light) and would hold
            # itself there; the fit of tens of frames' light is right, following restarts
            log.info("LEDs followed %.1f px from the grid fit (camera %d): following restarts from the fit",
                     off, side)
            self._followed[side] = None
            self.counters["following_resets"] += 1
            return fit
        r, c = np.divmod(np.arange(fit.rows * fit.cols), fit.cols)
        g = np.stack([c, r], 1).astype(np.float64)
        gc, fc = g - g.mean(0), fol - fol.mean(0)
        pitch = float((gc * fc).sum() / (gc * gc).sum())
        if not pitch > 0:
            return fit
        origin = fol.mean(0) - pitch * g.mean(0)
        return replace(fit, origin=(float(origin[0]), float(origin[1])), pitch_px=pitch)

    def _exclude(self, tr: _Track, now: int, why: str) -> None:
        """Reject a candidate: acquisition ignores its place for ``exclude_packets`` packets."""
        log.warning("candidate at %.0f,%.0f %s: not a transmitter; ignored for %g packets",
                    *tr.left.center, why, self.settings.exclude_packets)
        self.counters["rejected_candidates"] += 1
        until = now + int(self.settings.exclude_packets * self.packet_frames)
        self.excluded.append((tr.left.bbox(4), until))
