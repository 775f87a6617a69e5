"""The typed output records (SPEC section 7, :mod:`iscd.core.records`): every record a live
run writes is one of them and has what SPEC section 7 promises for its type."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from iscd.core import config as C
from iscd.core.records import (RECORD_TYPES, PacketRecord, RangeFilteredRecord, RangeRecord, RecordError, StatsRecord,
                               check_record)
from iscd.outputs.jsonl import read_records
from iscd.service.daemon import Daemon


def test_to_json_order_and_extras() -> None:
    r = RangeRecord(tx=1, frame=7, t_s=0.007, z_m=30.5, disparity_px=10.2, sigma_m=0.03).to_json()
    assert list(r) == ["type", "tx", "frame", "t_s", "z_m", "disparity_px", "sigma_m"]
    assert check_record(r) == "range"
    # the decoder's shortcut makes the same dict, keys in the same order
    fast = RangeRecord.json_of(1, 7, 0.007, 30.5, 10.2, 0.03)
    assert fast == r and list(fast) == list(r)
    p = PacketRecord(tx=0, frame=3, t_s=0.003, crc_ok=True, payload_hex="ab", levels=[1, 2],
                     extra={"ser_hint": 0.0}).to_json()
    assert list(p)[-1] == "ser_hint" and check_record(p) == "packet"
    s = StatsRecord(tx=0, frame=-1, t_s=None, extra={"uptime_s": 0.5}).to_json()
    assert s["latency_ms_p99"] is None and check_record(s) == "stats"
    assert set(RECORD_TYPES) == {"range", "packet", "range_leds", "range_filtered", "stats"}
    # the JSON Lines writer writes a non-finite number as null: read back, it is still a record
    f = RangeFilteredRecord(tx=0, frame=1, t_s=0.001, z_m=30.0, sigma_m=0.1,
                            closing_speed_mps=float("nan")).to_json()
    assert check_record({**f, "closing_speed_mps": None}) == "range_filtered"
    assert StatsRecord.spec_fields()[:2] == ("frames_in", "frames_dropped")


@pytest.mark.parametrize("bad, msg", [
    ({"type": "range", "tx": 0, "frame": 1, "t_s": 0.0, "z_m": 1.0, "sigma_m": 0.1}, "no 'disparity_px'"),
    ({"type": "packet", "tx": 0, "frame": 1, "t_s": 0.0, "crc_ok": 1, "payload_hex": "", "levels": []}, "crc_ok"),
    ({"type": "stats", "tx": 0, "frame": True, "t_s": 0.0}, "frame"),
    ({"type": "hello", "tx": 0}, "unknown"),
])
def test_check_record_names_the_field(bad: dict, msg: str) -> None:
    with pytest.raises(RecordError, match=msg):
        check_record(bad)


def test_every_record_of_a_live_run_is_typed(tmp_path: Path) -> None:
    out = tmp_path / "out.jsonl"
    cfg = C.loads("[daemon]\nstats_interval_s = 0.5\n[ranging]\nkalman = true\nper_led = true\n"
                  "per_led_every_frames = 50\n")
    Daemon(cfg, out=str(out), duration_s=2.0, install_signals=False).run()
    recs = read_records(out)
    kinds = Counter(check_record(r) for r in recs)
    assert kinds["stats"] >= 2 and kinds["range"] > 100 and kinds["range_filtered"] > 0
    assert kinds["range_leds"] > 0
    assert recs[-1]["type"] == "stats" and recs[-1]["final"] is True
