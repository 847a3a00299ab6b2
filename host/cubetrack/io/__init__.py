"""File formats of the contracts (docs/contracts.md), one module per format.

Each module has a ``read_*``/``write_*`` pair (or a reader and a writer class) and raises a
:class:`cubetrack.core.errors.CubetrackError` subclass whose message names the file and says what a
valid entry looks like.
"""
