"""``iscd replay``: offline decode + ranging of a recorded stereo pair."""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from iscd.core.errors import UserError
from iscd.core.records import StatsRecord
from iscd.cli.commands.run import add_calibration_options


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay", help="decode and range a recorded stereo pair offline",
        description=(
            "Decodes the packets and measures the range of the transmitter in a recorded stereo "
            "pair, with the same pipeline as the daemon, and writes JSON Lines records (SPEC "
            "section 7: packet, range, stats). LEFT and RIGHT may each be an .iscr file, a Photron "
            ".cih/.cihx (with its .mraw beside it) or a folder of PNG/TIFF frames; frames are paired "
            "by frame id. A recording made by 'iscd simulate' holds left.iscr, right.iscr, config.toml "
            "and calibration.yml: give the folder as LEFT and omit RIGHT, --config and --calibration. "
            "A recording made by 'iscd run --record' (a run folder of stereo .iscr files, any mode, "
            "or one of its files) is given alone as LEFT: it is decoded in the blocks the live "
            "daemon decoded, with the config and calibration stored beside it, and gives the "
            "live run's packet records."),
        epilog="Example: iscd replay sim/left.iscr sim/right.iscr --config sim/config.toml "
               "--calibration sim/calibration.yml --out sim.jsonl")
    p.add_argument("left", help="left-camera recording (or a simulate output folder, or an 'iscd run --record' "
                                "run folder or file)")
    p.add_argument("right", nargs="?", help="right-camera recording")
    p.add_argument("--config", help="TOML config with the [transmitter] the recording shows")
    add_calibration_options(p, "the recording's image size")
    p.add_argument("--allow-mismatch", action="store_true",
                   help="decode even when the recording's size or frame rate differ from [camera] "
                        "(a warning instead of an error)")
    p.add_argument("--out", required=True, help="JSON Lines output file")
    p.add_argument("--block", type=int, default=64, help="frames per processing block (default 64)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _resolve(args: argparse.Namespace) -> tuple[Path, Path, str | None, str | None]:
    left = Path(args.left)
    if args.right is None:
        if not left.is_dir() or not (left / "left.iscr").exists():
            raise UserError(f"{left}: give LEFT and RIGHT recordings, or a folder made by 'iscd simulate'")
        cfg = args.config or (str(left / "config.toml") if (left / "config.toml").exists() else None)
        cal = args.calibration or (str(left / "calibration.yml") if (left / "calibration.yml").exists() else None)
        return left / "left.iscr", left / "right.iscr", cfg, cal
    return left, Path(args.right), args.config, args.calibration


def config_mismatch(rec: object, camera: object) -> tuple[list[str], list[str]]:
    """What differs between a recording and the config's [camera], as (refuse, warn) lists of
    phrases. The size and the frame rate refuse: the decoder takes frames per symbol from
    camera.fps and the ideal rig from camera.width/height, so a recording that differs decodes
    nothing (or ranges wrongly) without a word. The bit depth only warns: the decoder works
    on the pixel values as they are (an unknown fps, e.g. a PNG folder without sidecar, is
    not compared)."""
    refuse: list[str] = []
    warn: list[str] = []
    w, h = rec.width, rec.height  # type: ignore[attr-defined]
    cw, ch = camera.width, camera.height  # type: ignore[attr-defined]
    if (w, h) != (cw, ch):
        refuse.append(f"size {w}x{h} px vs camera.width x height {cw}x{ch}")
    fps, cfps = rec.fps, camera.fps  # type: ignore[attr-defined]
    if fps and abs(fps / cfps - 1.0) > 1e-3:
        refuse.append(f"frame rate {fps:g} fps vs camera.fps {cfps:g}")
    bits, cbits = rec.bit_depth, camera.bit_depth  # type: ignore[attr-defined]
    if bits != cbits:
        warn.append(f"bit depth {bits}-bit vs camera.bit_depth {cbits}-bit")
    return refuse, warn


def _is_stereo(path: Path) -> bool:
    """Whether ``path`` is an ``iscd run --record`` recording: a version-2 .iscr file, or a
    folder holding some (and no simulate-style left.iscr)."""
    from iscd.recording.pairs import is_pair_file

    if path.is_dir():
        return not (path / "left.iscr").exists() and any(is_pair_file(f) for f in path.glob("*.iscr"))
    return path.is_file() and is_pair_file(path)


def run_stereo(args: argparse.Namespace) -> int:
    """Replay of an ``iscd run --record`` recording: block by block as the live daemon
    decoded it (pairs rebuilt with the recorded windows at their positions, zeros
    elsewhere; exposure start t_s as the daemon's intake takes it; the ranging the daemon's
    overload policy shed on a block, from its block note, shed again)."""
    from iscd.calibration.io import CalibrationError, load_calibration
    from iscd.core import config as C
    from iscd.decode.stream import StreamDecoder
    from iscd.outputs.jsonl import JsonlWriter
    from iscd.recording import RecordingError
    from iscd.recording.pairs import open_stereo

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            session = open_stereo(args.left)
        except RecordingError as e:
            raise UserError(str(e)) from None
    for w in caught:
        print(f"iscd replay: warning: {w.message}", file=sys.stderr)
    with session:
        if session.n_pairs == 0:
            raise UserError(f"{args.left}: the recording holds no whole pair")
        if args.config:
            cfg = C.load(args.config)
        else:
            text = session.config_text()
            if text is None:
                raise UserError(f"{args.left}: no config stored with the recording; give --config")
            cfg = C.loads(text, f"{args.left}: {'config.toml'}")
        cal_path = args.calibration or session.calibration_path()
        try:
            cal = load_calibration(cal_path) if cal_path else None
        except CalibrationError as e:
            raise UserError(str(e)) from None
        refuse, warn = config_mismatch(session, cfg.camera)
        if refuse and not args.allow_mismatch:
            raise UserError(f"{args.left}: the recording differs from the config: {'; '.join(refuse + warn)}; "
                            f"set [camera] to match the recording, or pass --allow-mismatch to decode anyway")
        for w in refuse + warn:
            print(f"iscd replay: warning: {args.left}: the recording differs from the config: {w}", file=sys.stderr)
        fps = float(cfg.camera.fps)
        dec = StreamDecoder(cfg, cal)
        counts: dict[str, int] = {}
        t0 = time.perf_counter()
        last = prev = None
        gaps = 0
        with JsonlWriter(args.out) as out:
            def emit(recs: list[dict]) -> None:
                for r in recs:
                    counts[r["type"]] = counts.get(r["type"], 0) + 1
                    out.write(r)

            for blk in session.iter_blocks():
                ids = blk.frame_ids
                # t_s as iscd.service.blocks.BlockReader takes it: the left timestamp, or id / fps
                t_s = np.array([t * 1e-9 if t else i / fps for i, t in zip(ids.tolist(), blk.ts_left_ns.tolist())])
                if prev is not None:
                    gaps += int(np.clip(np.diff(np.concatenate([[prev], ids])) - 1, 0, None).sum())
                prev = int(ids[-1])
                # what the live decoder shed on this block (overload), so that the ranges match too
                every, per_led = session.block_service(blk.block)
                emit(dec.push(ids, t_s, blk.left, blk.right, ranging_every=every, per_led=per_led))
                last = (int(ids[-1]), float(t_s[-1]))
            emit(dec.finish())
            wall = time.perf_counter() - t0
            n = session.n_pairs
            stats = StatsRecord(
                tx=0, frame=last[0], t_s=last[1], frames_in=2 * n, frames_dropped=gaps, pairs_decoded=n,
                packets_ok=dec.counters["packets_ok"], packets_bad=dec.counters["packets_bad"],
                latency_ms_p50=None, latency_ms_p99=None,
                extra={"wall_s": round(wall, 3), "pairs_per_s": round(n / wall, 1) if wall > 0 else None,
                       "recording_mode": session.mode,
                       **{k: v for k, v in dec.counters.items() if k not in ("packets_ok", "packets_bad")}}).to_json()
            out.write(stats)
    print(json.dumps({k: stats[k] for k in ("pairs_decoded", "packets_ok", "packets_bad", "ranges",
                                            "frames_dropped", "pairs_per_s")}), file=sys.stderr)
    return 0


def run(args: argparse.Namespace) -> int:
    if args.right is None and _is_stereo(Path(args.left)):
        if args.block < 2:
            raise UserError("--block must be >= 2")
        return run_stereo(args)
    from iscd.calibration.io import CalibrationError, load_calibration
    from iscd.core import config as C
    from iscd.outputs.jsonl import JsonlWriter
    from iscd.decode.stream import StreamDecoder
    from iscd.recording import RecordingError, open_recording
    from iscd.recording.base import match_frames

    lpath, rpath, cfg_path, cal_path = _resolve(args)
    if cfg_path is None:
        raise UserError("--config is required (the transmitter's rows, cols and levels must be known)")
    cfg = C.load(cfg_path)
    try:
        cal = load_calibration(cal_path) if cal_path else None  # fail early, before the recordings
    except CalibrationError as e:
        raise UserError(str(e)) from None
    if args.block < 2:
        raise UserError("--block must be >= 2")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            left = open_recording(lpath)
            right = open_recording(rpath)
        except RecordingError as e:
            raise UserError(str(e)) from None
    for w in caught:
        print(f"iscd replay: warning: {w.message}", file=sys.stderr)
    if (left.width, left.height) != (right.width, right.height):
        raise UserError(f"left is {left.width}x{left.height} px but right is {right.width}x{right.height} px")
    refuse, warn = config_mismatch(left, cfg.camera)
    if refuse and not args.allow_mismatch:
        raise UserError(f"{lpath}: the recording differs from the config: {'; '.join(refuse + warn)}; "
                        f"set [camera] to match the recording, or pass --allow-mismatch to decode anyway")
    for w in refuse + warn:
        print(f"iscd replay: warning: {lpath}: the recording differs from the config: {w}", file=sys.stderr)
    if cal is not None:
        from iscd.cli.commands.run import checked_calibration

        cal, _ = checked_calibration(cal_path, left.width, left.height, scale=args.scale_calibration,
                                     what="the recording's size")
    li, ri = match_frames(left.frame_ids, right.frame_ids)
    if li.size == 0:
        raise UserError(f"{lpath} and {rpath} share no frame ids: not a stereo pair")
    unpaired = (left.n_frames - li.size) + (right.n_frames - ri.size)
    fps = left.fps or cfg.camera.fps
    dec = StreamDecoder(cfg, cal)
    t0 = time.perf_counter()
    counts = {"packet": 0, "range": 0}
    progress = None
    if not args.no_progress and sys.stderr.isatty():
        from tqdm import tqdm

        progress = tqdm(total=int(li.size), unit="pair", desc="replay", file=sys.stderr)
    with JsonlWriter(args.out) as out:
        def emit(recs: list[dict]) -> None:
            for r in recs:
                counts[r["type"]] = counts.get(r["type"], 0) + 1
                out.write(r)

        for s in range(0, li.size, args.block):
            lsel, rsel = li[s:s + args.block], ri[s:s + args.block]
            contiguous = lsel[-1] - lsel[0] == len(lsel) - 1 and rsel[-1] - rsel[0] == len(rsel) - 1
            try:
                if contiguous:
                    L = left.read(int(lsel[0]), int(lsel[-1]) + 1)
                    R = right.read(int(rsel[0]), int(rsel[-1]) + 1)
                else:
                    L = np.stack([left[int(i)] for i in lsel])
                    R = np.stack([right[int(i)] for i in rsel])
            except RecordingError as e:  # a corrupt frame part-way (the records so far are kept)
                if progress is not None:
                    progress.close()
                raise UserError(str(e)) from None
            ids = left.frame_ids[lsel]
            ts = left.timestamps_ns[lsel]
            t_s = ts * 1e-9 if np.any(ts) else ids / fps
            emit(dec.push(ids, t_s, L, R))
            if progress is not None:
                progress.update(len(lsel))
        emit(dec.finish())
        wall = time.perf_counter() - t0
        stats = StatsRecord(
            tx=0, frame=int(left.frame_ids[li[-1]]), t_s=float(left.frame_ids[li[-1]] / fps),
            frames_in=int(left.n_frames + right.n_frames), frames_dropped=int(unpaired),
            pairs_decoded=int(li.size), packets_ok=dec.counters["packets_ok"],
            packets_bad=dec.counters["packets_bad"], latency_ms_p50=None, latency_ms_p99=None,
            extra={"wall_s": round(wall, 3), "pairs_per_s": round(li.size / wall, 1) if wall > 0 else None,
                   **{k: v for k, v in dec.counters.items() if k not in ("packets_ok", "packets_bad")}}).to_json()
        out.write(stats)
    if progress is not None:
        progress.close()
    print(json.dumps({k: stats[k] for k in ("pairs_decoded", "packets_ok", "packets_bad", "ranges",
                                            "frames_dropped", "pairs_per_s")}), file=sys.stderr)
    return 0
