"""The daemon's recording of its stereo pairs (``[record]``, ``iscd run --record DIR``):
:class:`~iscd.recording.recorder.Recorder` fed by the intake, one folder per run with the
config and calibration in force beside the files, and the blackbox triggers (a packet that
fails its CRC, the transmitter lost, SIGUSR1).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from iscd.core.config import Config, section
from iscd.recording.pairs import CALIBRATION_NAME, CONFIG_NAME
from iscd.recording.recorder import Recorder, RecordSettings

log = logging.getLogger(__name__)


def run_folder(root: str | Path) -> Path:
    """A new folder for this run's files under ``root``: ``run-YYYYmmdd-HHMMSS`` (UTC),
    ``-2``, ``-3``... when it exists (a restarted service never writes over a recording)."""
    base = Path(root) / time.strftime("run-%Y%m%d-%H%M%S", time.gmtime())
    p, k = base, 1
    while p.exists():
        k += 1
        p = base.with_name(f"{base.name}-{k}")
    return p


class LiveRecording:
    """The recorder as the daemon sees it: the intake's tap (:meth:`pair`), the records
    (:meth:`observe`: a failed packet triggers the blackbox), the stats (:meth:`counters`).

    Parameters
    ----------
    recorder : the recorder
    losses : how many times the decoder has lost its transmitter so far (a rise triggers)
    """

    def __init__(self, recorder: Recorder, losses: Callable[[], int]) -> None:
        self.recorder = recorder
        self.settings = recorder.settings
        self._losses = losses
        self._seen_losses = 0
        self._block = -1

    @property
    def folder(self) -> Path:
        """The run's folder."""
        return self.recorder.folder

    def pair(self, slot: Any, windows: Any, block: int) -> None:
        """The intake's tap (:class:`iscd.service.blocks.BlockReader`): one pair of block ``block``."""
        if block != self._block:
            self._block = block
            if self.settings.trigger_lost:
                n = self._losses()
                if n > self._seen_losses:
                    self.recorder.trigger("transmitter lost")
                self._seen_losses = n
        self.recorder.pair(slot, windows, block)

    def observe(self, records: list[dict[str, Any]]) -> None:
        """The records the daemon emits: a packet that failed its CRC triggers the blackbox."""
        if self.settings.trigger_bad_packet:
            for r in records:
                if r.get("type") == "packet" and not r.get("crc_ok", True):
                    self.recorder.trigger("bad packet")

    def note_block(self, block: int, ranging_every: int, per_led: bool, ahead: int = 0) -> None:
        """What the overload policy let the decoder do on ``block`` and how many of its first
        pairs were ranged ahead; stored (a block note) only when it shed something or ranged
        ahead, so that a replay does the same."""
        if ranging_every != 1 or not per_led or ahead:
            self.recorder.note_block(block, ranging_every, per_led, ahead)

    def trigger(self, reason: str) -> None:
        """Trigger the blackbox (other modes: nothing); safe from a signal handler."""
        self.recorder.trigger(reason)

    def on_signal(self, signum: int, _frame: object = None) -> None:
        """SIGUSR1's handler: a blackbox trigger."""
        if self.recorder.mode == "blackbox":
            self.recorder.trigger("SIGUSR1")
        else:
            log.info("SIGUSR1: the recording is in %s mode, not blackbox; nothing to trigger", self.recorder.mode)

    def drain(self) -> None:
        """At the end of a run: write what is queued (at most ``[record] drain_s``)."""
        self.recorder.drain(self.settings.drain_s)

    def counters(self) -> dict[str, int | float]:
        """The recorder's stats fields (``record_*``)."""
        return self.recorder.counters()

    def close(self) -> None:
        """Seal the last file (idempotent)."""
        self.recorder.close()


def live_recording(cfg: Config, calibration_path: str | None, losses: Callable[[], int],
                   intake_buffers: int) -> LiveRecording | None:
    """The run's recording per ``[record]`` (None when ``dir`` is empty): a new run folder
    under ``dir`` holding ``config.toml`` (the config in force) and ``calibration.yml`` (a
    copy of the calibration file, if one is used), both also stored in every file's
    metadata (each file replays alone).

    Parameters
    ----------
    cfg : the daemon's config
    calibration_path : the calibration file the decoder uses (None: the ideal rig)
    losses : the decoder's count of lost transmitters so far
    intake_buffers : the block buffers the intake reuses (``[daemon] block_max``), stored
        so that a replay rebuilds the very arrays the decoder was handed
    """
    st = section(cfg, RecordSettings)
    if not st.dir:
        return None
    from iscd.sim.tomlout import config_to_toml

    folder = run_folder(st.dir)
    config_text = config_to_toml(cfg, header="the config in force when this recording was made (iscd run --record)")
    cal_text = Path(calibration_path).read_text(encoding="utf-8") if calibration_path else None
    beside = {CONFIG_NAME: config_text, **({CALIBRATION_NAME: cal_text} if cal_text is not None else {})}
    cam = cfg.camera
    rec = Recorder(folder, st, width=cam.width, height=cam.height,
                   dtype=np.uint8 if cam.bit_depth == 8 else np.uint16, fps=cam.fps, exposure_s=cam.exposure_s,
                   bit_depth=cam.bit_depth, beside=beside,
                   meta={"session": folder.name, "config_toml": config_text, "calibration": cal_text,
                         "intake_buffers": int(intake_buffers)})
    return LiveRecording(rec, losses)
