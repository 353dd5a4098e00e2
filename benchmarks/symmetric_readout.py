"""A readout that is fair per bit on unmarked images: the sign of ``D(x) - D(t(x))`` for a symmetry ``t`` (#22).

A measurement only (``gsw.extract`` is unchanged). The shipped decoders read each bit as the sign of a logit
``D(x)``; on unmarked photos and drawings those bits lean one way (BENCHMARKS.md, #22: max |P(1) - 1/2| 0.30 / 0.19
/ 0.29 on the held-out photos for 32 / 48 / 64 bits, p < 1e-3 against a fair decoder). If ``t`` is a symmetry of
the image population (a flip, a half turn: a flipped photo is as likely as the photo), the bits of
``D(x) - D(t(x))`` are fair per bit on that population by construction for any decoder, whatever it leans to.

1. **Choice of t on the calibration half** (``gsw.decoder.null.is_holdout`` false; sun80, urban100, manga109,
   read as given at 1x): among the horizontal flip, the vertical flip and the half turn, the one with the smallest
   largest per-bit deviation, per bit length.
2. **Per-bit deviation on the hold-out half** (never used for the choice), direct and for every ``t`` (the chosen
   one marked), per kind, against a fair decoder's sampling noise
   (:func:`gsw.decoder.pretrain.evaluation.max_dev_p_value`).
3. **Marked images**: ``--marked N`` hold-out photos watermarked by :func:`gsw.embed_images` (the optimisation
   encoder, default settings, one random message per bit length; made for the direct readout) and read both ways:
   how much of the mark the differential readout keeps without being embedded for it.
4. ``klein``: ``D(x) - D(h(x)) - D(v(x)) + D(r(x))`` (h, v: the flips, r: the half turn), which each flip negates:
   fair per bit on a population symmetric under either flip, with no t to choose (hold-out and marked images).

    PYTHONPATH=. python benchmarks/symmetric_readout.py --out benchmarks/results/symmetric_readout.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from calibrate_null import DATA, ROOT, photo_files
from gsw._atomic import atomic_write
from recentre_bias import deviation
from gsw.decoder.zoo import load_decoder
from gsw.mark.scales import read_images

SYMMETRIES = {"hflip": lambda im: im.flip(-1), "vflip": lambda im: im.flip(-2),
              "rot180": lambda im: im.flip(-1).flip(-2)}


def logits(images: list[torch.Tensor], decoder) -> np.ndarray:
    """[N, k] logits of each image read once, at its own size."""
    return np.stack([r.logits[0].numpy() for r in read_images(images, decoder, factors=(1.0,))])


def klein(direct: np.ndarray, transformed: dict) -> np.ndarray:
    """``D(x) - D(h(x)) - D(v(x)) + D(r(x))``: negated by the horizontal flip and by the vertical flip alike, so
    fair per bit on a population symmetric under either one (no choice of t)."""
    return direct - transformed["hflip"] - transformed["vflip"] + transformed["rot180"]


def by_kind(bits: np.ndarray, kinds: np.ndarray) -> dict:
    out = {"all": deviation(bits)}
    for k in sorted(set(kinds)):
        out[k] = deviation(bits[kinds == k])
    return out


def split(data: Path, holdout: bool) -> tuple[list[torch.Tensor], np.ndarray]:
    from gsw.data.images import read_image

    files = [(n, k) for n, k in photo_files(data, holdout) if not n.startswith("bsds500")]
    return [read_image(data / n)[:3] for n, _ in files], np.array([k for _, k in files])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--bits", type=int, nargs="+", default=[32, 48, 64])
    ap.add_argument("--marked", type=int, default=8, help="hold-out photos to watermark (0: none)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--skip-calibration", action="store_true", help="only the hold-out half (no choice of t)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "symmetric_readout.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    cal, cal_kinds = split(args.data, False)
    hold, hold_kinds = split(args.data, True)
    res: dict = {"calibration_images": len(cal), "holdout_images": len(hold), "threads": args.threads, "bits": {}}
    for k in args.bits:
        dec = load_decoder(k)
        row: dict = {}
        if not args.skip_calibration:
            a = logits(cal, dec)
            cal_dev = {name: deviation((a - logits([t(im) for im in cal], dec) > 0).astype(float))
                       for name, t in SYMMETRIES.items()}
            row["calibration"] = {"direct": deviation((a > 0).astype(float)), **cal_dev}
            row["chosen"] = min(cal_dev, key=lambda n: cal_dev[n]["max_abs_dev"])
        h = logits(hold, dec)
        row["holdout"] = {"direct": by_kind((h > 0).astype(float), hold_kinds)}
        ht = {name: logits([t(im) for im in hold], dec) for name, t in SYMMETRIES.items()}
        for name in SYMMETRIES:
            row["holdout"][name] = by_kind((h - ht[name] > 0).astype(float), hold_kinds)
        row["holdout"]["klein"] = by_kind((klein(h, ht) > 0).astype(float), hold_kinds)
        if args.marked:
            import gsw
            from gsw.mark.message import random_message

            msg = random_message(k)
            photos = [im for im, kind in zip(hold, hold_kinds) if kind == "photo"][:args.marked]
            marked = [r.image for r in gsw.embed_images(photos, msg, num_bits=k, progress=False)]
            m = logits(marked, dec)
            target = msg.numpy().astype(bool)
            row["marked"] = {"images": len(marked), "direct": float(((m > 0) == target).mean())}
            mt = {name: logits([t(im) for im in marked], dec) for name, t in SYMMETRIES.items()}
            for name in SYMMETRIES:
                row["marked"][name] = float(((m - mt[name] > 0) == target).mean())
            row["marked"]["klein"] = float(((klein(m, mt) > 0) == target).mean())
        res["bits"][str(k)] = row
        print(k, json.dumps(row), flush=True)
    res["seconds"] = time.perf_counter() - t0
    with atomic_write(args.out, "w") as f:
        f.write(json.dumps(res, indent=2) + "\n")
    print("written", args.out)


if __name__ == "__main__":
    main()
