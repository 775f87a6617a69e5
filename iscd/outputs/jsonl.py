"""JSON Lines output (SPEC section 7): one compact JSON object a line, rotated, flushed often.

Durability without a background thread: :meth:`JsonlWriter.write` keeps whole lines in a
memory buffer and hands them to the OS (one ``os.write`` on an ``O_APPEND`` descriptor)
when ``flush_interval_s`` has passed since the last hand-over, when the buffer passes
``max_buffer_bytes``, on :meth:`flush` and on :meth:`close`. Data handed to the OS survives
the process being killed (SIGKILL, a crash, the systemd watchdog), so a killed daemon loses
only the records of the last ``flush_interval_s`` (plus the records since the last write,
if the writer then idled: call :meth:`maybe_flush` from an idle loop; the daemon's
once-a-second stats record also triggers it). ``os.fsync`` every ``fsync_interval_s``
bounds what a power cut loses. Only whole lines are ever written, so a reader never sees
half a record (except after a power cut, where the file system decides).

Rotation: before a line would take the file past ``rotate_bytes`` the file is closed and
renamed ``PATH.1`` (``PATH.1`` -> ``PATH.2`` ..., the oldest beyond ``keep`` deleted) and
a new ``PATH`` is started; a line is never split between files. Reading ``PATH.keep`` ...
``PATH.1``, ``PATH`` in that order gives the records in order. An existing ``PATH`` is
appended to (a restarted daemon continues the file), and a file that is moved or deleted
under the writer (an external logrotate) is noticed at the next flush and re-created.

I/O errors (disk full) never raise out of :meth:`write`: they are counted in
:attr:`errors`, the records of the failed hand-over in :attr:`dropped` (and
:attr:`io_dropped`), and logged at most once a second (:attr:`LOG_INTERVAL_S`: the first
error at once, then one line a second saying how many records were lost meanwhile); the
first successful write after a failure says so. A hand-over that the disk took only part
of (``write`` wrote some bytes, then ENOSPC) is cut back to its last whole line
(``ftruncate``), so the file never holds half a record and the next records do not glue
onto one; the whole lines it did take are kept and counted written. Writing resumes by
itself when space returns (each hand-over tries again).
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
import time
from pathlib import Path
from typing import Any

from iscd.outputs.base import Output, OutputError

log = logging.getLogger(__name__)

# the writer's system calls and clock, by module name so that tests can inject a full disk
# (ENOSPC, partial writes) or a fake clock without patching the os and time modules
_write = os.write
_monotonic = time.monotonic


def _default(obj: Any) -> Any:
    """JSON for numpy scalars/arrays and bytes (records should be plain, but be forgiving)."""
    tolist = getattr(obj, "tolist", None)
    if tolist is not None:  # numpy scalar or array
        return tolist()
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return bytes(obj).hex()
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")


def _finite(obj: Any) -> Any:
    """``obj`` with non-finite floats replaced by None (JSON has no NaN/Infinity)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if hasattr(obj, "tolist"):
        return _finite(obj.tolist())
    return obj


def encode_record(record: dict[str, Any]) -> bytes:
    """One record as a compact JSON line (with ``\\n``); NaN/inf become ``null``.

    Raises TypeError for a value JSON cannot hold.
    """
    try:
        text = json.dumps(record, separators=(",", ":"), allow_nan=False, default=_default)
    except ValueError:  # a NaN or inf somewhere
        text = json.dumps(_finite(record), separators=(",", ":"), allow_nan=False, default=_default)
    return text.encode("utf-8") + b"\n"


def rotated_paths(path: str | Path) -> list[Path]:
    """The files of a rotated output, oldest first: ``PATH.n`` ... ``PATH.1``, ``PATH`` (existing ones)."""
    p = Path(path)
    numbered = []
    for q in p.parent.glob(p.name + ".*"):
        suffix = q.name[len(p.name) + 1:]
        if suffix.isdigit():
            numbered.append((int(suffix), q))
    out = [q for _, q in sorted(numbered, reverse=True)]
    if p.exists():
        out.append(p)
    return out


def read_records(path: str | Path, *, rotated: bool = True) -> list[dict[str, Any]]:
    """All records of an output (with its rotated files when ``rotated``), in order.

    A final line without its newline (a power cut mid-write) is skipped.
    """
    out: list[dict[str, Any]] = []
    for p in (rotated_paths(path) if rotated else [Path(path)]):
        data = p.read_bytes()
        for line in data.split(b"\n")[:-1] if data else []:
            if line.strip():
                out.append(json.loads(line))
    return out


class JsonlWriter(Output):
    """Appends records to ``path`` as JSON Lines; see the module docstring for flushing and rotation.

    ``rotate_bytes``: size at which the file is rotated, bytes. ``flush_interval_s``: longest
    time a record waits in memory, s (0 = every write goes straight to the OS).
    ``fsync_interval_s``: how often the data is forced to the disk, s (0 = on every flush,
    None = only at :meth:`close`). ``keep``: rotated files kept (None = all).
    ``max_buffer_bytes``: flush earlier when this much is buffered. Thread-safe.

    Raises :class:`~iscd.outputs.OutputError` (one line) when the file cannot be opened.
    """

    def __init__(self, path: str | Path, *, rotate_bytes: int = 256 * 2**20,
                 flush_interval_s: float = 0.5, fsync_interval_s: float | None = 5.0,
                 keep: int | None = 10, max_buffer_bytes: int = 2**20) -> None:
        if rotate_bytes <= 0:
            raise OutputError(f"rotate_bytes must be > 0, got {rotate_bytes}")
        if flush_interval_s < 0:
            raise OutputError(f"flush_interval_s must be >= 0, got {flush_interval_s}")
        if keep is not None and keep < 0:
            raise OutputError(f"keep must be >= 0 or None, got {keep}")
        self.path = Path(path)
        self.rotate_bytes = int(rotate_bytes)
        self.flush_interval_s = float(flush_interval_s)
        self.fsync_interval_s = fsync_interval_s
        self.keep = keep
        self.max_buffer_bytes = int(max_buffer_bytes)
        self.records = 0
        """Records accepted by :meth:`write`."""
        self.written = 0
        """Records handed to the OS."""
        self.dropped = 0
        """Records lost to I/O errors, unencodable records, or writes after close."""
        self.errors = 0
        """I/O errors (each is logged, the first few and then every 100th)."""
        self.rotations = 0
        self.io_dropped = 0
        """Records lost because the file system refused them (disk full, I/O error)."""
        self._failing = False
        self._last_log = -math.inf
        self._unlogged_errors = 0
        self._unlogged_dropped = 0
        self._buf: list[bytes] = []
        self._buf_bytes = 0
        self._lock = threading.Lock()
        self._fd: int | None = None
        self._size = 0
        self._ino: tuple[int, int] | None = None
        now = _monotonic()
        self._last_flush = now
        self._last_fsync = now
        self._closed = False
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._open()
        except OSError as e:
            raise OutputError(f"cannot open output file {self.path}: {e.strerror or e}") from None

    # -- public API ---------------------------------------------------------------------

    def write(self, record: dict[str, Any]) -> None:
        """Queue one record; hands the buffer to the OS when ``flush_interval_s`` has passed."""
        try:
            line = encode_record(record)
        except (TypeError, ValueError) as e:
            self.dropped += 1
            self._log_error(f"record not JSON-encodable, dropped: {e}")
            return
        with self._lock:
            if self._closed:
                self.dropped += 1
                return
            self.records += 1
            if self._size + self._buf_bytes + len(line) > self.rotate_bytes and self._size + self._buf_bytes > 0:
                self._flush_locked(force_fsync=True)
                self._rotate_locked()
            self._buf.append(line)
            self._buf_bytes += len(line)
            now = _monotonic()
            if now - self._last_flush >= self.flush_interval_s or self._buf_bytes >= self.max_buffer_bytes:
                self._flush_locked(now=now)

    def maybe_flush(self) -> None:
        """Flush if ``flush_interval_s`` has passed (call from an idle loop; cheap otherwise)."""
        with self._lock:
            now = _monotonic()
            if self._buf and now - self._last_flush >= self.flush_interval_s:
                self._flush_locked(now=now)

    def flush(self, *, fsync: bool = False) -> None:
        """Hand every buffered record to the OS now (and force it to disk with ``fsync``)."""
        with self._lock:
            self._flush_locked(force_fsync=fsync)

    def close(self) -> None:
        """Flush, fsync and close; later writes are dropped (counted). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._flush_locked(force_fsync=True)
            self._closed = True
            if self._fd is not None:
                try:
                    os.close(self._fd)
                except OSError as e:
                    self._log_error(f"close failed: {e}")
                self._fd = None

    @property
    def buffered(self) -> int:
        """Records waiting in memory."""
        return len(self._buf)

    def counters(self) -> dict[str, int]:
        """For the daemon's stats record."""
        return {"jsonl_records": self.records, "jsonl_dropped": self.dropped,
                "jsonl_io_dropped": self.io_dropped, "jsonl_errors": self.errors,
                "jsonl_rotations": self.rotations}

    def __enter__(self) -> "JsonlWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals (called with the lock held) -----------------------------------------

    def _open(self) -> None:
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o640)
        st = os.fstat(fd)
        self._fd, self._size, self._ino = fd, st.st_size, (st.st_dev, st.st_ino)

    def _reopen_if_moved(self) -> None:
        """Re-create ``path`` if it was deleted or moved under us (else we'd write to a ghost)."""
        try:
            st = os.stat(self.path)
            if (st.st_dev, st.st_ino) == self._ino:
                return
        except FileNotFoundError:
            pass
        log.warning("%s was moved or deleted; starting a new file", self.path)
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        self._open()

    def _flush_locked(self, *, now: float | None = None, force_fsync: bool = False) -> None:
        now = _monotonic() if now is None else now
        self._last_flush = now
        if self._closed:
            return
        n = len(self._buf)
        data = b"".join(self._buf)
        self._buf.clear()
        self._buf_bytes = 0
        if n == 0 and not force_fsync:
            return
        done = 0
        try:
            if self._fd is None:
                self._open()
            elif n:
                self._reopen_if_moved()
            assert self._fd is not None
            view = memoryview(data)
            while done < len(data):
                k = _write(self._fd, view[done:])
                if k <= 0:  # pragma: no cover - write(2) returns > 0 or fails
                    raise OSError(28, "no progress writing")
                done += k
        except OSError as e:
            lost, kept = n, 0
            if done:  # part of the hand-over reached the file: keep its whole lines only
                keep = data.rfind(b"\n", 0, done) + 1
                kept = data.count(b"\n", 0, keep)
                try:
                    if self._fd is not None:
                        os.ftruncate(self._fd, self._size + keep)
                    self._size += keep
                    self.written += kept
                    lost = n - kept
                except OSError:  # cannot cut it back: the partial line stays; say so
                    self._size += done
                    self.written += kept
                    lost = n - kept
                    self._log_error(f"{self.path}: could not remove a partial line after a failed write")
            if kept and self._failing:  # some records got through: space came back, a little
                log.warning("jsonl output: writing to %s again, in part (%d records lost in all)",
                            self.path, self.io_dropped)
            self.dropped += lost
            self.io_dropped += lost
            self._failing = True
            self._log_error(f"write to {self.path} failed ({lost} records lost): {e.strerror or e}",
                            dropped=lost)
            return
        self._size += len(data)
        self.written += n
        if self._failing and n:
            self._failing = False
            log.warning("jsonl output: writing to %s again (%d records lost in all)", self.path, self.io_dropped)
            self._last_log = -math.inf
        fsync_s = self.fsync_interval_s
        if force_fsync or (fsync_s is not None and now - self._last_fsync >= fsync_s):
            try:
                os.fdatasync(self._fd)
                self._last_fsync = now
            except OSError as e:  # the records are in the OS's hands; the disk may lose them
                self._log_error(f"fsync of {self.path} failed: {e.strerror or e}")

    def _rotate_locked(self) -> None:
        try:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None
            base = str(self.path)
            if self.keep == 0:
                os.unlink(base)
            else:
                existing = sorted((int(q.name[len(self.path.name) + 1:]) for q in
                                   self.path.parent.glob(self.path.name + ".*")
                                   if q.name[len(self.path.name) + 1:].isdigit()), reverse=True)
                for i in existing:
                    if self.keep is not None and i >= self.keep:
                        os.unlink(f"{base}.{i}")
                    else:
                        os.replace(f"{base}.{i}", f"{base}.{i + 1}")
                os.replace(base, f"{base}.1")
            self.rotations += 1
            self._open()
        except OSError as e:
            self._log_error(f"rotation of {self.path} failed: {e.strerror or e}")
            if self._fd is None:
                try:
                    self._open()
                except OSError:
                    pass

    LOG_INTERVAL_S = 1.0
    """At most one error line this often (a full disk fails every flush)."""

    def _log_error(self, msg: str, dropped: int = 0) -> None:
        self.errors += 1
        self._unlogged_errors += 1
        self._unlogged_dropped += dropped
        now = _monotonic()
        if now - self._last_log < self.LOG_INTERVAL_S:
            return
        since = ""
        if self._unlogged_errors > 1:
            since = (f"; {self._unlogged_errors} errors and {self._unlogged_dropped} records lost since the "
                     f"last message")
        log.error("jsonl output: %s (error %d; %d records lost in all)%s", msg, self.errors, self.dropped, since)
        self._last_log = now
        self._unlogged_errors = 0
        self._unlogged_dropped = 0
