"""``iscd calibrate``: stereo calibration of the rig from board images, or live from the rig,
and ``--verify`` of a stored calibration against new pairs."""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

from iscd.core.errors import UserError

log = logging.getLogger(__name__)

DESCRIPTION = """\
Calibrate the stereo rig from pairs of board images: intrinsics of each camera, the rotation
and translation between them (T in metres, from --square), and the rectification used for
ranging (Z = f*b/d). Pairs are formed in name order from --left and --right. Pairs where the
board is not found in both images, and outliers with a reprojection error far above the
median, are rejected with the reason. Writes the calibration file (OpenCV FileStorage YAML,
written atomically) and a report (report.md, report.json, preview.png: the rectified pair
with horizontal epipolar lines).

With --verify CAL.yml, new pairs are checked against a stored calibration (e.g. at the start
of a test day): prints OK or RECALIBRATE with the numbers; exit status 0 for OK, 1 for
RECALIBRATE.

With --live, pairs come from the rig's two cameras (rig section of --config): hold the board
still in a new place or angle and a pair is taken automatically; watch coverage and angles in
Rerun with --rerun."""

EPILOG = """\
examples:
  iscd calibrate --left 'cal/left*.png' --right 'cal/right*.png' --board 9x6 --square 0.025 --out rig.yml
  iscd calibrate --left 'l/*.png' --right 'r/*.png' --board 7x5 --square 0.04 --charuco \\
      --marker 0.03 --dict 4X4_50 --out rig.yml
  iscd calibrate --left 'today/l*.png' --right 'today/r*.png' --board 9x6 --square 0.025 --verify rig.yml
  iscd calibrate --live --config rig.toml --board 9x6 --square 0.025 --out rig.yml --rerun"""


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("calibrate", help="stereo calibration of the camera rig (chessboard/ChArUco)",
                       description=DESCRIPTION, epilog=EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_argument_group("input")
    src.add_argument("--left", metavar="GLOB", help="left images (a glob, quoted, or a folder)")
    src.add_argument("--right", metavar="GLOB", help="right images, paired with --left in name order")
    src.add_argument("--live", action="store_true",
                     help="capture pairs live from the rig's cameras instead of files")
    src.add_argument("--config", metavar="FILE",
                     help="config file whose [rig] and [camera] sections select the cameras (--live)")
    b = p.add_argument_group("board")
    b.add_argument("--board", metavar="COLSxROWS", required=True,
                   help="chessboard: inner corners per row x per column (a 10x7-square board is "
                        "9x6); ChArUco: squares per row x per column")
    b.add_argument("--square", metavar="METRES", type=float, required=True,
                   help="side of one square in metres (sets the scale of T and the baseline)")
    b.add_argument("--charuco", action="store_true", help="the board is a ChArUco board")
    b.add_argument("--marker", metavar="METRES", type=float, default=0.0,
                   help="ChArUco marker side in metres")
    b.add_argument("--dict", metavar="NAME", default="4X4_50",
                   help="ChArUco ArUco dictionary, e.g. 4X4_50, 5X5_100, 6X6_250 (default 4X4_50)")
    b.add_argument("--legacy-charuco", action="store_true",
                   help="the ChArUco board was made with OpenCV < 4.6 (even row counts differ)")
    o = p.add_argument_group("output")
    o.add_argument("--out", metavar="FILE.yml", help="calibration file to write")
    o.add_argument("--report", metavar="DIR",
                   help="report folder (default: <out name>_report beside --out; with --verify "
                        "only when given)")
    o.add_argument("--verify", metavar="CAL.yml",
                   help="check the pairs against this calibration instead of calibrating")
    s = p.add_argument_group("solver")
    s.add_argument("--min-pairs", type=int, default=6, metavar="N",
                   help="fewest usable pairs to calibrate from (default 6)")
    s.add_argument("--outlier-factor", type=float, default=3.0, metavar="X",
                   help="reject a pair whose reprojection error exceeds X times the median (default 3)")
    s.add_argument("--outlier-floor", type=float, default=0.2, metavar="PX",
                   help="...and exceeds PX pixels (default 0.2)")
    s.add_argument("--dist-model", default="standard",
                   choices=("standard", "k1k2", "k1k2k3", "rational"),
                   help="lens distortion model (default standard: k1 k2 p1 p2 k3)")
    s.add_argument("--no-joint", action="store_true",
                   help="keep each camera's own intrinsics (skip the joint stereo refinement)")
    s.add_argument("--alpha", type=float, default=-1.0, metavar="A",
                   help="rectification scaling: -1 keeps the focal length, 0 crops to valid "
                        "pixels, 1 keeps all pixels (default -1)")
    v = p.add_argument_group("verify limits")
    v.add_argument("--max-epipolar-px", type=float, default=0.5, metavar="PX",
                   help="RMS vertical offset after rectification above which to recalibrate (0.5)")
    v.add_argument("--max-transfer-px", type=float, default=1.0, metavar="PX",
                   help="RMS left-to-right transfer error above which to recalibrate (1.0)")
    v.add_argument("--max-scale-error", type=float, default=0.01, metavar="FRACTION",
                   help="relative error of reconstructed square size above which to recalibrate (0.01)")
    lv = p.add_argument_group("live capture")
    lv.add_argument("--pairs", type=int, default=20, metavar="N", help="pairs to take (default 20)")
    lv.add_argument("--steady-px", type=float, default=0.75, metavar="PX",
                    help="a corner moving less than this between analysed frames is steady (px)")
    lv.add_argument("--steady-frames", type=int, default=5, metavar="N",
                    help="analysed frames the board must be steady before a pair is taken")
    lv.add_argument("--max-seconds", type=float, default=600.0, metavar="S", help="give up after this long")
    lv.add_argument("--save-pairs", metavar="DIR",
                    help="also save the taken pairs as PNG (left_NNN.png, right_NNN.png)")
    lv.add_argument("--rerun", action="store_true", help="show the capture in a Rerun viewer")
    lv.add_argument("--rerun-save", metavar="FILE.rrd", help="record the capture to a Rerun file")
    p.set_defaults(func=run)


def _board(args: argparse.Namespace):  # -> BoardSpec
    from iscd.calibration.boards import BoardError, BoardSpec, parse_board_size

    try:
        cols, rows = parse_board_size(args.board)
        if args.charuco and not args.marker:
            raise BoardError("--charuco needs --marker METRES (the marker side)")
        return BoardSpec("charuco" if args.charuco else "chessboard", cols, rows,
                         float(args.square), float(args.marker), args.dict, args.legacy_charuco)
    except BoardError as e:
        raise UserError(str(e)) from None


def _check_args(args: argparse.Namespace) -> None:
    if args.live and (args.left or args.right):
        raise UserError("use either --live or --left/--right, not both")
    if not args.live and not (args.left and args.right):
        raise UserError("give --left GLOB and --right GLOB (or --live)")
    if not args.verify and not args.out:
        raise UserError("give --out FILE.yml (or --verify CAL.yml)")
    if args.out and Path(args.out).is_dir():
        raise UserError(f"--out {args.out} is a folder; give a file name such as rig.yml")
    if args.min_pairs < 3:
        raise UserError("--min-pairs must be at least 3")
    if not (args.outlier_factor > 1 and math.isfinite(args.outlier_factor)):
        raise UserError(f"--outlier-factor must be a finite number > 1, got {args.outlier_factor}")
    if not (args.outlier_floor >= 0 and math.isfinite(args.outlier_floor)):
        raise UserError(f"--outlier-floor must be a finite number of pixels >= 0, got {args.outlier_floor}")
    if not (args.alpha == -1 or 0 <= args.alpha <= 1):
        raise UserError(f"--alpha must be -1 or in 0..1, got {args.alpha}")
    for opt, value in (("--max-epipolar-px", args.max_epipolar_px), ("--max-transfer-px", args.max_transfer_px),
                       ("--max-scale-error", args.max_scale_error), ("--steady-px", args.steady_px),
                       ("--max-seconds", args.max_seconds)):
        if not (value > 0 and math.isfinite(value)):
            raise UserError(f"{opt} must be a finite number > 0, got {value}")
    for opt, n in (("--pairs", args.pairs), ("--steady-frames", args.steady_frames)):
        if n < 1:
            raise UserError(f"{opt} must be at least 1, got {n}")
    if args.out and not args.verify:
        _check_target(args.out, "--out", folder=False)
    if args.report:
        _check_target(args.report, "--report", folder=True)
    if args.save_pairs:
        _check_target(args.save_pairs, "--save-pairs", folder=True)


def _check_target(path: str, what: str, *, folder: bool) -> None:
    """Refuse (one line) an output path that cannot be made, before the slow part and
    without making anything (a failed calibration leaves nothing behind): a file where a
    folder is needed, or a file in the way of a folder to be made; other failures (a
    read-only file system) are reported when writing."""
    p = Path(path)
    if folder and p.exists() and not p.is_dir():
        raise UserError(f"{what} {path}: is a file; give a folder")
    parent = p if folder else p.parent
    for a in (parent, *parent.parents):
        if a.exists():
            if not a.is_dir():
                raise UserError(f"{what} {path}: cannot write there: {a} is a file")
            break


def run(args: argparse.Namespace) -> int:
    from iscd.calibration.io import CalibrationError

    _check_args(args)
    board = _board(args)
    try:
        if args.live:
            return _run_live(args, board)
        return _run_files(args, board)
    except CalibrationError as e:
        raise UserError(str(e)) from None


def _progress(args: argparse.Namespace, n: int) -> bool:
    return n >= 8 and not getattr(args, "quiet", False)


def _run_files(args: argparse.Namespace, board) -> int:  # type: ignore[no-untyped-def]
    from iscd.calibration.pipeline import detect_files, pair_files

    if args.verify:
        from iscd.calibration.io import load_calibration

        cal = load_calibration(args.verify)  # fail before the slow part
    pairs = pair_files(args.left, args.right)
    det = detect_files(pairs, board, progress=_progress(args, len(pairs)))
    if args.verify:
        return _verify(args, board, cal, det)
    from iscd.calibration.detect import read_image
    from iscd.calibration.pipeline import pair_name

    by_name = {pair_name(lp, rp): (lp, rp) for lp, rp in pairs}

    def images(name: str):  # type: ignore[no-untyped-def]
        lp, rp = by_name[name]
        return read_image(lp), read_image(rp)

    return _calibrate(args, board, det, images)


def _calibrate(args: argparse.Namespace, board, det, images) -> int:  # type: ignore[no-untyped-def]
    """Calibrate, write the file and the report; ``images(name)`` gives a pair's images."""
    from iscd.calibration.io import save_calibration
    from iscd.calibration.pipeline import no_board_message
    from iscd.calibration.report import write_report
    from iscd.calibration.solve import calibrate_stereo

    msg = no_board_message(det, board)
    if msg:
        raise UserError(msg)
    res = calibrate_stereo(
        det.observations, det.image_size, rejected=det.rejected, min_pairs=args.min_pairs,
        outlier_factor=args.outlier_factor, outlier_floor_px=args.outlier_floor,
        dist_model=args.dist_model, joint=not args.no_joint, alpha=args.alpha,
        board_label=board.label)
    for p in res.rejected:
        print(f"rejected pair {p.name}: {p.reason}", file=sys.stderr)
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    out = Path(args.out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        save_calibration(res.calibration, out)
    except OSError as e:
        raise UserError(f"--out {out}: cannot write there: {e.strerror or e}") from None
    report_dir = Path(args.report) if args.report else out.with_name(f"{out.stem}_report")
    preview = None
    shown = res_first_used(res, det)
    if shown is not None:
        left_img, right_img = images(shown.name)
        if left_img is not None and right_img is not None:
            preview = (left_img, right_img, shown)
    try:
        write_report(res, report_dir, str(out), preview)
    except OSError as e:
        raise UserError(f"wrote {out}, but not the report: {report_dir}: {e.strerror or e}") from None
    c = res.calibration
    print(f"calibrated from {len(res.used)} of {len(det.names)} pairs: baseline {c.baseline_m:.5f} m, "
          f"focal {c.focal_px:.2f} px (rectified), rotation {c.rotation_deg:.3f} deg")
    print(f"RMS reprojection error: left {res.rms_mono_left:.3f} px, right {res.rms_mono_right:.3f} px, "
          f"stereo {res.rms_stereo:.3f} px; epipolar error RMS {res.epipolar_rms_px:.3f} px "
          f"(max {res.epipolar_max_px:.3f} px)")
    print(f"wrote {out}; report in {report_dir}/")
    return 0


def res_first_used(res, det):  # type: ignore[no-untyped-def]
    """The observation shown in the preview: the first used pair."""
    used = {p.name for p in res.used}
    return next((o for o in det.observations if o.name in used), None)


def _verify(args: argparse.Namespace, board, cal, det) -> int:  # type: ignore[no-untyped-def]
    from iscd.calibration.pipeline import no_board_message
    from iscd.calibration.report import write_verify_report
    from iscd.calibration.verify import VerifyThresholds, verify_calibration

    if det.image_size != cal.image_size:
        raise UserError(f"the images are {det.image_size[0]}x{det.image_size[1]} px but "
                        f"{args.verify} is for {cal.image_width}x{cal.image_height} px")
    msg = no_board_message(det, board)
    if msg:
        raise UserError(msg)
    for p in det.rejected:
        print(f"skipped pair {p.name}: {p.reason}", file=sys.stderr)
    th = VerifyThresholds(args.max_epipolar_px, args.max_transfer_px, args.max_scale_error)
    vr = verify_calibration(cal, det.observations, board, th)
    print(vr.summary())
    if args.report:
        try:
            write_verify_report(vr, args.report, args.verify)
        except OSError as e:
            raise UserError(f"--report {args.report}: cannot write the report: {e.strerror or e}") from None
    return 0 if vr.ok else 1


def _run_live(args: argparse.Namespace, board) -> int:  # type: ignore[no-untyped-def]
    import cv2

    from iscd.calibration.live import LiveSettings, RerunView, run_capture
    from iscd.calibration.pipeline import Detected
    from iscd.drivers.base import CameraError
    from iscd.core.config import load

    cfg = load(args.config)
    try:
        from iscd.drivers.registry import open_stereo
    except ImportError:
        raise UserError("live capture needs iscd.drivers.registry (camera backends), which is not "
                        "installed") from None
    if args.verify:
        from iscd.calibration.io import load_calibration

        cal = load_calibration(args.verify)
    view = None
    if args.rerun or args.rerun_save:
        view = RerunView.open(spawn=args.rerun, save_path=args.rerun_save)
    settings = LiveSettings(n_pairs=args.pairs if not args.verify else max(3, min(args.pairs, 6)),
                            steady_px=args.steady_px, steady_frames=args.steady_frames,
                            max_seconds=args.max_seconds)

    def show(ev) -> None:  # type: ignore[no-untyped-def]
        if ev.state in ("captured", "duplicate", "rejected") and not getattr(args, "quiet", False):
            print(f"{ev.state}: {ev.message}", file=sys.stderr)

    cam = cfg.camera
    try:
        # Opened and configured from [camera] (left = trigger master, right = slave).
        left, right = open_stereo(cfg)
        try:
            right.start()  # the slave first, so that it sees the master's first pulse
            left.start()
            logic = run_capture(left, right, board, settings, view, on_event=show)
        finally:
            for c in (left, right):
                try:
                    c.stop()
                finally:
                    c.close()
    except CameraError as e:
        raise UserError(f"camera: {e}") from None
    if args.save_pairs:
        folder = Path(args.save_pairs)
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise UserError(f"--save-pairs {folder}: cannot write there: {e.strerror or e}") from None
        for i, c in enumerate(logic.captures):
            for side, img in (("left", c.left), ("right", c.right)):
                if not cv2.imwrite(str(folder / f"{side}_{i:03d}.png"), img):
                    raise UserError(f"--save-pairs {folder}: cannot write {side}_{i:03d}.png")
    if not logic.captures:
        raise UserError("no pairs were taken (board never steady in both views?)")
    size = logic.image_size or (cam.width, cam.height)
    det = Detected([c.observation for c in logic.captures], [], size,
                   [c.name for c in logic.captures])
    if args.verify:
        return _verify(args, board, cal, det)
    by_name = {c.name: (c.left, c.right) for c in logic.captures}
    return _calibrate(args, board, det, lambda name: by_name[name])
