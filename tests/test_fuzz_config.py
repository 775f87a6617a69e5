"""Property-based fuzzing (hypothesis) of the two text files a user hands iscd: the TOML
config (:func:`iscd.core.config.loads` plus :func:`iscd.core.config.check_sections`, as ``iscd
run`` does) and the stereo calibration (:func:`iscd.calibration.io.loads_calibration`). Any text
gives a value or the module's own error (:class:`~iscd.core.config.ConfigError`,
:class:`~iscd.calibration.io.CalibrationError`), whose message is one line.

Bounds: config texts of up to ~40 keys drawn from the real schema (every section and key, plus
unknown ones) with values of every TOML type (integers up to 2**70, NaN, inf, strings,
arrays, tables); calibration texts up to ~4 KiB, made by mutating a valid file (numbers,
matrix sizes up to 10**9 claimed, types, deleted lines) or raw. CI runs a few dozen
derandomized cases per target; ``ISCD_FUZZ_EXAMPLES=N`` for a long run (docs/hardening.md).
"""

from __future__ import annotations

import dataclasses
import json
import os
import typing

import numpy as np
import pytest
from fuzzing import fuzz
from hypothesis import example, given
from hypothesis import strategies as st

from iscd.calibration.io import CalibrationError, StereoCalibration, dumps_calibration, loads_calibration
from iscd.cli.sections import OWNERS
from iscd.core import config as C
from iscd.sim.tomlout import _scalar as _toml_value  # the project's own TOML scalar writer


# --------------------------------------------------------------------------- TOML text of a table
def to_toml(doc: dict[str, dict[str, object]]) -> str:
    """``{section: {key: value}}`` as TOML text (values inline)."""
    return "".join(f"[{name}]\n" + "".join(f"{json.dumps(k)} = {_toml_value(v)}\n" for k, v in table.items())
                   for name, table in doc.items())


def _schema() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    hints = typing.get_type_hints(C.Config)
    for f in dataclasses.fields(C.Config):
        if f.name != "extra" and dataclasses.is_dataclass(hints[f.name]):
            out[f.name] = [g.name for g in dataclasses.fields(hints[f.name])]
    for name, cls in OWNERS.items():
        out[name] = [g.name for g in dataclasses.fields(cls)]
    return out


SCHEMA = _schema()
scalars = st.one_of(
    st.integers(-3, 3000), st.integers(-2**63, 2**63 - 1), st.floats(allow_nan=True, allow_infinity=True),
    st.floats(-1e6, 1e6), st.booleans(), st.text(max_size=12),
    st.sampled_from(["mock", "genicam", "v4l2", "texture", "text", "hex", "file", "left", "right", "master",
                     "", "/proc/nope", "iscd"]))
values = st.recursive(scalars, lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=6), c, max_size=3),
                      max_leaves=5)


@st.composite
def config_docs(draw: st.DrawFn) -> dict[str, dict[str, object]]:
    doc: dict[str, dict[str, object]] = {}
    for name in draw(st.lists(st.sampled_from([*SCHEMA, "nosuch"]), max_size=5, unique=True)):
        keys = SCHEMA.get(name, []) + ["bogus"]
        table: dict[str, object] = {}
        for k in draw(st.lists(st.sampled_from(keys), max_size=8, unique=True)):
            table[k] = draw(values)
        doc[name] = table
    return doc


def _load_config(text: str) -> None:
    try:
        cfg = C.loads(text, "fuzz.toml")
        C.check_sections(cfg)
    except C.ConfigError as e:
        assert "\n" not in str(e).strip(), str(e)


@fuzz(250)
@given(config_docs())
@example({"camera": {"fps": 1e-320}})
@example({"camera": {"fps": 2**63 - 1, "exposure_s": 1e-300}})
@example({"transmitter": {"symbol_rate_hz": 1e308, "pwm_hz": 1e308}})
@example({"scene": {"distance_m": 1e308}})
def test_config_loader(doc: dict[str, dict[str, object]]) -> None:
    _load_config(to_toml(doc))


@fuzz(80)
@given(st.text(max_size=400))
@example("[camera]\nfps = 1e400\n")
@example("a = " + "[" * 2000 + "]" * 2000)
def test_config_loader_raw_text(text: str) -> None:
    _load_config(text)


# --------------------------------------------------------------------------- calibration
GOOD = dumps_calibration(StereoCalibration.from_parameters(512, 512, 3500.0, baseline_m=0.25))
GOOD_LINES = GOOD.splitlines()
tokens = st.sampled_from(["0", "-1", "1e400", "nan", ".nan", "inf", "-.inf", "1e-320", "3", "9", "1000000000",
                          "abc", "[", "]", "{", "}", '"x"', "d", "f", "i", "u", "!!opencv-matrix", ":", "- ",
                          "2147483648", "-2147483649", "0x10", "%YAML:1.0", "---", "&a", "*a"])


@st.composite
def calibration_texts(draw: st.DrawFn) -> str:
    lines = list(GOOD_LINES)
    for _ in range(draw(st.integers(0, 6))):
        i = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["replace_token", "delete", "duplicate", "size", "truncate"]))
        if op == "delete":
            del lines[i]
        elif op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "truncate":
            lines[i] = lines[i][: draw(st.integers(0, len(lines[i])))]
        elif op == "size":  # claim another matrix size
            key = draw(st.sampled_from(["rows", "cols"]))
            lines = [ln.replace(f"{key}: 3", f"{key}: {draw(st.sampled_from(['0', '1', '4', '1000', '1000000000', '-3']))}")
                     if f"{key}: 3" in ln and draw(st.booleans()) else ln for ln in lines]
        else:
            parts = lines[i].split(" ")
            j = draw(st.integers(0, len(parts) - 1))
            parts[j] = draw(tokens)
            lines[i] = " ".join(parts)
        if not lines:
            break
    return "\n".join(lines) + "\n"


def _load_cal(text: str) -> None:
    try:
        cal = loads_calibration(text, "fuzz.yml")
    except CalibrationError as e:
        assert "\n" not in str(e), str(e)
        return
    assert cal.is_rectified and cal.image_width > 0 and cal.image_height > 0
    assert np.isfinite(cal.focal_px)


@fuzz(250)
@given(calibration_texts())
@example(GOOD.replace("rows: 3", "rows: 1000000000", 1))
@example(GOOD.replace("image_width: 512", "image_width: 99999999999", 1))
@example(GOOD.replace("   cols: 3\n", "   \n", 1))  # found: OpenCV read M1 without cols from the heap: abort
@example(GOOD.replace("   rows: 3\n", "", 1))
@example(GOOD.replace("   dt: d\n", "   dt: 3d\n", 1))
@example(GOOD.replace(" 0., 0., 1. ]", " 0., 0. ]", 1))
@example(GOOD.replace("data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]", "data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1.", 1))
def test_calibration_reader(text: str) -> None:
    _load_cal(text)


@fuzz(80)
@given(st.text(max_size=400))
@example("M1: !!opencv-matrix\n  rows: 100000\n  cols: 100000\n  dt: d\n  data: [1]\n")
@example("%YAML:1.0\n\U0010bd28")  # the last text before OpenCV's parser crashed the fuzz run (SIGSEGV/abort)
def test_calibration_reader_raw_text(text: str) -> None:
    _load_cal(text)


def test_calibration_file_size_is_bounded(tmp_path: "os.PathLike[str]") -> None:
    from pathlib import Path

    from iscd.calibration.io import MAX_CALIBRATION_BYTES, load_calibration

    p = Path(tmp_path) / "big.yml"
    p.write_text(GOOD + "#" * (MAX_CALIBRATION_BYTES + 1))
    with pytest.raises(CalibrationError, match="larger than"):
        load_calibration(p)


def test_calibration_text_outside_opencv_subset_never_reaches_opencv(monkeypatch: pytest.MonkeyPatch) -> None:
    """Regression: OpenCV's FileStorage parser aborted/segfaulted the whole fuzz run on malformed
    text (not reproducible alone: heap state). Such text is refused in Python, before cv2."""
    import iscd.calibration.io as io

    def boom(text: str, source: str) -> object:
        raise AssertionError("OpenCV's parser was reached")

    monkeypatch.setattr(io, "_read_storage", boom)
    for text in ("%YAML:1.0\n\U0010bd28", "image_width: [1, 2", "a: b: c\n", "M1: !!opencv-matrix\n  rows: {x\n",
                 "%YAML:1.0\nimage_width: 512\n\x00\n"):
        with pytest.raises(CalibrationError, match="not an OpenCV FileStorage YAML file"):
            loads_calibration(text, "t.yml")
    with pytest.raises(AssertionError, match="reached"):
        loads_calibration(GOOD, "t.yml")  # a good file does reach it


@pytest.mark.parametrize("mutation, message", [
    (("   cols: 3\n", ""), "without cols"),
    (("   rows: 3\n", ""), "without rows"),
    (("   dt: d\n", ""), "without dt"),
    (("   dt: d\n", "   dt: 3d\n"), "unsupported opencv-matrix dt"),
    ((" 0., 0., 1. ]", " 0., 0. ]"), "has 8 values"),
])
def test_malformed_matrix_blocks_are_refused_before_opencv(mutation: tuple[str, str], message: str,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """Regression (fuzzer finding): a matrix block without cols made OpenCV read uninitialised
    memory ("free(): invalid next size", the test process aborted)."""
    import iscd.calibration.io as io

    monkeypatch.setattr(io, "_read_storage", lambda *a: pytest.fail("OpenCV's parser was reached"))
    text = GOOD.replace(*mutation, 1)
    assert text != GOOD
    with pytest.raises(CalibrationError, match=message):
        loads_calibration(text, "t.yml")
