"""The ``gsw`` command line (``gsw --help``; also ``python -m gsw``)."""

from gsw.cli.main import main

__all__ = ["main"]
