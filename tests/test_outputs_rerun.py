"""RerunView: save a .rrd, read it back with rerun.chunk.RrdReader, check entities and values."""

from __future__ import annotations

import socket
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from iscd.outputs import OutputError, RerunConfig, rerun_config
from iscd.outputs.rerun_view import RerunView, stat_group

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402


def read_rrd(path: Path) -> dict[str, dict[str, list[tuple[int | None, Any]]]]:
    """{entity: {component: [(frame, value), ...] sorted by frame}} of the recording store."""
    out: dict[str, dict[str, list[tuple[int | None, Any]]]] = defaultdict(lambda: defaultdict(list))
    for chunk in RrdReader(path).stream().to_chunks():
        rb = chunk.to_record_batch()
        names = rb.schema.names
        frames = rb.column("frame").to_pylist() if "frame" in names else [None] * rb.num_rows
        for n in names:
            if ":" not in n:
                continue  # row ids and timelines
            for f, v in zip(frames, rb.column(n).to_pylist()):
                out[chunk.entity_path][n].append((f, v))
    for comps in out.values():
        for rows in comps.values():
            rows.sort(key=lambda fv: -1 if fv[0] is None else fv[0])
    return out


def blueprint_views(path: Path) -> dict[str, str]:
    """{space origin: view class} of the blueprint store in the file."""
    r = RrdReader(path)
    (bp,) = r.blueprints()
    views = {}
    for chunk in r.stream(store=bp).to_chunks():
        rb = chunk.to_record_batch()
        if "ViewBlueprint:space_origin" in rb.schema.names:
            views[rb.column("ViewBlueprint:space_origin").to_pylist()[0][0]] = \
                rb.column("ViewBlueprint:class_identifier").to_pylist()[0][0]
    return views


def test_recording_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    path = tmp_path / "view.rrd"
    n_led, n_frames = 4, 120
    boxes = np.array([[100, 40, 110, 52], [120, 40, 130, 52], [100, 60, 110, 72], [120, 60, 130, 72]], float)
    lum_l = rng.uniform(0, 255, (n_frames, n_led))
    lum_r = lum_l / 4
    levels = rng.integers(1, 9, (600, n_led))
    view = RerunView(save=str(path), image_every=50, image_scale=0.5, fps=1000.0, frames_per_symbol=2.0)
    logged = []
    for f in range(n_frames):
        left = np.full((64, 160), f, np.uint8)
        if view.log_images(f, f / 1000, left, left // 2, boxes, boxes - (20, 0, 20, 0)):
            logged.append(f)
        view.log_luminance(np.array([f]), np.array([f / 1000]), lum_l[f:f + 1], lum_r[f:f + 1])
        view.log_record({"type": "range", "tx": 0, "frame": f, "t_s": f / 1000, "z_m": 30 + f / 100,
                         "disparity_px": 29.17 - f / 1000, "sigma_m": 0.05})
    view.log_levels(7, 0.007, levels)
    view.log_record({"type": "range", "tx": 0, "led": 3, "frame": 5, "t_s": 0.005, "z_m": 31.0,
                     "disparity_px": 28.2, "sigma_m": 0.2})
    for f, ok in ((10, True), (20, False), (30, True)):
        view.log_record({"type": "packet", "tx": 0, "frame": f, "t_s": f / 1000, "crc_ok": ok,
                         "payload_hex": "48656c6c6f", "levels": [1, 2]})
    view.log_record({"type": "stats", "tx": 0, "frame": 119, "t_s": 0.119, "frames_in": 120,
                     "frames_dropped": 2, "pairs_decoded": 118, "packets_ok": 2, "packets_bad": 1,
                     "latency_ms_p50": 3.5, "latency_ms_p99": 9.0, "ring_fill": 0.25, "ser": 1e-3,
                     "zmq_dropped": 0, "running": True, "note": "x"})
    view.log_record({"type": "range_leds", "tx": 0, "frame": 40, "t_s": 0.04, "n_valid": 2,
                     "z_m": [30.5, None, 30.7, None], "sigma_m": [0.1, None, 0.1, None]})
    view.log_record({"type": "range_filtered", "tx": 0, "frame": 41, "t_s": 0.041, "z_m": 30.4,
                     "sigma_m": 0.01, "closing_speed_mps": 11.1, "accepted": True})
    view.log_record({"type": "hello"})              # unknown types are ignored
    assert view.errors == 0
    view.close()
    view.close()                                    # idempotent

    data = read_rrd(path)
    assert logged == [0, 50, 100]                   # reduced rate
    img = data["/left/image"]
    assert [f for f, _ in img["Image:format"]] == logged
    fmt = img["Image:format"][0][1][0]
    assert (fmt["width"], fmt["height"]) == (80, 32)          # downscaled by 0.5
    assert [v[0][0] for _, v in img["Image:buffer"]] == logged  # pixel value = frame index
    assert data["/right/image"]["Image:buffer"][1][1][0][0] == 25
    centers = np.array(data["/left/leds"]["Boxes2D:centers"][0][1])
    np.testing.assert_allclose(centers, (boxes[:, :2] + boxes[:, 2:]) / 2 * 0.5)
    np.testing.assert_allclose(np.array(data["/right/leds"]["Boxes2D:half_sizes"][0][1]),
                               (boxes[:, 2:] - boxes[:, :2]) / 2 * 0.5)

    lum = data["/luminance/left"]["Scalars:scalars"]
    assert [f for f, _ in lum] == list(range(n_frames))      # every frame, batched
    np.testing.assert_allclose([v for _, v in lum], lum_l)
    np.testing.assert_allclose([v for _, v in data["/luminance/right"]["Scalars:scalars"]], lum_r)
    assert data["/luminance/left"]["SeriesLines:names"][0][1] == [f"led {i}" for i in range(n_led)]

    lv = data["/levels"]["Scalars:scalars"]
    assert [f for f, _ in lv] == [7 + 2 * k for k in range(600)]   # symbol k at frame + 2k
    np.testing.assert_array_equal([v for _, v in lv], levels)

    z = data["/range/z_m/tx0"]["Scalars:scalars"]
    np.testing.assert_allclose([v[0] for _, v in z], 30 + np.arange(n_frames) / 100)
    assert data["/range/z_m/tx0/led3"]["Scalars:scalars"] == [(5, [31.0])]
    assert data["/range/sigma_m/tx0"]["Scalars:scalars"][0] == (0, [0.05])
    assert data["/range/z_m/tx0/led0"]["Scalars:scalars"] == [(40, [30.5])]
    assert data["/range/z_m/tx0/led2"]["Scalars:scalars"] == [(40, [30.7])]
    assert "/range/z_m/tx0/led1" not in data              # null: no valid range
    assert data["/range_filtered/closing_speed_mps/tx0"]["Scalars:scalars"] == [(41, [11.1])]

    assert data["/packets/ok/tx0"]["Scalars:scalars"] == [(10, [1.0]), (30, [2.0])]
    assert data["/packets/bad/tx0"]["Scalars:scalars"] == [(20, [1.0])]
    texts = [v[0] for _, v in data["/log/packets"]["TextLog:text"]]
    assert texts[1] == "tx0 frame 20: CRC BAD, 5 B: 48656c6c6f"

    def stat(group: str, key: str) -> list[tuple[int | None, Any]]:
        return data[f"/stats/{group}/{key}"]["Scalars:scalars"]

    assert stat("frames", "frames_in") == [(119, [120.0])]
    assert stat("frames", "frames_dropped") == [(119, [2.0])]
    assert stat("latency", "latency_ms_p99") == [(119, [9.0])]
    assert stat("ring", "ring_fill") == [(119, [0.25])]
    assert stat("link", "ser") == [(119, [1e-3])]
    assert stat("packets", "packets_bad") == [(119, [1.0])]
    assert stat("outputs", "zmq_dropped") == [(119, [0.0])]
    assert not any("running" in e or "note" in e or "hello" in e for e in data)

    views = blueprint_views(path)
    assert views["left"] == views["right"] == "2D"
    for origin in ("luminance/left", "levels", "range/z_m", "packets", "stats/latency", "stats/ring"):
        assert views[origin] == "TimeSeries", origin


def test_stat_groups() -> None:
    assert [stat_group(k) for k in ("frames_in", "pairs_decoded", "latency_ms_p50", "ring_fill",
                                    "packets_ok", "ser", "goodput_bps", "jsonl_dropped", "cpu_cores", "rss_mb", "temp_c")] == \
        ["frames", "frames", "latency", "ring", "packets", "link", "link", "outputs", "process", "process",
         "other"]


def test_never_raises_into_the_daemon(tmp_path: Path) -> None:
    view = RerunView(save=str(tmp_path / "bad.rrd"))
    assert view.log_images(0, 0.0, "not an image", None) is None   # type: ignore[arg-type]
    view.log_luminance(np.arange(3), np.arange(3), np.ones((2, 5)), None)   # 3 frames, 2 rows
    view.log_record({"type": "range", "frame": "x"})
    assert view.errors == 3
    view.log_record({"type": "range", "tx": 0, "frame": 1, "t_s": 0.001, "z_m": 20.0})
    view.close()
    assert read_rrd(tmp_path / "bad.rrd")["/range/z_m/tx0"]["Scalars:scalars"] == [(1, [20.0])]


def test_disabled_without_sinks_is_a_no_op() -> None:
    view = RerunView()
    assert not view.enabled and not view.want_image(0)
    assert view.log_images(0, 0.0, np.zeros((4, 4), np.uint8), None) is None
    view.log_record({"type": "range", "frame": 0, "z_m": 1.0})
    view.close()
    assert view.errors == 0


def test_jpeg_images(tmp_path: Path) -> None:
    path = tmp_path / "j.rrd"
    img = (np.arange(64 * 64) % 251).astype(np.uint8).reshape(64, 64)
    with RerunView(save=str(path), image_scale=1.0, jpeg_quality=90) as view:
        assert view.log_images(0, 0.0, img, None)
    data = read_rrd(path)["/left/image"]
    assert data["EncodedImage:media_type"][0][1] == ["image/jpeg"]
    import cv2

    blob = np.array(data["EncodedImage:blob"][0][1][0], np.uint8)
    back = cv2.imdecode(blob, cv2.IMREAD_GRAYSCALE)
    assert back.shape == img.shape and np.abs(back.astype(int) - img).mean() < 4


def test_serve_binds_loopback_and_bad_save_path(tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    view = RerunView(serve=True, serve_port=port)
    try:
        assert view.serve_uri is not None and "127.0.0.1" in view.serve_uri
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            pass                                         # the gRPC server listens ...
        proc_tcp = Path("/proc/net/tcp")
        if proc_tcp.exists():                            # ... on loopback only, not 0.0.0.0
            listening = [ln.split()[1] for ln in proc_tcp.read_text().splitlines()[1:]
                         if ln.split()[3] == "0A" and ln.split()[1].endswith(f":{port:04X}")]
            assert listening == [f"0100007F:{port:04X}"], listening
    finally:
        view.close()
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        with pytest.raises(OutputError, match="cannot set up --serve.*cannot listen"):
            RerunView(serve=True, serve_port=busy.getsockname()[1])
    with pytest.raises(OutputError, match="cannot set up --save"):
        RerunView(save=str(tmp_path / "missing-dir" / "x.rrd"))


def test_rerun_config_section() -> None:
    from iscd.core.config import ConfigError, loads

    rc = rerun_config(loads('[rerun]\nimage_every = 25\nsave = "/tmp/x.rrd"\n'))
    assert rc.image_every == 25 and rc.save == "/tmp/x.rrd" and rc.serve_bind == RerunConfig.serve_bind
    with pytest.raises(ConfigError, match="rerun.image_scale"):
        rerun_config(loads("[rerun]\nimage_scale = 2.0\n"))


def test_command_line_flags_like_rerun_examples(tmp_path: Path) -> None:
    import argparse

    from iscd.outputs.rerun_view import DEFAULT_CONNECT_URL, add_rerun_arguments, rerun_view_from

    p = argparse.ArgumentParser()
    add_rerun_arguments(p)
    a = p.parse_args(["--connect"])
    assert a.connect == "" and not a.serve and a.save is None
    assert p.parse_args(["--connect", "rerun+http://10.0.0.2:9876/proxy"]).connect.startswith("rerun+http://10.")
    assert p.parse_args([]).connect is None
    assert RerunView.sink_names("", False, None) == [f"--connect {DEFAULT_CONNECT_URL}"]
    out = tmp_path / "flags.rrd"
    view = rerun_view_from(p.parse_args(["--save", str(out)]), RerunConfig(image_every=7), fps=500.0)
    assert view.enabled and view.image_every == 7 and view.fps == 500.0
    view.close()
    assert RrdReader(out).recordings()
    assert not rerun_view_from(p.parse_args([])).enabled       # nothing asked: disabled


def test_write_is_the_fanout_entry_and_shows_a_packets_levels(tmp_path: Path) -> None:
    """Through :class:`iscd.outputs.Outputs` the view gets records by ``write``: the record is
    logged and a packet's levels appear per LED, symbol k at frame + k * frames_per_symbol."""
    from iscd.outputs import Outputs

    path = tmp_path / "fan.rrd"
    levels = np.arange(1, 13).reshape(3, 4) % 8 + 1
    view = RerunView(save=str(path), fps=1000.0, frames_per_symbol=2.0, n_leds=4)
    outs = Outputs([view])
    outs.write({"type": "packet", "tx": 0, "frame": 40, "t_s": 0.040, "ok": True,
                "payload_hex": "00", "levels": levels.ravel().tolist()})
    outs.close()
    assert outs.counters()["output_errors"] == 0
    lv = read_rrd(path)["/levels"]["Scalars:scalars"]
    assert [f for f, _ in lv] == [40, 42, 44]
    np.testing.assert_array_equal([v for _, v in lv], levels)
