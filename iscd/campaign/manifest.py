"""The campaign manifest: which recordings (or simulated points) to decode, read from TOML
or CSV and checked before anything runs.

TOML (paths relative to the manifest's folder)::

    [defaults]                      # optional
    config = "rig.toml"             # two-file recordings: TOML config ([transmitter], [camera], ...)
    calibration = "rig.yml"         # two-file recordings: stereo calibration
    block = 64                      # every entry: pairs per decode step

    [[recording]]                   # two recordings + config (+ calibration, truth)
    name = "day1-030m"              # optional: default from the left path
    left = "day1/030m/left.iscr"
    right = "day1/030m/right.iscr"
    truth = "day1/030m"             # optional: folder with truth.npz + truth.json

    [[recording]]                   # a folder written by 'iscd simulate' (its config,
    left = "sim/p01"                # calibration and truth are used) or 'iscd run --record'

    [[simulate]]                    # a simulated point: rendered, then replayed, on a worker
    name = "hdr-40m"
    config = "hdr40.toml"
    frames = 2000                   # default: two whole packets
    seed = 7                        # optional scene.seed
    randomize = 3                   # optional: iscd simulate --randomize SEED

CSV: a header row naming columns from :data:`CSV_COLUMNS` (``kind`` is ``recording``,
the default, or ``simulate``); an empty cell leaves a key unset; rows whose first cell
starts with ``#`` are comments. Every problem (a missing file, an unknown key, a bad value,
a missing recording path) is a :class:`ManifestError`: one line naming the file, the
entry and the key.
"""

from __future__ import annotations

import csv
import re
import tomllib
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from iscd.core.errors import UserError

KINDS = ("recording", "simulate")


class ManifestError(UserError):
    """A manifest that cannot be run: one line naming the file, the entry and the key."""


@dataclass(frozen=True)
class TaskSpec:
    """One task of a campaign.

    Attributes
    ----------
    name : str
        Unique, file-name safe: the task's outputs are ``tasks/NAME.jsonl`` and ``.json``.
    kind : str
        ``recording`` (replay files that exist) or ``simulate`` (render, then replay).
    left, right : str or None
        Recording paths (absolute); ``right`` None for a simulate or run folder as ``left``.
    config, calibration : str or None
        TOML config and calibration YAML (absolute; None: stored with the recording, or
        the embedded default config / the ideal rig).
    truth : str or None
        Folder with ``truth.npz`` + ``truth.json`` (a simulate folder's own by default).
    block : int
        Pairs per decode step.
    allow_mismatch : bool
        Decode a recording whose size or frame rate differ from ``[camera]``.
    frames, seed, randomize : int or None
        Simulated points: frames to render (None: two whole packets), ``scene.seed``,
        the ``iscd simulate --randomize`` seed.
    noise : bool
        Simulated points: render with sensor noise.
    keep : bool
        Simulated points: keep the rendered recording in ``tasks/NAME.rec/``.
    """

    name: str
    kind: str = "recording"
    left: str | None = None
    right: str | None = None
    config: str | None = None
    calibration: str | None = None
    truth: str | None = None
    block: int = 64
    allow_mismatch: bool = False
    frames: int | None = None
    seed: int | None = None
    randomize: int | None = None
    noise: bool = True
    keep: bool = False

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def params(self) -> dict[str, Any]:
        """The parameters that shape the output (not paths: a moved recording with the
        same content is the same task)."""
        return {k: v for k, v in asdict(self).items()
                if k not in ("name", "left", "right", "config", "calibration", "truth", "keep")}

    def inputs(self) -> dict[str, Path]:
        """{role: file} of every input file: a folder's files each (``left/left.iscr``), a
        Photron ``.cih``/``.cihx`` with its ``.mraw``, a truth folder's truth.npz + truth.json."""
        out: dict[str, Path] = {}
        for role in ("left", "right", "config", "calibration"):
            p = getattr(self, role)
            if p is None:
                continue
            p = Path(p)
            if p.is_dir():
                for f in sorted(q for q in p.rglob("*") if q.is_file()):
                    out[f"{role}/{f.relative_to(p).as_posix()}"] = f
            else:
                out[role] = p
                if p.suffix.lower() in (".cih", ".cihx") and p.with_suffix(".mraw").exists():
                    out[f"{role}.mraw"] = p.with_suffix(".mraw")
        if self.truth is not None:
            for n in ("truth.npz", "truth.json"):
                out[f"truth/{n}"] = Path(self.truth) / n
        return out


_TYPES: dict[str, type] = {f.name: f.type for f in fields(TaskSpec)}  # type: ignore[misc]
RECORDING_KEYS = ("name", "left", "right", "config", "calibration", "truth", "block", "allow_mismatch")
SIMULATE_KEYS = ("name", "config", "frames", "seed", "randomize", "noise", "keep", "block")
DEFAULT_KEYS = ("config", "calibration", "block", "allow_mismatch")
CSV_COLUMNS = ("kind",) + tuple(dict.fromkeys(RECORDING_KEYS + SIMULATE_KEYS))
PATH_KEYS = ("left", "right", "config", "calibration", "truth")
INT_KEYS = {"block": 2, "frames": 1, "seed": 0, "randomize": 0}
"""integer keys and their least value"""
BOOL_KEYS = ("allow_mismatch", "noise", "keep")
_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def load_manifest(path: str | Path) -> list[TaskSpec]:
    """The tasks of a TOML (``.toml``) or CSV (``.csv``) manifest, checked.

    Parameters
    ----------
    path : str or Path
        The manifest; relative paths in it are relative to its folder.

    Returns
    -------
    list of TaskSpec
        In manifest order (the summary's row order).

    Raises
    ------
    ManifestError
        One line naming the problem.
    """
    p = Path(path)
    if p.is_dir():
        raise ManifestError(f"{p}: is a folder, not a manifest file (a .toml or .csv file)")
    if not p.is_file():
        raise ManifestError(f"{p}: no such manifest file")
    suffix = p.suffix.lower()
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ManifestError(f"{p}: cannot read the manifest: {e}") from None
    if suffix == ".toml":
        entries = _toml_entries(p, text)
    elif suffix == ".csv":
        entries = _csv_entries(p, text)
    else:
        raise ManifestError(f"{p}: a manifest is a .toml or .csv file")
    if not entries:
        raise ManifestError(f"{p}: no [[recording]] or [[simulate]] entry: nothing to run")
    specs = [_spec(p, where, kind, raw) for where, kind, raw in entries]
    seen: dict[str, str] = {}
    for (where, _, _), s in zip(entries, specs):
        if s.name in seen:
            raise ManifestError(f"{p}: {where}: name {s.name!r} is used twice (also by {seen[s.name]}); "
                                f"give each entry its own name")
        seen[s.name] = where
    return specs


def _toml_entries(p: Path, text: str) -> list[tuple[str, str, dict[str, Any]]]:
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ManifestError(f"{p}: not valid TOML: {e}") from None
    unknown = [k for k in doc if k not in ("defaults",) + KINDS]
    if unknown:
        raise ManifestError(f"{p}: unknown table {unknown[0]!r} (known: defaults, recording, simulate)")
    defaults = doc.get("defaults", {})
    if not isinstance(defaults, dict):
        raise ManifestError(f"{p}: [defaults] must be a table")
    _check_keys(p, "[defaults]", defaults, DEFAULT_KEYS)
    out = []
    for kind in KINDS:
        items = doc.get(kind, [])
        if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
            raise ManifestError(f"{p}: '{kind}' must be an array of tables ([[{kind}]])")
        for i, raw in enumerate(items, 1):
            where = f"[[{kind}]] {i}"
            _check_keys(p, where, raw, RECORDING_KEYS if kind == "recording" else SIMULATE_KEYS)
            out.append((where, kind, {**_defaults_for(kind, raw, defaults), **raw}))
    return out


def _defaults_for(kind: str, raw: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    """The [defaults] an entry takes: block for every entry, allow_mismatch for recordings,
    config and calibration only for two-file recordings (a folder brings its own)."""
    keys = {"block"} | ({"allow_mismatch"} if kind == "recording" else set())
    if kind == "recording" and "right" in raw:
        keys |= {"config", "calibration"}
    return {k: v for k, v in defaults.items() if k in keys}


def _csv_entries(p: Path, text: str) -> list[tuple[str, str, dict[str, Any]]]:
    rows = [r for r in csv.reader(text.splitlines()) if r and any(c.strip() for c in r)
            and not r[0].lstrip().startswith("#")]
    if not rows:
        raise ManifestError(f"{p}: empty CSV manifest (a header row is needed: {', '.join(CSV_COLUMNS)})")
    header = [h.strip() for h in rows[0]]
    bad = [h for h in header if h not in CSV_COLUMNS]
    if bad:
        raise ManifestError(f"{p}: unknown column {bad[0]!r} (known: {', '.join(CSV_COLUMNS)})")
    if len(set(header)) != len(header):
        raise ManifestError(f"{p}: a column is named twice in the header")
    out = []
    for n, row in enumerate(rows[1:], 2):
        where = f"row {n}"
        if len(row) > len(header):
            raise ManifestError(f"{p}: {where}: {len(row)} cells but {len(header)} columns")
        raw = {h: c.strip() for h, c in zip(header, row) if c.strip() != ""}
        kind = raw.pop("kind", "recording")
        if kind not in KINDS:
            raise ManifestError(f"{p}: {where}: kind {kind!r} is not one of {', '.join(KINDS)}")
        _check_keys(p, where, raw, RECORDING_KEYS if kind == "recording" else SIMULATE_KEYS)
        out.append((where, kind, {k: _csv_value(p, where, k, v) for k, v in raw.items()}))
    return out


def _csv_value(p: Path, where: str, key: str, v: str) -> Any:
    if key in INT_KEYS:
        try:
            return int(v)
        except ValueError:
            raise ManifestError(f"{p}: {where}: {key}: expected an integer, got {v!r}") from None
    if key in BOOL_KEYS:
        t = v.lower()
        if t not in ("true", "false", "1", "0", "yes", "no"):
            raise ManifestError(f"{p}: {where}: {key}: expected true or false, got {v!r}")
        return t in ("true", "1", "yes")
    return v


def _check_keys(p: Path, where: str, raw: dict[str, Any], known: tuple[str, ...]) -> None:
    for k in raw:
        if k not in known:
            raise ManifestError(f"{p}: {where}: unknown key {k!r} (known: {', '.join(known)})")


def _spec(p: Path, where: str, kind: str, raw: dict[str, Any]) -> TaskSpec:
    vals: dict[str, Any] = {"kind": kind}
    for k, v in raw.items():
        if k in PATH_KEYS or k == "name":
            if not isinstance(v, str) or not v:
                raise ManifestError(f"{p}: {where}: {k}: expected a non-empty string, got {v!r}")
            vals[k] = str((p.parent / v).resolve()) if k in PATH_KEYS else v
        elif k in INT_KEYS:
            if not isinstance(v, int) or isinstance(v, bool) or v < INT_KEYS[k]:
                raise ManifestError(f"{p}: {where}: {k}: expected an integer >= {INT_KEYS[k]}, got {v!r}")
            vals[k] = v
        elif k in BOOL_KEYS:
            if not isinstance(v, bool):
                raise ManifestError(f"{p}: {where}: {k}: expected true or false, got {v!r}")
            vals[k] = v
    if kind == "recording":
        if "left" not in vals:
            raise ManifestError(f"{p}: {where}: 'left' is missing (a recording, or a folder of 'iscd simulate' "
                                f"or 'iscd run --record')")
        left = Path(vals["left"])
        if "right" not in vals and left.is_dir() and (left / "truth.npz").exists() and "truth" not in vals:
            vals["truth"] = str(left)  # a simulate folder's own truth
    for k in PATH_KEYS:
        if k in vals and not Path(vals[k]).exists():
            raise ManifestError(f"{p}: {where}: {k}: {vals[k]}: no such file or folder")
    if "truth" in vals:
        for n in ("truth.npz", "truth.json"):
            if not (Path(vals["truth"]) / n).is_file():
                raise ManifestError(f"{p}: {where}: truth: {vals['truth']} holds no {n}")
    name = vals.get("name") or _default_name(vals)
    safe = _SAFE.sub("_", name).strip("._") or "task"
    vals["name"] = safe
    return TaskSpec(**vals)


def _default_name(vals: dict[str, Any]) -> str:
    if vals["kind"] == "simulate":
        base = Path(vals["config"]).stem if "config" in vals else "default"
        return f"{base}-seed{vals['seed']}" if "seed" in vals else base
    left = Path(vals["left"])
    return left.name if left.is_dir() else left.stem
