"""``python -m gsw``: the same as the ``gsw`` command."""

import sys

from gsw.cli import main

if __name__ == "__main__":
    sys.exit(main())
