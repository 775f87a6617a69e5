"""The stereo calibration file (SPEC section 7): data class, atomic save, checked load.

A calibration describes the rig as OpenCV does:

- ``M1``, ``M2``: 3x3 camera matrices of the left and right camera, px
  (``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``; f/rho of the dissertation's eq. (2.2) is fx).
- ``D1``, ``D2``: distortion coefficients ``(k1, k2, p1, p2[, k3, ...])``, dimensionless.
- ``R``, ``T``: rotation and translation taking a point from left-camera coordinates into
  right-camera coordinates, ``X_r = R @ X_l + T`` (T in metres, as cv2.stereoCalibrate gives
  it; a right camera at +b along x has ``T = (-b, 0, 0)``).
- ``R1 R2 P1 P2 Q``: the rectification of cv2.stereoRectify (rectified images have
  horizontal epipolar lines; disparity ``d = x_l - x_r`` in px, range ``Z = f*b/d``, eq. (2.2)).

The file is OpenCV FileStorage YAML, readable by ``cv2.FileStorage`` in any language.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from iscd.core.config import CameraConfig

Which = Literal["left", "right"]


class CalibrationError(ValueError):
    """A calibration file or calibration input is unusable; ``str(err)`` is one line."""


_MATRIX_SHAPES: dict[str, tuple[int, int] | None] = {
    "M1": (3, 3), "D1": None, "M2": (3, 3), "D2": None, "R": (3, 3), "T": (3, 1),
    "R1": (3, 3), "R2": (3, 3), "P1": (3, 4), "P2": (3, 4), "Q": (4, 4),
    "E": (3, 3), "F": (3, 3),
}
_REQUIRED = ("image_width", "image_height", "M1", "D1", "M2", "D2", "R", "T")
_RECT = ("R1", "R2", "P1", "P2", "Q")
_SCALARS = ("rms_left", "rms_right", "rms_stereo", "epipolar_rms_px")
_STRINGS = ("board", "created")


@dataclass
class StereoCalibration:
    """Intrinsics, extrinsics and rectification of the stereo rig (see module docstring).

    Matrices are float64 numpy arrays; ``T`` has shape (3, 1) in metres. The optional
    ``rms_*`` fields are the RMS reprojection errors in px of the calibration that produced
    this file (left camera, right camera, stereo pair) and ``epipolar_rms_px`` the RMS
    vertical offset of corresponding corners after rectification, px.
    """

    image_width: int
    image_height: int
    M1: np.ndarray
    D1: np.ndarray
    M2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    R1: np.ndarray | None = None
    R2: np.ndarray | None = None
    P1: np.ndarray | None = None
    P2: np.ndarray | None = None
    Q: np.ndarray | None = None
    E: np.ndarray | None = None
    F: np.ndarray | None = None
    rms_left: float | None = None
    rms_right: float | None = None
    rms_stereo: float | None = None
    epipolar_rms_px: float | None = None
    board: str | None = None
    created: str | None = None
    n_pairs: int | None = None
    extra: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.image_width = int(self.image_width)
        self.image_height = int(self.image_height)
        if self.image_width <= 0 or self.image_height <= 0:
            raise CalibrationError(
                f"image size must be positive, got {self.image_width}x{self.image_height}")
        for name, shape in _MATRIX_SHAPES.items():
            val = getattr(self, name)
            if val is None:
                continue
            arr = np.asarray(val, dtype=np.float64)
            if name in ("D1", "D2"):
                arr = arr.reshape(1, -1)
                if arr.shape[1] not in (4, 5, 8, 12, 14):
                    raise CalibrationError(
                        f"{name}: expected 4, 5, 8, 12 or 14 distortion coefficients, "
                        f"got {arr.shape[1]}")
            elif name == "T":
                if arr.size != 3:
                    raise CalibrationError(f"T: expected 3 values, got {arr.size}")
                arr = arr.reshape(3, 1)
            elif arr.shape != shape:
                raise CalibrationError(f"{name}: expected shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise CalibrationError(f"{name}: contains non-finite values")
            setattr(self, name, arr)

    # ------------------------------------------------------------------ properties
    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in px, as OpenCV wants it."""
        return (self.image_width, self.image_height)

    @property
    def is_rectified(self) -> bool:
        """True when R1, R2, P1, P2 and Q are all present."""
        return all(getattr(self, n) is not None for n in _RECT)

    @property
    def focal_px(self) -> float:
        """Focal length f/rho in px: of the rectified views (P1) if present, else M1's fx."""
        if self.P1 is not None:
            return float(self.P1[0, 0])
        return float(self.M1[0, 0])

    @property
    def baseline_m(self) -> float:
        """Distance between the two camera centres, m (|T|)."""
        return float(np.linalg.norm(self.T))

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation R between the cameras, degrees."""
        rvec, _ = cv2.Rodrigues(self.R)
        return math.degrees(float(np.linalg.norm(rvec)))

    def range_m(self, disparity_px: np.ndarray | float) -> np.ndarray | float:
        """Range Z = f*b/d in m for a rectified disparity d in px (eq. 2.2, f/rho = focal_px)."""
        return self.focal_px * self.baseline_m / np.asarray(disparity_px, dtype=np.float64)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_parameters(cls, width: int, height: int, fx: float, fy: float | None = None,
                        cx: float | None = None, cy: float | None = None,
                        baseline_m: float = 0.25, D1: np.ndarray | None = None,
                        D2: np.ndarray | None = None, rvec: np.ndarray | None = None,
                        M2: np.ndarray | None = None, alpha: float = -1.0) -> "StereoCalibration":
        """A rig from explicit parameters, with rectification computed.

        width, height: px. fx, fy: focal length in px (fy defaults to fx). cx, cy: principal
        point in px (default the image centre ``((w-1)/2, (h-1)/2)``). baseline_m: the right
        camera sits at +baseline_m along the left camera's x axis, so ``T = -R @ (b, 0, 0)``.
        D1, D2: distortion (k1, k2, p1, p2, k3), default none. rvec: Rodrigues vector of R,
        radians (default identity). M2: right camera matrix (default equal to the left's).
        """
        fy = fx if fy is None else fy
        cx = (width - 1) / 2.0 if cx is None else cx
        cy = (height - 1) / 2.0 if cy is None else cy
        M1 = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        R = np.eye(3) if rvec is None else cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
        T = -R @ np.array([[baseline_m], [0.0], [0.0]])
        cal = cls(width, height, M1, np.zeros(5) if D1 is None else D1,
                  M1.copy() if M2 is None else M2, np.zeros(5) if D2 is None else D2, R, T)
        return cal.with_rectification(alpha=alpha)

    @classmethod
    def ideal(cls, camera_cfg: "CameraConfig") -> "StereoCalibration":
        """The ideal rig of a config: fx = fy = focal_length_m/pixel_pitch_m, principal point at
        the image centre, no distortion, R = I, T = (-baseline_m, 0, 0); rectified."""
        return cls.from_parameters(camera_cfg.width, camera_cfg.height, camera_cfg.focal_px,
                                   baseline_m=camera_cfg.baseline_m)

    def with_rectification(self, alpha: float = -1.0) -> "StereoCalibration":
        """A copy with R1 R2 P1 P2 Q from cv2.stereoRectify (CALIB_ZERO_DISPARITY: both rectified
        principal points coincide, so disparity is x_l - x_r). alpha: -1 keeps the focal length
        (no zoom), 0 crops to valid pixels, 1 keeps all source pixels."""
        R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(
            self.M1, self.D1, self.M2, self.D2, self.image_size, self.R, self.T,
            flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha)
        return replace(self, R1=R1, R2=R2, P1=P1, P2=P2, Q=Q)

    def rectification_maps(self, which: Which) -> tuple[np.ndarray, np.ndarray]:
        """cv2.remap maps (map_x, map_y as float32, px) that rectify the ``which`` image."""
        cal = self if self.is_rectified else self.with_rectification()
        M, D, Rr, P = cal._camera(which)
        return cv2.initUndistortRectifyMap(M, D, Rr, P, self.image_size, cv2.CV_32FC1)

    def _camera(self, which: Which) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        if which == "left":
            return self.M1, self.D1, self.R1, self.P1  # type: ignore[return-value]
        if which == "right":
            return self.M2, self.D2, self.R2, self.P2  # type: ignore[return-value]
        raise ValueError(f"which must be 'left' or 'right', got {which!r}")

    def to_dict(self) -> dict[str, object]:
        """Plain-Python form (lists) of every present field, e.g. for JSON reports."""
        out: dict[str, object] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None or (f.name == "extra" and not v):
                continue
            out[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
        return out


# ---------------------------------------------------------------------- geometry helpers
def rectify_points(cal: StereoCalibration, pts: np.ndarray, which: Which) -> np.ndarray:
    """Image points (N, 2) px of the ``which`` camera -> rectified image points (N, 2) px.

    Undistorts with M/D and applies the rectification R1/P1 (left) or R2/P2 (right)
    (cv2.undistortPoints). In rectified coordinates corresponding points share y, and the
    disparity d = x_left - x_right gives the range Z = f*b/d (eq. 2.2) with
    ``f = cal.focal_px`` and ``b = cal.baseline_m``. A calibration without rectification is
    rectified on the fly (call :meth:`StereoCalibration.with_rectification` once instead
    when converting many points).
    """
    c = cal if cal.is_rectified else cal.with_rectification()
    arr = np.asarray(pts, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 2))
    if arr.ndim == 1 and arr.size == 2:
        arr = arr.reshape(1, 2)
    if arr.shape[-1] != 2:
        raise ValueError(f"points must have shape (N, 2), got {arr.shape}")
    M, D, Rr, P = c._camera(which)
    out = cv2.undistortPoints(arr.reshape(-1, 1, 2), M, D, R=Rr, P=P,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10))
    return out.reshape(-1, 2)


def project_points(cal: StereoCalibration, points_left_m: np.ndarray, which: Which) -> np.ndarray:
    """3-D points (N, 3) in left-camera coordinates, m -> image points (N, 2) px of the
    ``which`` camera, with its lens distortion (cv2.projectPoints). For simulators that
    render a non-ideal rig."""
    X = np.asarray(points_left_m, dtype=np.float64).reshape(-1, 3)
    if which == "left":
        rvec, tvec, M, D = np.zeros(3), np.zeros(3), cal.M1, cal.D1
    elif which == "right":
        rvec, tvec, M, D = cv2.Rodrigues(cal.R)[0], cal.T, cal.M2, cal.D2
    else:
        raise ValueError(f"which must be 'left' or 'right', got {which!r}")
    img, _ = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, tvec, M, D)
    return img.reshape(-1, 2)


def scale_calibration(cal: StereoCalibration, width: int, height: int,
                      rtol: float = 0.005) -> StereoCalibration:
    """``cal`` for images resampled to ``width`` x ``height`` px (the same view at another
    resolution, e.g. 2x2 binning): fx, cx of both cameras scale by s = width / cal.image_width,
    fy, cy by height / cal.image_height, about pixel centres (``c' = (c + 0.5) s - 0.5``);
    distortion (in normalised coordinates), R and T are unchanged; the rectification is
    recomputed. Refuses (:class:`CalibrationError`) a change of aspect ratio by more than
    ``rtol``: that is a crop or another sensor mode, not a resampling, and needs a new
    calibration."""
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise CalibrationError(f"cannot scale a calibration to {width}x{height} px")
    sx, sy = width / cal.image_width, height / cal.image_height
    if abs(sx / sy - 1.0) > rtol:
        raise CalibrationError(
            f"cannot scale a calibration for {cal.image_width}x{cal.image_height} px to "
            f"{width}x{height} px: the aspect ratio differs (a crop or another sensor mode); "
            f"recalibrate at {width}x{height}")

    def scaled(M: np.ndarray) -> np.ndarray:
        out = np.array(M, dtype=np.float64, copy=True)
        out[0, 0] *= sx
        out[0, 1] *= sx
        out[0, 2] = (out[0, 2] + 0.5) * sx - 0.5
        out[1, 1] *= sy
        out[1, 2] = (out[1, 2] + 0.5) * sy - 0.5
        return out

    base = replace(cal, image_width=width, image_height=height, M1=scaled(cal.M1), M2=scaled(cal.M2),
                   R1=None, R2=None, P1=None, P2=None, Q=None, E=None, F=None)
    return base.with_rectification()


def check_image_size(cal: StereoCalibration, width: int, height: int, source: str = "calibration") -> None:
    """Raise :class:`CalibrationError` naming both sizes unless ``cal`` is for ``width`` x
    ``height`` px images (a calibration of another size gives wrong ranges without a word:
    the principal point and focal length in px are those of the other size)."""
    if cal.image_size != (int(width), int(height)):
        raise CalibrationError(
            f"{source}: calibration is for {cal.image_width}x{cal.image_height} px images but the "
            f"camera is {int(width)}x{int(height)} px")


# ---------------------------------------------------------------------- file I/O
def dumps_calibration(cal: StereoCalibration) -> str:
    """The calibration as OpenCV FileStorage YAML text."""
    fs = cv2.FileStorage("calibration.yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY
                         | cv2.FILE_STORAGE_FORMAT_YAML)
    fs.write("image_width", int(cal.image_width))
    fs.write("image_height", int(cal.image_height))
    for name in _MATRIX_SHAPES:
        val = getattr(cal, name)
        if val is not None:
            fs.write(name, np.asarray(val, dtype=np.float64))
    for name in _SCALARS:
        val = getattr(cal, name)
        if val is not None:
            fs.write(name, float(val))
    if cal.n_pairs is not None:
        fs.write("n_pairs", int(cal.n_pairs))
    for name in _STRINGS:
        val = getattr(cal, name)
        if val:
            fs.write(name, str(val))
    for k, v in cal.extra.items():
        fs.write(k, float(v))
    fs.write("baseline_m", cal.baseline_m)
    fs.write("focal_px", cal.focal_px)
    return fs.releaseAndGetString()


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically: a temp file in the same folder, fsync, then
    os.replace. Readers see the old file or the whole new one, never a half file; on any
    error the temp file is removed and the old file is left untouched."""
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise CalibrationError(f"{p}: folder {folder} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def save_calibration(cal: StereoCalibration, path: str | Path) -> None:
    """Write ``cal`` as FileStorage YAML to ``path`` atomically (see :func:`atomic_write_text`)."""
    try:
        atomic_write_text(path, dumps_calibration(cal))
    except OSError as e:
        raise CalibrationError(f"{path}: cannot write calibration: {e.strerror or e}") from None


def _read_storage(text: str, source: str) -> "cv2.FileStorage":
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY
                             | cv2.FILE_STORAGE_FORMAT_YAML)
    except (cv2.error, SystemError) as e:
        cause = e.__cause__ if isinstance(e, SystemError) and e.__cause__ else e
        text_err = " ".join(str(cause).split())
        m = re.search(r"in function '(.*)'", text_err)
        msg = m.group(1) if m else (text_err or "parse error")
        raise CalibrationError(f"{source}: not an OpenCV FileStorage YAML file ({msg})") from None
    if not fs.isOpened() or not fs.root().isMap():
        raise CalibrationError(f"{source}: not an OpenCV FileStorage YAML file")
    return fs


MAX_CALIBRATION_BYTES = 1 << 20
"""Largest calibration file read (1 MiB; a real one is about 3 KiB)."""
MAX_MATRIX_SIDE = 64
"""Largest rows/cols a matrix may claim (the largest real one is 4x4 or 1x14): checked in the
text before OpenCV parses it, which would allocate rows*cols first."""
_SIZE_CLAIM = re.compile(r"(?m)^\s*(rows|cols)\s*:\s*([-+]?\d+)")


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?\.(?:inf|Inf|INF|nan|NaN|NAN)"
_NUMLIST = rf"(?:{_NUM})(?:\s*,\s*(?:{_NUM}))*\s*,?"
_SCALAR = rf"(?:{_NUM})|\"[^\"\\\x00-\x1f]*\"|'[^'\x00-\x1f]*'|[A-Za-z0-9_.+-][A-Za-z0-9_.+\-/, ]*"
_LINE = re.compile("|".join([
    r"\s*(?:#.*)?",  # blank, comment
    r"%YAML[: ]\d+\.\d+", r"---", r"\.\.\.",
    rf"[A-Za-z_][A-Za-z0-9_]*:(?:\s+(?:{_SCALAR}|!!opencv-matrix))?\s*",  # top-level key
    r"\s+(?:rows|cols):\s+[-+]?\d+\s*", r"\s+dt:\s+[a-z0-9]{1,8}\s*",
    rf"\s+data:\s+\[\s*(?:{_NUMLIST})?\s*\]?\s*",  # a matrix's data, maybe continued
    rf"\s+(?:{_NUMLIST})\s*\]?\s*", r"\s+\]\s*",
]))


def _check_grammar(text: str, source: str) -> None:
    """Refuse, in Python, text outside the YAML subset that OpenCV writes for a calibration
    (ASCII; top-level ``key: scalar`` or ``key: !!opencv-matrix`` with indented rows, cols,
    dt and a data list of numbers). OpenCV's FileStorage parser can crash the process (abort,
    segfault) on malformed input, found by fuzzing: it only ever sees this subset."""
    if not text.isascii():
        raise CalibrationError(f"{source}: not an OpenCV FileStorage YAML file (non-ASCII characters)")
    lines = [ln.rstrip("\r") for ln in text.splitlines()]
    for i, line in enumerate(lines, 1):
        if not _LINE.fullmatch(line):
            shown = line.strip()[:40]
            raise CalibrationError(f"{source}: not an OpenCV FileStorage YAML file (line {i}: {shown!r})")
    _check_matrices(lines, source)


_DT = ("d", "f", "i", "u", "c", "s", "w")


def _check_matrices(lines: list[str], source: str) -> None:
    """Every ``!!opencv-matrix`` block has exactly one ``rows``, ``cols``, ``dt`` (one
    channel: d f i u c s w) and a closed ``data`` list of exactly rows x cols numbers, and
    indented lines appear only inside such a block. OpenCV reads a block lacking one of them
    from uninitialised memory (a heap corruption that aborted the fuzz run)."""
    key: str | None = None
    block: dict[str, object] = {}
    data: list[str] | None = None
    closed = False

    def finish() -> None:
        if key is None:
            return
        missing = [k for k in ("rows", "cols", "dt", "data") if k not in block]
        if missing:
            raise CalibrationError(f"{source}: {key}: opencv-matrix without {', '.join(missing)}")
        if not closed:
            raise CalibrationError(f"{source}: {key}: opencv-matrix data list not closed with ']'")
        if block["dt"] not in _DT:
            raise CalibrationError(f"{source}: {key}: unsupported opencv-matrix dt {block['dt']!r}")
        n = int(block["rows"]) * int(block["cols"])  # type: ignore[call-overload]
        got = len(data or [])
        if got != n:
            raise CalibrationError(f"{source}: {key}: opencv-matrix of {block['rows']}x{block['cols']} "
                                   f"has {got} values")

    for line in lines:
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        indented = line[:1].isspace()
        if not indented:
            finish()
            key, block, data, closed = None, {}, None, False
            m = re.match(r"([A-Za-z_][A-Za-z0-9_]*):\s*!!opencv-matrix\s*$", line)
            if m:
                key = m.group(1)
            continue
        if key is None:
            raise CalibrationError(f"{source}: not an OpenCV FileStorage YAML file (indented line "
                                   f"{stripped[:40]!r} outside a matrix)")
        name, _, rest = stripped.partition(":")
        if name in ("rows", "cols", "dt", "data") and rest[:1] in (" ", "\t", ""):
            if name in block:
                raise CalibrationError(f"{source}: {key}: opencv-matrix with two {name}")
            rest = rest.strip()
            if name == "data":
                data, closed = [], False
                rest = rest.lstrip("[")
            else:
                block[name] = rest
                continue
            block["data"] = True
        elif data is None or closed:
            raise CalibrationError(f"{source}: {key}: unexpected line {stripped[:40]!r} in an opencv-matrix")
        else:
            rest = stripped
        if rest.endswith("]"):
            closed, rest = True, rest[:-1]
        data.extend(v for v in (t.strip() for t in rest.split(",")) if v)
    finish()


def loads_calibration(text: str, source: str = "<string>") -> StereoCalibration:
    """Parse FileStorage YAML text (see :func:`load_calibration`)."""
    if len(text) > MAX_CALIBRATION_BYTES:
        raise CalibrationError(f"{source}: larger than {MAX_CALIBRATION_BYTES >> 10} KiB: not a calibration file")
    _check_grammar(text, source)
    for m in _SIZE_CLAIM.finditer(text):
        if not 0 < int(m.group(2)) <= MAX_MATRIX_SIDE:
            raise CalibrationError(f"{source}: a matrix claims {m.group(1)}: {m.group(2)} "
                                   f"(expected 1..{MAX_MATRIX_SIDE})")
    if not text.lstrip().startswith("%YAML"):
        text = "%YAML:1.0\n" + text
    fs = _read_storage(text, source)
    root = fs.root()
    keys = set(root.keys())
    missing = [k for k in _REQUIRED if k not in keys]
    if missing:
        raise CalibrationError(f"{source}: missing key{'s' if len(missing) > 1 else ''} "
                               f"{', '.join(missing)}")
    kw: dict[str, object] = {}
    for k in ("image_width", "image_height"):
        node = fs.getNode(k)
        if not node.isInt():
            raise CalibrationError(f"{source}: {k}: expected an integer")
        kw[k] = int(node.real())
    for k in _MATRIX_SHAPES:
        if k not in keys:
            continue
        node = fs.getNode(k)
        try:
            mat = node.mat() if node.isMap() else None
        except (cv2.error, SystemError):  # e.g. data shorter than rows x cols
            mat = None
        if mat is None:
            raise CalibrationError(f"{source}: {k}: expected an opencv-matrix")
        kw[k] = mat
    for k in _SCALARS:
        if k in keys:
            node = fs.getNode(k)
            if node.isReal() or node.isInt():
                kw[k] = float(node.real())
    if "n_pairs" in keys and fs.getNode("n_pairs").isInt():
        kw["n_pairs"] = int(fs.getNode("n_pairs").real())
    for k in _STRINGS:
        if k in keys and fs.getNode(k).isString():
            kw[k] = fs.getNode(k).string()
    try:
        cal = StereoCalibration(**kw)  # type: ignore[arg-type]
    except CalibrationError as e:
        raise CalibrationError(f"{source}: {e}") from None
    present = [k for k in _RECT if k in keys]
    if 0 < len(present) < len(_RECT):
        raise CalibrationError(f"{source}: incomplete rectification: has {', '.join(present)} "
                               f"but not {', '.join(k for k in _RECT if k not in keys)}")
    if not cal.is_rectified:
        cal = cal.with_rectification()
    return cal


def load_calibration(path: str | Path) -> StereoCalibration:
    """Read a calibration file (SPEC section 7). Files without R1 R2 P1 P2 Q (e.g. from
    another tool) get the rectification computed. Raises :class:`CalibrationError` (one
    line) when the file is missing, unreadable, malformed or lacks a required key."""
    p = Path(path)
    try:
        if p.is_file() and p.stat().st_size > MAX_CALIBRATION_BYTES:
            raise CalibrationError(f"{p}: larger than {MAX_CALIBRATION_BYTES >> 10} KiB: not a calibration file")
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CalibrationError(f"{p}: calibration file not found") from None
    except IsADirectoryError:
        raise CalibrationError(f"{p}: is a folder, not a calibration file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise CalibrationError(f"{p}: cannot read calibration file: {e}") from None
    if not text.strip():
        raise CalibrationError(f"{p}: calibration file is empty")
    return loads_calibration(text, str(p))
