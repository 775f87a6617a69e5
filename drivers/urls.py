"""Cameras opened by URL, as pyserial opens ports (``serial.serial_for_url``).

A camera URL names a backend by its scheme and a device by the rest::

    mock://default                      the simulated stereo rig (both cameras)
    mock://default?seed=7&noise=false   ... with scene seed 7, noise-free frames
    genicam://21345678?cti=/opt/x.cti   GenICam camera by serial number or user id
    genicam://*?cti=simulated           the first camera of a producer ('' = '*')
    v4l2:///dev/video0                  a V4L2 device (an absolute path: three slashes)

    from iscd.drivers.urls import camera_for_url, rig_for_url
    cam = camera_for_url("v4l2:///dev/video0", name="left")        # one camera
    left, right = rig_for_url("mock://default")                    # a rig that is one device
    left, right = rig_for_url("genicam://0?cti=simulated", "genicam://1?cti=simulated")

Backends register into :data:`BACKENDS` (scheme -> :class:`Backend`) with
:func:`register`; the built-in ones (:mod:`iscd.drivers.mock`, :mod:`iscd.drivers.genicam`,
:mod:`iscd.drivers.v4l2`) register themselves when imported, and are imported on the first
look-up (the modules of :data:`BUILTIN_MODULES`, as pyserial imports its
``protocol_handler_packages``). A backend's hardware library is still imported only when a
camera is opened or listed.

A backend is either a **stereo** backend (the URL is the whole rig, both cameras, opened by
:func:`rig_for_url`: the mock rig, whose two cameras share one trigger clock and scene) or
a **camera** backend (the URL is one camera, :func:`camera_for_url`; a rig is two of them,
left = trigger master, right = slave).

Bad URLs raise :class:`CameraURLError` with one line naming the URL and the known forms.
The ``[rig]`` table's URLs are resolved here (:func:`resolve_rig`, installed into the config
loader when this module is imported: the core knows no backend).
This module imports nothing of the project but :mod:`iscd.drivers.base` and the config.
"""

from __future__ import annotations

import importlib
import logging
import sys
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qsl, quote, unquote, urlencode, urlsplit

from iscd.core.config import ConfigError, RigConfig, RigURLs, set_rig_resolver
from iscd.drivers.base import Camera, CameraError

log = logging.getLogger(__name__)

BUILTIN_MODULES = ("iscd.drivers.mock", "iscd.drivers.genicam", "iscd.drivers.v4l2")
"""Modules that register a backend when imported (imported on the first look-up)."""


class CameraURLError(CameraError, ValueError):
    """A camera URL is malformed or names no registered backend; ``str(err)`` is one line
    naming the URL and listing the known URL forms."""


@dataclass(frozen=True)
class CameraURL:
    """A parsed camera URL: ``scheme``, ``target`` (percent-decoded: the scene name of
    ``mock://``, the serial number / user id of ``genicam://``, the device path of
    ``v4l2://``) and the query ``options`` (sorted key/value pairs)."""

    scheme: str
    target: str
    options: tuple[tuple[str, str], ...] = ()
    given: str = field(default="", compare=False)
    """The URL as written (for messages)."""

    @property
    def backend(self) -> "Backend":
        return backend(self.scheme)

    @property
    def url(self) -> str:
        """The canonical URL (what :func:`parse_url` reads back into an equal value)."""
        return make_url(self.scheme, self.target, **dict(self.options))

    def option(self, key: str, default: str | None = None) -> str | None:
        return dict(self.options).get(key, default)

    def with_options(self, **options: str) -> "CameraURL":
        """A copy with ``options`` added or replaced (checked as :func:`parse_url` does)."""
        return parse_url(make_url(self.scheme, self.target, **{**dict(self.options), **options}))

    def __str__(self) -> str:
        return self.url


@dataclass(frozen=True)
class Backend:
    """One camera backend, registered under its URL scheme.

    opener: ``opener(url: CameraURL, **options)`` -> a :class:`Camera` (camera backend)
      or ``(left, right)`` (stereo backend); constructs, does not open.
    stereo: the URL is a whole stereo rig (both cameras).
    target: ``"host"`` (``scheme://TARGET``) or ``"path"`` (``scheme:///abs/path``).
    what: what the target names, for messages ("serial number or user id").
    form: the URL's form, for messages and docs (``genicam://SERIAL?cti=PATH``).
    options: query keys -> what they mean; other keys are errors.
    check: ``check(url)`` raises :class:`CameraURLError` for bad values (after the
      generic checks).
    default_target: the target that the old config form ``[rig] backend = SCHEME`` means
      (stereo backends: ``"default"``).
    rig_defaults: query key -> the ``[rig]`` key whose value it takes when the URL lacks
      it (genicam: ``{"cti": "producer"}``).
    discover: ``discover(**hints)`` -> the cameras attached, dicts with ``backend`` and
      ``url``; raises :class:`CameraError` or returns [] (None: nothing to list).
    hardware: real devices (the rig warns when a device refuses the trigger or rate).
    """

    scheme: str
    opener: Callable[..., Any]
    stereo: bool = False
    target: str = "host"
    what: str = "device"
    form: str = ""
    options: Mapping[str, str] = field(default_factory=dict)
    check: Callable[[CameraURL], None] | None = None
    default_target: str | None = None
    rig_defaults: Mapping[str, str] = field(default_factory=dict)
    discover: Callable[..., list[dict[str, Any]]] | None = None
    hardware: bool = True
    summary: str = ""


BACKENDS: dict[str, Backend] = {}
"""scheme -> backend; fill with :func:`register`, read with :func:`backends`."""

_lock = threading.RLock()
_builtins_loaded = False


def register(b: Backend, *, replace: bool = False) -> Backend:
    """Register backend ``b`` under ``b.scheme`` (lower case letters, digits, ``+-.``).
    Registering a taken scheme again is an error unless ``replace``."""
    s = b.scheme
    if not s or not s[0].isalpha() or not all(c.isalnum() or c in "+-." for c in s) or s != s.lower():
        raise ValueError(f"camera URL scheme {s!r}: lower case letters, digits and +-. only")
    if b.target not in ("host", "path"):
        raise ValueError(f"camera URL scheme {s!r}: target must be 'host' or 'path', not {b.target!r}")
    with _lock:
        old = BACKENDS.get(s)
        if old is not None and not replace and old != b:
            raise ValueError(f"camera URL scheme {s!r} is already registered ({old.opener!r})")
        BACKENDS[s] = b
    return b


def unregister(scheme: str) -> None:
    """Remove a backend (tests)."""
    with _lock:
        BACKENDS.pop(scheme, None)


def _load_builtins() -> None:
    global _builtins_loaded
    if _builtins_loaded:
        return
    with _lock:
        if _builtins_loaded:
            return
        _builtins_loaded = True
        for mod in BUILTIN_MODULES:
            try:
                importlib.import_module(mod)
            except ImportError as e:  # pragma: no cover - a partial install
                log.warning("camera backend module %s not available: %s", mod, e)


def backends() -> dict[str, Backend]:
    """Every registered backend (the built-in ones included), by scheme, sorted."""
    _load_builtins()
    with _lock:
        return dict(sorted(BACKENDS.items()))


def schemes(*, stereo: bool | None = None, hardware: bool | None = None) -> tuple[str, ...]:
    """The registered schemes, sorted; ``stereo`` / ``hardware`` filter (None: all)."""
    return tuple(s for s, b in backends().items()
                 if (stereo is None or b.stereo == stereo) and (hardware is None or b.hardware == hardware))


def known_forms() -> str:
    """The URL forms of every backend, for messages: ``genicam://SERIAL?cti=PATH, ...``."""
    return ", ".join(b.form or f"{s}://" for s, b in backends().items())


def backend(scheme: str) -> Backend:
    """The backend of ``scheme``; :class:`CameraURLError` for an unknown one."""
    b = backends().get(scheme)
    if b is None:
        raise CameraURLError(f"unknown camera backend {scheme!r} (known: {', '.join(schemes())}; "
                             f"URLs: {known_forms()})")
    return b


def make_url(scheme: str, target: str, **options: str) -> str:
    """The URL of ``target`` (serial, path, scene name) on backend ``scheme`` with query
    ``options`` (sorted; empty values left out), percent-encoded where needed."""
    b = backend(scheme)
    if b.target == "path":
        body = "//" + quote(target, safe="/:@!$&'()*+,;=-._~")
    else:
        body = "//" + quote(target, safe="*!$'()+,;=-._~")
    query = urlencode(sorted((k, v) for k, v in options.items() if v not in (None, "")),
                      safe="/:*")
    return f"{scheme}:{body}" + (f"?{query}" if query else "")


def _fail(url: str, problem: str) -> CameraURLError:
    return CameraURLError(f"camera URL {url!r}: {problem} (known: {known_forms()})")


def parse_url(url: str) -> CameraURL:
    """Parse and check a camera URL; :class:`CameraURLError` (one line) if it is malformed,
    its scheme is not registered, or its options are unknown or bad for the backend."""
    if not isinstance(url, str):
        raise CameraURLError(f"camera URL: expected a string, got {url!r} (known: {known_forms()})")
    if not url.strip():
        raise _fail(url, "empty")
    if any(ord(c) < 32 or ord(c) == 127 for c in url) or url != url.strip():
        raise _fail(url, "contains spaces or control characters at its ends or inside")
    scheme, sep, _rest = url.partition("://")
    if not sep:
        raise _fail(url, "not a URL (expected SCHEME://...)")
    scheme = scheme.lower()
    b = backends().get(scheme)
    if b is None:
        raise _fail(url, f"unknown scheme {scheme + '://'!r}")
    try:
        parts = urlsplit(url)
    except ValueError as e:
        raise _fail(url, f"malformed: {e}") from None
    if parts.fragment or url.endswith("#"):
        raise _fail(url, "a '#' fragment is not part of a camera URL (write '#' as %23)")
    try:
        pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError:
        raise _fail(url, f"malformed query {parts.query!r} (expected key=value&key=value)") from None
    options: dict[str, str] = {}
    for k, v in pairs:
        if k in options:
            raise _fail(url, f"option {k!r} given twice")
        if k not in b.options:
            known = ", ".join(sorted(b.options)) or "none"
            raise _fail(url, f"unknown option {k!r} for {scheme}:// (its options: {known})")
        options[k] = v
    netloc, path = unquote(parts.netloc), unquote(parts.path)
    if b.target == "path":
        if netloc:
            raise _fail(url, f"{scheme}:// takes an absolute device path after '//', e.g. "
                             f"{scheme}:///{netloc}{path} (three slashes)")
        if not path.startswith("/") or path == "/":
            raise _fail(url, f"{scheme}:// needs an absolute {b.what}, e.g. {b.form or scheme + ':///dev/...'}")
        target = path
    else:
        if path not in ("", "/"):
            raise _fail(url, f"unexpected path {parts.path!r} after the {b.what}")
        target = netloc
    u = CameraURL(scheme, target, tuple(sorted(options.items())), given=url)
    if b.check is not None:
        b.check(u)
    return u


def int_option(u: CameraURL, key: str, lo: int | None = None) -> int | None:
    """Query option ``key`` of ``u`` as an integer (>= ``lo``), None if absent; for a
    backend's ``check`` and opener."""
    v = u.option(key)
    if v is None:
        return None
    try:
        n = int(v)
    except ValueError:
        raise _fail(u.given or u.url, f"option {key}: expected an integer, got {v!r}") from None
    if lo is not None and n < lo:
        raise _fail(u.given or u.url, f"option {key}: expected an integer >= {lo}, got {v!r}")
    return n


def bool_option(u: CameraURL, key: str) -> bool | None:
    """Query option ``key`` as true/false (``1 0 true false yes no on off``), None if absent."""
    v = u.option(key)
    if v is None:
        return None
    low = v.lower()
    if low in ("1", "true", "yes", "on"):
        return True
    if low in ("0", "false", "no", "off"):
        return False
    raise _fail(u.given or u.url, f"option {key}: expected true or false, got {v!r}")


def fail(u: CameraURL, problem: str) -> CameraURLError:
    """A :class:`CameraURLError` about ``u`` (for a backend's ``check``)."""
    return _fail(u.given or u.url, problem)


def _parsed(url: str | CameraURL) -> CameraURL:
    return url if isinstance(url, CameraURL) else parse_url(url)


def camera_for_url(url: str | CameraURL, **options: Any) -> Camera:
    """The camera of ``url`` (constructed, not opened), by the backend registered for its
    scheme; ``options`` go to the backend's opener (e.g. ``name="left"``,
    ``num_buffers=16``). A stereo URL (``mock://``) is refused: use :func:`rig_for_url`."""
    u = _parsed(url)
    b = u.backend
    if b.stereo:
        raise fail(u, "a whole stereo rig (both cameras), not one camera: open it with rig_for_url "
                      "([rig] url)")
    return b.opener(u, **options)


def rig_for_url(url: str | CameraURL, right: str | CameraURL | None = None,
                **options: Any) -> tuple[Camera, Camera]:
    """The (left, right) cameras of a stereo rig, constructed, not opened.

    ``rig_for_url(STEREO_URL, **options)``: a rig that is one device (``mock://default``;
    options such as ``cfg=`` (the config whose scene it shows; None = the embedded default),
    ``buffer_frames=``). ``rig_for_url(LEFT_URL, RIGHT_URL, **options)``: two cameras of one
    camera backend, named ``left`` and ``right`` (options go to both openers).
    """
    u = _parsed(url)
    b = u.backend
    if right is None:
        if not b.stereo:
            raise fail(u, "one camera, not a stereo rig: give the right camera's URL too")
        return b.opener(u, **options)
    r = _parsed(right)
    for side in (u, r):
        if side.backend.stereo:
            raise fail(side, "a whole stereo rig, not one camera of a pair: give it alone")
    if r.scheme != u.scheme:
        raise fail(r, f"the right camera's backend differs from the left one's ({u.url}): "
                      f"the two cameras of a rig use one backend")
    if r == u:
        raise fail(r, "the same camera as the left one")
    return (camera_for_url(u, name="left", **options), camera_for_url(r, name="right", **options))


def discover(scheme: str | None = None, **hints: Any) -> list[dict[str, Any]]:
    """The cameras attached, per backend (``scheme`` None: every hardware backend), as dicts
    with ``backend`` and ``url``. ``hints`` go to each backend's ``discover`` (genicam:
    ``producer``). A backend whose library is missing contributes nothing (logged);
    :class:`CameraError` from a backend (a producer path that does not exist) propagates."""
    chosen = [backend(scheme)] if scheme is not None else [
        b for b in backends().values() if b.hardware]
    out: list[dict[str, Any]] = []
    for b in chosen:
        if b.discover is not None:
            out.extend(b.discover(**hints))
    return out


def resolve_rig(rig: RigConfig) -> RigURLs:
    """``[rig]`` (:class:`iscd.core.config.RigConfig`) resolved against the registered
    backends: the stereo URL, the (left, right) camera URLs (the old keys -- ``backend`` +
    serial numbers / device paths, ``producer`` -- mapped to URLs) and the scheme. Installed
    as the config's resolver when this module is imported
    (:func:`iscd.core.config.set_rig_resolver`), so that ``[rig]`` is checked at load.

    Raises
    ------
    ConfigError
        One line naming the ``rig.`` key and the problem.
    """
    urls = sys.modules[__name__]

    def parse(key: str, value: str) -> Any:
        try:
            return urls.parse_url(value)
        except urls.CameraURLError as e:
            raise ConfigError(f"rig.{key}: {e}") from None

    known = urls.schemes()
    if rig.backend and rig.backend not in known:
        raise ConfigError(f"rig.backend: expected one of {list(known)} (the camera URL schemes), "
                          f"got {rig.backend!r}")
    if rig.url:
        u = parse("url", rig.url)
        if not u.backend.stereo:
            raise ConfigError(f"rig.url: {rig.url!r} is one camera, not a stereo rig: set the two "
                              f"cameras as rig.left and rig.right")
        for side in ("left", "right"):
            if getattr(rig, side):
                raise ConfigError(f"rig.{side}: not used with rig.url = {rig.url!r} (that rig gives "
                                  f"both cameras): remove it")
        if rig.backend and rig.backend != u.scheme:
            raise ConfigError(f"rig.backend: {rig.backend!r} contradicts rig.url = {rig.url!r} "
                              f"(remove rig.backend: the URL names the backend)")
        return RigURLs(u.url, ("", ""), u.scheme)
    given = {side: getattr(rig, side) for side in ("left", "right")}
    parsed = {side: parse(side, v) for side, v in given.items() if "://" in v}
    for side, u in parsed.items():
        if u.backend.stereo:
            raise ConfigError(f"rig.{side}: {given[side]!r} is a whole stereo rig (both cameras): "
                              f"set it as rig.url")
    if len(parsed) == 1 and all(given.values()):
        (side, u), = parsed.items()
        other = "right" if side == "left" else "left"
        raise ConfigError(f"rig.{other}: give a camera URL like rig.{side} ({u.scheme}://...), "
                          f"not {given[other]!r}")
    if len({u.scheme for u in parsed.values()}) > 1:
        raise ConfigError(f"rig.right: {given['right']!r} is another backend than rig.left "
                          f"{given['left']!r}: the two cameras of a rig use one backend")
    if parsed:
        scheme = next(iter(parsed.values())).scheme
        if rig.backend and rig.backend != scheme:
            side = next(iter(parsed))
            raise ConfigError(f"rig.backend: {rig.backend!r} contradicts rig.{side} = {given[side]!r} "
                              f"(remove rig.backend: the URLs name the backend)")
    else:
        scheme = rig.backend or "mock"
    b = urls.backend(scheme)
    if b.stereo:  # the old form: backend = "mock" (left/right unused, as before)
        return RigURLs(urls.make_url(scheme, b.default_target or ""), ("", ""), scheme)
    cams = []
    for side, v in given.items():
        if not v:
            cams.append("")  # refused when the rig is built (make_stereo), as before
            continue
        if side in parsed:
            u = parsed[side]
        else:  # the old form: a serial number / user id or a device path
            if b.target == "path":
                import os.path

                v = os.path.abspath(v)
            u = parse(side, urls.make_url(scheme, v))
        defaults = {opt: getattr(rig, key) for opt, key in b.rig_defaults.items()
                    if getattr(rig, key, "") and u.option(opt) is None}
        if defaults:
            try:
                u = u.with_options(**defaults)
            except urls.CameraURLError as e:
                raise ConfigError(f"rig.{b.rig_defaults[next(iter(defaults))]}: {e}") from None
        cams.append(u.url)
    return RigURLs("", (cams[0], cams[1]), scheme)



set_rig_resolver(resolve_rig)
