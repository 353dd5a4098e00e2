"""Thin wrapper over ``gsw decoder train`` (the pre-training lives in :mod:`gsw.decoder.pretrain`).

    python benchmarks/train_decoder.py --data ../shared/data/bsds500 --output out/decoders \
        --bits 32 48 64 --time-budget-s 330 --ft-s 25

takes the options of ``gsw decoder train --help``.
"""

from __future__ import annotations

import sys

from gsw.cli.main import main

if __name__ == "__main__":
    sys.exit(main(["decoder", "train", *sys.argv[1:]]))
