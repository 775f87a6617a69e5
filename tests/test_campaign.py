"""``iscd campaign`` (issue 17): a campaign of simulated recordings on a LocalCluster of two
workers gives, per recording, the figures of ``iscd replay`` run alone; a re-run does no
work; a corrupt recording is one failed row and the others stay right; ``iscd eval`` on the
runner gives the serial results; bad input is one line and exit 2.

The recordings are short (400 pairs of 128x128 px, a 4x4 array with 60-symbol packets) so
that the module costs some 30 s; speed is measured in ``benchmarks/bench_campaign.py``.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest

from benchmarks.bench_campaign import FRAMES, N_RECORDINGS, SMALL, make_recordings, write_manifest
from fakes import cli, one_error_line

TIMING_KEYS = ("wall_s", "pairs_per_s")
"""Fields of the stats record that measure time, not the recording."""


def copies(recordings: list[Path], n: int, into: Path) -> list[Path]:
    """Copies of the first ``n`` recordings in ``into`` (to change or corrupt)."""
    out = []
    for r in recordings[:n]:
        shutil.copytree(r, into / r.name)
        out.append(into / r.name)
    return out


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return make_recordings(tmp_path_factory.mktemp("recordings"))


@pytest.fixture(scope="module")
def runner2() -> Any:
    """A LocalCluster of 2 worker processes (one thread each) for the module's campaigns."""
    from iscd.campaign.runner import Runner

    with Runner(workers=2, say=lambda _m: None) as r:
        yield r


@pytest.fixture(scope="module")
def campaign12(recordings: list[Path], runner2: Any, tmp_path_factory: pytest.TempPathFactory) -> Any:
    """The 12 recordings' campaign, run once: (result, out folder, manifest)."""
    from iscd.campaign.campaign import run_campaign

    root = tmp_path_factory.mktemp("campaign12")
    manifest = write_manifest(root / "campaign.toml", recordings)
    res = run_campaign(manifest, root / "out", runner=runner2, say=lambda _m: None)
    return res, root / "out", manifest


def replay_alone(capsys: pytest.CaptureFixture[str], rec: Path, out: Path) -> dict[str, Any]:
    """``iscd replay REC --out OUT`` in this process, then its figures as the summary counts them."""
    from iscd.campaign.rows import FIGURES, figures, read_records
    from iscd.core.config import load

    rc, _, err = cli(capsys, "replay", str(rec), "--out", str(out), "--no-progress")
    assert rc == 0, err
    f = figures(read_records(out), load(rec / "config.toml"), rec)
    return {k: f[k] for k in FIGURES}


def without_timing(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k not in TIMING_KEYS} for r in records]


def test_the_summary_equals_iscd_replay_alone_on_each_recording(campaign12: Any, recordings: list[Path],
                                                                 capsys: pytest.CaptureFixture[str],
                                                                 tmp_path: Path) -> None:
    from iscd.campaign.rows import FIGURES, read_records
    from iscd.campaign.summary import read_summary

    res, out, _ = campaign12
    assert res.failed == [] and len(res.submitted) == N_RECORDINGS
    table = read_summary(out / "summary.parquet")
    assert [r["name"] for r in table] == [r.name for r in recordings]  # manifest order
    with open(out / "summary.csv") as f:
        assert len(f.read().strip().splitlines()) == 1 + N_RECORDINGS
    delivered = 0
    for rec, row in zip(recordings, table):
        alone = replay_alone(capsys, rec, tmp_path / f"{rec.name}.jsonl")
        assert {k: row[k] for k in FIGURES} == alone, rec.name
        # and record for record what iscd replay wrote (the stats' timings aside)
        assert without_timing(read_records(out / "tasks" / f"{rec.name}.jsonl")) == \
            without_timing(read_records(tmp_path / f"{rec.name}.jsonl"))
        stats = read_records(tmp_path / f"{rec.name}.jsonl")[-1]
        assert (row["pairs"], row["packets_ok"], row["ranges"]) == \
            (stats["pairs_decoded"], stats["packets_ok"], stats["ranges"])
        assert row["status"] == "ok" and row["pairs"] == FRAMES and row["packets_sent"] >= 1
        assert row["range_mae_m"] is not None and row["range_mae_m"] < 0.5
        delivered += row["packets_delivered"]
    assert delivered >= N_RECORDINGS - 2  # the short recordings decode (not a test of the receiver)
    report = (out / "report.md").read_text()
    assert all(r.name in report for r in recordings) and "campaign.svg" in report
    svg = ET.parse(out / "campaign.svg").getroot()  # well-formed; a name under each task's bars
    assert [t.text for t in svg.iter("{http://www.w3.org/2000/svg}text")][-N_RECORDINGS:] == [r.name for r in recordings]


def test_a_finished_campaign_run_again_does_no_work(campaign12: Any, runner2: Any) -> None:
    from iscd.campaign.campaign import run_campaign

    res, out, manifest = campaign12
    before = {p.name: p.stat().st_mtime_ns for p in (out / "tasks").iterdir()}
    again = run_campaign(manifest, out, runner=runner2, say=lambda _m: None)
    assert again.submitted == []
    assert all(r["reused"] and r["status"] == "ok" for r in again.results)
    assert {p.name: p.stat().st_mtime_ns for p in (out / "tasks").iterdir()} == before
    assert [r["figures"] for r in again.results] == [r["figures"] for r in res.results]


def test_a_touched_input_is_hashed_again_and_a_changed_one_decoded_again(recordings: list[Path], runner2: Any,
                                                                         campaign12: Any, tmp_path: Path) -> None:
    from iscd.campaign.campaign import run_campaign

    recs = copies(recordings, 2, tmp_path)
    manifest = write_manifest(tmp_path / "m.toml", recs)
    first = run_campaign(manifest, tmp_path / "out", runner=runner2, say=lambda _m: None)
    assert first.failed == []
    jsonl = tmp_path / "out" / "tasks" / f"{recs[0].name}.jsonl"
    mtime = jsonl.stat().st_mtime_ns
    (recs[0] / "config.toml").touch()  # same content, new stamp: the worker hashes, no decoding
    cfg = recs[1] / "config.toml"
    cfg.write_text(cfg.read_text() + "\n# changed\n")  # new content: decoded again
    second = run_campaign(manifest, tmp_path / "out", runner=runner2, say=lambda _m: None)
    assert second.submitted == [recs[0].name, recs[1].name]
    assert [r["reused"] for r in second.results] == [True, False]
    assert jsonl.stat().st_mtime_ns == mtime
    assert second.results[1]["identity"] != first.results[1]["identity"]
    from iscd.campaign.rows import FIGURES

    assert [second.results[1]["figures"][k] for k in FIGURES] == \
        [first.results[1]["figures"][k] for k in FIGURES]  # a comment changes no figure
    forced = run_campaign(manifest, tmp_path / "out", runner=runner2, say=lambda _m: None, force=True)
    assert forced.submitted == [recs[0].name, recs[1].name]
    assert [r["reused"] for r in forced.results] == [False, False]  # decoded again, on the workers too
    assert jsonl.stat().st_mtime_ns != mtime


def test_one_corrupt_recording_is_a_failed_row_and_the_others_are_right(recordings: list[Path], runner2: Any,
                                                                        campaign12: Any, tmp_path: Path) -> None:
    from iscd.campaign.campaign import run_campaign
    from iscd.campaign.rows import FIGURES
    from iscd.campaign.summary import read_summary

    recs = copies(recordings, 4, tmp_path)
    bad = recs[1] / "left.iscr"
    data = bytearray(bad.read_bytes())
    data[:64] = b"\xff" * 64  # the header destroyed
    bad.write_bytes(bytes(data))
    manifest = write_manifest(tmp_path / "m.toml", recs)
    res = run_campaign(manifest, tmp_path / "out", runner=runner2, say=lambda _m: None)
    rows = read_summary(tmp_path / "out" / "summary.parquet")
    good = {r["name"]: r for r in read_summary(campaign12[1] / "summary.parquet")}
    assert [r["status"] for r in rows] == ["ok", "failed", "ok", "ok"]
    assert [r["name"] for r in res.failed] == [recs[1].name]
    err = rows[1]["error"]
    assert err and "\n" not in err and "left.iscr" in err, err
    assert all(rows[1][k] is None for k in FIGURES)
    assert not (tmp_path / "out" / "tasks" / f"{recs[1].name}.jsonl").exists()
    for r in (rows[0], rows[2], rows[3]):
        assert {k: r[k] for k in FIGURES} == {k: good[r["name"]][k] for k in FIGURES}
    assert "## Failed" in (tmp_path / "out" / "report.md").read_text()
    # a failed task is run again on the next run; the good ones are not
    again = run_campaign(manifest, tmp_path / "out", runner=runner2, say=lambda _m: None)
    assert again.submitted == [recs[1].name]


def test_a_simulated_point_is_rendered_on_its_worker_and_scored(runner2: Any, tmp_path: Path) -> None:
    from iscd.campaign.campaign import run_campaign

    (tmp_path / "small.toml").write_text(SMALL.format(distance=30))
    manifest = tmp_path / "m.csv"
    manifest.write_text("kind,name,config,frames,seed\n# a comment row\nsimulate,p30,small.toml,300,5\n")
    res = run_campaign(manifest, tmp_path / "out", runner=runner2, say=lambda _m: None)
    (r,) = res.results
    assert r["status"] == "ok", r["error"]
    f = r["figures"]
    assert f["pairs"] == 300 and f["packets_sent"] == 1 and f["ser"] is not None
    assert 29.0 < f["range_median_m"] < 31.0
    assert not list((tmp_path / "out" / "tasks").glob("*.rec*"))  # the rendering is not kept


def test_eval_on_the_runner_gives_the_serial_results(runner2: Any) -> None:
    from iscd.campaign.evalplan import run_plan_on
    from iscd.core.config import default_config
    from iscd.eval.suites import EvalPlan, run_plan

    plan = EvalPlan(suites=("comms", "ranging"), quick=True, comms_distances=(60.0,), ranging_distances=(60.0,),
                    frames=120, methods=("iscd", "poc"))
    serial = run_plan(default_config(), plan).as_dict()
    spread = run_plan_on(runner2, default_config(), plan).as_dict()

    def strip(o: Any) -> Any:  # wall times aside
        if isinstance(o, dict):
            return {k: strip(v) for k, v in o.items() if k != "seconds"}
        return [strip(v) for v in o] if isinstance(o, list) else o
    assert len(serial["comms"]) == 4 and len(serial["ranging"]) == 1  # PWM-8 and OOK, two modes each
    assert json.dumps(strip(spread), sort_keys=True) == json.dumps(strip(serial), sort_keys=True)


# ----------------------------------------------------------------------------- bad input


def free_port() -> int:
    """A TCP port free on loopback now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize("case", ["missing", "toml", "unknown_key", "no_path", "csv_column", "suffix", "empty"])
def test_a_bad_manifest_is_one_line_and_exit_2(case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                               recordings: list[Path]) -> None:
    m = tmp_path / ("m.csv" if case == "csv_column" else "m.txt" if case == "suffix" else "m.toml")
    text, want = {
        "missing": (None, "no such manifest"),
        "toml": ("[[recording]\nleft = 1", "not valid TOML"),
        "unknown_key": (f'[[recording]]\nleft = "{recordings[0]}"\nlft = "x"\n', "unknown key 'lft'"),
        "no_path": ('[[recording]]\nleft = "nowhere/left.iscr"\nright = "nowhere/right.iscr"\n',
                    "no such file or folder"),
        "csv_column": ("name,left,speed\nx,y,z\n", "unknown column 'speed'"),
        "suffix": ("x", ".toml or .csv"),
        "empty": ("[defaults]\nblock = 32\n", "nothing to run"),
    }[case]
    if text is not None:
        m.write_text(text)
    rc, _, err = cli(capsys, "campaign", str(m), "--out", str(tmp_path / "out"))
    line = one_error_line(err, "campaign")
    assert rc == 2 and want in line, line


def test_an_unreachable_scheduler_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                         recordings: list[Path],
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from iscd.campaign import runner

    monkeypatch.setattr(runner, "CONNECT_TIMEOUT_S", 2.0)
    manifest = write_manifest(tmp_path / "m.toml", recordings[:1])
    rc, _, err = cli(capsys, "campaign", str(manifest), "--out", str(tmp_path / "out"),
                     "--scheduler", f"tcp://127.0.0.1:{free_port()}")
    line = one_error_line(err, "campaign")
    assert rc == 2 and "--scheduler" in line and "cannot connect" in line, line


def test_manifest_paths_are_relative_to_it_and_defaults_apply(tmp_path: Path, recordings: list[Path]) -> None:
    from iscd.campaign.manifest import load_manifest

    rec = recordings[0]
    (tmp_path / "sub").mkdir()
    m = tmp_path / "sub" / "m.toml"
    m.write_text(f'[defaults]\nblock = 32\nconfig = "{rec / "config.toml"}"\n\n'
                 f'[[recording]]\nname = "pair"\nleft = "{rec / "left.iscr"}"\nright = "{rec / "right.iscr"}"\n'
                 f'truth = "{rec}"\n\n[[recording]]\nleft = "../{Path(os.path.relpath(rec, tmp_path)).as_posix()}"\n')
    a, b = load_manifest(m)
    assert (a.name, a.block, a.config, a.truth) == ("pair", 32, str(rec / "config.toml"), str(rec))
    assert (b.name, b.block, b.config, b.truth, b.left) == (rec.name, 32, None, str(rec), str(rec))
    assert set(b.inputs()) >= {"left/left.iscr", "left/right.iscr", "left/config.toml", "truth/truth.npz"}
    assert a.params() == {**b.params()}  # the paths are not parameters


def _fails_on_odd(x: int) -> int:
    if x % 2:
        raise ValueError(f"odd {x}")
    return x


def test_a_task_that_raises_becomes_its_error_result_and_the_others_go_on(runner2: Any) -> None:
    out = runner2.map(_fails_on_odd, [0, 1, 2, 3], error_result=lambda i, e: f"#{i}: {e}")
    assert out == [0, "#1: odd 1", 2, "#3: odd 3"]
    with pytest.raises(ValueError, match="odd 1"):  # without error_result the caller sees it
        runner2.map(_fails_on_odd, [1])


def _worker_settings() -> tuple[Any, ...]:
    import dask

    return tuple(dask.config.get(k) for k in LEAN_KEYS)


LEAN_KEYS = ("distributed.worker.profile.enabled", "distributed.admin.tick.interval",
             "distributed.admin.system-monitor.interval", "distributed.worker.memory.monitor-interval")


def test_the_local_cluster_runs_without_its_background_samplers_and_this_process_keeps_its_settings(
        runner2: Any) -> None:
    import dask

    from iscd.campaign.runner import LOCAL_CLUSTER_CONFIG

    want = tuple(LOCAL_CLUSTER_CONFIG[k] for k in LEAN_KEYS)
    assert set(runner2.client.run(_worker_settings).values()) == {want}  # each worker got them
    assert runner2.cluster.scheduler._tick_interval == 0.5  # the in-process scheduler too
    # and this process's own settings are the defaults again (the whole section intact)
    assert dask.config.get("distributed.worker.profile.enabled") is True
    assert dask.config.get("distributed.admin.tick.interval") == "20ms"
    assert dask.config.get("distributed.comm.timeouts.connect")


def test_range_figures_do_not_depend_on_the_order_of_the_records() -> None:
    """A loaded machine can emit range records out of frame order (the frame loop's and the
    worker's): the summary's sums are taken in frame order, so the figures are the same to
    the last bit whatever order the records came in."""
    import numpy as np

    from iscd.campaign.rows import figures
    from iscd.core.config import default_config

    rng = np.random.default_rng(5)
    z = rng.lognormal(3.0, 2.0, 997)  # (ranges of many magnitudes: the sum order shows in the last bits)
    recs = [{"type": "range", "frame": int(k), "z_m": float(v)} for k, v in enumerate(z)]
    a = figures(recs, default_config())
    b = figures(list(rng.permutation(np.array(recs, dtype=object))), default_config())
    assert a["ranges"] == 997
    assert {k: v for k, v in a.items() if k.startswith("range")} == {k: v for k, v in b.items() if k.startswith("range")}
