"""Command-line interfaces: one module per command (``add_arguments`` + ``run``), and ``main``,
the single error boundary."""
