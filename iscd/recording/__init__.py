"""Recordings of one camera behind one reader interface.

``open_recording(path)`` picks the reader by what ``path`` is:

- a folder -> :class:`~iscd.recording.images.ImageFolderRecording` (PNG/TIFF frames in
  natural name order);
- ``*.cih`` / ``*.cihx`` / ``*.mraw`` -> :class:`~iscd.recording.photron.PhotronRecording`;
- ``*.iscr`` or any file starting with the ``.iscr`` magic ->
  :class:`~iscd.recording.iscr.IscrRecording` (the project's own format, written by
  :class:`~iscd.recording.iscr.IscrWriter`).

Every reader is a :class:`~iscd.recording.base.Recording`; every problem is a
:class:`~iscd.recording.base.RecordingError` whose message is one line naming the file.
A stereo recording is two recordings (left, right) paired by frame id
(:func:`~iscd.recording.base.match_frames`), or one stereo ``.iscr`` (version 2, both
cameras, what ``iscd run --record`` writes): :func:`open_stereo` opens one such file or a
run's folder of them (:mod:`iscd.recording.pairs`); :func:`open_recording` refuses it with
a line saying so.
"""

from __future__ import annotations

from pathlib import Path

from iscd.recording.base import Recording, RecordingError, RecordingWarning, match_frames
from iscd.recording.iscr import MAGIC, IscrRecording, IscrWriter

__all__ = ["Recording", "RecordingError", "RecordingWarning", "IscrWriter", "IscrRecording", "open_recording",
           "match_frames", "open_stereo"]

PHOTRON_SUFFIXES = (".cih", ".cihx", ".mraw")


def open_recording(path: str | Path) -> Recording:
    """Open a recording (see the module docstring for how the reader is chosen)."""
    p = Path(path)
    if p.is_dir():
        from iscd.recording.images import ImageFolderRecording
        return ImageFolderRecording(p)
    suffix = p.suffix.lower()
    if suffix in PHOTRON_SUFFIXES:
        from iscd.recording.photron import PhotronRecording
        return PhotronRecording(p)
    if not p.exists():
        raise RecordingError(p, "no such file or folder")
    if suffix == ".iscr" or _has_iscr_magic(p):
        return IscrRecording(p)
    raise RecordingError(p, "unknown recording format (expected an .iscr file, a Photron "
                            ".cih/.cihx/.mraw file or a folder of PNG/TIFF frames)")


def open_stereo(path: str | Path) -> "PairSession":  # noqa: F821
    """A stereo recording of ``iscd run --record`` (a run folder or one of its files) as a
    :class:`~iscd.recording.pairs.PairSession`."""
    from iscd.recording.pairs import PairSession

    return PairSession(path)


def _has_iscr_magic(p: Path) -> bool:
    try:
        with open(p, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError as e:
        raise RecordingError(p, f"cannot read: {e.strerror or e}") from None
