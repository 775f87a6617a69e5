"""Hardware (and mock-hardware) drivers: cameras and the LED transmitter board.

Every camera backend implements :class:`iscd.drivers.base.Camera`. Hardware backends are
imported lazily so that the daemon starts without their libraries or devices.
"""
