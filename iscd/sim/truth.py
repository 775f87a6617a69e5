"""Ground truth of a simulated recording: what every frame saw and what was sent.

Per frame (index ``f`` into ``frames``):
  ``t_s`` exposure start (camera clock, s), ``z_m`` distance at mid-exposure (m),
  ``disparity_px`` = f_px b / Z (px, geometric, without vibration/jitter),
  ``u_left, v_left, u_right, v_right`` (F, N) LED centres in px (with vibration and
  jitter: these are where the spots are drawn), ``shift_left/right`` (F, 2) image shift
  (dx, dy) px, ``on_fraction`` (F, N) integrated on-time / exposure (0..1),
  ``symbol_mid`` (F,) LED symbol index at mid-exposure, ``clean`` (F,) True when the
  exposure lies inside one symbol, ``present`` (F,) True when the transmitter is in view
  during (part of) the exposure (``[[scene.transmitters]]`` ``start_s``/``stop_s``; always
  True for the main transmitter).
Symbol schedule: ``symbol_index`` (S,), ``symbol_t_s`` (S,) start of each symbol (camera
clock, s), ``levels`` (S, N) transmitted levels 1..M.
Packets overlapping the frames: ``packet_index`` (P,), ``packet_start_symbol`` (P,),
``packet_t_s`` (P,), ``payloads`` (list of bytes).
``meta``: scalars (focal_px, baseline_m, fps, exposure_s, levels, n_leds, symbol_rate_hz,
pwm_hz, led_phase_s, led_drift_ppm, seed, payload_bytes, ...), distractor positions, and
``config`` (the whole config as a dict).

``save(dir)`` writes ``truth.npz`` (arrays) + ``truth.json`` (meta, payloads as hex);
``save(dir, name="truth_tx1")`` writes ``truth_tx1.npz`` + ``truth_tx1.json`` (the truth of a
further transmitter, :meth:`iscd.sim.Scene.truths`, as ``iscd simulate`` names them).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

_ARRAYS = ("frames", "t_s", "z_m", "disparity_px", "u_left", "v_left", "u_right", "v_right",
           "shift_left", "shift_right", "on_fraction", "symbol_mid", "clean", "symbol_index",
           "symbol_t_s", "levels", "packet_index", "packet_start_symbol", "packet_t_s")


@dataclass
class Truth:
    frames: np.ndarray
    t_s: np.ndarray
    z_m: np.ndarray
    disparity_px: np.ndarray
    u_left: np.ndarray
    v_left: np.ndarray
    u_right: np.ndarray
    v_right: np.ndarray
    shift_left: np.ndarray
    shift_right: np.ndarray
    on_fraction: np.ndarray
    symbol_mid: np.ndarray
    clean: np.ndarray
    symbol_index: np.ndarray
    symbol_t_s: np.ndarray
    levels: np.ndarray
    packet_index: np.ndarray
    packet_start_symbol: np.ndarray
    packet_t_s: np.ndarray
    payloads: list[bytes] = field(default_factory=list)
    meta: dict[str, Any] = field(default_factory=dict)
    present: np.ndarray | None = None  # (F,) bool; None: all True (filled in)

    def __post_init__(self) -> None:
        if self.present is None:
            self.present = np.ones(np.shape(self.frames), bool)

    def __len__(self) -> int:
        return int(self.frames.size)

    def row(self, frame: int) -> int:
        """Index into the per-frame arrays of frame number ``frame`` (KeyError if absent).

        Parameters
        ----------
        frame : int
            Frame index.

        Returns
        -------
        int
        """
        i = np.searchsorted(self.frames, frame)
        if i >= self.frames.size or self.frames[i] != frame:
            raise KeyError(f"frame {frame} is not in this truth")
        return int(i)

    def levels_of(self, k0: int, k1: int) -> np.ndarray:
        """(k1 - k0, N) levels of symbols k0..k1-1 (must lie in ``symbol_index``).

        Parameters
        ----------
        k0, k1 : int
            Symbol index range, k1 exclusive.

        Returns
        -------
        ndarray
            (k1 - k0, N) levels 1..M (a view of ``levels``).
        """
        i0 = int(k0 - self.symbol_index[0])
        if i0 < 0 or k1 - self.symbol_index[0] > self.symbol_index.size:
            raise KeyError(f"symbols {k0}..{k1} are outside this truth")
        return self.levels[i0:i0 + (k1 - k0)]

    def save(self, directory: str | Path, name: str = "truth") -> None:
        """Write ``NAME.npz`` (arrays) and ``NAME.json`` (meta, payloads as hex).

        Parameters
        ----------
        directory : str or Path
            Output directory (created if missing).
        name : str
            File stem: ``truth`` (the main transmitter), ``truth_tx1``, ... (further ones).
        """
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(d / f"{name}.npz", **{k: getattr(self, k) for k in _ARRAYS},
                            present=self.present)
        doc = {"meta": self.meta, "payloads_hex": [p.hex() for p in self.payloads]}
        (d / f"{name}.json").write_text(json.dumps(doc, indent=1, default=_json_default) + "\n")

    @classmethod
    def load(cls, directory: str | Path, name: str = "truth") -> "Truth":
        """Read a truth written by :meth:`save` (one without ``present``: all True).

        Parameters
        ----------
        directory : str or Path
            The directory holding ``NAME.npz`` and ``NAME.json``.
        name : str
            File stem (``truth``, ``truth_tx1``, ...).

        Returns
        -------
        Truth
        """
        d = Path(directory)
        with np.load(d / f"{name}.npz") as z:
            arrays = {k: z[k] for k in _ARRAYS}
            present = z["present"] if "present" in z.files else None
        doc = json.loads((d / f"{name}.json").read_text())
        return cls(**arrays, payloads=[bytes.fromhex(h) for h in doc["payloads_hex"]],
                   meta=doc["meta"], present=present)

    def __eq__(self, other: object) -> bool:  # arrays compare by value
        if not isinstance(other, Truth):
            return NotImplemented
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray):
                if not np.array_equal(a, b):
                    return False
            elif a != b:
                return False
        return True


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (bytes, bytearray)):
        return o.hex()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")
