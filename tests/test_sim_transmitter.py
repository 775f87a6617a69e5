"""Level sources: packets from the air interface, payload options, replayed arrays."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.core.config import ConfigError, default_config
from iscd.sim.transmitter import ArraySource, LevelSource, PacketSource
from iscd.sim.presets import override


def test_packets_back_to_back_with_random_payloads_random_access():
    src = PacketSource.from_config(default_config())
    air = src.air
    P = air.period_symbols
    assert isinstance(src, LevelSource)
    lv = src.levels(-3, 2 * P + 5)
    assert (lv[:3] == 1).all()
    np.testing.assert_array_equal(lv[3:3 + 13], air.header())
    np.testing.assert_array_equal(lv[3 + P:3 + P + 13 + 40], np.concatenate([air.header(), air.training()]))
    for p in (0, 1):
        body, ok = air.decode_data(lv[3 + p * P + air.data_offset: 3 + p * P + air.data_offset + 600])
        assert ok and body == src.payload(p)
    assert src.payload(0) != src.payload(1)
    # random access: a fresh source gives the same symbols anywhere
    np.testing.assert_array_equal(PacketSource.from_config(default_config()).levels(P + 100, P + 140),
                                  lv[3 + P + 100:3 + P + 140])
    # another seed, other payloads
    other = PacketSource.from_config(override(default_config(), scene={"seed": 2}))
    assert other.payload(0) != src.payload(0)


def test_fixed_payloads(tmp_path):
    cfg = override(default_config(), transmitter={"rows": 1, "cols": 1},
                   payload={"source": "text", "value": "hello road"})
    src = PacketSource.from_config(cfg)
    assert src.payload(0) == src.payload(7) == b"hello road".ljust(221, b"\0")
    cfg = override(cfg, payload={"source": "hex", "value": "00ff10"})
    assert PacketSource.from_config(cfg).payload(3)[:4] == b"\x00\xff\x10\x00"
    f = tmp_path / "p.bin"
    f.write_bytes(b"\x01" * 221)
    cfg = override(cfg, payload={"source": "file", "value": str(f)})
    assert PacketSource.from_config(cfg).payload(0) == b"\x01" * 221


@pytest.mark.parametrize("payload,msg", [
    ({"source": "hex", "value": "zz"}, "not a hex string"),
    ({"source": "file", "value": "/nonexistent/p.bin"}, "cannot read"),
    ({"source": "text", "value": "x" * 300}, "exceed"),
])
def test_bad_payloads_are_config_errors(payload, msg):
    cfg = override(default_config(), transmitter={"rows": 1, "cols": 1}, payload=payload)
    with pytest.raises(ConfigError, match=msg) as e:
        PacketSource.from_config(cfg)
    assert "payload.value" in str(e.value) and "\n" not in str(e.value)


def test_array_source():
    a = ArraySource(np.array([[2, 3], [4, 5]]))
    np.testing.assert_array_equal(a.levels(-1, 3), [[1, 1], [2, 3], [4, 5], [1, 1]])
    r = ArraySource(np.array([[2, 3], [4, 5]]), repeat=True)
    np.testing.assert_array_equal(r.levels(1, 4), [[4, 5], [2, 3], [4, 5]])
    with pytest.raises(ValueError):
        ArraySource(np.zeros((2, 2)))


def test_idle_symbols_between_packets():
    cfg = override(default_config(), transmitter={"rows": 1, "cols": 2, "idle_symbols": 7})
    src = PacketSource.from_config(cfg)
    air = AirInterface.from_config(cfg.transmitter)
    lv = src.levels(0, 2 * air.period_symbols)
    assert (lv[air.packet_symbols:air.period_symbols] == 1).all()
    np.testing.assert_array_equal(lv[air.period_symbols:air.period_symbols + 13], air.header())
