"""The LED transmitter board: serial protocol v1, host driver, emulator and USB discovery.

* :mod:`iscd.drivers.board.protocol` — framing (COBS, CRC-16), message layouts; pure, no I/O.
* :mod:`iscd.drivers.board.client` — :class:`BoardClient`, the host driver on a pyserial port.
* :mod:`iscd.drivers.board.emulator` — the board's side in Python (the firmware reference) and
  a pty runner; its ``levels()`` feeds the simulator's transmitter.
* :mod:`iscd.drivers.board.discovery` — find boards by USB VID:PID (pyusb + pyserial).
* :mod:`iscd.drivers.board.settings` — the ``[board]`` config section.

The protocol is documented for firmware authors in ``docs/board-protocol.md``.
"""
