"""Session 32's bad-input audit of the command line: each case below was a traceback, a hang,
exit status 0 on bad input or an error that did not name the bad file/key/option; now it is
one line on stderr naming it and exit status 2 (or, for a closed stdout pipe, exit 1 and no
traceback).

The ``iscd run`` case must stop before the daemon is built (the ``no_daemon`` fixture).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fakes import cli, one_error_line
from iscd.core.config import ConfigError, load

SMALL = """\
[transmitter]
rows = 1
cols = 1
levels = 4
training_symbols = 10
data_symbols = 40
[camera]
width = 64
height = 64
"""


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 40-frame 64x64 'iscd simulate' recording (left.iscr, right.iscr, config, calibration)."""
    from iscd.cli.main import main

    d = tmp_path_factory.mktemp("audit")
    (d / "small.toml").write_text(SMALL)
    assert main(["-q", "simulate", "--config", str(d / "small.toml"), "--out", str(d / "sim"),
                 "--frames", "40"]) == 0
    return d / "sim"


def _toml(tmp: Path, name: str, text: str) -> Path:
    p = tmp / name
    p.write_text(text)
    return p


# --------------------------------------------------------------------------- config: owned tables
def test_config_check_owned_table_error_names_the_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # before: "daemon.rotate_mb: expected ..." without the file ([camera] errors named it)
    cfg = _toml(tmp_path, "c.toml", "[daemon]\nrotate_mb = -1\n")
    rc, _, err = cli(capsys, "config", "--check", str(cfg))
    assert rc == 2
    line = one_error_line(err, "config")
    assert f"{cfg}: daemon.rotate_mb:" in line


def test_run_owned_table_error_names_the_file(tmp_path: Path, no_daemon: None,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    cfg = _toml(tmp_path, "c.toml", "[board]\nport = 5\n")
    rc, _, err = cli(capsys, "run", "--duration", "1", "--config", str(cfg))
    assert rc == 2
    assert f"{cfg}: board.port:" in one_error_line(err, "run")


def test_section_error_names_the_file_once(tmp_path: Path) -> None:
    from iscd.core import config as C
    from iscd.decode.ranging.config import RangingSettings

    cfg = load(_toml(tmp_path, "c.toml", "[ranging]\nnope = 1\n"))
    assert cfg.source == str(tmp_path / "c.toml")
    assert cfg.with_keys("daemon", out="x").source == cfg.source  # carried over
    with pytest.raises(ConfigError, match=r"c\.toml: ranging\.nope: unknown key") as e:
        C.section(cfg, RangingSettings)
    assert str(e.value).count("c.toml") == 1
    assert "source" not in C.to_dict(cfg)  # not a field: not in recordings' metadata nor hashes


def test_config_that_is_a_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # before: "cannot read config file: [Errno 21] Is a directory: '...'"
    rc, _, err = cli(capsys, "config", "--check", str(tmp_path))
    assert rc == 2
    assert one_error_line(err, "config").endswith(f"{tmp_path}: is a folder, not a config file")


# --------------------------------------------------------------------------- replay
def test_replay_swapped_cameras_refused(sim: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # before: exit 0, 0 packets, 0 ranges, not a word
    out = tmp_path / "o.jsonl"
    rc, _, err = cli(capsys, "replay", str(sim / "right.iscr"), str(sim / "left.iscr"), "--config",
                     str(sim / "config.toml"), "--out", str(out), "--no-progress")
    assert rc == 2
    assert "swap LEFT and RIGHT" in one_error_line(err, "replay")
    assert not out.exists()


def test_replay_swapped_with_allow_mismatch_is_a_warning(sim: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    rc, _, err = cli(capsys, "replay", str(sim / "right.iscr"), str(sim / "left.iscr"), "--config",
                     str(sim / "config.toml"), "--out", str(tmp_path / "o.jsonl"), "--no-progress",
                     "--allow-mismatch")
    assert rc == 0
    assert "iscd replay: warning: " in err and "swap LEFT and RIGHT" in err


def test_replay_missing_left_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # before: "give LEFT and RIGHT recordings, or a folder made by 'iscd simulate'"
    rc, _, err = cli(capsys, "replay", str(tmp_path / "nope"), "--out", str(tmp_path / "o.jsonl"))
    assert rc == 2
    assert one_error_line(err, "replay").endswith(f"{tmp_path / 'nope'}: no such file or folder")


def test_replay_bad_receiver_key_names_the_file(sim: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    cfg = _toml(tmp_path, "c.toml", (sim / "config.toml").read_text() + "\n[receiver]\nfoo = 1\n")
    rc, _, err = cli(capsys, "replay", str(sim), "--config", str(cfg), "--out", str(tmp_path / "o.jsonl"),
                     "--no-progress")
    assert rc == 2
    assert f"{cfg}: receiver.foo: unknown key" in one_error_line(err, "replay")


# --------------------------------------------------------------------------- simulate
def test_simulate_empty_out_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    # before: --out '' rendered into the current folder, exit 0
    monkeypatch.chdir(tmp_path)
    rc, _, err = cli(capsys, "simulate", "--out", "", "--frames", "2")
    assert rc == 2
    assert "--out: the path is empty" in one_error_line(err, "simulate")
    assert list(tmp_path.iterdir()) == []


def test_simulate_more_than_the_disk_holds_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # before: wrote until the disk was full (or for hours: 10^10 frames, 327680 GB)
    out = tmp_path / "big"
    rc, _, err = cli(capsys, "simulate", "--out", str(out), "--frames", "10000000000")
    assert rc == 2
    assert "GB free" in one_error_line(err, "simulate")
    assert not out.exists()  # refused before anything was made (it left an empty folder before)


def test_simulate_refused_for_space_keeps_the_recording_it_would_replace(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # before: --overwrite deleted the old recording, then refused for lack of space
    out = tmp_path / "rec"
    assert cli(capsys, "simulate", "--out", str(out), "--frames", "2")[0] == 0
    before = sorted(p.name for p in out.iterdir())
    rc, _, err = cli(capsys, "simulate", "--out", str(out), "--frames", "10000000000", "--overwrite")
    assert rc == 2 and "GB free" in one_error_line(err, "simulate")
    assert sorted(p.name for p in out.iterdir()) == before and "left.iscr" in before


# --------------------------------------------------------------------------- eval
@pytest.mark.parametrize("key", ["distance_m", "seed"])
def test_eval_scene_key_the_cases_set(key: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # before: TypeError: chapter3_cfg() got multiple values for argument 'distance_m'
    rc, _, err = cli(capsys, "eval", "--suite", "motion", "--quick", "--scene", f"{key}=3",
                     "--out", str(tmp_path / "ev"))
    assert rc == 2
    assert f"--scene {key}:" in one_error_line(err, "eval")


@pytest.mark.parametrize("argv, message", [
    (["--distances", ""], "--distances: expected a comma-separated list, got ''"),  # before: the defaults, exit 0
    (["--out", ""], "--out: the path is empty"),  # before: wrote the report into the current folder
])
def test_eval_empty_option_values(argv: list[str], message: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    out = [] if "--out" in argv else ["--out", str(tmp_path / "ev")]
    rc, _, err = cli(capsys, "eval", "--suite", "comms", "--quick", *argv, *out)
    assert rc == 2
    assert message in one_error_line(err, "eval")
    assert list(tmp_path.iterdir()) == []


def test_eval_bad_receiver_key_names_the_file_before_any_point(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    cfg = _toml(tmp_path, "c.toml", "[receiver]\nfoo = 1\n")
    rc, _, err = cli(capsys, "eval", "--quick", "--config", str(cfg), "--out", str(tmp_path / "ev"))
    assert rc == 2
    assert f"{cfg}: receiver.foo: unknown key" in one_error_line(err, "eval")


@pytest.mark.parametrize("address", ["bogus", "http://host:1", "tcp://127.0.0.1:abc", "inproc://x",
                                     "tcp://127.0.0.1:99999"])
def test_scheduler_address_refused_at_once(address: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # before: a Client made of it failed, and its clean-up printed a TimeoutError traceback 20 s later
    rc, _, err = cli(capsys, "eval", "--quick", "--scheduler", address, "--out", str(tmp_path / "ev"))
    assert rc == 2
    assert f"--scheduler {address}: not a scheduler address" in one_error_line(err, "eval")


def test_check_address_accepts_good_addresses() -> None:
    from iscd.campaign.runner import check_address

    for a in ("tcp://127.0.0.1:8786", "tcp://[::1]:8786", "tls://head:8786"):
        check_address(a, a)


# --------------------------------------------------------------------------- campaign
def test_campaign_manifest_that_is_a_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # before: "DIR: no such manifest file"
    rc, _, err = cli(capsys, "campaign", str(tmp_path), "--out", str(tmp_path / "out"))
    assert rc == 2
    assert "is a folder, not a manifest file" in one_error_line(err, "campaign")


# --------------------------------------------------------------------------- calibrate
BOARD = ["--left", "nope/l*.png", "--right", "nope/r*.png", "--board", "9x6", "--square", "0.025"]


@pytest.mark.parametrize("argv, message", [
    (["--alpha", "5"], "--alpha must be -1 or in 0..1"),  # before: accepted, exit 0
    (["--alpha", "nan"], "--alpha must be -1 or in 0..1"),
    (["--outlier-floor", "nan"], "--outlier-floor must be"),
    (["--outlier-factor", "inf"], "--outlier-factor must be"),
    (["--max-epipolar-px", "nan"], "--max-epipolar-px must be"),  # before: RECALIBRATE, exit 1
    (["--max-transfer-px", "-1"], "--max-transfer-px must be"),
    (["--max-scale-error", "0"], "--max-scale-error must be"),
    (["--pairs", "0"], "--pairs must be at least 1"),  # before: "no pairs were taken"
    (["--steady-px", "-1"], "--steady-px must be"),
    (["--steady-frames", "0"], "--steady-frames must be at least 1"),
    (["--max-seconds", "nan"], "--max-seconds must be"),
])
def test_calibrate_option_out_of_range(argv: list[str], message: str, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    rc, _, err = cli(capsys, "calibrate", *BOARD, "--out", str(tmp_path / "rig.yml"), *argv)
    assert rc == 2
    assert message in one_error_line(err, "calibrate")


@pytest.mark.parametrize("where", ["out_under_a_file", "report_is_a_file", "report_under_a_file",
                                   "save_pairs_is_a_file"])
def test_calibrate_output_path_refused_before_the_work(where: str, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    # before: a traceback (FileExistsError, NotADirectoryError) after calibrating
    f = tmp_path / "f"
    f.write_text("x")
    argv = {"out_under_a_file": ["--out", str(f / "rig.yml")],
            "report_is_a_file": ["--out", str(tmp_path / "rig.yml"), "--report", str(f)],
            "report_under_a_file": ["--out", str(tmp_path / "rig.yml"), "--report", str(f / "rep")],
            "save_pairs_is_a_file": ["--out", str(tmp_path / "rig.yml"), "--save-pairs", str(f)]}[where]
    rc, _, err = cli(capsys, "calibrate", *BOARD, *argv)
    assert rc == 2
    line = one_error_line(err, "calibrate")
    assert str(f) in line and ("is a file" in line)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


@pytest.fixture(scope="module")
def board_pairs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from iscd.calibration.synthetic import make_pairs

    folder = tmp_path_factory.mktemp("pairs")
    make_pairs(7, seed=5).write(folder)
    return folder


@pytest.mark.parametrize("what", ["calibration", "report"])
def test_calibrate_write_failure_is_one_line(what: str, board_pairs: Path, tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    # before: FileNotFoundError traceback (e.g. --out /proc/x/rig.yml), after the calibration
    import iscd.calibration.io
    import iscd.calibration.report

    def fail(*_a: object, **_k: object) -> None:
        raise OSError(28, "No space left on device")

    if what == "calibration":
        monkeypatch.setattr(iscd.calibration.io, "save_calibration", fail)
    else:
        monkeypatch.setattr(iscd.calibration.report, "write_report", fail)
    out = tmp_path / "rig.yml"
    rc, _, err = cli(capsys, "-q", "calibrate", "--left", str(board_pairs / "left_*.png"), "--right",
                     str(board_pairs / "right_*.png"), "--board", "9x6", "--square", "0.08", "--out", str(out))
    assert rc == 2
    line = one_error_line(err, "calibrate")
    assert "No space left on device" in line
    assert (f"--out {out}: cannot write there" in line if what == "calibration"
            else line.startswith(f"iscd calibrate: error: wrote {out}, but not the report"))


# --------------------------------------------------------------------------- tx
@pytest.mark.parametrize("argv, message", [
    (["--timeout", "nan"], "--timeout must be > 0 and <= 10 s"),  # before: "within nan s", exit 1
    (["--timeout", "inf"], "--timeout must be > 0 and <= 10 s"),  # before: hung on a silent board
    (["--timeout", "0"], "--timeout must be > 0 and <= 10 s"),
    (["--retries", "1000000000"], "--retries must be in 0..20"),  # before: hung
    (["--retries", "-1"], "--retries must be in 0..20"),
])
def test_tx_link_options_out_of_range(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    rc, _, err = cli(capsys, "tx", "--port", "loop://", "--status", *argv)
    assert rc == 2
    assert message in one_error_line(err, "tx")


@pytest.mark.parametrize("value", ["nan", "-1", "inf"])
def test_tx_emulate_duration_out_of_range(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    # before: nan and -1 served for no time and exited 0
    rc, _, err = cli(capsys, "tx", "--emulate", "--status", f"--duration={value}")
    assert rc == 2
    assert "--duration must be a finite number of seconds >= 0" in one_error_line(err, "tx")


# --------------------------------------------------------------------------- python -m iscd.eval.lumtrace
def _trace(tmp: Path, **meta: object) -> Path:
    from iscd.core.config import TransmitterConfig
    from iscd.decode.comms.settings import ReceiverConfig
    from iscd.eval.lumtrace import Trace, save

    path = save(Trace("t", TransmitterConfig(rows=1, cols=1), ReceiverConfig(), 1000.0, 0.001, []), tmp / "t.npz")
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    m = json.loads(str(data["meta"]))
    for k, v in meta.items():
        m[k] = {**m[k], **v} if isinstance(v, dict) else v
    data["meta"] = np.array(json.dumps(m))
    np.savez(path, **data)
    return path


@pytest.mark.parametrize("meta, message", [
    ({"transmitter": {"rows": "a"}}, "transmitter.rows: expected an integer"),  # before: TypeError in the demodulator
    ({"transmitter": {"levels": 3}}, "transmitter.levels: expected one of"),  # before: AirInterfaceError traceback
    ({"fps": float("nan")}, "camera.fps: expected a finite number"),  # before: ValueError traceback
    ({"fps": 0}, "camera.fps: expected a number > 0"),
])
def test_lumtrace_damaged_settings_are_one_line(meta: dict, message: str, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    from iscd.eval.lumtrace import main

    path = _trace(tmp_path, **meta)
    assert main([str(path)]) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"lumtrace: {path}: a damaged trace (") and message in lines[0]


def test_lumtrace_undamaged_trace_still_reads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from iscd.eval.lumtrace import main

    assert main([str(_trace(tmp_path))]) == 0
    assert "in all: 0 of 0 delivered" in capsys.readouterr().out


# --------------------------------------------------------------------------- a closed stdout
def test_closed_stdout_pipe_is_no_traceback(monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    # before: 'iscd config --describe | head' ended in a BrokenPipeError traceback
    import iscd.cli.commands.config as config_cmd

    def describe(_args: object) -> int:
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(config_cmd, "run", describe)
    rc, _, err = cli(capsys, "config", "--describe")
    assert rc == 1
    assert err == ""
