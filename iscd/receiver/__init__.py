"""The communication half of the receiver (docs/receiver.md).

Frames -> LED luminance (:mod:`~iscd.receiver.luminance`) -> packets
(:class:`~iscd.receiver.packets.PacketAssembler`: header search and symbol timing
(:mod:`~iscd.receiver.timing`), channel estimation (:mod:`~iscd.receiver.channel`),
decisions combining both cameras (:mod:`~iscd.receiver.decide`), Gray demapping and
CRC-32). LED detection and tracking live beside them (``detect``, ``track``).

    asm = PacketAssembler(cfg.transmitter, cfg.camera.fps, cfg.camera.exposure_s,
                          receiver_config(cfg))
    for packet in asm.push(frame_ids, t_s, L_left, L_right):
        print(packet.record())
"""

from iscd.receiver.luminance import SpotLuminance, roi_mean
from iscd.receiver.packets import Packet, PacketAssembler
from iscd.receiver.settings import ReceiverConfig, receiver_config

__all__ = ["Packet", "PacketAssembler", "ReceiverConfig", "SpotLuminance", "receiver_config",
           "roi_mean"]
