"""Image marks embedded for :class:`gsw.decoder.KleinReadout` (issue #22): bits, PSNR, time, robustness.

``benchmarks/symmetric_readout.py --marked 3`` found that marks embedded by :func:`gsw.embed_images` for the direct
readout ``D`` keep only 93-97 % of their bits under the combined readout. Here the same hold-out photos (its
selection, imported) are embedded per bit length with one seeded random message, default settings, twice: for the
direct readout (``decoder=None``, the shipped decoder) and for ``KleinReadout(D)`` (``decoder=``: the loss on
``(D(ll) - D(h ll) - D(v ll) + D(r ll)) / 2``). Each marked photo is read at its own size (one reading at 1x) directly
and through ``KleinReadout``, clean, after a real JPEG at quality 50 (:func:`gsw.attacks.jpeg`) and after Gaussian
noise of sigma 0.05 (:func:`gsw.attacks.gaussian_noise`, seed 0). PSNR is against the original photo (8-bit marked
image); ``seconds`` is the wall time of the image's embedding (``ImageEmbedResult.seconds``; the photos differ in
size, so each is optimised alone).

    python benchmarks/klein_embed.py --out benchmarks/results/klein_embed.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from bench_cpu import machine_info
from calibrate_null import DATA, ROOT, photo_files
from gsw._atomic import atomic_write
from symmetric_readout import logits, split

READOUTS = ("direct", "klein")


def bits_read(images: list[torch.Tensor], decoders: dict, target: np.ndarray) -> dict:
    """Share of the target bits per image, through each readout (one reading at 1x each)."""
    return {name: ((logits(images, dec) > 0) == target).mean(1).tolist() for name, dec in decoders.items()}


def main() -> None:
    import gsw
    from gsw.attacks import gaussian_noise, jpeg
    from gsw.decoder import KleinReadout, load_decoder
    from gsw.mark.message import message_to_hex, random_message

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--bits", type=int, nargs="+", default=[32, 48, 64])
    ap.add_argument("--photos", type=int, default=3, help="hold-out photos per length (symmetric_readout --marked)")
    ap.add_argument("--readouts", nargs="+", default=list(READOUTS), choices=READOUTS)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "klein_embed.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    # symmetric_readout.main's selection: the hold-out half read by split(), its first N photos
    hold, kinds = split(args.data, True)
    names = [n for n, _ in photo_files(args.data, True) if not n.startswith("bsds500")]
    assert len(names) == len(hold)
    picked = [i for i, kind in enumerate(kinds) if kind == "photo"][:args.photos]
    photos = [hold[i] for i in picked]
    attacks = {"jpeg50": lambda im: jpeg(im, quality=50), "noise0.05": lambda im: gaussian_noise(im, 0.05, seed=0)}
    res: dict = {"script": "benchmarks/klein_embed.py", "machine": machine_info(),
                 "settings": {"config": vars(gsw.ImageEmbedConfig()), "klein": "KleinReadout (LL2 flips, halved)",
                              "messages": "random_message(k, seed=k)", "readings": "one at 1x (read_images)"},
                 "photos": [{"name": names[i], "size": list(hold[i].shape[1:])} for i in picked],
                 "bits": {}, "complete": False}
    for k in args.bits:
        dec = load_decoder(k)
        decoders = {"direct": dec, "klein": KleinReadout(dec)}
        msg = random_message(k, seed=k)
        target = msg.numpy().astype(bool)
        row: dict = {"message_hex": message_to_hex(msg)}
        for readout in args.readouts:
            t1 = time.perf_counter()
            out = gsw.embed_images(photos, msg, num_bits=k, progress=False,
                                   decoder=None if readout == "direct" else decoders[readout])
            wall = time.perf_counter() - t1
            marked = [r.image for r in out]
            entry = {"wall_seconds": wall, "seconds": [r.seconds for r in out], "psnr": [r.psnr for r in out],
                     "embed_bit_accuracy": [r.bit_accuracy for r in out], "clean": bits_read(marked, decoders, target)}
            for name, attack in attacks.items():
                entry[name] = bits_read([attack(im) for im in marked], decoders, target)
            row[readout] = entry
            print(k, readout, json.dumps({key: v for key, v in entry.items()}), flush=True)
        res["bits"][str(k)] = row
        res["seconds"] = time.perf_counter() - t0
        with atomic_write(args.out, "w") as f:  # after every length: a cut run keeps what it measured
            f.write(json.dumps(res, indent=2) + "\n")
    res["complete"] = True
    res["machine"]["load_at_end"] = os.getloadavg()[0]
    res["seconds"] = time.perf_counter() - t0
    with atomic_write(args.out, "w") as f:
        f.write(json.dumps(res, indent=2) + "\n")
    print("written", args.out, f"{res['seconds']:.0f} s")


if __name__ == "__main__":
    main()
