"""``iscd simulate``: render a simulated stereo recording with ground truth."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

OUTPUTS = ("left.iscr", "right.iscr", "truth.npz", "truth.json", "config.toml", "calibration.yml")
EXTRA_TRUTH_GLOB = "truth_tx*.*"
"""The truths of further transmitters ([[scene.transmitters]]): truth_tx1.npz/json, ..."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate", help="render a simulated stereo recording (with ground truth) from a config",
        description=(
            "Renders what the two cameras would see of the configured LED transmitters "
            "(physics simulator, docs/simulator.md) and writes DIR/left.iscr and DIR/right.iscr "
            "(the project's recording format), DIR/truth.npz + DIR/truth.json (ground truth per "
            "frame and per symbol: distance, disparity, LED positions, on-times, levels, "
            "payloads) of the main transmitter ([transmitter] + [scene]), DIR/truth_tx1.npz + "
            "DIR/truth_tx1.json, truth_tx2.* ... the same for each further transmitter of "
            "[[scene.transmitters]] in config order (none without them), DIR/config.toml (the "
            "exact config used, to reproduce the run) and "
            "DIR/calibration.yml (the ideal stereo calibration of the rig). Replay it with "
            "'iscd replay DIR/left.iscr DIR/right.iscr --config DIR/config.toml --calibration "
            "DIR/calibration.yml'."))
    p.add_argument("--config", metavar="FILE",
                   help="TOML config (default: the embedded default, an 8x8 PWM-8 array at 30 m)")
    p.add_argument("--out", metavar="DIR", required=True,
                   help="output folder (created if missing)")
    n = p.add_mutually_exclusive_group()
    n.add_argument("--frames", type=int, metavar="N",
                   help="frames to render per camera (default: two whole packets)")
    n.add_argument("--duration", type=float, metavar="S",
                   help="seconds of recording to render (frames = S * camera.fps)")
    p.add_argument("--seed", type=int, metavar="S",
                   help="override scene.seed (noise, texture, LED phase, random payloads)")
    p.add_argument("--randomize", type=int, metavar="SEED",
                   help="draw the simulator's physics for SEED (vibration model, PSF, glare, "
                        "diffuser, blooming, defocus, noise, background, exposure, LED clock, "
                        "lateral motion; iscd.sim.randomize, docs/simulator.md) on top of the "
                        "config; the drawn values go to DIR/config.toml and truth.json "
                        "(meta.randomized)")
    p.add_argument("--no-noise", action="store_true",
                   help="render without sensor noise and PRNU (for debugging)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing recording in DIR")
    p.set_defaults(func=run)


def default_frames(cfg: object, scene: object, packets: int = 2) -> int:
    """Frames that cover ``packets`` whole packets after the LED phase offset."""
    from iscd.core.airinterface_v2 import from_config

    air = from_config(cfg.transmitter)  # type: ignore[attr-defined]
    clock = scene.clock  # type: ignore[attr-defined]
    t_end = float(clock.symbol_start_cam(packets * air.period_symbols))
    return int(math.ceil((t_end + cfg.camera.exposure_s) * cfg.camera.fps)) + 1  # type: ignore[attr-defined]


def run(args: argparse.Namespace) -> int:
    from iscd.core.errors import UserError
    from iscd.core.config import load
    from iscd.sim import Scene
    from iscd.sim.presets import override
    from iscd.sim.tomlout import config_to_toml

    cfg = load(args.config)
    if args.seed is not None:
        cfg = override(cfg, scene={"seed": args.seed})
    randomized_meta = None
    if args.randomize is not None:
        from iscd.sim.randomize import drawn, randomized

        cfg = randomized(cfg, args.randomize)
        randomized_meta = drawn(cfg)
    if args.frames is not None and args.frames < 1:
        raise UserError(f"--frames: expected a number of frames >= 1, got {args.frames}")
    if args.duration is not None and not (args.duration > 0 and math.isfinite(args.duration)):
        raise UserError(f"--duration: expected seconds > 0, got {args.duration}")
    if not args.out:
        raise UserError("--out: the path is empty; give a folder")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out: {out} exists and is not a folder")
    existing = [name for name in OUTPUTS if (out / name).exists()]
    if out.is_dir():
        existing += sorted(p.name for p in out.glob(EXTRA_TRUTH_GLOB)
                           if p.suffix in (".npz", ".json"))
    if existing and not args.overwrite:
        raise UserError(f"--out: {out} already holds a recording ({', '.join(existing)}); "
                        f"use --overwrite to replace it")
    try:
        scene = Scene(cfg, noise=not args.no_noise)
    except ValueError as e:
        raise UserError(str(e)) from None
    if args.frames is not None:
        n_frames = args.frames
    elif args.duration is not None:
        n_frames = max(1, int(round(args.duration * cfg.camera.fps)))
    else:
        n_frames = default_frames(cfg, scene)
    gb = 2 * n_frames * cfg.camera.width * cfg.camera.height / 1e9
    # checked before anything is created or replaced: a refusal leaves the folder as it was
    # (no empty folder, and an old recording that --overwrite would replace still there)
    free_gb = _free_gb(out)
    if free_gb is not None:
        free_gb += sum((out / name).stat().st_size for name in existing) / 1e9
    if free_gb is not None and gb > free_gb:
        raise UserError(f"--out: {n_frames} stereo frames need {gb:.2f} GB but {out} has {free_gb:.2f} GB "
                        f"free; render fewer frames (--frames, --duration)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"--out: cannot create {out}: {e.strerror or e}") from None
    for name in existing:
        (out / name).unlink()
    print(f"iscd simulate: {n_frames} stereo frames ({n_frames / cfg.camera.fps:.3f} s, "
          f"{gb:.2f} GB) -> {out}", file=sys.stderr)
    from iscd.recording import RecordingError

    try:
        write_recording(scene, out, n_frames,
                        extra_meta={"randomized": randomized_meta} if randomized_meta else None)
        (out / "config.toml").write_text(config_to_toml(
            cfg, f"Config of the simulated recording in this folder ({n_frames} frames).\n"
                 f"Reproduce: iscd simulate --config config.toml --out DIR --frames {n_frames}"))
        cal_note = _write_calibration(cfg, out / "calibration.yml")
    except RecordingError as e:
        raise UserError(str(e)) from None
    except OSError as e:
        raise UserError(f"--out: cannot write to {out}: {e.strerror or e}") from None
    extra = "".join(f", truth_tx{k}.npz/json" for k in range(1, scene.n_transmitters))
    print(f"iscd simulate: wrote left.iscr, right.iscr, truth.npz, truth.json{extra}, config.toml"
          f"{cal_note}", file=sys.stderr)
    return 0


def _free_gb(folder: Path) -> float | None:
    """Free space on the file system ``folder`` is (or would be made) on: that of its nearest
    existing ancestor, GB (None where it cannot be told)."""
    import shutil

    here = folder.absolute()
    while not here.exists() and here != here.parent:
        here = here.parent
    try:
        return shutil.disk_usage(here).free / 1e9
    except OSError:
        return None


def write_recording(scene: object, out: Path, n_frames: int, block: int = 32,
                    extra_meta: dict | None = None) -> None:
    """Render frames 0..n_frames-1 into out/left.iscr, out/right.iscr and save the truth:
    ``truth.npz``/``.json`` of the main transmitter, ``truth_tx{k}.npz``/``.json`` of further
    transmitter k = 1.. (``[[scene.transmitters]]`` in order); ``extra_meta``: added to each
    truth's meta, e.g. the randomized draw."""
    from tqdm import tqdm

    from iscd.core.config import to_dict
    from iscd.recording.iscr import IscrWriter

    s = scene  # iscd.sim.Scene
    cfg = s.cfg  # type: ignore[attr-defined]
    H, W = s.height, s.width  # type: ignore[attr-defined]
    meta = {"simulated": True, "truth": "truth.npz", "seed": cfg.scene.seed,
            "config": to_dict(cfg)}
    writers = []
    try:
        for cam in s.cams:  # type: ignore[attr-defined]
            writers.append(IscrWriter(
                out / f"{cam.name}.iscr", width=W, height=H, dtype="uint8", camera=cam.name,
                fps=s.fps, exposure_s=s.exposure_s, bit_depth=8,  # type: ignore[attr-defined]
                meta=meta, settings={"f_number": cam.f_number,
                                     "trigger": "master" if cam.idx == 0 else "slave"}))
        buf_l = np.empty((block, H, W), np.uint8)
        buf_r = np.empty((block, H, W), np.uint8)
        with tqdm(total=n_frames, unit="frame", desc="simulate", disable=None,
                  file=sys.stderr) as bar:
            for b0 in range(0, n_frames, block):
                m = min(block, n_frames - b0)
                for j in range(m):
                    s.render_pair_into(b0 + j, buf_l[j], buf_r[j])  # type: ignore[attr-defined]
                ids = np.arange(b0, b0 + m, dtype=np.int64)
                ts = np.round(ids * (1e9 / s.fps)).astype(np.int64)  # type: ignore[attr-defined]
                writers[0].append_many(ids, ts, buf_l[:m])
                writers[1].append_many(ids, ts, buf_r[:m])
                bar.update(m)
    finally:
        for w in writers:
            w.close()
    for k, truth in enumerate(s.truths(np.arange(n_frames))):  # type: ignore[attr-defined]
        truth.meta.update(extra_meta or {})
        truth.save(out, "truth" if k == 0 else f"truth_tx{k}")


def _write_calibration(cfg: object, path: Path) -> str:
    try:
        from iscd.calibration.io import StereoCalibration, save_calibration
    except ImportError:
        return " (no calibration: iscd.calibration.io is not available)"
    if not hasattr(StereoCalibration, "ideal"):
        return " (no calibration: StereoCalibration.ideal is not available)"
    save_calibration(StereoCalibration.ideal(cfg.camera), path)  # type: ignore[attr-defined]
    return ", calibration.yml"
