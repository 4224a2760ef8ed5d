"""The ``lelsonar`` command line: one module per command, dispatched by :mod:`lelsonar.cli.main`."""
