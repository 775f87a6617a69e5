"""Guided live capture of calibration pairs from the rig (``iscd calibrate --live``).

The operator moves the board in front of both cameras. Each processed frame pair is searched
for the board (fast detector); a pair is *taken* when the board has been steady in both views
(every corner moved less than ``steady_px`` between processed frames, ``steady_frames`` times
in a row) and the view is new (mean corner distance to every earlier capture at least
``novelty_px``). Taken pairs are re-detected with sub-pixel refinement. Coverage of the field
(an ``cells`` x ``cells`` grid per camera) and the board's tilt angles are tracked and, when a
Rerun recording is attached, shown live so the operator knows where the board is still missing.

:class:`CaptureLogic` is pure (images in, events out) and testable without cameras;
:func:`run_capture` drives it from two :class:`iscd.drivers.base.Camera` objects.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from iscd.calibration.boards import BoardSpec
from iscd.calibration.detect import Detection, PairObservation, detect, pair_detections, to_gray8
from iscd.drivers.base import Camera, CameraError, CameraTimeout, Frame

log = logging.getLogger(__name__)


@dataclass
class LiveSettings:
    """Capture parameters. Motions in px; ``novelty_px`` <= 0 means 6 % of the image diagonal.
    A view is new when its corners are on average ``novelty_px`` away from every earlier
    capture's, or its tilt differs from theirs by ``novelty_deg``."""

    n_pairs: int = 20
    steady_px: float = 0.75
    steady_frames: int = 5
    novelty_px: float = 0.0
    novelty_deg: float = 10.0
    cells: int = 8
    process_interval_s: float = 0.05
    max_seconds: float = 600.0


@dataclass
class CaptureEvent:
    """What one processed frame pair did: ``state`` is one of ``no board``, ``moving``,
    ``steady``, ``duplicate``, ``captured``, ``rejected``; ``message`` explains it."""

    state: str
    message: str
    motion_px: float = float("nan")
    steady_count: int = 0


@dataclass
class Capture:
    """A taken pair: the images and the sub-pixel observation."""

    name: str
    left: np.ndarray
    right: np.ndarray
    observation: PairObservation
    tilt_deg: tuple[float, float]


def board_tilt_deg(det: Detection, image_size: tuple[int, int]) -> tuple[float, float]:
    """Approximate tilt of the board about the camera's x and y axes, degrees, from a pose
    estimate with a nominal camera (f = image width, principal point at the centre); good
    enough to tell the operator which angles are still missing."""
    w, h = image_size
    K = np.array([[w, 0, (w - 1) / 2], [0, w, (h - 1) / 2], [0, 0, 1.0]])
    ok, rvec, _ = cv2.solvePnP(det.object_points.astype(np.float64),
                               det.image_points.astype(np.float64), K, None)
    if not ok:
        return (float("nan"), float("nan"))
    n = cv2.Rodrigues(rvec)[0][:, 2]  # board normal in the camera frame
    if n[2] > 0:
        n = -n
    return (math.degrees(math.atan2(n[1], -n[2])), math.degrees(math.atan2(n[0], -n[2])))


class CaptureLogic:
    """Steadiness, novelty and coverage bookkeeping (see module docstring)."""

    def __init__(self, board: BoardSpec, settings: LiveSettings | None = None) -> None:
        self.board = board
        self.s = settings or LiveSettings()
        self.captures: list[Capture] = []
        self._prev: tuple[np.ndarray, np.ndarray] | None = None
        self._prev_ids: tuple[np.ndarray, np.ndarray] | None = None
        self._steady = 0
        self.coverage: np.ndarray | None = None  # (2, cells, cells) corner counts
        self.image_size: tuple[int, int] | None = None
        self.last_detections: tuple[Detection | None, Detection | None] = (None, None)

    @property
    def done(self) -> bool:
        return len(self.captures) >= self.s.n_pairs

    def coverage_fraction(self) -> tuple[float, float]:
        """Share of grid cells that have seen a corner, left and right."""
        if self.coverage is None:
            return (0.0, 0.0)
        return tuple(float((c > 0).mean()) for c in self.coverage)  # type: ignore[return-value]

    def _novelty_px(self) -> float:
        if self.s.novelty_px > 0:
            return self.s.novelty_px
        w, h = self.image_size or (512, 512)
        return 0.06 * math.hypot(w, h)

    @staticmethod
    def _motion(a: np.ndarray, ida: np.ndarray, b: np.ndarray, idb: np.ndarray) -> float:
        common, ia, ib = np.intersect1d(ida, idb, return_indices=True)
        if common.size < 4:
            return float("inf")
        return float(np.max(np.linalg.norm(a[ia] - b[ib], axis=1)))

    def step(self, left: np.ndarray, right: np.ndarray) -> CaptureEvent:
        """Process one frame pair (any depth); maybe take it."""
        gl, gr = to_gray8(left), to_gray8(right)
        if self.image_size is None:
            self.image_size = (gl.shape[1], gl.shape[0])
            self.coverage = np.zeros((2, self.s.cells, self.s.cells), np.int64)
        dl, dr = detect(gl, self.board, fast=True), detect(gr, self.board, fast=True)
        dl_ok, dr_ok = isinstance(dl, Detection), isinstance(dr, Detection)
        self.last_detections = (dl if dl_ok else None, dr if dr_ok else None)  # type: ignore[assignment]
        if not (dl_ok and dr_ok):
            self._prev = None
            self._steady = 0
            where = "either view" if not dl_ok and not dr_ok else ("left view" if not dl_ok else "right view")
            return CaptureEvent("no board", f"board not seen in {where}")
        assert isinstance(dl, Detection) and isinstance(dr, Detection)
        cur = (dl.image_points, dr.image_points)
        ids = (dl.ids, dr.ids)
        if self._prev is None or self._prev_ids is None:
            motion = float("inf")
        else:
            motion = max(self._motion(cur[0], ids[0], self._prev[0], self._prev_ids[0]),
                         self._motion(cur[1], ids[1], self._prev[1], self._prev_ids[1]))
        self._prev, self._prev_ids = cur, ids
        if not motion < self.s.steady_px:
            self._steady = 0
            return CaptureEvent("moving", "hold the board still", motion, 0)
        self._steady += 1
        if self._steady < self.s.steady_frames:
            return CaptureEvent("steady", f"steady {self._steady}/{self.s.steady_frames}",
                                motion, self._steady)
        # Steady long enough: is this view new?
        nov = self._novelty_px()
        tilt_now = board_tilt_deg(dl, self.image_size)
        for c in self.captures:
            turned = max(abs(tilt_now[0] - c.tilt_deg[0]), abs(tilt_now[1] - c.tilt_deg[1]))
            if self._mean_distance(cur[0], ids[0], c) < nov and not turned >= self.s.novelty_deg:
                return CaptureEvent("duplicate", f"already have this view ({c.name}); move "
                                    "the board to a new place or angle", motion, self._steady)
        fl, fr = detect(gl, self.board), detect(gr, self.board)
        if not isinstance(fl, Detection) or not isinstance(fr, Detection):
            self._steady = 0
            return CaptureEvent("rejected", "sub-pixel detection failed; try again", motion, 0)
        name = f"live_{len(self.captures):03d}"
        obs = pair_detections(name, fl, fr, self.board)
        if obs is None:
            self._steady = 0
            return CaptureEvent("rejected", "too few corners in both views", motion, 0)
        tilt = board_tilt_deg(fl, self.image_size)
        self.captures.append(Capture(name, gl.copy(), gr.copy(), obs, tilt))
        self._add_coverage(obs)
        self._steady = 0
        cl, cr = self.coverage_fraction()
        return CaptureEvent("captured", f"took pair {len(self.captures)}/{self.s.n_pairs} "
                            f"(coverage left {cl:.0%}, right {cr:.0%}, tilt "
                            f"{tilt[0]:+.0f}/{tilt[1]:+.0f} deg)", motion, 0)

    def _mean_distance(self, pts: np.ndarray, ids: np.ndarray, c: Capture) -> float:
        cids = c.observation.ids
        if cids is None:
            cids = np.arange(len(c.observation.left_points))
        common, ia, ib = np.intersect1d(ids, cids, return_indices=True)
        if common.size < 4:
            return float("inf")
        return float(np.mean(np.linalg.norm(pts[ia] - c.observation.left_points[ib], axis=1)))

    def _add_coverage(self, obs: PairObservation) -> None:
        assert self.coverage is not None and self.image_size is not None
        w, h = self.image_size
        n = self.s.cells
        for k, pts in enumerate((obs.left_points, obs.right_points)):
            cx = np.clip((pts[:, 0] / w * n).astype(int), 0, n - 1)
            cy = np.clip((pts[:, 1] / h * n).astype(int), 0, n - 1)
            np.add.at(self.coverage[k], (cy, cx), 1)


class RerunView:
    """Optional live display of the capture in Rerun (rerun-sdk 0.41).

    ``recording`` is a ``rerun.RecordingStream`` already connected (spawned viewer, file
    sink or memory recording)."""

    def __init__(self, recording: Any) -> None:
        self.rec = recording
        self.n = 0

    @classmethod
    def open(cls, spawn: bool = False, save_path: str | None = None) -> "RerunView":
        import rerun as rr

        rec = rr.RecordingStream("iscd-calibrate")
        if save_path:
            rec.save(save_path)
        elif spawn:
            rec.spawn()
        return cls(rec)

    def update(self, logic: CaptureLogic, left: np.ndarray, right: np.ndarray,
               event: CaptureEvent) -> None:
        import rerun as rr

        rec = self.rec
        rec.set_time("frame", sequence=self.n)
        self.n += 1
        for k, (name, img) in enumerate((("left", left), ("right", right))):
            rec.log(f"{name}/image", rr.Image(to_gray8(img)))
            det = logic.last_detections[k]
            colour = {"captured": (0, 255, 0), "steady": (255, 200, 0)}.get(event.state, (255, 60, 60))
            if det is not None:
                rec.log(f"{name}/image/corners", rr.Points2D(det.image_points, radii=2.0,
                                                              colors=[colour]))
            else:
                rec.log(f"{name}/image/corners", rr.Clear(recursive=False))
            if logic.coverage is not None:
                cov = logic.coverage[k].astype(np.float32)
                heat = (255 * np.minimum(cov / max(1.0, float(cov.max())), 1.0)).astype(np.uint8)
                heat = cv2.resize(heat, (left.shape[1] // 4 or 1, left.shape[0] // 4 or 1),
                                  interpolation=cv2.INTER_NEAREST)
                rec.log(f"coverage/{name}", rr.Image(cv2.applyColorMap(heat, cv2.COLORMAP_VIRIDIS)[:, :, ::-1]))
        if event.state == "captured":
            tilts = np.array([c.tilt_deg for c in logic.captures], np.float64)
            rec.log("angles/tilt_x_y_deg", rr.Points2D(tilts[:, ::-1], radii=1.5))
            cl, cr = logic.coverage_fraction()
            rec.log("progress/pairs", rr.Scalars(float(len(logic.captures))))
            rec.log("progress/coverage_left", rr.Scalars(cl))
            rec.log("progress/coverage_right", rr.Scalars(cr))
        if np.isfinite(event.motion_px):
            rec.log("progress/motion_px", rr.Scalars(float(event.motion_px)))
        rec.log("status", rr.TextLog(f"{event.state}: {event.message}",
                                     level="INFO" if event.state == "captured" else "DEBUG"))


def read_pair(left: Camera, right: Camera, timeout_s: float = 1.0,
              max_skips: int = 64) -> tuple[Frame, Frame]:
    """The next left/right frames with equal ``frame_id`` (the shared trigger), skipping
    frames that lost their partner. Raises CameraError if they do not line up."""
    fl, fr = left.read(timeout_s), right.read(timeout_s)
    for _ in range(max_skips):
        if fl.frame_id == fr.frame_id:
            return fl, fr
        if fl.frame_id < fr.frame_id:
            fl = left.read(timeout_s)
        else:
            fr = right.read(timeout_s)
    raise CameraError(f"left and right frame ids do not line up (left {fl.frame_id}, "
                      f"right {fr.frame_id}); is the trigger shared?")


def run_capture(left: Camera, right: Camera, board: BoardSpec,
                settings: LiveSettings | None = None, view: RerunView | None = None,
                on_event: Any = None, clock: Any = time.monotonic) -> CaptureLogic:
    """Capture pairs from two started cameras until ``n_pairs`` are taken, ``max_seconds``
    pass, or Ctrl-C (KeyboardInterrupt ends the capture, keeping what was taken).

    Frames are read continuously (so the cameras' queues do not overflow) but only one pair
    per ``process_interval_s`` of device time (frame timestamps) is analysed, so steadiness
    is judged over a fixed time, whatever the frame rate. ``on_event(event)`` is called for
    each analysed pair (e.g. to print progress)."""
    s = settings or LiveSettings()
    logic = CaptureLogic(board, s)
    t0 = clock()
    last_ns: int | None = None
    interval_ns = int(s.process_interval_s * 1e9)
    timeouts = 0
    try:
        while not logic.done and clock() - t0 < s.max_seconds:
            try:
                fl, fr = read_pair(left, right)
            except CameraTimeout:
                timeouts += 1
                if timeouts >= 5:
                    raise CameraError("no frames from the cameras for 5 s") from None
                continue
            timeouts = 0
            if last_ns is not None and 0 <= fl.timestamp_ns - last_ns < interval_ns:
                continue
            last_ns = fl.timestamp_ns
            ev = logic.step(fl.image, fr.image)
            if view is not None:
                view.update(logic, fl.image, fr.image, ev)
            if on_event is not None:
                on_event(ev)
    except KeyboardInterrupt:
        log.warning("capture interrupted; %d pairs taken", len(logic.captures))
    return logic
