"""The ``cubecam`` subcommands, one module each (see :mod:`cubecam.cli`)."""
