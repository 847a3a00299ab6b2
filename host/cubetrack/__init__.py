"""cubetrack: indoor robot tracking with Wi-Fi camera nodes and an ArUco cube.

The package is a one-way pipeline (see docs/architecture.md):
source -> detect -> estimate -> fuse -> sink, with calibrate, simulate and evaluate beside it.
Importing it does nothing but define names: no logging setup, no files, no globals.
"""

import logging

from cubetrack.core.errors import CubetrackError

__all__ = ["CubetrackError", "__version__"]
__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
