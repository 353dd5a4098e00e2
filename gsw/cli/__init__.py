"""The ``gsw`` command line (``gsw --help``; also ``python -m gsw``).

Each command group is a module with ``register(subparsers)``; :mod:`gsw.cli.main` assembles them. This
package imports nothing eagerly, so ``gsw.cli.decoder`` works without the compiled extension.
"""

from __future__ import annotations

from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``gsw`` command (see :func:`gsw.cli.main.main`)."""
    from gsw.cli.main import main as _main

    return _main(argv)


__all__ = ["main"]
