"""The daemon's overload policy: what it gives up, in which order, when it falls behind.

The cameras never wait: the acquisition writes every pair into the ring and, when the
ring is full, the oldest pair is dropped (a lost frame; :mod:`iscd.rig.ringbuffer`). Before
that happens the decoder sheds work, in this order, as the ring fills (its fill is the
measure of how far the frame loop is behind):

=====  ==================  ==================================================================
level  ring fill above     what is shed (cumulative)
=====  ==================  ==================================================================
0      --                  nothing: full service
1      ``led_fill``        per-LED range records (``range_leds``)
2      ``ranging_fill``    ranging on all but every ``ranging_every``-th frame
3      ``images_fill``     Rerun images (and the luminance plots)
=====  ==================  ==================================================================

Packets are never shed: the LEDs are followed and measured on every frame and every
block goes to the demodulation. A level is left when the fill falls below half of its
threshold (hysteresis, so the service does not flap), and full service returns once the
ring is nearly empty. Every shed is counted in the stats records: the decoder's
``led_ranges_shed`` and ``ranging_skipped`` (frames), this policy's ``shed_image_blocks``,
``overload_blocks``, ``overload_level`` (now) and ``overload_max_level``.

The policy is a pure function of the fills it is shown, block by block: no clock, no
threads (``tests/test_overload.py`` drives it with made-up fills).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class OverloadSettings:
    """Ring fills (shares of its capacity) at which each level starts; see module docstring."""

    led_fill: float = field(default=0.05, metadata={"lo": 0, "hi": 1, "doc": "shed per-LED ranges above this ring fill"})
    ranging_fill: float = field(default=0.15, metadata={"lo": 0, "hi": 1, "doc": "range only every ranging_every-th frame above this ring fill"})
    images_fill: float = field(default=0.35, metadata={"lo": 0, "hi": 1, "doc": "shed Rerun images above this ring fill"})
    ranging_every: int = field(default=4, metadata={"lo": 2, "hi": 1000, "doc": "frames between ranged frames while shedding ranging"})

    def __post_init__(self) -> None:
        if not self.led_fill <= self.ranging_fill <= self.images_fill:
            raise ValueError("overload: expected led_fill <= ranging_fill <= images_fill, got "
                             f"{self.led_fill}, {self.ranging_fill}, {self.images_fill}")


@dataclass(frozen=True)
class Service:
    """What one block gets: ``per_led`` ranges, ranging on every ``ranging_every``-th frame
    (1 = every frame), Rerun ``images``."""

    level: int
    per_led: bool
    ranging_every: int
    images: bool


class OverloadPolicy:
    """Chooses each block's :class:`Service` from the ring fill (see module docstring)."""

    def __init__(self, settings: OverloadSettings | None = None) -> None:
        self.settings = settings or OverloadSettings()
        s = self.settings
        self._starts = (s.led_fill, s.ranging_fill, s.images_fill)
        self.level = 0
        self.counters: dict[str, int] = {"shed_image_blocks": 0, "overload_level": 0,
                                         "overload_max_level": 0, "overload_blocks": 0}

    def _level_for(self, fill: float) -> int:
        """The level for ``fill`` (0..1), from the current one with hysteresis."""
        up = sum(fill > t for t in self._starts)
        if up >= self.level:
            return up
        # leave a level only once the fill is below half of its threshold
        lvl = self.level
        while lvl > 0 and fill < 0.5 * self._starts[lvl - 1]:
            lvl -= 1
        return max(lvl, up)

    def service(self, fill: float) -> Service:
        """The service for the next block, decoded while the ring is ``fill`` full
        (queued / capacity)."""
        self.level = self._level_for(max(0.0, float(fill)))
        c = self.counters
        c["overload_level"] = self.level
        c["overload_max_level"] = max(c["overload_max_level"], self.level)
        if self.level:
            c["overload_blocks"] += 1
        return Service(self.level, per_led=self.level < 1,
                       ranging_every=1 if self.level < 2 else self.settings.ranging_every,
                       images=self.level < 3)

    def shed_images(self) -> None:
        """Count a Rerun image pair not logged because of the overload."""
        self.counters["shed_image_blocks"] += 1
