"""ZmqPublisher: the records on a loopback ZeroMQ socket, topic filtering, drops counted, binds checked."""

from __future__ import annotations

import json

import pytest
import zmq

from iscd.outputs import OutputError
from iscd.outputs.socket import ZmqPublisher, is_local_endpoint

RECORDS = [
    {"type": "range", "tx": 0, "frame": 10, "t_s": 0.01, "z_m": 30.1, "disparity_px": 29.2, "sigma_m": 0.05},
    {"type": "packet", "tx": 0, "frame": 3, "t_s": 0.003, "crc_ok": True, "payload_hex": "00ff",
     "levels": [1, 2, 8]},
    {"type": "stats", "tx": 0, "frame": 999, "t_s": 1.0, "frames_in": 1000, "frames_dropped": 0},
    {"type": "range", "tx": 1, "frame": 11, "t_s": 0.011, "z_m": float("nan"), "disparity_px": 1.0,
     "sigma_m": 0.1},
]


@pytest.fixture
def ctx():
    c = zmq.Context()
    yield c
    c.destroy(linger=0)   # closes sockets a failed test left open


def test_endpoint_locality() -> None:
    for ok in ("tcp://127.0.0.1:5556", "tcp://localhost:5556", "tcp://[::1]:5556", "tcp://lo:5556",
               "tcp://127.0.0.1:*", "ipc:///run/iscd/records.sock", "inproc://x"):
        assert is_local_endpoint(ok), ok
    for bad in ("tcp://*:5556", "tcp://0.0.0.0:5556", "tcp://192.168.1.5:5556", "tcp://eth0:5556",
                "tcp://[::]:5556", "pgm://eth0;239.192.1.1:5555"):
        assert not is_local_endpoint(bad), bad
    with pytest.raises(OutputError, match="transport://address"):
        is_local_endpoint("127.0.0.1:5556")


def test_refuses_remote_bind_unless_allowed(ctx: zmq.Context) -> None:
    with pytest.raises(OutputError, match="not loopback") as e:
        ZmqPublisher("tcp://0.0.0.0:*", context=ctx)
    assert "\n" not in str(e.value)
    with ZmqPublisher("tcp://0.0.0.0:*", allow_remote=True, context=ctx) as pub:
        assert pub.endpoint.startswith("tcp://0.0.0.0:")


def test_port_in_use_is_a_one_line_error(ctx: zmq.Context) -> None:
    with ZmqPublisher("tcp://127.0.0.1:*", context=ctx) as pub:
        with pytest.raises(OutputError, match="cannot bind"):
            ZmqPublisher(pub.endpoint, context=ctx)


def test_subscriber_gets_the_records_it_subscribed_to(ctx: zmq.Context) -> None:
    with ZmqPublisher("tcp://127.0.0.1:*", context=ctx) as pub:
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.connect(pub.endpoint)
        sub.setsockopt(zmq.SUBSCRIBE, b"range")
        sub.setsockopt(zmq.SUBSCRIBE, b"packet")
        assert pub.wait_for_subscribers(2, timeout_s=10)
        for r in RECORDS:
            assert pub.write(r)
        got = []
        while sub.poll(2000):
            topic, body = sub.recv_multipart()
            got.append((topic.decode(), json.loads(body)))
            if len(got) == 3:
                break
        sub.close()
    want = [(r["type"], json.loads(json.dumps(r).replace("NaN", "null"))) for r in RECORDS
            if r["type"] != "stats"]
    assert got == want           # in order, exactly the JSONL payload, stats filtered out
    assert pub.sent == 4 and pub.dropped == 0


def test_stalled_subscriber_never_blocks_drops_are_counted(ctx: zmq.Context) -> None:
    with ZmqPublisher("tcp://127.0.0.1:*", hwm=20, context=ctx) as pub:
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.RCVHWM, 20)
        sub.setsockopt(zmq.RCVBUF, 4096)
        sub.connect(pub.endpoint)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        assert pub.wait_for_subscribers(1, timeout_s=10)
        n = 20_000                                   # the subscriber reads nothing meanwhile
        rec = {"type": "range", "tx": 0, "frame": 0, "t_s": 0.0, "z_m": 30.0, "pad": "x" * 200}
        results = [pub.write(rec) for _ in range(n)]
        assert pub.sent + pub.dropped == n and pub.sent == sum(results)
        assert pub.dropped > 0                       # queues + TCP buffers hold fewer than n
        received = 0
        while received < pub.sent and sub.poll(2000):
            sub.recv_multipart()
            received += 1
        sub.close()
    assert received == pub.sent                     # no silent loss: what was not counted arrives
    assert pub.counters()["zmq_dropped"] == pub.dropped


def test_write_after_close_and_bad_record(ctx: zmq.Context) -> None:
    pub = ZmqPublisher("tcp://127.0.0.1:*", context=ctx)
    assert pub.write(RECORDS[0]) and pub.sent == 0          # nobody listens: nothing encoded or sent
    sub = ctx.socket(zmq.SUB)
    sub.connect(pub.endpoint)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    assert pub.wait_for_subscribers(1, timeout_s=10)
    assert not pub.write({"type": "x", "bad": object()})
    pub.close()
    pub.close()
    assert not pub.write(RECORDS[0])
    assert pub.dropped == 2 and pub.errors == 1
