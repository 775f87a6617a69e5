"""The LED board speaks air interface v2 (issue 14): CONFIG ``flags`` = FLAG_AIR_V2 | fec id
<< 1; the emulator then sends v2 packets (PHY header, Reed-Solomon) of the loaded payload's
own length; ``iscd tx --air-interface v2 --fec ...`` drives it; the receiver's codec reads
back exactly what was loaded. A v1 board's rule (other flag bits refused) still holds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from iscd.cli.main import main
from iscd.core import airinterface_v2 as v2
from iscd.drivers.board import protocol as P
from iscd.drivers.board.emulator import Board, PtyEmulator

SMALL = """
[transmitter]
rows = 4
cols = 4
levels = 8
training_symbols = 8
data_symbols = 120
idle_symbols = 3
"""


def _ask(board: Board, ftype: int, payload: bytes = b"", seq: int = 1) -> P.Frame:
    (body,) = P.Deframer().feed(board.receive(P.encode_frame(ftype, seq, payload)))
    return P.parse_body(body)


def _read_back(board: Board, n_leds: int) -> tuple[v2.PhyHeader, v2.DataResult]:
    """Header and data of the 2nd packet on the board's LEDs, as a receiver reads them."""
    period = board.sequence().shape[0]
    lv = board.levels(period, period, n_leds)
    H = v2.header_symbols(n_leds)
    m = int(lv[:13].max())
    hdr = v2.parse_header(v2.header_soft(lv[13:13 + H], m), n_leds)
    air = v2.AirInterfaceV2.from_header(hdr)
    return hdr, air.decode_data(lv[air.data_offset:air.packet_symbols])


@pytest.mark.parametrize("fec", list(P.FEC_IDS))
def test_emulator_sends_v2_packets(fec: str) -> None:
    board = Board()
    cfg = P.BoardConfig(levels=8, rows=4, cols=4, flags=P.FLAG_AIR_V2 | (P.FEC_IDS.index(fec) << 1),
                        training_symbols=8, data_symbols=120, idle_symbols=3)
    assert cfg.air_interface == "v2" and cfg.fec == fec
    assert _ask(board, P.Command.SET_CONFIG, cfg.pack()).type == P.ReplyType.ACK
    payload = b"v2 over the board " * 3
    assert _ask(board, P.Command.LOAD_PAYLOAD, P.LoadChunk(0, len(payload), payload).pack()).type == P.ReplyType.ACK
    assert _ask(board, P.Command.START).type == P.ReplyType.ACK
    assert board.sequence().shape[0] == 13 + v2.header_symbols(16) + 8 + 120 + 3
    hdr, res = _read_back(board, 16)
    assert (hdr.fec, hdr.payload_len, hdr.data_symbols) == (fec, len(payload), 120)
    assert res.payload == payload


def test_v2_capacity_and_bad_flags_are_refused() -> None:
    board = Board()
    cfg = P.BoardConfig(levels=8, rows=4, cols=4, flags=P.FLAG_AIR_V2 | (3 << 1), training_symbols=8,
                        data_symbols=120)
    _ask(board, P.Command.SET_CONFIG, cfg.pack())
    cap = v2.AirInterfaceV2.for_capacity(120, levels=8, rows=4, cols=4, training_symbols=8, fec="rs255_191").payload_len
    r = _ask(board, P.Command.LOAD_PAYLOAD, P.LoadChunk(0, cap + 1, b"").pack())
    assert r.type == P.ReplyType.NAK and P.Nak.unpack(r.payload).arg == cap
    for flags in (0x08, 0x02, 0x80):  # unknown bits, a code without v2
        r = _ask(board, P.Command.SET_CONFIG, P.BoardConfig(levels=8, rows=4, cols=4, flags=flags).pack())
        nak = P.Nak.unpack(r.payload)
        assert r.type == P.ReplyType.NAK and nak.code == P.NakCode.BAD_PARAMETER and nak.arg == 3


def test_tx_air_interface_v2(capsys, tmp_path: Path) -> None:
    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL)
    with PtyEmulator() as emu:
        rc = main(["tx", "--port", emu.port, "--config", str(cfg), "--air-interface", "v2", "--fec", "rs255_191",
                   "--payload-text", "hello v2"])
        out, err = capsys.readouterr()
        assert rc == 0, err
        rep = json.loads(out.strip().splitlines()[-1])
        assert rep["config"]["air_interface"] == "v2" and rep["config"]["fec"] == "rs255_191"
        hdr, res = _read_back(emu.board, 16)
        assert hdr.fec == "rs255_191" and res.payload == b"hello v2"
        big = np.zeros(5000, np.uint8).tobytes().hex()
        rc = main(["tx", "--port", emu.port, "--config", str(cfg), "--air-interface", "v2", "--payload-hex", big])
        _, err = capsys.readouterr()
        assert rc == 2 and "v2 packet" in err and len(err.strip().splitlines()) == 1
