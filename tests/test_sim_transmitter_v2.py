"""The simulator's transmitter sends air interface v2 (issue 14, stage 2): the
``[transmitter]`` keys ``air_interface``, ``fec``, ``payload_len`` read through the one codec
(iscd.core.airinterface_v2), their errors naming the key, and ``iscd config --describe``
listing them."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.core import airinterface_v2 as v2
from iscd.core.airinterface import AirInterface
from iscd.core.config import FEC_NAMES, ConfigError, config_from_dict, describe
from iscd.sim.transmitter import PacketSource


def _cfg(**tx: object) -> object:
    return config_from_dict({"transmitter": {"levels": 16, **tx}, "scene": {"seed": 7}})


def test_fec_names_are_the_codec_modes() -> None:
    assert FEC_NAMES == tuple(v2.FEC_MODES)


def test_v1_stays_the_default() -> None:
    src = PacketSource.from_config(_cfg())
    assert type(src.air) is AirInterface and src.period == 653


@pytest.mark.parametrize("payload_len", [0, 100])
def test_packet_source_sends_v2(payload_len: int) -> None:
    cfg = _cfg(air_interface="v2", fec="rs255_191", payload_len=payload_len, idle_symbols=5)
    src = PacketSource.from_config(cfg)
    air = src.air
    assert isinstance(air, v2.AirInterfaceV2) and air.fec == "rs255_191" and air.idle_symbols == 5
    if payload_len:
        assert air.payload_len == 100 and air.data_symbols < 600
    else:
        assert air.data_symbols == 600 and air.payload_len == 14321
    lv = src.levels(0, 3 * src.period)
    for p in range(3):
        pk = lv[p * src.period:(p + 1) * src.period]
        assert np.array_equal(pk, air.packet(src.payload(p)))
        hdr = v2.parse_header(v2.header_soft(pk[13:air.training_offset], 16), 64)
        rx = v2.AirInterfaceV2.from_header(hdr)
        assert rx.decode_data(pk[air.data_offset:air.packet_symbols]).payload == src.payload(p)
    assert src.payload(0) != src.payload(1)


def test_fixed_text_payload_is_padded_to_payload_len() -> None:
    cfg = config_from_dict({"transmitter": {"air_interface": "v2", "payload_len": 32},
                            "payload": {"source": "text", "value": "hello"}})
    src = PacketSource.from_config(cfg)
    assert src.payload(3) == b"hello".ljust(32, b"\0")
    with pytest.raises(ConfigError, match="payload.value"):
        PacketSource.from_config(config_from_dict({"transmitter": {"air_interface": "v2", "payload_len": 3},
                                                   "payload": {"source": "text", "value": "hello"}}))


@pytest.mark.parametrize("tx,key", [
    ({"air_interface": "v3"}, "transmitter.air_interface"),
    ({"fec": "rs255_200"}, "transmitter.fec"),
    ({"payload_len": -1}, "transmitter.payload_len"),
    ({"payload_len": 1 << 24}, "transmitter.payload_len"),
    ({"air_interface": "v2", "rows": 1, "cols": 1, "levels": 2, "data_symbols": 10}, "transmitter.data_symbols"),
    ({"air_interface": "v2", "training_symbols": 70000}, "transmitter.training_symbols"),
])
def test_config_errors_name_the_key(tx: dict, key: str) -> None:
    with pytest.raises(ConfigError) as e:
        config_from_dict({"transmitter": tx})
    assert str(e.value).startswith(key + ":") and "\n" not in str(e.value)


def test_describe_lists_the_keys() -> None:
    text = describe()
    for key in ("air_interface = 'v1'", "fec = 'rs255_223'", "payload_len = 0"):
        assert key in text
