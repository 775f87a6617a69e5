"""Write a :class:`~iscd.core.config.Config` back as TOML (so a simulated run can be reproduced).

Only what configs contain: tables of strings, booleans, numbers and lists (of scalars or of
tables, written as arrays of tables), and nested tables (e.g. raw extra sections). Keys whose
value is None (optional keys left out, e.g. those of ``[[scene.transmitters]]`` that default
to the main transmitter's) are left out, so they read back as None.
"""

from __future__ import annotations

import json
import math
from typing import Any

from iscd.core.config import Config, to_dict


def _scalar(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)  # a valid TOML basic string
    if isinstance(v, list):
        return "[" + ", ".join(_scalar(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_scalar(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def _key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else json.dumps(k)


def _table(name: str, d: dict[str, Any], out: list[str]) -> None:
    simple = {k: v for k, v in d.items() if v is not None and not isinstance(v, dict)
              and not (isinstance(v, list) and v and all(isinstance(x, dict) for x in v))}
    out.append(f"[{name}]")
    out.extend(f"{_key(k)} = {_scalar(v)}" for k, v in simple.items())
    out.append("")
    for k, v in d.items():
        if isinstance(v, dict):
            _table(f"{name}.{_key(k)}", v, out)
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for item in v:
                out.append(f"[[{name}.{_key(k)}]]")
                out.extend(f"{_key(a)} = {_scalar(b)}" for a, b in item.items() if b is not None)
                out.append("")


def config_to_toml(cfg: Config, header: str = "") -> str:
    """TOML text that :func:`iscd.core.config.loads` reads back into an equal config.

    Parameters
    ----------
    cfg : Config
        The config to write.
    header : str
        Text written first as ``#`` comment lines ('' for none).

    Returns
    -------
    str
        The TOML document, ending in a newline.
    """
    d = to_dict(cfg)
    owned = d.pop("owned", {}) or {}
    out: list[str] = [f"# {line}" for line in header.splitlines()] + ([""] if header else [])
    for name, table in [*d.items(), *owned.items()]:
        _table(name, table, out)
    return "\n".join(out).rstrip() + "\n"
