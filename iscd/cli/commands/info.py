"""``iscd info RECORDING``: print what a recording holds, as JSON."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from typing import Any

import numpy as np


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "info", help="describe a recording (frames, size, fps, bit depth) as JSON",
        description=("Prints a JSON object describing one camera's recording: frames, width, "
                     "height, fps, bit_depth, dtype, format, path, camera, duration_s, exposure_s, "
                     "first/last frame id, missing_frame_ids (dropped frames) and format-specific "
                     "details under 'extra'. RECORDING is a Photron .cih/.cihx/.mraw file (its "
                     "partner beside it), a folder of PNG/TIFF frames, or an .iscr file. For a "
                     "recording of 'iscd run --record' (a run folder, or one of its stereo .iscr "
                     "files): the mode, pairs, frame ranges, windows, blocks and each file; with "
                     "--check also how much of each file was recovered (a file cut by a crash: "
                     "its whole pairs, the trailing bytes ignored). Problems "
                     "with the recording are printed as one line on stderr (exit status 2)."))
    p.add_argument("recording", metavar="RECORDING",
                   help="a .cih/.cihx/.mraw file, a folder of PNG/TIFF frames, or an .iscr file")
    p.add_argument("--check", action="store_true",
                   help="also read every frame (finds unreadable or odd-sized frames) and report "
                        "the pixel minimum and maximum")
    p.add_argument("--compact", action="store_true", help="print the JSON on one line")
    p.set_defaults(func=run)


def check_pixels(rec: Any, block: int = 64) -> dict[str, Any]:
    """Read every frame; return pixel_min / pixel_max over the whole recording."""
    lo, hi = None, None
    for b in rec.iter_blocks(block):
        if b.size:
            bl, bh = int(b.min()), int(b.max())
            lo = bl if lo is None else min(lo, bl)
            hi = bh if hi is None else max(hi, bh)
    return {"pixel_min": lo, "pixel_max": hi}


def stereo_info(path: str, check: bool) -> dict[str, Any]:
    """The summary of an ``iscd run --record`` recording (folder or file); ``check``: also
    read every pair and say, per file, how much was recovered (``recovery``: sealed, whole
    pairs read back, the share of the file's records in them, the trailing bytes ignored)."""
    from iscd.recording.pairs import open_stereo

    with open_stereo(path) as session:
        info = session.info()
        if check:
            checks = [{"path": r.path.name, **r.check()} for r in session.files]
            info["check"] = checks
            lo = [c["pixel_min"] for c in checks if c["pixel_min"] is not None]
            hi = [c["pixel_max"] for c in checks if c["pixel_max"] is not None]
            info.update(pixel_min=min(lo) if lo else None, pixel_max=max(hi) if hi else None,
                        recovered_pairs=sum(c["pairs"] for c in checks),
                        unsealed_files=sum(not c["sealed"] for c in checks))
    return info


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from iscd.core.errors import UserError
    from iscd.recording import RecordingError, open_recording
    from iscd.recording.pairs import is_pair_file

    p = Path(args.recording)
    stereo = (p.is_file() and is_pair_file(p)) or (p.is_dir() and any(is_pair_file(f) for f in p.glob("*.iscr"))
                                                   and not (p / "left.iscr").exists())

    def read() -> dict[str, Any]:
        if stereo:
            return stereo_info(args.recording, args.check)
        with open_recording(args.recording) as rec:
            info = rec.info()
            if args.check:
                info.update(check_pixels(rec))
            return info

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            info = read()
        except RecordingError as e:
            raise UserError(str(e)) from None
        except (OSError, ValueError) as e:
            raise UserError(f"{args.recording}: {e}") from None
    notes = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    for msg in notes:
        print(f"iscd info: warning: {msg}", file=sys.stderr)
    if notes:
        info["warnings"] = notes
    print(json.dumps(info, indent=None if args.compact else 2, default=_jsonable))
    return 0


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
