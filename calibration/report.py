"""The calibration report: JSON (for tools), Markdown (for people), rectified preview PNG."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from iscd.calibration.detect import PairObservation
from iscd.calibration.io import StereoCalibration, atomic_write_text, rectify_points
from iscd.calibration.solve import CalibrationResult
from iscd.calibration.verify import VerifyResult


def summary_dict(res: CalibrationResult) -> dict[str, Any]:
    """The report's numbers as plain JSON-able data. Errors in px, lengths in m."""
    cal = res.calibration

    def cam(M: np.ndarray, D: np.ndarray) -> dict[str, Any]:
        return {"fx_px": float(M[0, 0]), "fy_px": float(M[1, 1]), "cx_px": float(M[0, 2]),
                "cy_px": float(M[1, 2]), "distortion": [float(v) for v in np.ravel(D)]}

    return {
        "image_width": cal.image_width,
        "image_height": cal.image_height,
        "board": cal.board,
        "focal_px": cal.focal_px,
        "baseline_m": cal.baseline_m,
        "rotation_deg": cal.rotation_deg,
        "T_m": [float(v) for v in cal.T.ravel()],
        "left": cam(cal.M1, cal.D1),
        "right": cam(cal.M2, cal.D2),
        "rms_left_px": res.rms_mono_left,
        "rms_right_px": res.rms_mono_right,
        "rms_stereo_px": res.rms_stereo,
        "rms_stereo_left_px": res.rms_stereo_left,
        "rms_stereo_right_px": res.rms_stereo_right,
        "epipolar_rms_px": res.epipolar_rms_px,
        "epipolar_max_px": res.epipolar_max_px,
        "joint_refinement": res.joint,
        "pairs_used": len(res.used),
        "pairs_rejected": len(res.rejected),
        "pairs": [{"name": p.name, "used": p.used, "reason": p.reason,
                   "err_left_px": p.err_left_px, "err_right_px": p.err_right_px,
                   "epipolar_rms_px": p.epipolar_rms_px} for p in res.pairs],
        "warnings": list(res.warnings),
        "created": cal.created,
    }


def _fmt(v: float | None, nd: int = 3) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{nd}f}"


def markdown(res: CalibrationResult, out_file: str | None = None) -> str:
    """A human-readable report."""
    s = summary_dict(res)
    L, R = s["left"], s["right"]
    lines = [
        "# Stereo calibration report",
        "",
        f"- calibration file: `{out_file}`" if out_file else "- calibration file: (not written)",
        f"- created: {s['created']}",
        f"- board: {s['board']}",
        f"- image size: {s['image_width']} x {s['image_height']} px",
        f"- pairs: {s['pairs_used']} used, {s['pairs_rejected']} rejected",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| baseline | {s['baseline_m']:.5f} m |",
        f"| focal length (rectified, for Z = f*b/d) | {s['focal_px']:.2f} px |",
        f"| rotation between the cameras | {s['rotation_deg']:.4f} deg |",
        f"| RMS reprojection error, left camera | {s['rms_left_px']:.4f} px |",
        f"| RMS reprojection error, right camera | {s['rms_right_px']:.4f} px |",
        f"| RMS reprojection error, stereo pair | {s['rms_stereo_px']:.4f} px |",
        f"| epipolar error after rectification, RMS / max | {s['epipolar_rms_px']:.4f} / "
        f"{s['epipolar_max_px']:.4f} px |",
        "",
        "| camera | fx px | fy px | cx px | cy px | distortion |",
        "|---|---|---|---|---|---|",
        f"| left | {L['fx_px']:.2f} | {L['fy_px']:.2f} | {L['cx_px']:.2f} | {L['cy_px']:.2f} | "
        f"{', '.join(f'{v:.4g}' for v in L['distortion'])} |",
        f"| right | {R['fx_px']:.2f} | {R['fy_px']:.2f} | {R['cx_px']:.2f} | {R['cy_px']:.2f} | "
        f"{', '.join(f'{v:.4g}' for v in R['distortion'])} |",
        "",
        "Mono RMS values are from each camera's own calibration; the stereo RMS is of the final "
        + ("joint refinement of all parameters." if s["joint_refinement"] else
           "stereo step with the intrinsics fixed."),
        "",
        "## Pairs",
        "",
        "| pair | used | error left px | error right px | epipolar RMS px | reason |",
        "|---|---|---|---|---|---|",
    ]
    for p in s["pairs"]:
        lines.append(f"| {p['name'].replace('|', chr(92) + '|')} | {'yes' if p['used'] else 'no'} | {_fmt(p['err_left_px'])} | "
                     f"{_fmt(p['err_right_px'])} | {_fmt(p['epipolar_rms_px'])} | {p['reason']} |")
    if s["warnings"]:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in s["warnings"]]
    lines += ["", "`preview.png`: the first used pair, rectified, with horizontal epipolar lines; "
              "corresponding corners (green left, red right) must lie on the same row.", ""]
    return "\n".join(lines)


def rectified_preview(cal: StereoCalibration, left: np.ndarray, right: np.ndarray,
                      obs: PairObservation | None = None, line_step_px: int = 24) -> np.ndarray:
    """Side-by-side rectified pair (BGR) with horizontal epipolar lines every
    ``line_step_px`` px and, if given, the pair's corners after rectification."""
    c = cal if cal.is_rectified else cal.with_rectification()
    views = []
    for which, img in (("left", left), ("right", right)):
        mx, my = c.rectification_maps(which)  # type: ignore[arg-type]
        r = cv2.remap(img, mx, my, cv2.INTER_LINEAR)
        views.append(cv2.cvtColor(r, cv2.COLOR_GRAY2BGR) if r.ndim == 2 else r)
    canvas = np.hstack(views)
    h, w = canvas.shape[:2]
    for y in range(line_step_px // 2, h, line_step_px):
        cv2.line(canvas, (0, y), (w - 1, y), (0, 200, 255), 1, cv2.LINE_AA)
    if obs is not None:
        off = views[0].shape[1]
        for pts, dx, col in ((rectify_points(c, obs.left_points, "left"), 0, (0, 220, 0)),
                             (rectify_points(c, obs.right_points, "right"), off, (0, 0, 255))):
            for x, y in pts:
                cv2.circle(canvas, (int(round(x + dx)), int(round(y))), 2, col, -1, cv2.LINE_AA)
    return canvas


def write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover
        raise OSError(f"cannot encode {path}")
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(buf.tobytes())
    tmp.replace(path)


def write_report(res: CalibrationResult, folder: str | Path, out_file: str | None = None,
                 preview: tuple[np.ndarray, np.ndarray, PairObservation | None] | None = None) -> Path:
    """Write ``report.json``, ``report.md`` and (given a pair) ``preview.png`` into ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    data = summary_dict(res)
    data["calibration_file"] = out_file
    atomic_write_text(folder / "report.json", json.dumps(data, indent=2))
    atomic_write_text(folder / "report.md", markdown(res, out_file))
    if preview is not None:
        write_png(folder / "preview.png", rectified_preview(res.calibration, *preview))
    return folder


def write_verify_report(vr: VerifyResult, folder: str | Path, calibration_file: str) -> Path:
    """``verify.json`` with the verdict and the per-pair measures."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    data = {
        "calibration_file": calibration_file,
        "verdict": vr.verdict,
        "reasons": vr.reasons,
        "epipolar_rms_px": vr.epipolar_rms_px,
        "epipolar_max_px": vr.epipolar_max_px,
        "transfer_rms_px": vr.transfer_rms_px,
        "scale_error": vr.scale_error,
        "thresholds": vars(vr.thresholds),
        "pairs": [vars(p) for p in vr.pairs],
    }
    atomic_write_text(folder / "verify.json", json.dumps(data, indent=2))
    return folder
