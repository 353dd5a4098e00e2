"""The `gsw` command line: watermark 3DGS models and images, read and identify marks, fingerprint copies, more.

Run `gsw <command> --help` for the options of each command. Each command group lives in its own module
(:mod:`gsw.cli.demo`, :mod:`gsw.cli.mark`, :mod:`gsw.cli.evaluate`, :mod:`gsw.cli.train`, :mod:`gsw.cli.render`,
:mod:`gsw.cli.registry`, :mod:`gsw.cli.export`, :mod:`gsw.cli.decoder`, :mod:`gsw.cli.fingerprint`) and adds its
sub-commands with ``register(subparsers)``; :func:`main` is the one place that turns an expected failure into one
line on stderr and exit status 2 (``gsw --debug ...`` shows the traceback instead).
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from gsw import __version__
from gsw.cli import decoder, demo, evaluate, export, fingerprint, mark, registry, render, train

#: Failures reported as ``gsw <command>: error: ...`` (exit status 2): bad input (ValueError, including JSON and
#: dataset errors), files (OSError), devices and decoder weights (RuntimeError), missing optional packages.
EXPECTED_ERRORS = (ValueError, OSError, RuntimeError, ImportError)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the `gsw` command."""
    parser = argparse.ArgumentParser(prog="gsw", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"gsw {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True)
    demo.register(sub)
    mark.register(sub)
    evaluate.register(sub)
    train.register(sub)
    render.register(sub)
    registry.register(sub)
    export.register(sub)
    decoder.register(sub)
    fingerprint.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `gsw` command: runs one command and returns its exit status."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except EXPECTED_ERRORS as err:
        if args.debug:
            raise
        text = " ".join(str(err).split()) or type(err).__name__
        print(f"gsw {args.command}: error: {text}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C: temporaries are already removed (gsw._atomic)
        if args.debug:
            raise
        print(f"gsw {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
