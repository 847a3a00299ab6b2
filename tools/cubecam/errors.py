"""The one exception tree of cubecam.

Every error a user can cause (a bad option, a missing recording, a port in use, a board that
does not answer) is a :class:`CubecamError`; ``cubecam.cli.main`` prints its message on one
line and exits 1. It subclasses :class:`cubetrack.core.errors.CubetrackError`, so code that drives
both packages can catch one base.
"""

from cubetrack.core.errors import CubetrackError


class CubecamError(CubetrackError):
    """Base of every error cubecam raises on bad input or a failing peer."""


class EmulatorError(CubecamError):
    """The emulator cannot start: no frames, a port in use, a bad option."""


class ImprovError(CubecamError):
    """An Improv serial frame or RPC result is malformed."""


class SerialDeviceError(CubecamError):
    """A serial port cannot be opened, vanished, or the board on it does not answer."""


class ProvisionError(CubecamError):
    """The board answered but refused a setting or could not join the network."""


class FlashError(CubecamError):
    """PlatformIO is missing, its Spresense platform is missing, or a build/upload failed."""
