"""Thin wrapper over ``gsw decoder export`` (the export lives in :mod:`gsw.decoder.pretrain.export`).

    python benchmarks/export_decoders.py out/decoders --data ../shared/data/bsds500 \
        --report benchmarks/results/decoder --refit-whitening --force
    python benchmarks/export_decoders.py --shipped --data ../shared/data/bsds500 \
        --report benchmarks/results/decoder --force

takes the options of ``gsw decoder export --help``.
"""

from __future__ import annotations

import sys

from gsw.cli.main import main

if __name__ == "__main__":
    sys.exit(main(["decoder", "export", *sys.argv[1:]]))
