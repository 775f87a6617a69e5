"""Physics simulator of the stereo image-sensor-communication link (docs/simulator.md).

:class:`Scene` renders synchronized left/right 8-bit frames of a PWM-M LED transmitter and
gives the ground truth (:class:`Truth`); the modules hold the pure numerical parts
(geometry, exposure integral, optics, sensor, background, level sources).
"""

from iscd.sim.scene import Scene
from iscd.sim.transmitter import ArraySource, LevelSource, PacketSource
from iscd.sim.truth import Truth

__all__ = ["ArraySource", "LevelSource", "PacketSource", "Scene", "Truth"]
