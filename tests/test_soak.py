"""The soak of issue 16 (benchmarks/soak.py): ``iscd run`` on the mock rig with camera
faults injected (stall, drop, duplicate, desync, the left and then the right camera
vanishing and returning), its process tree sampled from /proc.

* ``test_soak_short`` (CI, ~75 s of daemon): every fault kind once, 9 s apart. Built to
  hold on a busy 2-core machine: drops outside the fault windows are forgiven while
  the host's every core was >= 90 % busy or other processes held >= half a core
  (``soak.OTHERS_BUSY``; the packet check is then not asserted), and otherwise up to 1 % of the pairs (stray
  stalls of a shared VM; reported as a warning), >= 90 % of the packets outside the
  faults must come -- both only where the machine kept up before the first fault (on a host
  too slow for the rig they are reported as a warning, not asserted), CPU flatness is not asserted (a minute on a shared machine says little
  about it); private memory, fds, threads and the process count must be flat, no
  CRC-valid packet may carry a payload that was not sent, and the run must end cleanly.
* ``test_soak_one_hour`` (slow: ISCD_SLOW=1): 60 minutes, a fault every 150 s, every
  check of benchmarks/soak.py strict.

(The LED board is not part of these runs: the mock rig's transmitter is its scene and
``[board] emulate`` is off, so the daemon has no board to unplug.)
"""

from __future__ import annotations

import json
import os
import sys
import warnings
from pathlib import Path

import pytest

from benchmarks import soak

ROOT = Path(__file__).resolve().parents[1]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def _summary(d: Path) -> dict:
    return json.loads((d / "summary.json").read_text())


def test_fault_schedule_cycles_every_kind() -> None:
    f = soak.fault_schedule(75, 9, first_s=12)
    assert [x["name"] for x in f] == list(soak.KINDS)
    assert [x["frame"] for x in f] == [12000, 21000, 30000, 39000, 48000, 57000]
    text = soak.config_text(f, 2000)
    from iscd.core import config as C

    cfg = C.loads(text)
    assert [x.kind for x in cfg.rig.faults] == ["stall", "drop", "duplicate", "id_offset", "vanish", "vanish"]
    assert cfg.rig.faults[3].offset == 3 and cfg.rig.buffer_frames == 2000
    f2 = soak.fault_schedule(3600, 150)
    offsets = [x["offset"] for x in f2 if x["name"] == "desync"]
    assert offsets[:2] == [3, -3] and len(f2) == 24  # desyncs come back in step


def test_soak_short(tmp_path: Path) -> None:
    d = tmp_path / "soak"
    soak.run(d, 1.25, 9.0, first_s=12.0, warmup_s=8.0, sample_s=1.0, python=sys.executable, env=_env())
    s = _summary(d)
    c = s["checks"]
    assert s["faults"] == 6 and s["final"] is True
    assert c["clean_end"]["ok"], c["clean_end"]
    assert s["reopens"] == [1, 1] and s["resyncs"] >= 1  # both cameras came back, the desync was seen
    assert s["frames_dropped_in_faults"] >= 200  # the stall at least
    assert c["no_wrong_payload"]["ok"], c["no_wrong_payload"]
    assert s["packets_outside_faults"] >= 20
    if s["keeps_up"]:
        # where the drops fall and how many packets come say something only on a machine
        # that served the rig before the first fault (a real-time claim; the 1-hour form and
        # benchmarks/bench_daemon.py hold it strictly)
        # a few stray drops outside the faults on a shared VM (neighbours' steal time) are
        # reported, not failed: bounded to 1 % of the pairs; zero is the 1-hour form's claim
        stray = s["frames_dropped_outside_faults_host_not_saturated"]
        assert stray <= 0.01 * s["pairs_decoded"], c["drops_only_in_faults"]
        if stray:
            warnings.warn(f"soak: {stray} frames dropped outside the faults on a host that was not "
                          f"saturated: {c['drops_only_in_faults']['outside']}", stacklevel=1)
        if s["frames_dropped_outside_faults_host_saturated"]:
            warnings.warn(f"soak: {s['frames_dropped_outside_faults_host_saturated']} frames dropped outside the "
                          "faults while other work held the host: the packet check was not asserted", stacklevel=1)
        else:
            assert s["packets_outside_faults_decoded"] >= 0.9 * s["packets_outside_faults"], c["packets_outside_faults"]
    else:
        warnings.warn(f"soak: this machine dropped {s['frames_dropped_before_first_fault']} frames before "
                      "the first fault (it does not keep up with the mock rig): the drop and packet "
                      "checks were not asserted", stacklevel=1)
    for k in ("fds_flat", "threads_flat", "processes_same"):
        assert c[k]["ok"], (k, s["resources"])
    # memory: 75 s is short, and on a machine that falls behind the bounded queues (the
    # worker's blocks, the pipes) fill late in the run; asserted where the machine served
    # the rig and nothing else held it, else warned (the one-hour form asserts it always)
    if s["keeps_up"] and not s["frames_dropped_outside_faults_host_saturated"]:
        assert c["rss_flat"]["ok"], ("rss_flat", s["resources"])
    elif not c["rss_flat"]["ok"]:
        warnings.warn(f"soak: memory grew on a machine that did not keep up: {s['resources']}", stacklevel=1)


@pytest.mark.slow
def test_soak_one_hour(tmp_path: Path) -> None:
    d = tmp_path / "soak"
    soak.run(d, 60.0, 150.0, python=sys.executable, env=_env())
    s = _summary(d)
    assert s["ok"], {k: v for k, v in s["checks"].items() if not v["ok"]}
