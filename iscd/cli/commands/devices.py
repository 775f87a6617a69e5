"""``iscd devices``: the cameras per backend (GenICam per producer, V4L2) with the camera
URL of each (what ``[rig] left`` / ``right`` take), the simulated rig's URL, and LED boards."""

from __future__ import annotations

import argparse
import json
import logging
from typing import Any

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "devices", help="list the cameras (GenICam, V4L2) and LED boards attached",
        description=(
            "Lists the GenICam cameras of each GenTL producer (the .cti given with --producer "
            "or [rig] producer, else every .cti in the GENICAM_GENTL64_PATH directories), the "
            "V4L2 capture devices (/dev/video*) and the LED transmitter boards on USB "
            "([board] vid:pid), each camera with its URL: paste two of them into the config as "
            "[rig] left (trigger master) and right (slave), or url = \"mock://default\" for the "
            "simulated rig. '--producer simulated' lists the three simulated cameras of the "
            "producer shipped with the genicam package."))
    p.add_argument("--producer", metavar="CTI", action="append", default=None,
                   help="GenTL producer file (.cti) to ask for GenICam cameras, or 'simulated'; "
                        "repeat for several (default: [rig] producer, else GENICAM_GENTL64_PATH)")
    p.add_argument("--backend", metavar="SCHEME", default="all",
                   help="which camera backend to list: a camera URL scheme (genicam, v4l2, mock) "
                        "or all (default)")
    p.add_argument("--no-boards", action="store_true", help="do not look for LED boards")
    p.add_argument("--config", metavar="FILE",
                   help="config file whose GenTL producers ([rig] producer, the cti of its "
                        "genicam URLs) and [board] vid/pid to use")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object {genicam: {producers, cameras}, v4l2: {pattern, "
                        "cameras}, mock: {urls}, boards, notes} instead of text (every camera "
                        "with its url)")
    p.set_defaults(func=run)


def _genicam(producers: list[str] | None, notes: list[str]) -> dict[str, Any]:
    from iscd.drivers.base import CameraError
    from iscd.drivers import genicam
    from iscd.core.errors import UserError

    try:
        ctis = ([c for p in producers for c in genicam.find_producers(p)] if producers
                else genicam.find_producers())
    except CameraError as e:
        raise UserError(str(e)) from None
    ctis = list(dict.fromkeys(ctis))
    if not ctis:
        notes.append(f"genicam: no GenTL producer: pass --producer CTI or set {genicam.ENV_VAR} "
                     f"to the directory of your camera vendor's .cti")
    cameras: list[dict[str, Any]] = []
    for cti in ctis:
        try:
            cameras.extend({**c, "url": genicam.device_url(c)} for c in genicam.list_devices(cti))
        except CameraError as e:
            notes.append(f"genicam: {cti}: {e}")
        except Exception as e:  # noqa: BLE001 - a broken producer must not end the listing
            notes.append(f"genicam: {cti}: producer failed: {type(e).__name__}: {e}")
    return {"producers": ctis, "cameras": cameras}


def _v4l2(notes: list[str]) -> dict[str, Any]:
    from iscd.drivers.base import CameraError
    from iscd.drivers import v4l2

    try:
        cams = [{**c, "url": v4l2.device_url(c)} for c in v4l2.list_devices()]
    except CameraError as e:
        notes.append(f"v4l2: {e}")
        cams = []
    return {"pattern": v4l2.V4L2_GLOB, "cameras": cams}


def _boards(cfg: Any, notes: list[str]) -> list[dict[str, Any]]:
    try:
        from iscd.drivers.board import discovery
    except ImportError:
        notes.append("boards: board discovery is not available")
        return []
    kwargs: dict[str, Any] = {}
    if cfg is not None:
        try:
            from iscd.drivers.board.settings import board_settings

            bs = board_settings(cfg)
            kwargs = {"vid": bs.vid, "pid": bs.pid}
        except ImportError:
            pass
    try:
        found = discovery.find_boards(**kwargs)
    except Exception as e:  # noqa: BLE001 - USB/serial enumeration errors are reported, not fatal
        notes.append(f"boards: search failed: {type(e).__name__}: {e}")
        return []
    return [b.as_dict() if hasattr(b, "as_dict") else dict(b) for b in found]


def collect(producers: list[str] | None = None, backend: str = "all", boards: bool = True,
            cfg: Any = None) -> dict[str, Any]:
    """Everything ``iscd devices`` reports, as a JSON-ready dict."""
    from iscd.drivers import urls
    from iscd.core.errors import UserError

    known = urls.schemes()
    if backend != "all" and backend not in known:
        raise UserError(f"--backend: unknown camera backend {backend!r} (known: {', '.join(known)}, all)")
    notes: list[str] = []
    out: dict[str, Any] = {}
    if producers is None and cfg is not None:
        producers = _config_producers(cfg) or None
    if backend in ("genicam", "all"):
        out["genicam"] = _genicam(producers, notes)
    if backend in ("v4l2", "all"):
        out["v4l2"] = _v4l2(notes)
    if backend in ("mock", "all"):
        out["mock"] = {"urls": [c["url"] for c in urls.discover("mock")]}
    if boards:
        out["boards"] = _boards(cfg, notes)
    out["notes"] = notes
    return out


def _config_producers(cfg: Any) -> list[str]:
    """The GenTL producers a config names: the cti of its genicam camera URLs (which hold
    ``[rig] producer`` where they had none), else ``[rig] producer``."""
    from iscd.drivers import urls

    ctis = [urls.parse_url(u).option("cti") for u in cfg.rig.camera_urls if u.startswith("genicam:")]
    ctis = [c for c in dict.fromkeys(ctis) if c]
    return ctis or ([cfg.rig.producer] if cfg.rig.producer else [])


def suggested_rig(report: dict[str, Any]) -> dict[str, str] | None:
    """``{"left": URL, "right": URL}`` of the first two available cameras of one backend in
    ``report`` (for the config's ``[rig]``), or None."""
    for name in ("genicam", "v4l2"):
        cams = [c for c in report.get(name, {}).get("cameras", [])
                if c.get("url") and "error" not in c and c.get("available", True)]
        if len(cams) >= 2:
            return {"left": cams[0]["url"], "right": cams[1]["url"]}
    return None


def _fmt(v: Any) -> str:
    return "-" if v in (None, "") else str(v)


def render(report: dict[str, Any]) -> str:
    """The report as text, one device a line."""
    lines: list[str] = []
    if "genicam" in report:
        g = report["genicam"]
        lines.append(f"GenICam cameras ({len(g['cameras'])}):")
        for cti in g["producers"]:
            cams = [c for c in g["cameras"] if c["producer"] == cti]
            lines.append(f"  producer {cti}: {len(cams)} camera(s)")
            for c in cams:
                state = "available" if c.get("available", True) else "in use"
                lines.append(f"    {c.get('url', '-')}  serial {_fmt(c['serial'])}  user id {_fmt(c['user_id'])}  "
                             f"{_fmt(c['vendor'])} {_fmt(c['model'])}  id {_fmt(c['id'])}  {state}")
    if "v4l2" in report:
        v = report["v4l2"]
        lines.append(f"V4L2 cameras ({len(v['cameras'])}):")
        if not v["cameras"]:
            lines.append(f"  none found ({v['pattern']})")
        for c in v["cameras"]:
            if "error" in c:
                lines.append(f"  {c['device']}: cannot open: {c['error']}")
            else:
                mono = "" if c.get("mono") else "  (no Mono format)"
                lines.append(f"  {c.get('url', c['device'])}  {c['card']} ({c['driver']}, {c['bus']})  "
                             f"formats {' '.join(c['formats']) or '-'}{mono}")
    if "mock" in report:
        for u in report["mock"]["urls"]:
            lines.append(f"Simulated rig: {u}  (no hardware: [rig] url = \"{u}\")")
    rig = suggested_rig(report)
    if rig is not None:
        lines.append("[rig] of a config with two of these cameras (left = trigger master, right = slave):")
        lines.append(f"  left = \"{rig['left']}\"")
        lines.append(f"  right = \"{rig['right']}\"")
    if "boards" in report:
        b = report["boards"]
        lines.append(f"LED boards ({len(b)}):")
        if not b:
            lines.append("  none found")
        for d in b:
            lines.append(f"  {_fmt(d.get('device'))}  serial {_fmt(d.get('serial_number'))}  "
                         f"usb {_fmt(d.get('usb_id'))} at {_fmt(d.get('location'))}  "
                         f"{_fmt(d.get('description'))}")
    for n in report.get("notes", []):
        lines.append(f"note: {n}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    cfg = None
    if args.config:
        from iscd.core.config import load

        cfg = load(args.config)
    report = collect(args.producer, args.backend, not args.no_boards, cfg)
    print(json.dumps(report, indent=2) if args.json else render(report))
    return 0
