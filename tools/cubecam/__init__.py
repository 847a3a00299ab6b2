"""cubecam: device-side tools for cubetrack camera nodes.

- :mod:`cubecam.emulator`: serve a recording (or a folder of JPEGs) as camera nodes speaking
  the firmware's HTTP API (contracts §1), with fault injection for testing clients.
- :mod:`cubecam.improv` (the Improv codec) and :mod:`cubecam.link` (Improv and the line console on one
  serial port): the serial protocols (contracts §2).
- :mod:`cubecam.provision`, :mod:`cubecam.boards`, :mod:`cubecam.flash`: set up real boards.

The ``cubecam`` command is :func:`cubecam.cli.main`.
"""

__version__ = "0.1.0"
