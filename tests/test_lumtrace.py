"""Luminance traces (iscd.eval.lumtrace): what the receiver's demodulator was fed in a motion
scene, written by the oracle, read back, and demodulated again to the same packets."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from iscd.core.config import default_config
from iscd.eval import lumtrace
from iscd.eval.oracle import run_oracle
from iscd.eval.suites import MOTION_CASES, motion_cfg
from iscd.eval.sweeps import ReceiverMode


@pytest.fixture(scope="module")
def traced(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    """One LED closing at 40 km/h under 0.5 px of engine vibration, randomized physics,
    short packets (``quick``); the oracle writes its trace."""
    case = next(c for c in MOTION_CASES if c.key == "1led-40kmh-0.5px")
    cfg, _ = motion_cfg(default_config(), case, 4242, quick=True, scene={"vibration_model": "engine", "background_motion": "whole"},
                        randomize=True)
    path = tmp_path_factory.mktemp("traces") / "scene.npz"
    res = run_oracle(cfg, case.packets, mode=ReceiverMode("diversity", "both"), block=16, genie=False,
                     trace_to=path, trace_label="1led-40kmh-0.5px-4242")
    return path, res


def test_the_trace_holds_what_the_demodulator_was_fed(traced: tuple[Path, object]) -> None:
    """The pushed luminance is the receiver's, frame for frame (the oracle's own record of
    it), the sent packets are the truth's, and the scores are the receiver's."""
    path, res = traced
    tr = lumtrace.load(path)
    assert tr.label == "1led-40kmh-0.5px-4242" and tr.steps[0] == ("new",)
    pushes = [st for st in tr.steps if st[0] == "push"]
    assert len(pushes) > 10
    ids = np.concatenate([st[1] for st in pushes])
    assert np.all(np.diff(ids) > 0)
    lum = res.luminance["receiver"]  # (2, frames, N): NaN where the receiver decoded nothing
    got = np.stack([np.concatenate([st[3] for st in pushes]), np.concatenate([st[4] for st in pushes])])
    assert np.array_equal(got, lum[:, ids], equal_nan=True)
    assert np.isfinite(got).mean() > 0.9
    # one LED: the followed centres each luminance was measured at (the phase attempt's)
    for side in (0, 1):
        cen = np.concatenate([st[5][side] for st in pushes])
        assert cen.shape == (ids.size, 1, 2) and np.isfinite(cen).mean() > 0.9
        assert np.array_equal(np.isfinite(cen[:, 0, 0]), np.isfinite(got[side, :, 0]))
    assert [p.index for p in tr.sent] == [p.index for p in res.packets]
    assert all(p.levels.shape == (tr.transmitter.data_symbols, 1) for p in tr.sent)
    assert all(1 <= p.levels.min() and p.levels.max() <= tr.transmitter.levels for p in tr.sent)
    for sc, po in zip(tr.captured, res.packets):
        st = po.stages["receiver"]
        assert (sc.found, sc.crc_ok, sc.errors) == (st.found, st.crc_ok, st.errors)


def test_demodulated_again_it_gives_the_receivers_packets(traced: tuple[Path, object]) -> None:
    """With the trace's own settings the packets come out as the run had them (every
    score); other settings reach the demodulator (a header contrast no packet has: none
    is found)."""
    path, _ = traced
    tr = lumtrace.load(path)
    assert lumtrace.redemodulate(tr) == tr.captured
    assert any(s.found for s in tr.captured)
    strict = lumtrace.redemodulate(tr, lumtrace._with_receiver_keys(tr.receiver, ["min_contrast=1e9"]))
    assert [s.index for s in strict] == [s.index for s in tr.captured] and not any(s.found for s in strict)


def test_the_command_line_reports_and_bad_input_is_one_line(traced: tuple[Path, object],
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = traced
    assert lumtrace.main([str(path.parent)]) == 0
    out = capsys.readouterr().out
    n = sum(s.delivered for s in lumtrace.load(path).captured)
    assert f"in all: {n} of 2 delivered bit-exact (the runs that wrote the traces: {n})" in out
    for argv, message in (([str(path), "--receiver", "channel_window_symbols=-4"], "channel_window_symbols"),
                          ([str(path), "--receiver", "nonsense"], "expected KEY=VALUE"),
                          ([str(path.parent / "absent.npz")], "no such file")):
        assert lumtrace.main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1 and err.startswith("lumtrace:")


def test_damaged_files_are_one_clear_error(traced: tuple[Path, object], tmp_path: Path) -> None:
    path, _ = traced
    cut = tmp_path / "cut.npz"
    cut.write_bytes(path.read_bytes()[:2000])  # a crash while copying
    with pytest.raises(lumtrace.TraceError, match="not a readable trace"):
        lumtrace.load(cut)
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(lumtrace.TraceError, match="not a trace"):
        lumtrace.load(other)
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    meta = json.loads(str(data["meta"]))
    meta["format"] = 99
    newer = tmp_path / "newer.npz"
    np.savez(newer, **{**data, "meta": np.array(json.dumps(meta))})
    with pytest.raises(lumtrace.TraceError, match="format 99"):
        lumtrace.load(newer)
    # written under a temporary name first: no partial file is left under the name asked for
    assert not list(path.parent.glob("*.part"))


def test_a_trace_without_centres_still_reads(traced: tuple[Path, object], tmp_path: Path) -> None:
    """A trace written before the centres were kept (its pushes have none) reads and
    demodulates as it was (no phase attempt)."""
    path, _ = traced
    tr = lumtrace.load(path)
    old = lumtrace.Trace(tr.label, tr.transmitter, tr.receiver, tr.fps, tr.exposure_s, tr.sent,
                         [st[:5] if st[0] == "push" else st for st in tr.steps], tr.captured)
    back = lumtrace.load(lumtrace.save(old, tmp_path / "old.npz"))
    assert all(st[5] is None for st in back.steps if st[0] == "push")
    assert [s.index for s in lumtrace.redemodulate(back)] == [s.index for s in tr.captured]
