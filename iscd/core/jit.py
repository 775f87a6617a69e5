"""Compiled kernels: one place that sets up Numba for the whole package.

Every hot per-frame kernel in iscd is a plain Python function decorated with :func:`njit`
(``numba.njit(cache=True, nogil=True)``) and has a pure-numpy reference beside it that the
tests compare it with. This module is the contract for how they are compiled:

* **Cache directory.** Compiled machine code is cached on disk so that a restart does not
  compile again. The directory is, in order: ``$NUMBA_CACHE_DIR`` if set; systemd's
  ``$CACHE_DIRECTORY`` (``CacheDirectory=iscd`` in the unit) + ``/numba``;
  ``$XDG_CACHE_HOME/iscd/numba`` or ``~/.cache/iscd/numba``. The first writable one is
  used; if none is, one warning line says so and the kernels compile at every start
  (correct, only slower to start).
* **Warm-up.** :func:`warm_up` compiles (or loads from the cache) every registered kernel on
  tiny inputs; the daemon calls it before it reports READY=1, so the first frames are not
  spent compiling. It returns the seconds it took (cold: compiling; warm: loading).

Import :func:`njit` from here, never ``numba`` directly, so that the cache directory is set
before Numba is first imported.
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

log = logging.getLogger(__name__)

F = TypeVar("F", bound=Callable[..., Any])


def _writable(d: Path) -> bool:
    try:
        d.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=d, prefix=".probe-"):
            pass
        return True
    except OSError:
        return False


def cache_dir() -> Path | None:
    """The directory compiled kernels are cached in (see module docstring), or None."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    cands: list[Path] = [Path(env)] if env else []
    if os.environ.get("CACHE_DIRECTORY"):  # systemd CacheDirectory= (may list several, ':')
        cands.append(Path(os.environ["CACHE_DIRECTORY"].split(":")[0]) / "numba")
    xdg = os.environ.get("XDG_CACHE_HOME")
    cands.append((Path(xdg) if xdg else Path.home() / ".cache") / "iscd" / "numba")
    for d in cands:
        if _writable(d):
            return d
    return None


_CACHE = cache_dir()
if _CACHE is not None:
    os.environ["NUMBA_CACHE_DIR"] = str(_CACHE)
else:
    log.warning("no writable cache directory for compiled kernels (tried $NUMBA_CACHE_DIR, "
                "$CACHE_DIRECTORY, ~/.cache/iscd): they compile again at every start")

import numba  # noqa: E402  (after NUMBA_CACHE_DIR is set)

CACHE_ENABLED = _CACHE is not None
CACHE_DIR: Path | None = _CACHE
"""The cache directory in use (None: no cache)."""

_REGISTRY: list[tuple[Callable[..., Any], Callable[[], tuple]]] = []


def njit(fn: F | None = None, *, warm: Callable[[], tuple] | None = None, **kw: Any) -> F:
    """``numba.njit(cache=True, nogil=True, **kw)``; ``warm``: a function returning example
    arguments, called by :func:`warm_up` to compile the kernel ahead of use."""

    def deco(f: F) -> F:
        opts = {"cache": CACHE_ENABLED, "nogil": True, **kw}
        jf = numba.njit(**opts)(f)
        if warm is not None:
            _REGISTRY.append((jf, warm))
        return jf  # type: ignore[return-value]

    return deco(fn) if fn is not None else deco  # type: ignore[return-value]


def register_warm(jf: Callable[..., Any], args: Callable[[], tuple]) -> None:
    """Have :func:`warm_up` compile ``jf`` for the argument types ``args()`` returns (a
    kernel used with several dtypes registers once per dtype)."""
    _REGISTRY.append((jf, args))


def warm_up(should_stop: Callable[[], bool] | None = None) -> float:
    """Compile (or load from the cache) every kernel registered so far (a kernel registers
    when its module is imported: import what you will run first); returns the seconds taken.
    ``should_stop`` is asked before each kernel: when it says True the rest are left (a
    daemon stopped during its first start, whose compiling takes minutes, stops within one
    kernel's compile time)."""
    t0 = time.perf_counter()
    for jf, args in list(_REGISTRY):
        if should_stop is not None and should_stop():
            break
        jf(*args())
    return time.perf_counter() - t0


def signatures() -> dict[str, int]:
    """How many compiled signatures each registered kernel has (a kernel that gains one
    while running compiled in the middle of it: ``tests/test_frame_kernels.py`` checks that
    the live path needs none beyond :func:`warm_up`)."""
    out: dict[str, int] = {}
    for jf, _ in _REGISTRY:
        name = f"{jf.py_func.__module__}.{jf.py_func.__qualname__}"
        out[name] = len(jf.signatures)
    return out
