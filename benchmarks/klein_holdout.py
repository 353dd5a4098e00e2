"""Per-bit fairness of :class:`gsw.decoder.KleinReadout` on the held-out unmarked images (#22 must-show 3).

The hold-out half of ``../shared/data/unmarked`` (``gsw.decoder.null.is_holdout``: 85 photos, 59 manga pages), each
read once at its own size through ``KleinReadout(load_decoder(k))``; per bit length, the largest deviation of a bit's
P(1) from 1/2 and its p-value against a fair decoder's sampling noise (``max_dev_p_value``), over all images and per
kind. Nothing is fitted or chosen: the readout has no parameter.

    PYTHONPATH=. python benchmarks/klein_holdout.py --out benchmarks/results/klein_holdout.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from calibrate_null import DATA, ROOT
from gsw._atomic import atomic_write
from gsw.decoder import KleinReadout, load_decoder
from symmetric_readout import by_kind, logits, split


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--bits", type=int, nargs="+", default=[32, 48, 64])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "klein_holdout.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    hold, kinds = split(args.data, True)
    res: dict = {"holdout_images": len(hold), "threads": args.threads, "torch": torch.__version__, "bits": {}}
    for k in args.bits:
        read = logits(hold, KleinReadout(load_decoder(k)).eval())
        res["bits"][str(k)] = by_kind((read > 0).astype(float), kinds)
        print(k, json.dumps(res["bits"][str(k)]), flush=True)
    res["seconds"] = time.perf_counter() - t0
    with atomic_write(args.out, "w") as f:
        f.write(json.dumps(res, indent=2) + "\n")
    print("written", args.out)


if __name__ == "__main__":
    main()
