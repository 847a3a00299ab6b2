"""Command-line interfaces: one module per command (``add_arguments`` + ``run``, over a workflow
of :mod:`cubetrack.app`), ``main`` (the ``cubetrack`` command) and ``command`` (the parser and
the single error boundary, shared with ``cubecam``)."""
