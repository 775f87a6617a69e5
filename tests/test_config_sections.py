"""Config sections owned by their code (issue 13 item 3): iscd.core.config knows the names of
the tables it does not define, each owner module declares its dataclass with
``@config_section``, and every table the file holds is applied where it is used (the
``[acquisition]`` table reached no acquisition process before)."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

import iscd.cli.sections as sections
from iscd.cli.main import main
from iscd.core import config as C
from iscd.rig import acquisition as A
from iscd.service.daemon import Daemon

ROOT = Path(__file__).resolve().parents[1]


def test_every_section_name_has_exactly_its_owner() -> None:
    owners = C.section_owners()
    assert list(owners) == list(C.SECTION_NAMES)
    assert owners == sections.OWNERS
    for name, cls in owners.items():
        assert cls.__config_section__ == name
        assert dataclasses.is_dataclass(cls) and cls.__doc__


def test_core_config_names_no_module_above_it() -> None:
    """No importlib discovery, no "module:Class" strings: the layer below knows names only."""
    tree = ast.parse((ROOT / "iscd/core/config.py").read_text())
    imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert "importlib" not in imported
    strings = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)]
    assert not [s for s in strings if s.startswith(("iscd.decode", "iscd.service", "iscd.outputs", "iscd.rig"))
                and ":" in s]


def test_no_consumer_digs_in_the_raw_tables() -> None:
    """Owners read their table with config.section(cfg, Owner); only iscd.core.config touches
    Config.owned, the raw tables (the receiver's raw-table entry point goes through Config.table)."""
    offenders = []
    for p in [*(ROOT / "iscd").rglob("*.py"), *(ROOT / "drivers").rglob("*.py")]:
        if p == ROOT / "iscd/core/config.py":
            continue
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in ("owned", "extra") and \
                    isinstance(node.value, ast.Name) and node.value.id in ("cfg", "c", "config"):
                offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}")
    assert not offenders, offenders


def test_section_reads_defaults_and_names_a_bad_key() -> None:
    cfg = C.loads("[acquisition]\nmax_pending = 17\n")
    opt = C.section(cfg, A.AcquisitionOptions)
    assert opt.max_pending == 17 and opt.read_timeout_s == A.AcquisitionOptions().read_timeout_s
    assert C.section(C.loads(""), A.AcquisitionOptions) == A.AcquisitionOptions()
    with pytest.raises(C.ConfigError, match=r"acquisition\.max_pending"):
        C.section(C.loads("[acquisition]\nmax_pending = 0\n"), A.AcquisitionOptions)
    with pytest.raises(TypeError):
        C.section(cfg, A.AcquisitionStats)  # not a config section
    assert cfg.with_keys("acquisition", resync_after=3).table("acquisition") == {"max_pending": 17, "resync_after": 3}
    assert cfg.table("acquisition") == {"max_pending": 17}  # with_keys made a copy


def test_a_second_owner_is_refused() -> None:
    with pytest.raises(ValueError, match="owned by"):
        @C.config_section("daemon")
        @dataclasses.dataclass(frozen=True)
        class Other:
            x: int = 0
    with pytest.raises(ValueError, match="not a config section"):
        C.config_section("eval")


def test_eval_table_is_no_longer_silently_accepted() -> None:
    with pytest.raises(C.ConfigError, match=r"eval: unknown section"):
        C.loads("[eval]\nanything = 1\n")


def test_config_check_validates_the_acquisition_table(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[acquisition]\nmax_pending = 0\n")
    assert main(["config", "--check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "acquisition.max_pending" in err and err.count("\n") == 1
    assert main(["config", "--describe"]) == 0
    out = capsys.readouterr().out
    assert all(f"[{n}]" in out for n in C.SECTION_NAMES)
    assert "  pairs_at_once = True" in out


def test_the_acquisition_table_reaches_every_acquisition_process(tmp_path: Path, monkeypatch) -> None:
    """The daemon hands [acquisition] to the process it starts (the keys passed --check and
    were never applied before); the run still decodes with them."""
    seen: list[A.AcquisitionOptions] = []
    orig = A.AcquisitionProcess.__init__

    def spy(self, *args, **kwargs):
        orig(self, *args, **kwargs)
        seen.append(self.options)

    monkeypatch.setattr(A.AcquisitionProcess, "__init__", spy)
    cfg = C.loads("[acquisition]\nread_timeout_s = 0.07\nmax_pending = 23\nresync_after = 5\n"
                  "[daemon]\nstats_interval_s = 0.5\n")
    d = Daemon(cfg, out=str(tmp_path / "out.jsonl"), duration_s=1.5, install_signals=False)
    assert d.acquisition_options.max_pending == 23
    stats = d.run()
    assert seen and all(o == A.AcquisitionOptions(read_timeout_s=0.07, max_pending=23, resync_after=5)
                        for o in seen)
    assert stats["pairs_decoded"] > 0


def test_finish_within_abandons_a_step_that_does_not_end_in_time() -> None:
    """The daemon's bounded stop (``[daemon] stop_demod_s``) is the decoder's own method now,
    not a walk through its private queue."""
    import threading
    import time

    from iscd.decode.stream import StreamDecoder

    dec = StreamDecoder(C.default_config(), async_demod="thread")
    release = threading.Event()
    dec._pool.submit(release.wait)  # the one pool thread busy
    dec._pending.append((dec._pool.submit(lambda: []), 0))  # queued behind it
    t0 = time.monotonic()
    out, abandoned = dec.finish_within(0.2)
    assert abandoned == 1 and out == [] and 0.15 < time.monotonic() - t0 < 5
    release.set()
    idle = StreamDecoder(C.default_config(), async_demod="thread")
    assert idle.finish_within(0.2) == ([], 0)
