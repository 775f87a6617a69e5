"""Offline decode + ranging of a recorded stereo pair: the code of ``iscd replay`` and of a
campaign's recording tasks (:mod:`iscd.campaign`), so that both give the same records.

:func:`replay` opens the recording(s) where they lie, decodes them with the daemon's
:class:`~iscd.decode.stream.StreamDecoder` block by block and writes every packet, range
and the final stats record to a JSON Lines file (SPEC section 7). Three kinds of input:

- LEFT and RIGHT recordings (``.iscr``, Photron ``.cih/.cihx``, PNG/TIFF folders), paired
  by frame id, with a config (``[transmitter]``, ``[camera]``) and an optional calibration;
- a folder written by ``iscd simulate`` as LEFT alone (its ``config.toml`` and
  ``calibration.yml`` are used unless given);
- an ``iscd run --record`` run folder or file as LEFT alone: decoded in the live blocks,
  with its stored config and calibration, giving the live run's packet records.

Bad input raises :class:`~iscd.core.errors.UserError` with one line naming the problem.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from iscd.core.errors import UserError
from iscd.core.records import StatsRecord

Warn = Callable[[str], None]
"""Called with one line for each warning (a recording that differs from the config...)."""
Progress = Callable[[int, int], None]
"""Called with (pairs just decoded, pairs in the recording)."""
CalibrationLoader = Callable[[str, int, int], Any]
"""(path, width px, height px) -> the calibration for images of that size, or UserError."""

SUMMARY_KEYS = ("pairs_decoded", "packets_ok", "packets_bad", "ranges", "frames_dropped", "pairs_per_s")
"""The stats fields ``iscd replay`` prints on stderr when it ends."""


@dataclass(frozen=True)
class ReplayInputs:
    """What to replay and how.

    Attributes
    ----------
    left : Path
        Left recording, a simulate folder, or an ``iscd run --record`` run folder or file.
    right : Path or None
        Right recording (None for the folder forms).
    config : str or None
        TOML config (None: the one stored with the recording, where there is one).
    calibration : str or None
        Stereo calibration YAML (None: the stored one, else the ideal rig of ``[camera]``).
    allow_mismatch : bool
        Decode a recording whose size or frame rate differ from ``[camera]`` (a warning).
    block : int
        Pairs per decode step (>= 2).
    """

    left: Path
    right: Path | None = None
    config: str | None = None
    calibration: str | None = None
    allow_mismatch: bool = False
    block: int = 64


def resolve(inp: ReplayInputs) -> tuple[Path, Path, str | None, str | None]:
    """The files of a two-file or ``iscd simulate`` folder input.

    Parameters
    ----------
    inp : ReplayInputs
        The input.

    Returns
    -------
    tuple
        (left, right, config or None, calibration or None); a folder's own config and
        calibration unless given.
    """
    left = Path(inp.left)
    if inp.right is None:
        if not left.exists():
            raise UserError(f"{left}: no such file or folder")
        if not left.is_dir() or not (left / "left.iscr").exists():
            raise UserError(f"{left}: give LEFT and RIGHT recordings, or a folder made by 'iscd simulate'")
        cfg = inp.config or (str(left / "config.toml") if (left / "config.toml").exists() else None)
        cal = inp.calibration or (str(left / "calibration.yml") if (left / "calibration.yml").exists() else None)
        return left / "left.iscr", left / "right.iscr", cfg, cal
    return left, Path(inp.right), inp.config, inp.calibration


def config_mismatch(rec: object, camera: object) -> tuple[list[str], list[str]]:
    """What differs between a recording and the config's [camera].

    The size and the frame rate refuse: the decoder takes frames per symbol from
    camera.fps and the ideal rig from camera.width/height, so a recording that differs
    decodes nothing (or ranges wrongly) without a word. The bit depth only warns: the
    decoder works on the pixel values as they are (an unknown fps, e.g. a PNG folder
    without sidecar, is not compared).

    Parameters
    ----------
    rec : Recording
        Has width, height (px), fps (1/s) and bit_depth.
    camera : CameraConfig
        The config's [camera].

    Returns
    -------
    tuple of (list of str, list of str)
        (refuse, warn) phrases.
    """
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


def is_stereo(path: Path) -> bool:
    """Whether ``path`` is an ``iscd run --record`` recording.

    Parameters
    ----------
    path : Path
        A file or folder.

    Returns
    -------
    bool
        True for a version-2 .iscr file, or a folder holding some (and no simulate-style
        left.iscr).
    """
    from iscd.recording.pairs import is_pair_file

    if path.is_dir():
        return not (path / "left.iscr").exists() and any(is_pair_file(f) for f in path.glob("*.iscr"))
    return path.is_file() and is_pair_file(path)


def load_sized_calibration(path: str, width: int, height: int) -> Any:
    """The calibration at ``path``, refused unless it is for ``width`` x ``height`` images.

    Parameters
    ----------
    path : str
        Stereo calibration YAML.
    width, height : int
        The recording's image size, px.

    Returns
    -------
    StereoCalibration

    Raises
    ------
    UserError
        Naming the file and both sizes.
    """
    from iscd.calibration.io import CalibrationError, check_image_size, load_calibration

    try:
        cal = load_calibration(path)
        check_image_size(cal, width, height, path)
    except CalibrationError as e:
        msg = str(e)
        raise UserError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    return cal


def camera_mismatch(lpath: Path, rpath: Path, left: object, right: object) -> list[str]:
    """What says that LEFT and RIGHT are swapped: two recordings whose own metadata name the
    other camera each (``camera`` "right" for LEFT and "left" for RIGHT, as ``iscd simulate``
    writes them). One name alone is not trusted (the .iscr writer's default is "left"), other
    names (a Photron model) are not compared, and one recording given as both is allowed (a
    test of the decoder on one camera's frames).

    Parameters
    ----------
    lpath, rpath : Path
        The LEFT and RIGHT paths.
    left, right : Recording
        Opened; each has ``camera`` (str or None).

    Returns
    -------
    list of str
        Phrases, empty when nothing is wrong.
    """
    lcam, rcam = getattr(left, "camera", None), getattr(right, "camera", None)
    if (lcam, rcam) == ("right", "left"):
        return [f"LEFT {lpath} is the right camera's recording and RIGHT {rpath} the left one's (their "
                "metadata say so): swap LEFT and RIGHT"]
    return []


def _check_mismatch(rec: object, cfg: Any, where: object, allow: bool, warn: Warn) -> None:
    refuse, warned = config_mismatch(rec, cfg.camera)
    if refuse and not allow:
        raise UserError(f"{where}: the recording differs from the config: {'; '.join(refuse + warned)}; "
                        f"set [camera] to match the recording, or pass --allow-mismatch to decode anyway")
    for w in refuse + warned:
        warn(f"{where}: the recording differs from the config: {w}")


def _opened(opener: Callable[[], Any], warn: Warn) -> Any:
    """``opener()`` with its Python warnings handed to ``warn`` and a RecordingError as one line."""
    from iscd.recording import RecordingError

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            out = opener()
        except RecordingError as e:
            raise UserError(str(e)) from None
    for w in caught:
        warn(str(w.message))
    return out


def _decoder(make: Callable[[Any, Any], Any], cfg: Any, cal: Any) -> Any:
    """``make(cfg, cal)``; a bad ``[tracking]``/``[receiver]``/``[ranging]`` key, which the
    decoder reads, named with the config file it is in."""
    from iscd.core.config import ConfigError, named_error

    try:
        return make(cfg, cal)
    except ConfigError as e:
        raise named_error(cfg, e) from None


@dataclass(frozen=True)
class ReplayResult:
    """What :func:`replay` did: ``stats``, the stats record it wrote last; ``config``, the
    :class:`~iscd.core.config.Config` it decoded with."""

    stats: dict[str, Any]
    config: Any


def replay(inp: ReplayInputs, out: str | Path, *, warn: Warn | None = None, progress: Progress | None = None,
           calibration: CalibrationLoader | None = None, rotate_bytes: int = 256 * 2**20) -> ReplayResult:
    """Decode and range a recording into the JSON Lines file ``out``.

    Parameters
    ----------
    inp : ReplayInputs
        The recording and its config, calibration and block size.
    out : str or Path
        JSON Lines output (packet, range, ... records, then one stats record).
    warn : callable, optional
        Gets each warning as one line (default: dropped).
    progress : callable, optional
        ``progress(pairs, total)`` after each block (two-file and simulate inputs).
    calibration : callable, optional
        ``(path, width, height) -> calibration`` for a two-file input's calibration
        (default :func:`load_sized_calibration`; ``iscd replay`` passes one that scales).
    rotate_bytes : int
        Size at which the JSON Lines file is rotated, bytes.

    Returns
    -------
    ReplayResult
        The stats record written last (``wall_s``: decoding time, s) and the config used.
    """
    warn = warn or (lambda _msg: None)
    if inp.block < 2:
        raise UserError("--block must be >= 2")
    if inp.right is None and is_stereo(Path(inp.left)):
        return _replay_stereo(inp, out, warn, rotate_bytes)
    return _replay_pair(inp, out, warn, progress, calibration or load_sized_calibration, rotate_bytes)


def _replay_stereo(inp: ReplayInputs, out: str | Path, warn: Warn, rotate_bytes: int) -> ReplayResult:
    """Replay of an ``iscd run --record`` recording: block by block as the live daemon
    decoded it (pairs rebuilt with the recorded windows at their positions, zeros
    elsewhere; exposure start t_s as the daemon's intake takes it; the ranging the daemon's
    overload policy shed on a block, from its block note, shed again)."""
    from iscd.calibration.io import CalibrationError, load_calibration
    from iscd.core import config as C
    from iscd.decode.multi import make_decoder
    from iscd.outputs.jsonl import JsonlWriter
    from iscd.recording.pairs import open_stereo

    session = _opened(lambda: open_stereo(inp.left), warn)
    with session:
        if session.n_pairs == 0:
            raise UserError(f"{inp.left}: the recording holds no whole pair")
        if inp.config:  # the receiver's own config (no [transmitter]: the shape is inferred)
            cfg = C.load(inp.config, receiver=True)
        else:
            text = session.config_text()
            if text is None:
                raise UserError(f"{inp.left}: no config stored with the recording; give --config")
            cfg = C.loads(text, f"{inp.left}: {'config.toml'}")
        cal_path = inp.calibration or session.calibration_path()
        try:
            cal = load_calibration(cal_path) if cal_path else None
        except CalibrationError as e:
            raise UserError(str(e)) from None
        _check_mismatch(session, cfg, inp.left, inp.allow_mismatch, warn)
        fps = float(cfg.camera.fps)
        dec = _decoder(make_decoder, cfg, cal)
        t0 = time.perf_counter()
        last = prev = None
        gaps = 0
        with JsonlWriter(out, rotate_bytes=rotate_bytes) as sink:
            def emit(recs: list[dict]) -> None:
                for r in recs:
                    sink.write(r)

            for blk in session.iter_blocks():
                ids = blk.frame_ids
                # t_s as iscd.service.blocks.BlockReader takes it: the left timestamp, or id / fps
                t_s = np.array([t * 1e-9 if t else i / fps for i, t in zip(ids.tolist(), blk.ts_left_ns.tolist())])
                if prev is not None:
                    gaps += int(np.clip(np.diff(np.concatenate([[prev], ids])) - 1, 0, None).sum())
                prev = int(ids[-1])
                # what the live decoder shed on this block (overload), so that the ranges match too
                every, per_led = session.block_service(blk.block)
                ahead = session.block_ahead(blk.block)  # its first pairs ranged apart, as live
                if 0 < ahead < len(ids):
                    emit(dec.range_ahead(ids[:ahead], t_s[:ahead], blk.left[:ahead], blk.right[:ahead],
                                         ranging_every=every, per_led=per_led))
                emit(dec.push(ids, t_s, blk.left, blk.right, ranging_every=every, per_led=per_led))
                last = (int(ids[-1]), float(t_s[-1]))
            emit(dec.finish())
            wall = time.perf_counter() - t0
            n = session.n_pairs
            stats = _stats(dec, frame=last[0], t_s=last[1], frames_in=2 * n, dropped=gaps, pairs=n, wall=wall,
                           mode={"recording_mode": session.mode})
            sink.write(stats)
    return ReplayResult(stats, cfg)


def _stats(dec: Any, *, frame: int, t_s: float, frames_in: int, dropped: int, pairs: int, wall: float,
           mode: dict[str, Any] | None = None) -> dict[str, Any]:
    """The final stats record of a replay (``wall_s``, s; ``pairs_per_s``, 1/s)."""
    return StatsRecord(
        tx=0, frame=frame, t_s=t_s, frames_in=frames_in, frames_dropped=dropped, pairs_decoded=pairs,
        packets_ok=dec.counters["packets_ok"], packets_bad=dec.counters["packets_bad"],
        latency_ms_p50=None, latency_ms_p99=None,
        extra={"wall_s": round(wall, 3), "pairs_per_s": round(pairs / wall, 1) if wall > 0 else None,
               **(mode or {}),
               **{k: v for k, v in dec.counters.items() if k not in ("packets_ok", "packets_bad")},
               **({"transmitters": dec.transmitters()} if hasattr(dec, "transmitters") else {})}).to_json()


def _replay_pair(inp: ReplayInputs, out: str | Path, warn: Warn, progress: Progress | None,
                 calibration: CalibrationLoader, rotate_bytes: int) -> ReplayResult:
    from iscd.calibration.io import CalibrationError, load_calibration
    from iscd.core import config as C
    from iscd.decode.multi import make_decoder
    from iscd.outputs.jsonl import JsonlWriter
    from iscd.recording import RecordingError, open_recording
    from iscd.recording.base import match_frames

    lpath, rpath, cfg_path, cal_path = resolve(inp)
    if cfg_path is None:
        raise UserError("--config is required (the cameras' fps and exposure must be known; without a "
                        "[transmitter] table the receiver infers the array's shape)")
    cfg = C.load(cfg_path, receiver=True)
    try:
        if cal_path:
            load_calibration(cal_path)  # fail early, before the recordings
    except CalibrationError as e:
        raise UserError(str(e)) from None
    left, right = _opened(lambda: (open_recording(lpath), open_recording(rpath)), warn)
    if (left.width, left.height) != (right.width, right.height):
        raise UserError(f"left is {left.width}x{left.height} px but right is {right.width}x{right.height} px")
    for problem in camera_mismatch(lpath, rpath, left, right):
        if not inp.allow_mismatch:
            raise UserError(f"{problem} (--allow-mismatch decodes anyway)")
        warn(problem)
    _check_mismatch(left, cfg, lpath, inp.allow_mismatch, warn)
    cal = calibration(cal_path, left.width, left.height) if cal_path else None
    li, ri = match_frames(left.frame_ids, right.frame_ids)
    if li.size == 0:
        raise UserError(f"{lpath} and {rpath} share no frame ids: not a stereo pair")
    unpaired = (left.n_frames - li.size) + (right.n_frames - ri.size)
    fps = left.fps or cfg.camera.fps
    dec = _decoder(make_decoder, cfg, cal)
    t0 = time.perf_counter()
    block = inp.block
    with JsonlWriter(out, rotate_bytes=rotate_bytes) as sink:
        def emit(recs: list[dict]) -> None:
            for r in recs:
                sink.write(r)

        for s in range(0, li.size, block):
            lsel, rsel = li[s:s + block], ri[s:s + block]
            contiguous = lsel[-1] - lsel[0] == len(lsel) - 1 and rsel[-1] - rsel[0] == len(rsel) - 1
            try:
                if contiguous:
                    L = left.read(int(lsel[0]), int(lsel[-1]) + 1)
                    R = right.read(int(rsel[0]), int(rsel[-1]) + 1)
                else:
                    L = np.stack([left[int(i)] for i in lsel])
                    R = np.stack([right[int(i)] for i in rsel])
            except RecordingError as e:  # a corrupt frame part-way (the records so far are kept)
                raise UserError(str(e)) from None
            ids = left.frame_ids[lsel]
            ts = left.timestamps_ns[lsel]
            t_s = ts * 1e-9 if np.any(ts) else ids / fps
            emit(dec.push(ids, t_s, L, R))
            if progress is not None:
                progress(len(lsel), int(li.size))
        emit(dec.finish())
        wall = time.perf_counter() - t0
        stats = _stats(dec, frame=int(left.frame_ids[li[-1]]), t_s=float(left.frame_ids[li[-1]] / fps),
                       frames_in=int(left.n_frames + right.n_frames), dropped=int(unpaired), pairs=int(li.size),
                       wall=wall)
        sink.write(stats)
    return ReplayResult(stats, cfg)


def score_against_truth(packets: list[dict[str, Any]], truth_dir: str | Path, cfg: Any) -> Any:
    """Score a replay's packet records against the simulator's truth, as ``iscd eval`` does.

    Parameters
    ----------
    packets : list of dict
        The replay's ``packet`` records.
    truth_dir : str or Path
        Folder with ``truth.npz`` and ``truth.json`` (:class:`iscd.sim.truth.Truth`).
    cfg : Config
        The config the recording was decoded with (its ``[transmitter]``).

    Returns
    -------
    tuple of (CommsResult, Truth)
        The scores over the recording's whole packets (``packets_sent``; found, exact,
        symbol and bit errors: :class:`iscd.eval.sweeps.CommsResult`), and the truth
        (for the range errors).
    """
    from iscd.core.airinterface import AirInterface
    from iscd.eval.oracle import whole_packets
    from iscd.eval.sweeps import CommsResult, ReceiverMode, _score
    from iscd.sim.truth import Truth

    try:
        truth = Truth.load(truth_dir)
    except (OSError, KeyError, ValueError) as e:
        raise UserError(f"{truth_dir}: cannot read the truth (truth.npz, truth.json): {e}") from None
    tx = cfg.transmitter
    if tx.shape_auto:  # the receiver inferred the shape; the truth knows it
        if not truth.meta.get("rows") or not truth.meta.get("cols"):
            raise UserError(f"{truth_dir}: the truth does not say the array's rows and cols "
                            "(the replay's config has none)")
        tx = dataclasses.replace(tx, rows=int(truth.meta["rows"]), cols=int(truth.meta["cols"]), air_interface="v1")
    air = AirInterface.from_config(tx)
    n = whole_packets(truth, air.packet_symbols, cfg.camera.fps, cfg.camera.exposure_s)
    res = CommsResult(mode=ReceiverMode("replay"), levels=tx.levels, n_leds=tx.n_leds,
                      data_symbols=tx.data_symbols, packet_s=air.period_symbols / tx.symbol_rate_hz,
                      payload_bytes=air.payload_bytes, packets_sent=n)
    _score(res, packets, truth, air, n, 0.5 / tx.symbol_rate_hz)
    return res, truth
