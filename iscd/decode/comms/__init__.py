"""The communication half of the receiver (docs/receiver.md).

Frames -> LED luminance (:mod:`~iscd.decode.tracking.luminance`) -> packets
(:class:`~iscd.decode.comms.packets.PacketAssembler`: header search and symbol timing
(:mod:`~iscd.decode.comms.timing`), channel estimation (:mod:`~iscd.decode.comms.channel`),
decisions combining both cameras (:mod:`~iscd.decode.comms.decide`), Gray demapping and
CRC-32). LED detection, following and luminance are :mod:`iscd.decode.tracking`.

    asm = PacketAssembler(cfg.transmitter, cfg.camera.fps, cfg.camera.exposure_s,
                          receiver_config(cfg))
    for packet in asm.push(frame_ids, t_s, L_left, L_right):
        print(packet.record())
"""

from iscd.decode.comms.packets import Packet, PacketAssembler
from iscd.decode.comms.settings import ReceiverConfig, receiver_config

__all__ = ["Packet", "PacketAssembler", "ReceiverConfig", "receiver_config"]
