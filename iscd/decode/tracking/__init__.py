"""Tracking: detecting the transmitter (:mod:`.detect`), following its LEDs frame by frame
and measuring their luminance (:mod:`.luminance`, compiled in :mod:`.follow_kernel`), the
tracking light map (:mod:`.track_kernel`). docs/receiver.md."""

from iscd.decode.tracking.luminance import SpotLuminance, roi_mean

__all__ = ["SpotLuminance", "roi_mean"]
