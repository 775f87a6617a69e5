"""What `pip install .` puts into site-packages: one top-level package, ``iscd`` (the
checkout's ``drivers/`` and ``calibration/`` folders are its subpackages ``iscd.drivers`` and
``iscd.calibration``; ``benchmarks/`` and ``tests/`` are not installed)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("iscd", "drivers", "calibration")


def _package_folders() -> set[str]:
    """Every folder of the installed sources with an ``__init__.py``, as its import name."""
    mapped = {"drivers": "iscd.drivers", "calibration": "iscd.calibration"}
    out = set()
    for top in SOURCES:
        for init in (ROOT / top).rglob("__init__.py"):
            parts = list(init.parent.relative_to(ROOT).parts)
            parts[:1] = mapped.get(parts[0], parts[0]).split(".")
            out.add(".".join(parts))
    return out


def test_every_package_folder_is_listed_in_pyproject() -> None:
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert set(meta["packages"]) == _package_folders()
    assert meta["package-dir"] == {"iscd.drivers": "drivers", "iscd.calibration": "calibration"}


def test_the_wheel_holds_only_iscd(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for top in (*SOURCES, "benchmarks"):
        shutil.copytree(ROOT / top, src / top, ignore=shutil.ignore_patterns("__pycache__"))
    out = tmp_path / "dist"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "-q", "-w", str(out), str(src)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = out.glob("iscd-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"iscd"}
    # the mapped folders are inside it, whole, and the benchmarks are not
    for sub, folder in (("iscd/drivers", "drivers"), ("iscd/calibration", "calibration")):
        want = {f"{sub}/{p.relative_to(ROOT / folder).as_posix()}" for p in (ROOT / folder).rglob("*.py")}
        assert want <= set(names), sorted(want - set(names))[:5]
    assert "iscd/data/default.toml" in names
    assert not any("bench_" in n for n in names)


def test_bench_from_an_installed_wheel_is_one_clear_line(monkeypatch, capsys) -> None:
    from iscd.cli import main as cli
    from iscd.cli.commands import bench

    assert bench.benchmarks_root() == ROOT  # this checkout: found beside the package
    monkeypatch.setattr(bench, "benchmarks_root", lambda: None)  # as from a wheel
    assert cli.main(["bench", "--quick", "ringbuffer"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not installed" in err[0] and "pip install -e" in err[0], err
